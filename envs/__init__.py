"""envs: the FactoredGrid world of the paper, for torchrl and gymnasium.

Importing the package registers the gymnasium id ``"FactoredGrid-v0"``. The torchrl classes and
the grid world load on first use, so code that needs only the obstacle regimes
(``factorq_envs.regimes``, torch-free: the reports) or the pure world functions
(``factorq_envs.grid_world``, the fast path) pays for nothing else.

The modules' former names (``factorq_envs.world``, ``grid``, ``gym``, ``minigrid``,
``minigrid_env``) still import, as deprecated aliases of the renamed modules (the same module
objects).
"""

import importlib
import importlib.abc
import importlib.machinery
import importlib.util
import sys
import types
import warnings
from collections.abc import Sequence
from typing import Any

import gymnasium

_LAZY = {
    "WorldConfig": "factorq_envs.grid_world",
    "FactoredGridEnv": "factorq_envs.torchrl_env",
    "SplitLocalReward": "factorq_envs.transforms",
    "ExperimentIndex": "factorq_envs.transforms",
    "RenderPixels": "factorq_envs.transforms",
}
#: former module name -> the module that holds it now
RENAMED = {
    "factorq_envs.world": "factorq_envs.grid_world",
    "factorq_envs.grid": "factorq_envs.torchrl_env",
    "factorq_envs.gym": "factorq_envs.gymnasium_env",
    "factorq_envs.minigrid": "factorq_envs.minigrid_adapter",
    "factorq_envs.minigrid_env": "factorq_envs.minigrid_torchrl",
}

__all__ = list(_LAZY)


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'envs' has no attribute {name!r}")


class _RenamedModules(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Imports a former module name as the renamed module itself, with a DeprecationWarning."""

    def find_spec(
        self,
        name: str,
        path: Sequence[str] | None = None,
        target: types.ModuleType | None = None,
    ) -> importlib.machinery.ModuleSpec | None:
        if name in RENAMED:
            return importlib.util.spec_from_loader(name, self)
        return None

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> types.ModuleType:
        warnings.warn(
            f"{spec.name} is deprecated: import {RENAMED[spec.name]}",
            DeprecationWarning,
            stacklevel=2,
        )
        module = importlib.import_module(RENAMED[spec.name])
        self._spec = module.__spec__  # importlib writes the alias's spec over it: put it back
        return module

    def exec_module(self, module: types.ModuleType) -> None:
        module.__spec__ = self._spec


if not any(isinstance(finder, _RenamedModules) for finder in sys.meta_path):
    sys.meta_path.insert(0, _RenamedModules())

# Episodes end inside the env (truncated at max_steps), so no TimeLimit wrapper is added.
if "FactoredGrid-v0" not in gymnasium.registry:
    gymnasium.register(
        id="FactoredGrid-v0", entry_point="factorq_envs.gymnasium_env:FactoredGridGym"
    )
