"""The examples in the docstrings of ``factorq_envs`` and ``factorq_trainers``.

Their folders (``envs/``, ``trainers/``) install under other names, so pytest's
``--doctest-modules`` would import them a second time under the folder name; these tests run
their doctests on the installed modules instead (``factorq_torch`` and README.md are collected by
pytest itself: pyproject's ``testpaths``).
"""

from __future__ import annotations

import doctest
import importlib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
FOLDERS = {"factorq_envs": "envs", "factorq_trainers": "trainers"}
FLAGS = doctest.NORMALIZE_WHITESPACE | doctest.ELLIPSIS


def modules_with_examples() -> list[str]:
    """Every module of the two packages whose source holds an example (``>>>``)."""
    names = []
    for package, folder in FOLDERS.items():
        for path in sorted((ROOT / folder).rglob("*.py")):
            if ">>>" in path.read_text():
                parts = path.relative_to(ROOT / folder).with_suffix("").parts
                parts = parts[:-1] if parts[-1] == "__init__" else parts
                names.append(".".join((package, *parts)))
    return names


def test_the_walk_finds_examples():
    assert {"factorq_envs.torchrl_env", "factorq_trainers.analysis.stats"} <= set(
        modules_with_examples()
    )


@pytest.mark.parametrize("name", modules_with_examples())
def test_docstring_examples(name):
    module = importlib.import_module(name)
    finder = doctest.DocTestFinder()
    runner = doctest.DocTestRunner(optionflags=FLAGS)
    tests = [t for t in finder.find(module) if t.examples]
    assert tests, f"{name} has '>>>' in its source but no doctest was found"
    for test in tests:
        runner.run(test)
    result = runner.summarize(verbose=False)
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples failed in {name}"
