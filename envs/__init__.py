"""envs: the FactoredGrid world of the paper, for torchrl and gymnasium.

Importing the package registers the gymnasium id ``"FactoredGrid-v0"``.
"""

import gymnasium

from envs.grid import FactoredGridEnv
from envs.transforms import SplitLocalReward, proximity_pattern, qlearning_state
from envs.world import WorldConfig

__all__ = [
    "FactoredGridEnv",
    "SplitLocalReward",
    "WorldConfig",
    "proximity_pattern",
    "qlearning_state",
]

# Episodes end inside the env (truncated at max_steps), so no TimeLimit wrapper is added.
if "FactoredGrid-v0" not in gymnasium.registry:
    gymnasium.register(id="FactoredGrid-v0", entry_point="envs.gym:FactoredGridGym")
