"""envs: the FactoredGrid world of the paper, for torchrl and gymnasium.

Importing the package registers the gymnasium id ``"FactoredGrid-v0"``. The torchrl classes load
on first use, so code that needs only the pure world functions (``factorq_envs.world``, the fast
path) does not pay for importing torchrl and tensordict.
"""

import importlib
from typing import Any

import gymnasium

from factorq_envs.world import WorldConfig

_LAZY = {
    "FactoredGridEnv": "factorq_envs.grid",
    "SplitLocalReward": "factorq_envs.transforms",
    "ExperimentIndex": "factorq_envs.transforms",
    "RenderPixels": "factorq_envs.transforms",
}

__all__ = ["WorldConfig", *_LAZY]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'envs' has no attribute {name!r}")


# Episodes end inside the env (truncated at max_steps), so no TimeLimit wrapper is added.
if "FactoredGrid-v0" not in gymnasium.registry:
    gymnasium.register(id="FactoredGrid-v0", entry_point="factorq_envs.gym:FactoredGridGym")
