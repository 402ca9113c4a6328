"""The import layers (docs/architecture.md): every module imports only its own layer or below.

base (``factorq_torch.base``) -> worlds (``factorq_envs``, folder ``envs/``) -> agent (the rest of
``factorq_torch``) -> compiled path (``factorq_trainers.compiled``) -> trainers
(``factorq_trainers``, folder ``trainers/``) -> CLI (``factorq_trainers.cli``). Imports inside
functions count too, and no two modules may import each other through any chain.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
#: the installed package name -> its folder in the repository (pyproject's ``package-dir``)
PACKAGES = {
    "factorq_torch": "factorq_torch",
    "factorq_envs": "envs",
    "factorq_trainers": "trainers",
}
#: the folder names the wheel does not install: nothing may import them
FOLDER_NAMES = ("envs", "trainers")
LAYERS = ("base", "worlds", "agent", "compiled", "trainers", "cli")


def layer_of(module: str) -> str:
    """The layer a project module belongs to."""
    if module == "factorq_torch.base" or module.startswith("factorq_torch.base."):
        return "base"
    if module.split(".")[0] == "factorq_envs":
        return "worlds"
    if module.split(".")[0] == "factorq_torch":
        return "agent"
    if module.startswith("factorq_trainers.compiled"):
        return "compiled"
    if module == "factorq_trainers.cli":
        return "cli"
    return "trainers"


def project_modules() -> dict[str, Path]:
    """Every module of the three packages, by dotted name."""
    modules = {}
    for package, folder in PACKAGES.items():
        for path in sorted((ROOT / folder).rglob("*.py")):
            parts = (package, *path.relative_to(ROOT / folder).with_suffix("").parts)
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            modules[name] = path
    return modules


def imports_of(name: str, path: Path, known: dict[str, Path]) -> set[str]:
    """The project modules ``path`` imports anywhere in its body (lazy imports included)."""
    found = set()
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            targets = [base] + [f"{base}.{alias.name}" for alias in node.names]
        else:
            continue
        for target in targets:
            # the deepest project module the import names (a package's attribute counts as it)
            while target and target not in known:
                target = target.rpartition(".")[0]
            if target and target != name:
                found.add(target)
    return found


MODULES = project_modules()
GRAPH = {name: imports_of(name, path, MODULES) for name, path in MODULES.items()}


def test_every_package_has_modules_in_the_walk():
    assert {
        "factorq_torch.base.rng",
        "factorq_envs.grid_world",
        "factorq_torch.functional",
        "factorq_trainers.compiled.fast",
    } <= set(MODULES)


@pytest.mark.parametrize("name", sorted(MODULES))
def test_module_imports_only_its_layer_or_below(name):
    own = LAYERS.index(layer_of(name))
    upward = sorted(t for t in GRAPH[name] if LAYERS.index(layer_of(t)) > own)
    assert not upward, f"{name} ({layer_of(name)}) imports upwards: {upward}"


def test_no_module_imports_itself_through_a_chain():
    def reach(start):
        seen, stack = set(), list(GRAPH[start])
        while stack:
            node = stack.pop()
            if node not in seen:
                seen.add(node)
                stack.extend(GRAPH[node])
        return seen

    circles = sorted(name for name in GRAPH if name in reach(name))
    assert not circles, f"modules on an import circle: {circles}"


def bare_folder_imports(path: Path) -> list[str]:
    """The imports in ``path`` of a folder name the wheel does not install (``envs``,
    ``trainers``)."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and not node.level:
            names = [node.module or ""]
        else:
            continue
        found += [
            f"{path.name}:{node.lineno} {n}" for n in names if n.split(".")[0] in FOLDER_NAMES
        ]
    return found


def test_bare_folder_imports_are_found(tmp_path):
    source = tmp_path / "m.py"
    source.write_text("import os\nfrom envs.world import x\ndef f():\n    import trainers.cli\n")
    assert bare_folder_imports(source) == ["m.py:2 envs.world", "m.py:4 trainers.cli"]


def test_nothing_imports_the_folder_names():
    """The repository's folders ``envs/`` and ``trainers/`` install as ``factorq_envs`` and
    ``factorq_trainers``; a bare ``import envs`` works only from a checkout (or finds another
    distribution's ``envs``), so no code, test, example or benchmark may use it."""
    files = [
        p
        for d in ("factorq_torch", "envs", "trainers", "tests", "examples", "benchmarks")
        for p in sorted((ROOT / d).rglob("*.py"))
    ]
    bad = [hit for path in files for hit in bare_folder_imports(path)]
    assert not bad, f"imports of uninstalled folder names: {bad}"


def trainers_folder(module: str) -> str | None:
    """The folder of ``factorq_trainers`` a module sits in (``runner``, ``experiments``, ...;
    ``cli`` for the modules at its top), None outside the trainers."""
    parts = module.split(".")
    if parts[0] != "factorq_trainers":
        return None
    if len(parts) > 1 and (ROOT / PACKAGES["factorq_trainers"] / parts[1]).is_dir():
        return parts[1]
    return "cli"  # the package's own modules: cli.py, __init__.py


def folder_circles(graph: dict[str, set[str]]) -> list[tuple[str, ...]]:
    """Every pair of trainers folders that reach each other through their modules' imports
    (a chain of imports across folders, lazy ones included), with a chain that shows it."""
    edges: dict[str, dict[str, str]] = {}
    for name, targets in graph.items():
        for target in targets:
            a, b = trainers_folder(name), trainers_folder(target)
            if a and b and a != b:
                edges.setdefault(a, {}).setdefault(b, f"{name} -> {target}")

    def path(start: str, goal: str) -> list[str] | None:
        stack, seen = [(start, [])], set()
        while stack:
            node, via = stack.pop()
            for nxt, why in edges.get(node, {}).items():
                if nxt == goal:
                    return [*via, why]
                if nxt not in seen:
                    seen.add(nxt)
                    stack.append((nxt, [*via, why]))
        return None

    found = []
    for a in sorted(edges):
        for b in sorted(edges):
            if a < b and (there := path(a, b)) and (back := path(b, a)):
                found.append((a, b, *there, *back))
    return found


def test_folder_circles_are_found_lazy_imports_included():
    graph = {
        "factorq_trainers.runner.frame": {"factorq_trainers.distributed.cluster"},
        "factorq_trainers.distributed.cluster": {"factorq_trainers.runner.options"},
        "factorq_trainers.runner.options": set(),
        "factorq_trainers.reports.x": {"factorq_trainers.runner.options"},
    }
    assert folder_circles(graph) == [
        (
            "distributed",
            "runner",
            "factorq_trainers.distributed.cluster -> factorq_trainers.runner.options",
            "factorq_trainers.runner.frame -> factorq_trainers.distributed.cluster",
        )
    ]
    graph["factorq_trainers.runner.frame"] = set()
    assert folder_circles(graph) == []


def test_a_lazy_import_is_an_edge(tmp_path):
    source = tmp_path / "frame.py"
    source.write_text("def f():\n    from factorq_trainers.distributed import cluster\n")
    known = {"factorq_trainers.distributed.cluster": source}
    assert imports_of("factorq_trainers.runner.frame", source, known) == {
        "factorq_trainers.distributed.cluster"
    }


def test_no_two_trainers_folders_import_each_other():
    """``runner`` holds what every command shares, a command's own pieces sit in its folder of
    ``commands``; no chain of imports (lazy ones included) leads from a folder back to itself
    through another."""
    circles = folder_circles(GRAPH)
    assert not circles, f"trainers folders that import each other: {circles}"


#: The order of the trainers folders docs/architecture.md states: each imports only later ones
#: (and ``compiled``, the layer below the trainers).
FOLDER_ORDER = ("cli", "distributed", "commands", "methods", "reports", "runner", "analysis")


def test_the_folder_order_the_architecture_states_holds():
    text = " ".join((ROOT / "docs" / "architecture.md").read_text().split())
    stated = (
        "`cli` -> `distributed` (`factorq sweep`) -> `commands` -> `methods` -> `reports` -> "
        "`runner` -> `analysis`"
    )
    assert stated in text
    backwards = sorted(
        f"{name} -> {target}"
        for name, targets in GRAPH.items()
        for target in targets
        if (a := trainers_folder(name)) in FOLDER_ORDER
        and (b := trainers_folder(target)) in FOLDER_ORDER
        and FOLDER_ORDER.index(b) < FOLDER_ORDER.index(a)
    )
    assert not backwards, f"imports against the stated order of the folders: {backwards}"


def command_of(module: str) -> str | None:
    """The command folder (``trainers/commands/<name>/``) a module sits in, None outside one."""
    parts = module.split(".")
    return parts[2] if parts[:2] == ["factorq_trainers", "commands"] and len(parts) > 3 else None


def test_command_of_names_the_folder():
    assert command_of("factorq_trainers.commands.paper.report") == "paper"
    assert command_of("factorq_trainers.commands") is None
    assert command_of("factorq_trainers.methods.dqn") is None


def test_no_command_imports_another_commands_folder():
    """What two commands share lives in ``methods/`` or ``runner/``, not in one of them."""
    crossing = sorted(
        f"{name} -> {target}"
        for name, targets in GRAPH.items()
        for target in targets
        if command_of(name) and command_of(target) and command_of(name) != command_of(target)
    )
    assert not crossing, f"commands importing another command's modules: {crossing}"


def test_every_command_folder_is_a_registered_command():
    from factorq_trainers.runner import registry

    folders = {p.parent.name for p in (ROOT / "trainers" / "commands").glob("*/__init__.py")}
    assert folders == set(registry.commands())
