"""The import layers (docs/architecture.md): every module imports only its own layer or below.

base (``factorq_torch.base``) -> worlds (``envs``) -> agent (the rest of ``factorq_torch``) ->
compiled path (``trainers.fast``) -> trainers (``trainers``) -> CLI (``trainers.cli``). Imports
inside functions count too, and no two modules may import each other through any chain.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("factorq_torch", "envs", "trainers")
LAYERS = ("base", "worlds", "agent", "compiled", "trainers", "cli")


def layer_of(module: str) -> str:
    """The layer a project module belongs to."""
    if module == "factorq_torch.base" or module.startswith("factorq_torch.base."):
        return "base"
    if module.split(".")[0] == "envs":
        return "worlds"
    if module.split(".")[0] == "factorq_torch":
        return "agent"
    if module == "trainers.fast":
        return "compiled"
    if module == "trainers.cli":
        return "cli"
    return "trainers"


def project_modules() -> dict[str, Path]:
    """Every module of the three packages, by dotted name."""
    modules = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
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
        "envs.world",
        "factorq_torch.functional",
        "trainers.fast",
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
