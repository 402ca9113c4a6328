"""What the wheel installs (the three project packages under project names, nothing generic) and
what the distributions carry (licence, one version, examples and docs in the sdist)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tarfile
import tomllib
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
TOOL = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]


def installed_packages(tool: dict) -> dict[str, Path]:
    """Every package directory of the repository (a folder with ``__init__.py``) by the name it
    installs under, from pyproject's ``package-dir`` (a folder not mapped installs as itself)."""
    folders = {name: ROOT / folder for name, folder in tool.get("package-dir", {}).items()}
    folders.setdefault("factorq_torch", ROOT / "factorq_torch")
    found = {}
    for top, folder in folders.items():
        for init in sorted(folder.rglob("__init__.py")):
            parts = init.parent.relative_to(folder).parts
            found[".".join((top, *parts))] = init.parent
    return found


def test_every_package_folder_is_listed():
    """A new subpackage that pyproject's ``packages`` forgets would be missing from the wheel."""
    assert sorted(installed_packages(TOOL)) == sorted(TOOL["packages"])


def test_no_generic_top_level_name():
    tops = {name.split(".")[0] for name in TOOL["packages"]}
    assert tops == {"factorq_torch", "factorq_envs", "factorq_trainers"}


def test_the_forgotten_package_is_caught():
    tool = {**TOOL, "packages": [p for p in TOOL["packages"] if p != "factorq_torch.base"]}
    assert sorted(installed_packages(tool)) != sorted(tool["packages"])


def test_entry_points_use_installed_names():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert project["scripts"]["factorq"] == "factorq_trainers.cli:main"
    assert (ROOT / "trainers" / "py.typed").exists() and (ROOT / "envs" / "py.typed").exists()
    assert "*.c" in TOOL["package-data"]["factorq_trainers.compiled"]
    assert (ROOT / "trainers" / "compiled" / "_kernel.c").exists()


# --- the distributions themselves (issue 28): licence, version in one place, sdist contents ---
# One sdist and one wheel built per test session by setuptools' own backend (no isolation, no
# download: about 2 s), in a temporary folder.

BUILD = """
import sys
from setuptools import build_meta
out = sys.argv[1]  # read first: build_meta rewrites sys.argv
print(build_meta.build_sdist(out))
print(build_meta.build_wheel(out))
"""


@pytest.fixture(scope="module")
def distributions(tmp_path_factory) -> tuple[tarfile.TarFile, zipfile.ZipFile]:
    out = tmp_path_factory.mktemp("dist")
    subprocess.run(
        [sys.executable, "-c", BUILD, str(out)], cwd=ROOT, check=True, capture_output=True
    )
    (sdist,) = out.glob("*.tar.gz")
    (wheel,) = out.glob("*.whl")
    return tarfile.open(sdist), zipfile.ZipFile(wheel)


def project_version() -> str:
    """``factorq_torch.__version__`` as written in the source (what the build reads)."""
    source = (ROOT / "factorq_torch" / "__init__.py").read_text()
    return re.search(r'^__version__ = "([^"]+)"$', source, re.MULTILINE).group(1)


def test_license_is_an_spdx_expression_with_its_file():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert project["license"] == "MIT" and project["license-files"] == ["LICENSE"]
    assert (ROOT / "LICENSE").read_text().startswith("MIT License")


def test_the_version_lives_in_one_place():
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert "version" not in pyproject["project"] and "version" in pyproject["project"]["dynamic"]
    dynamic = pyproject["tool"]["setuptools"]["dynamic"]["version"]
    assert dynamic == {"attr": "factorq_torch.__version__"}
    import factorq_torch

    assert factorq_torch.__version__ == project_version()
    assert f"## [{project_version()}]" in (ROOT / "CHANGELOG.md").read_text()


def test_the_wheel_metadata(distributions):
    _, wheel = distributions
    info = f"factorq_torch-{project_version()}.dist-info"
    metadata = wheel.read(f"{info}/METADATA").decode()
    assert f"\nVersion: {project_version()}\n" in metadata
    assert "\nLicense-Expression: MIT\n" in metadata and "\nLicense-File: LICENSE\n" in metadata
    names = set(wheel.namelist())
    assert f"{info}/licenses/LICENSE" in names and "factorq_trainers/compiled/_kernel.c" in names
    # the wheel installs packages only: examples and docs travel in the sdist
    assert not any(name.startswith(("examples/", "docs/", "envs/", "trainers/")) for name in names)


def test_the_sdist_carries_examples_docs_licence_and_changelog(distributions):
    sdist, _ = distributions
    top = f"factorq_torch-{project_version()}/"
    names = {name.removeprefix(top) for name in sdist.getnames()}
    tracked = ["LICENSE", "CHANGELOG.md", "README.md", "mkdocs.yml"]
    for folder in ("examples", "docs"):
        tracked += [
            str(path.relative_to(ROOT))
            for path in (ROOT / folder).rglob("*")
            if path.is_file() and "__pycache__" not in path.parts  # bytecode stays out
        ]
    missing = [name for name in tracked if (ROOT / name).exists() and name not in names]
    assert not missing, f"not in the sdist: {missing}"
    assert "examples/offpolicy_replay.py" in names and "docs/decisions.md" in names
    assert not any("__pycache__" in name for name in names)


USER_SCRIPT = '''"""A user's script, outside the repository, against the installed packages."""
import gymnasium
import numpy as np

from factorq_envs.gymnasium_adapter import Declaration, FactorQEnv, Transition
from factorq_torch.tables import TaskQTable
from factorq_trainers.analysis.stats import count_ratio


def holes(step: Transition) -> np.ndarray:
    return np.array([step.terminated and step.reward == 0] * 4)


declaration = Declaration(num_sensors=4, sensors=holes, collision=lambda step: False)
env = FactorQEnv(gymnasium.make("FrozenLake-v1"), declaration)
table = TaskQTable(1, env.config.num_cells, num_actions=env.config.num_actuators)
ratio: float | None = count_ratio(2.0, 1.0)
'''
WRONG_SCRIPT = """from factorq_envs.gymnasium_adapter import Declaration

name: str = Declaration.penalty  # a float: mypy must say so
"""


@pytest.mark.slow
def test_a_user_script_type_checks_with_plain_mypy(tmp_path):
    """``make setup`` installs in setuptools' strict editable mode (a tree of links on
    ``sys.path``), so plain ``mypy`` in a user's folder, with no configuration, finds the three
    packages, checks a correct script clean (under ``--strict``: the public API it calls is
    typed) and finds the error in a wrong one (issue 38; the default editable mode's import hook
    left every ``factorq_*`` import "not found")."""
    pytest.importorskip("mypy")
    (tmp_path / "user_script.py").write_text(USER_SCRIPT)
    (tmp_path / "wrong_script.py").write_text(WRONG_SCRIPT)
    done = subprocess.run(
        [sys.executable, "-m", "mypy", "--strict", "--cache-dir", str(tmp_path / "cache"),
         "user_script.py", "wrong_script.py"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=1800,
        env={key: value for key, value in os.environ.items() if key != "MYPYPATH"},
    )  # fmt: skip
    lines = done.stdout.splitlines()
    assert "import-not-found" not in done.stdout, done.stdout
    assert [line for line in lines if line.startswith("user_script.py")] == [], done.stdout
    assert any(line.startswith("wrong_script.py:3: error: Incompatible types") for line in lines), (
        done.stdout
    )
    assert lines[-1] == "Found 1 error in 1 file (checked 2 source files)", done.stdout
