"""What the documentation says about the repository holds (issue 37).

(a) Every path the README, the pages under ``docs/`` (tutorials and how-tos included) and the
released part of ``CHANGELOG.md`` name exists, so a move or a removal that leaves the docs behind
fails here. ``CHANGELOG.md``'s ``[Unreleased]`` part may name what it removed and is not read;
``docs/decisions.md`` included.

A path is inline code holding a ``/`` and ending in a file suffix (``runner/frame.py``), a folder
of two or more parts (``docs/howto/``; one part, ``units/``, is mostly a folder a command writes),
or a bare ``.py`` / ``.c`` file name. One whose first part is a top-level folder of the repository
(``trainers/runner/frame.py``, ``docs/howto/gpu.md``, ``benchmarks/bench_env.py``) must exist at
exactly that place; another may be written, as the docs do, from the folder of its package
(``runner/kept.py`` for ``trainers/runner/kept.py``), and a bare file name must be some file's.
Output files (``OUT/...``, ``results/...``), placeholders (``<name>``, ``*``) and paths outside
the repository (``../shared/...``) are not repository paths. Links of the README and the pages
are ``tests/test_docs.py``'s; those of the changelog are checked here.

(b) The layers ``docs/architecture.md`` states are the ones ``tests/test_layers.py`` checks with
``ast`` over the source tree (every module imports only its own layer or a lower one, lazy imports
included, no circles, no two trainers folders importing each other): the diagram's order of the
layers and the folders it names are read from the page and compared with that test's.
"""

from __future__ import annotations

import re
from pathlib import Path

import test_layers  # tests/test_layers.py: pytest puts tests/ on sys.path

ROOT = Path(__file__).resolve().parent.parent
#: Pages left out of the path check (none).
EXCLUDED_PAGES: tuple[str, ...] = ()
PAGES = [
    ROOT / "README.md",
    *(
        page
        for page in sorted((ROOT / "docs").rglob("*.md"))
        if page.relative_to(ROOT).as_posix() not in EXCLUDED_PAGES
    ),
]
CHANGELOG = ROOT / "CHANGELOG.md"
FENCE = re.compile(r"^```.*?^```", re.MULTILINE | re.DOTALL)
CODE = re.compile(r"`([^`\s]+)`")
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
SUFFIXES = "py|md|c|h|toml|yml|yaml|png|json|txt|cfg|npz|pt|ipynb|sh"
PATH = re.compile(rf"^[\w.+-]+(/[\w.+-]+)*/[\w.+-]+\.({SUFFIXES})$|^[\w.+-]+(/[\w.+-]+)+/$")
MODULE_FILE = re.compile(r"^[\w-]+\.(py|c)$")
NOT_OURS = ("OUT/", "DIR/", "out/", "results/", "build/", "/", "~", "../", ".venv/", "http")
#: The packages' folders, from which the docs name their files.
BASES = ("trainers/", "envs/", "factorq_torch/", "docs/")
#: Files of the shared numba anchor, another session's folder outside this repository, which
#: the speed pages name as such.
ANCHOR_FILES = ("fq_numba.py", "common.py", "drv_numba.py", "py312_intrinsics.py")
SKIPPED_FOLDERS = (".git", ".venv", "build", "dist", "__pycache__", ".pytest_cache", ".ruff_cache")


def top_level_folders() -> set[str]:
    """The repository's own top-level folders (not a build's, a cache's or an egg-info)."""
    return {
        path.name
        for path in ROOT.iterdir()
        if path.is_dir()
        and not path.name.startswith(".")
        and path.name not in SKIPPED_FOLDERS
        and not path.name.endswith(".egg-info")
    }


def repository_files() -> list[str]:
    return [
        path.relative_to(ROOT).as_posix()
        for path in ROOT.rglob("*")
        if not any(part in SKIPPED_FOLDERS for part in path.relative_to(ROOT).parts)
    ]


def released_part(changelog: str) -> str:
    """The changelog from its first released version on (``[Unreleased]`` may name removed
    files)."""
    match = re.search(r"^## \[(?!Unreleased\])", changelog, re.MULTILINE)
    return changelog[match.start() :] if match else ""


def named_paths(text: str) -> list[str]:
    """The repository paths ``text`` names in inline code (code blocks are other tests')."""
    found = []
    for token in CODE.findall(FENCE.sub("", text)):
        if token.startswith(NOT_OURS) or any(mark in token for mark in "<>*{}$"):
            continue
        if PATH.match(token) or (MODULE_FILE.match(token) and token not in ANCHOR_FILES):
            found.append(token)
    return found


def exists(token: str, files: list[str], top: set[str]) -> bool:
    """Whether ``token`` names a file or folder of the repository (see the module docstring)."""
    path = token.rstrip("/")
    if path.split("/", 1)[0] in top:  # written from the root: there exactly
        return (ROOT / path).exists()
    if any((ROOT / base / path).exists() for base in BASES):
        return True
    if "/" not in path:  # a module's file name: in some folder of the repository
        return any(file.rsplit("/", 1)[-1] == path for file in files)
    return False


def test_paths_are_found_in_inline_code_only():
    text = (
        "`runner/frame.py` and `grid_world.py`, `OUT/units/`, `<name>.py`, `1/K`, `results.json`,\n"
        "`configs/`, `docs/howto/`, `results/paper/figure3.png`\n"
        "```bash\ncat `not/this.py`\n```\n"
    )
    assert named_paths(text) == ["runner/frame.py", "grid_world.py", "docs/howto/"]


def test_a_path_from_the_root_must_be_there_exactly():
    files, top = repository_files(), top_level_folders()
    assert {"trainers", "envs", "factorq_torch", "docs", "tests"} <= top
    assert exists("runner/frame.py", files, top) and exists("grid_world.py", files, top)
    assert exists("trainers/runner/frame.py", files, top) and exists("docs/howto/", files, top)
    # found from a package's folder, but written from the root where it is not
    assert not exists("trainers/frame.py", files, top)
    assert not exists("docs/architecture.py", files, top)
    assert not exists("distributed/cluster.py", files, top) and not exists("world.py", files, top)


def test_only_the_released_part_of_the_changelog_is_read():
    text = "# Changelog\n## [Unreleased]\n`gone/file.py`\n## [0.1.0] - 2026-12-02\n`kept.py`\n"
    assert named_paths(released_part(text)) == ["kept.py"]
    assert released_part("## [Unreleased]\nonly this\n") == ""


def test_every_path_the_docs_name_exists():
    files, top = repository_files(), top_level_folders()
    sources = [(page.relative_to(ROOT).as_posix(), page.read_text()) for page in PAGES]
    sources.append(("CHANGELOG.md (released)", released_part(CHANGELOG.read_text())))
    missing = [
        f"{name}: {token}"
        for name, text in sources
        for token in named_paths(text)
        if not exists(token, files, top)
    ]
    assert not missing, f"paths the docs name that do not exist: {missing}"


def test_the_changelogs_links_point_at_files():
    text = FENCE.sub("", CHANGELOG.read_text())
    broken = [
        target
        for target in LINK.findall(text)
        if not re.match(r"^([a-z]+:|#)", target) and not (ROOT / target.split("#", 1)[0]).exists()
    ]
    assert not broken, f"links of CHANGELOG.md to no file of the repository: {broken}"


# (b) ---------------------------------------------------------------------------------------------

#: The diagram's rows: a layer's name, then where it lives.
DIAGRAM_ROW = re.compile(r"^ (\w+) +(\S+)", re.MULTILINE)
#: The diagram's names of the layers test_layers checks, in its own words.
DIAGRAM_NAMES = {
    "base": "base",
    "worlds": "worlds",
    "agent": "agent",
    "compiled": "compiled",
    "trainers": "trainers",
    "CLI": "cli",
}


def stated_layers() -> list[tuple[str, str]]:
    """The layers of architecture.md's diagram, lowest first, each with where it lives."""
    text = (ROOT / "docs" / "architecture.md").read_text()
    diagram = FENCE.findall(text)[0]
    return [(name, where) for name, where in DIAGRAM_ROW.findall(diagram)][::-1]


def test_the_diagram_states_the_layers_test_layers_checks():
    layers = stated_layers()
    assert [DIAGRAM_NAMES[name] for name, _ in layers] == list(test_layers.LAYERS)


def test_each_layers_modules_live_where_the_diagram_says():
    """Every module the diagram places in a layer (``envs/*.py``: the worlds) belongs to that
    layer in the rule test_layers checks, so the picture and the test are one rule."""
    folders = {folder: package for package, folder in test_layers.PACKAGES.items()}
    for name, where in stated_layers():
        folder, _, rest = where.partition("/")
        paths = sorted((ROOT / folder).glob(rest + "*.py" if rest.endswith("/") else rest))
        assert paths, f"the diagram's {name} layer names {where}, which matches no file"
        for path in paths:
            if path.suffix != ".py":
                continue
            parts = path.relative_to(ROOT / folder).with_suffix("").parts
            module = ".".join((folders[folder], *parts)).removesuffix(".__init__")
            layer = DIAGRAM_NAMES[name]
            # the trainers' row (trainers/*/) spans the compiled folder, a layer of its own
            if layer == "trainers" and test_layers.layer_of(module) == "compiled":
                continue
            assert test_layers.layer_of(module) == layer, (
                f"{path.relative_to(ROOT)} is in the {name} layer by the diagram but "
                f"{test_layers.layer_of(module)} by tests/test_layers.py"
            )
