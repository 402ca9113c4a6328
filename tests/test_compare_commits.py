"""benchmarks/compare_commits.py (issue 42): its arguments, its ratios and its package links
(nothing timed here)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def compare(script):
    module = script("benchmarks/compare_commits.py")
    assert "torch" not in vars(module)  # the parent imports no torch: the workers do
    return module


def test_the_defaults_run_every_benchmark_against_the_fork_point(compare):
    args = compare.parse_args([])
    assert args.base is None and args.base_dir is None and not args.worker
    assert args.only == list(compare.BENCHMARKS) and args.rounds == 3


def test_bad_arguments_are_refused_by_name(compare, capsys):
    for argv, needle in (
        (["HEAD", "--base-dir", "/tmp"], "not both"),
        (["--rounds", "0"], "--rounds=0"),
        (["--only", "everything"], "invalid choice"),
    ):
        with pytest.raises(SystemExit):
            compare.parse_args(argv)
        assert needle in capsys.readouterr().err


def test_speedups_are_base_over_this_per_round_with_their_median_and_range(compare):
    # rounds: 2.0 / 1.0 = 2, 3.0 / 2.0 = 1.5, 1.0 / 4.0 = 0.25 -> median 1.5, range 0.25-2
    assert compare.speedups([1.0, 2.0, 4.0], [2.0, 3.0, 1.0]) == (1.5, 0.25, 2.0)
    with pytest.raises(ValueError, match="as many"):
        compare.speedups([1.0], [1.0, 2.0])


def test_packages_are_linked_under_their_installed_names(compare, tmp_path):
    tree = tmp_path / "tree"
    for folder in ("factorq_torch", "source_envs", "trainers"):
        (tree / folder).mkdir(parents=True)
        (tree / folder / "__init__.py").write_text("")
    (tree / "pyproject.toml").write_text(
        '[tool.setuptools.package-dir]\nfactorq_envs = "source_envs"\n'
        'factorq_trainers = "trainers"\n'
    )
    links = compare.link_packages(tree, tmp_path / "links")
    assert sorted(path.name for path in links.iterdir()) == sorted(compare.DEFAULT_PACKAGES)
    assert (links / "factorq_envs").resolve() == (tree / "source_envs").resolve()
    (tree / "trainers" / "__init__.py").unlink()
    with pytest.raises(SystemExit, match="no package"):
        compare.package_folders(tree)


def test_this_checkout_links_its_own_packages(compare, tmp_path):
    links = compare.link_packages(ROOT, tmp_path / "links")
    assert (links / "factorq_envs").resolve() == (ROOT / "envs").resolve()
    assert sys.modules.get("compare_commits_under_test") is None  # loaded by path, not registered
