"""Pages generated at build time (mkdocs-gen-files): the API reference and the CLI reference.

The API pages are walked from the package folders as they are when the site is built, so a module
that moves or appears needs no edit here; the CLI page is each command's ``--help`` as argparse
prints it (``factorq_trainers.cli.build_parser``), so it cannot drift from the parsers either.
"""

from __future__ import annotations

import os
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
#: installed name -> folder (pyproject's ``[tool.setuptools.package-dir]``)
PACKAGES = {
    "factorq_torch": "factorq_torch",
    "factorq_envs": "envs",
    "factorq_trainers": "trainers",
}


def module_names(package: str, folder: Path) -> list[str]:
    """Every public module and subpackage under ``folder``, by its installed dotted name."""
    names = []
    for path in sorted(folder.rglob("*.py")):
        parts = list(path.relative_to(folder).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        if any(part.startswith("_") for part in parts):  # private modules (_kernel, ...)
            continue
        if not (path.parent / "__init__.py").exists():
            continue
        names.append(".".join([package, *parts]))
    return names


def write_api() -> None:
    import mkdocs_gen_files

    summary = mkdocs_gen_files.Nav()
    summary["Overview"] = "index.md"
    with mkdocs_gen_files.open("reference/api/index.md", "w") as handle:
        handle.write(
            "# API reference\n\n"
            "Generated from the docstrings at build time, one page per module. Three packages "
            "install: `factorq_torch` (the agent: equations, tables, networks, policies, losses, "
            "the online collector), `factorq_envs` (the worlds, the torchrl and gymnasium envs, "
            "the transforms; the folder `envs/`) and `factorq_trainers` (the experiments and the "
            "`factorq` command; the folder `trainers/`).\n\n"
            + "".join(f"- [`{p}`]({p}/index.md)\n" for p in PACKAGES)
        )
    for package, folder in PACKAGES.items():
        for name in module_names(package, ROOT / folder):
            parts = tuple(name.split("."))
            page = Path("reference", "api", *parts).with_suffix(".md")
            if name == package or (ROOT / folder / Path(*parts[1:]) / "__init__.py").exists():
                page = Path("reference", "api", *parts, "index.md")
            summary[parts] = page.relative_to("reference/api").as_posix()
            with mkdocs_gen_files.open(page, "w") as handle:
                handle.write(f"# `{name}`\n\n::: {name}\n")
    with mkdocs_gen_files.open("reference/api/SUMMARY.md", "w") as handle:
        handle.writelines(summary.build_literate_nav())


def write_cli() -> None:
    import mkdocs_gen_files

    os.environ["COLUMNS"] = "100"  # argparse wraps at the terminal's width: fix it for the page
    from factorq_trainers.cli import build_parser

    parser = build_parser()
    lines = [
        "# Command line\n\n",
        "Generated from the parsers when the site is built (`factorq COMMAND --help`). Every "
        "option of a command is a field of its config dataclass, with the field's docstring as "
        "its help (`factorq_trainers.runner.options`).\n\n",
        "```text\n",
        parser.format_help(),
        "```\n\n",
    ]
    commands = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    for name, command in commands.choices.items():
        if name == "sweep":  # main hands its arguments to factorq_trainers.sweep's own parser
            from factorq_trainers.distributed import sweep

            command = sweep.build_parser()
        lines += [f"## `factorq {name}`\n\n", "```text\n", command.format_help(), "```\n\n"]
    with mkdocs_gen_files.open("reference/cli.md", "w") as handle:
        handle.writelines(lines)


def write_changelog() -> None:
    import mkdocs_gen_files

    with mkdocs_gen_files.open("changelog.md", "w") as handle:
        handle.write((ROOT / "CHANGELOG.md").read_text())


if __name__ in ("__main__", "<run_path>"):  # mkdocs-gen-files runs it with runpy.run_path
    write_api()
    write_cli()
    write_changelog()
