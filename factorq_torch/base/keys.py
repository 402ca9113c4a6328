"""The keys every layer shares, declared once (DESIGN section 3).

The world writes them, the agent reads them; neither imports the other, both import this file.
Shapes use ``B`` for the env's batch, ``K`` for the sensors the agent receives and ``A`` for the
actuators of the body.
"""

from __future__ import annotations

CELL = "cell"
"""``[*B]`` int64: the agent's cell, ``row * size + col``."""
HEADING = "heading"
"""``[*B]`` int64 in ``[0, 4)``: the direction the agent faces (0 north, 1 west, 2 south, 3 east);
written only by bodies that have a heading."""
SENSORS = "sensors"
"""``[*B, K]`` bool: every sensor as the agent receives it (layout, distractors, noise and
permutation applied). What the agents read."""
PROXIMITY = "proximity"
"""``[*B, 4]`` bool: the paper's four proximity bits (N, W, S, E neighbour blocked), noise-free and
allocentric, whatever the body; equal to ``SENSORS`` for the paper's body."""
BUMP = "bump"
"""``[*B, A]`` bool: the actuator whose last firing hit something."""
COLLISION = "collision"
"""``[*B, A]`` float32: the collision (local) reward vector of the last step."""
LOCAL_REWARD = "local_reward"
"""``[*B, A]`` float32: the local reward vector after ``SplitLocalReward``."""
ACTION = "action"
"""``[*B]`` int64 in ``[0, A)``: the chosen actuator."""
EXPLORATORY = "exploratory"
"""``[*B]`` bool: the epsilon branch chose the action."""
ACTION_VALUE = "action_value"
LOCAL_VALUE = "local_value"
COMBINED_VALUE = "combined_value"
EXPERIMENT = "experiment"
"""``[*B]`` int64 in ``[0, S)``: which experiment of the agent's batch a transition belongs to, so
tables, policies and losses take transitions of any batch shape (replay minibatches, ``[S, T]``
rollouts). Absent, it is ``arange(S)`` over a ``[S]`` batch (leading dimension ``S`` of a
``[S, *T]`` batch) and 0 when ``S = 1`` (``factorq_torch.tables.experiment_index``); written by
``factorq_envs.transforms.ExperimentIndex``."""

#: What every driver (the online collector, the compiled path, DQN) records per episode, in this
#: order: path length, collisions, collisions on greedy actions, task return.
EPISODE_METRICS = ("steps", "collisions", "greedy_collisions", "task_return")
