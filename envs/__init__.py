"""factorq_envs (the folder ``envs/``): the FactoredGrid world of the paper, for torchrl and
gymnasium.

Importing the package registers the gymnasium ids ``"FactoredGrid-v0"`` and ``"PayingGrid-v0"``
(``factorq_envs.paying_grid``: items that pay a positive local reward). The torchrl classes and
the grid world load on first use, so code that needs only the obstacle regimes
(``factorq_envs.regimes``, torch-free: the reports) or the pure world functions
(``factorq_envs.grid_world``, the fast path) pays for nothing else.
"""

import importlib
from typing import Any

import gymnasium

_LAZY = {
    "WorldConfig": "factorq_envs.grid_world",
    "FactoredGridEnv": "factorq_envs.torchrl_env",
    "SplitLocalReward": "factorq_envs.transforms",
    "ExperimentIndex": "factorq_envs.transforms",
    "RenderPixels": "factorq_envs.transforms",
}
__all__ = list(_LAZY)


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'factorq_envs' has no attribute {name!r}")


# Episodes end inside the env (truncated at max_steps), so no TimeLimit wrapper is added.
if "FactoredGrid-v0" not in gymnasium.registry:
    gymnasium.register(
        id="FactoredGrid-v0", entry_point="factorq_envs.gymnasium_env:FactoredGridGym"
    )
if "PayingGrid-v0" not in gymnasium.registry:  # the grid that pays (factorq_envs.paying_grid)
    gymnasium.register(id="PayingGrid-v0", entry_point="factorq_envs.paying_grid:paying_gym")
