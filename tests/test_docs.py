"""The documentation site (mkdocs.yml, docs/): every page's code runs or is checked, every page is
reachable, and the generated references follow the code.

- ``python`` blocks run as doctests (the ``>>>`` form, as the README's do), page by page;
- ``bash`` blocks: every ``factorq`` command line is parsed by the real parser (the command and
  its options exist; nothing runs), every ``make`` target exists in the Makefile, every script
  named exists;
- ``toml`` blocks parse;
- the README stays what a visitor needs first (short; its bash blocks checked as the pages' are,
  its python block a doctest that pytest's ``--doctest-glob`` runs), and every relative link or
  image of the README and the pages points at a file that exists; every figure in ``docs/`` is
  shown on some page.

A page whose examples need an optional extra says so in a comment, ``<!-- requires: minigrid -->``:
its examples are skipped where the extra is not installed.

``mkdocs build --strict`` itself is ``make docs`` (a CI step of its own: it needs the ``docs``
extra and takes longer than a unit test should).
"""

from __future__ import annotations

import doctest
import logging
import re
import shlex
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
PAGES = sorted(path for path in DOCS.rglob("*.md"))
README = ROOT / "README.md"
#: The README's length limit: the two commands, what Factor-Q is, the figure and claims, a
#: quickstart and links; everything else lives in the site (issue 28).
README_LINES = 200
REQUIRES = re.compile(r"<!-- requires: ([\w, ]+) -->")
FENCE = re.compile(r"^```(\w*)[^\n]*\n(.*?)^```", re.MULTILINE | re.DOTALL)
FLAGS = doctest.NORMALIZE_WHITESPACE | doctest.ELLIPSIS


def blocks(language: str) -> list[tuple[Path, str]]:
    """The ``language`` blocks of every page and of the README."""
    return [
        (page, match.group(2))
        for page in [*PAGES, README]
        for match in FENCE.finditer(page.read_text())
        if match.group(1) == language
    ]


def page_id(page: Path) -> str:
    return str(page.relative_to(DOCS if page.is_relative_to(DOCS) else ROOT))


def test_every_python_block_is_a_doctest():
    """A block without ``>>>`` would not run: every python example is written as a session."""
    silent = [page_id(page) for page, code in blocks("python") if ">>>" not in code]
    assert not silent, f"python blocks that would not run: {silent}"


@pytest.mark.parametrize("page", [p for p in PAGES if "```python" in p.read_text()], ids=page_id)
def test_python_blocks_run(page, monkeypatch):
    for required in REQUIRES.findall(page.read_text()):
        for module in required.replace(",", " ").split():
            pytest.importorskip(module, reason=f"{page_id(page)} needs the extra {module}")
    monkeypatch.chdir(ROOT)
    import torch

    threads, torchrl_level = torch.get_num_threads(), logging.getLogger("torchrl").level
    try:
        failed, attempted = doctest.testfile(
            str(page), module_relative=False, optionflags=FLAGS, verbose=False, report=True
        )
    finally:  # the pages set one thread and quiet torchrl's info lines, as they recommend
        torch.set_num_threads(threads)
        logging.getLogger("torchrl").setLevel(torchrl_level)
    assert attempted and not failed, f"{failed} of {attempted} examples failed in {page}"


def _command_lines(code: str) -> list[list[str]]:
    """The shell lines of a block: continuations joined, comments and ``VAR=...`` dropped."""
    code = code.replace("\\\n", " ")
    lines, pending = [], ""
    for line in code.splitlines():
        pending += line + "\n"
        try:
            words = shlex.split(pending, comments=True)
        except ValueError:  # an open quote: the command goes on (python -c "...")
            continue
        pending = ""
        while words and re.match(r"^\w+=", words[0]):
            words = words[1:]
        if words:
            lines.append(words)
    return lines


def test_bash_blocks_name_real_commands_options_and_files():
    from factorq_trainers.cli import build_parser
    from factorq_trainers.distributed import sweep

    makefile = (ROOT / "Makefile").read_text()
    checked = 0
    for page, code in blocks("bash"):
        for words in _command_lines(code):
            program, args = words[0], words[1:]
            where = f"{page_id(page)}: {' '.join(words)}"
            if program.endswith("factorq"):
                if args[0] == "sweep":  # main hands it to its own parser
                    parser, args = sweep.build_parser(), args[1:]
                else:
                    parser = build_parser(compare_options=args[0] == "compare", command=args[0])
                try:
                    _, unknown = parser.parse_known_args(args)
                except SystemExit as exit_:  # argparse exits 0 for --help
                    assert exit_.code == 0, where
                    unknown = []
                assert not unknown, f"{where}: unknown {unknown}"
            elif program == "make":
                assert re.search(rf"^{args[0]}:", makefile, re.MULTILINE), where
            elif program.endswith("python") and args[0] != "-c":
                assert (ROOT / args[0]).is_file(), where
            elif program.endswith("python"):
                compile(args[1], where, "exec")  # a one-off script: at least valid Python
            elif program not in {"pip", "dask"}:
                raise AssertionError(f"{where}: no check for {program!r}")
            checked += 1
    assert checked >= 20


def test_toml_blocks_parse():
    for _page, code in blocks("toml"):
        tomllib.loads(code)


def _nav_pages(nav) -> list[str]:
    found = []
    for entry in nav:
        for value in entry.values() if isinstance(entry, dict) else [entry]:
            found += _nav_pages(value) if isinstance(value, list) else [value]
    return found


def test_every_page_is_in_the_navigation_and_every_entry_exists():
    text = (ROOT / "mkdocs.yml").read_text()
    # the nav section as plain YAML-like lines: "- Title: path"
    nav = re.findall(r"^\s*- [^:\n]+: (\S+)$", text.split("\nnav:\n", 1)[1], re.MULTILINE)
    generated = {"changelog.md", "reference/cli.md", "reference/api/"}
    for entry in nav:
        assert entry in generated or (DOCS / entry).is_file(), entry
    written = {page_id(page) for page in PAGES}
    assert written - set(nav) == set(), "pages no one can reach"


def test_the_api_reference_walks_every_module():
    """docs/gen_reference.py finds modules from the folders: one that moves is still documented."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("gen_reference", DOCS / "gen_reference.py")
    generator = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(generator)  # definitions only: it writes pages under mkdocs alone
    namespace = vars(generator)
    names = []
    for package, folder in namespace["PACKAGES"].items():
        names += namespace["module_names"](package, ROOT / folder)
    assert {"factorq_torch", "factorq_torch.base.rng", "factorq_envs.torchrl_env"} <= set(names)
    assert "factorq_trainers.analysis.stats" in names and not any("._" in name for name in names)
    for name in names:
        assert importlib.util.find_spec(name) is not None, name


def test_the_api_reference_renders_docstring_examples_as_code():
    pytest.importorskip("griffe")  # the docs extra
    import importlib.util

    spec = importlib.util.spec_from_file_location("griffe_doctests", DOCS / "griffe_doctests.py")
    extension = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(extension)
    failed, attempted = doctest.testmod(extension, optionflags=FLAGS)
    assert attempted and not failed


def test_the_readme_stays_short_and_opens_with_the_two_commands():
    text = README.read_text()
    assert len(text.splitlines()) < README_LINES, "the README grows: move the detail to docs/"
    first = FENCE.search(text)
    assert first.group(1) == "bash" and text.index(first.group(0)) < text.index("\n## ")
    commands = [words[:2] for words in _command_lines(first.group(2))]
    assert commands == [["make", "paper"], ["make", "test"]]
    quickstart = [code for page, code in blocks("python") if page == README]
    assert len(quickstart) == 1 and ">>>" in quickstart[0]  # a doctest (pytest's doctest-glob)


LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")


def test_relative_links_and_images_point_at_files():
    """Every relative link or image of the README and of every page resolves to a file in the
    repository, so it works when the repository is read as it is, not only in the built site
    (a page generated at build time, such as the API reference, is not a file here)."""
    broken = []
    for page in [*PAGES, README]:
        text = FENCE.sub("", page.read_text())  # code blocks hold no links
        for target in LINK.findall(text):
            path = target.split("#", 1)[0]
            if not path or re.match(r"^[a-z]+:", path):  # an anchor on the page, or a URL
                continue
            resolved = (page.parent / path).resolve()
            if not (resolved.is_relative_to(ROOT) and resolved.is_file()):
                broken.append(f"{page_id(page)}: {target}")
    assert not broken, f"links to no file of the repository: {broken}"


def test_every_figure_in_docs_is_shown_on_a_page():
    shown = {
        (page.parent / target).resolve()
        for page in PAGES
        for target in LINK.findall(page.read_text())
    }
    figures = sorted(DOCS.glob("*.png"))
    assert figures and not [f.name for f in figures if f.resolve() not in shown]


def test_the_set_up_installs_the_torch_that_pyproject_pins():
    # make setup installs torch through pip before uv installs the rest: were the two pins to
    # differ, uv would replace the local CPU wheel with another torch from the index.
    pinned = re.findall(r'"torch==([^"]+)"', (ROOT / "pyproject.toml").read_text())
    installed = re.findall(r"pip install [^\n]*torch==(\S+)", (ROOT / "Makefile").read_text())
    assert len(pinned) == 1 and installed == pinned, (pinned, installed)
