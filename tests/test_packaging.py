"""What the wheel installs: the three project packages under project names, nothing generic."""

from __future__ import annotations

import tomllib
from pathlib import Path

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
