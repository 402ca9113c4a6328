"""Every path the documentation names exists (issue 37): each file or folder written as inline
code in ``README.md`` and the pages under ``docs/`` (``docs/architecture.md``'s tables above
all), checked against the repository, so a move or a removal that leaves the docs behind fails
here. The layer rules ``docs/architecture.md`` states are ``tests/test_layers.py``'s.

A path is inline code holding a ``/`` and ending in a file suffix (``runner/frame.py``), a folder
of two or more parts (``docs/howto/``; one part, ``units/``, is mostly a folder a command writes),
or a bare ``.py`` / ``.c`` file name. It may be written from the repository's
root or, as the docs do, from the folder of its package (``runner/kept.py`` for
``trainers/runner/kept.py``, ``grid_world.py`` for ``envs/grid_world.py``). Output files
(``OUT/...``, ``results/...``), placeholders (``<name>``, ``*``) and paths outside the repository
(``../shared/...``) are not repository paths.
"""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
FENCE = re.compile(r"^```.*?^```", re.MULTILINE | re.DOTALL)
CODE = re.compile(r"`([^`\s]+)`")
SUFFIXES = "py|md|c|h|toml|yml|yaml|png|json|txt|cfg|npz|pt|ipynb|sh"
PATH = re.compile(rf"^[\w.+-]+(/[\w.+-]+)*/[\w.+-]+\.({SUFFIXES})$|^[\w.+-]+(/[\w.+-]+)+/$")
MODULE_FILE = re.compile(r"^[\w-]+\.(py|c)$")
NOT_OURS = ("OUT/", "DIR/", "out/", "results/", "build/", "/", "~", "../", ".venv/", "http")
#: The packages' folders, from which the docs name their files.
BASES = ("", "trainers/", "envs/", "factorq_torch/", "docs/")
#: Files of the shared numba anchor, another session's folder outside this repository, which
#: docs/decisions.md and the speed pages name as such.
ANCHOR_FILES = ("fq_numba.py", "common.py", "drv_numba.py", "py312_intrinsics.py")
SKIPPED_FOLDERS = (".git", ".venv", "build", "__pycache__", ".pytest_cache", ".ruff_cache")


def repository_files() -> list[str]:
    return [
        path.relative_to(ROOT).as_posix()
        for path in ROOT.rglob("*")
        if not any(part in SKIPPED_FOLDERS for part in path.relative_to(ROOT).parts)
    ]


def named_paths(text: str) -> list[str]:
    """The repository paths ``text`` names in inline code (code blocks are other tests')."""
    found = []
    for token in CODE.findall(FENCE.sub("", text)):
        if token.startswith(NOT_OURS) or any(mark in token for mark in "<>*{}$"):
            continue
        if PATH.match(token) or (MODULE_FILE.match(token) and token not in ANCHOR_FILES):
            found.append(token)
    return found


def exists(token: str, files: list[str]) -> bool:
    path = token.rstrip("/")
    if any((ROOT / base / path).exists() for base in BASES):
        return True
    if "/" not in path:  # a module's file name: in some folder of the repository
        return any(file.rsplit("/", 1)[-1] == path for file in files)
    return False


def test_paths_are_found_in_inline_code_only():
    text = (
        "`runner/frame.py` and `grid_world.py`, `OUT/units/`, `<name>.py`, `1/K`, `results.json`,\n"
        "`configs/`, `docs/howto/`\n"
        "```bash\ncat `not/this.py`\n```\n"
    )
    assert named_paths(text) == ["runner/frame.py", "grid_world.py", "docs/howto/"]
    files = repository_files()
    assert exists("runner/frame.py", files) and exists("grid_world.py", files)
    assert not exists("distributed/cluster.py", files) and not exists("world.py", files)


def test_every_path_the_docs_name_exists():
    files = repository_files()
    missing = [
        f"{page.relative_to(ROOT)}: {token}"
        for page in PAGES
        for token in named_paths(page.read_text())
        if not exists(token, files)
    ]
    assert not missing, f"paths the docs name that do not exist: {missing}"
