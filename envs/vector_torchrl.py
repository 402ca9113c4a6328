"""``VectorGridEnv``: ``S`` worlds of the two-drive body (``factorq_envs.vector_grid``) as one
torchrl env, its action a ``MultiCategorical`` vector ``[S, 2]`` (one value per actuator).

Keys: ``cell`` ``[S]`` int64, ``sensors`` ``[S, 4]`` bool, ``bump`` ``[S, 2]`` bool,
``collision`` ``[S, 2]`` float32 (the local reward vector, one entry per drive), ``reward``
``[S, 1]`` (the conventional one), ``task_reward`` ``[S, 1]`` (step + goal), ``done`` /
``terminated`` / ``truncated`` ``[S, 1]``. A ``_reset`` ``[S, 1]`` restarts only the marked
worlds. torchrl's ``check_env_specs`` passes (``tests/test_vector.py``).

Example:

    >>> env = VectorGridEnv(num_worlds=2, size=3, num_obstacles=0)
    >>> td = env.reset()
    >>> td["action"] = torch.tensor([[0, 2], [2, 2]])  # west + south, east + south
    >>> out = env.step(td)["next"]
    >>> out["collision"].tolist(), out["cell"].tolist()
    ([[-1.0, 0.0], [0.0, 0.0]], [3, 4])
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Binary, Bounded, Categorical, Composite, MultiCategorical, Unbounded
from torchrl.envs import EnvBase

from factorq_envs.torchrl_env import done_spec
from factorq_envs.vector_grid import (
    DRIVES,
    NVEC,
    VectorGridConfig,
    initial_vector_state,
    reset_vector_worlds,
    step_vector_worlds,
    vector_layout,
    vector_sensors,
)
from factorq_torch.base.rng import STREAM_WORLD, derive_keys
from factorq_torch.base.validation import check_int


class VectorGridEnv(EnvBase):
    """``num_worlds`` independent two-drive worlds (module docstring).

    Args:
        num_worlds: ``S``, the batch.
        size, num_obstacles, obstacle_period, max_steps, layout_seed: as ``VectorGridConfig``.
        seed: the worlds' streams (world ``i`` draws from key ``i`` of ``seed``).
    """

    def __init__(
        self,
        num_worlds: int = 1,
        size: int = 10,
        num_obstacles: int = 10,
        obstacle_period: int = 0,
        max_steps: int = 10_000,
        layout_seed: int = 0,
        seed: int = 0,
    ) -> None:
        check_int("num_worlds", num_worlds, 1)
        super().__init__(batch_size=torch.Size([num_worlds]))
        self.config = VectorGridConfig(size, num_obstacles, obstacle_period, max_steps, layout_seed)
        self.num_worlds = num_worlds
        self._layout = vector_layout(self.config) if obstacle_period == 0 else None
        self._state = initial_vector_state(num_worlds, self.config)
        self._set_seed(seed)
        batch = (num_worlds,)
        drives = (num_worlds, len(DRIVES))
        self.observation_spec = Composite(
            cell=Categorical(self.config.num_cells, shape=batch, dtype=torch.int64),
            sensors=Binary(n=4, shape=(num_worlds, 4), dtype=torch.bool),
            bump=Binary(n=len(DRIVES), shape=drives, dtype=torch.bool),
            collision=Bounded(low=-1.0, high=0.0, shape=drives, dtype=torch.float32),
            task_reward=Unbounded(shape=(num_worlds, 1), dtype=torch.float32),
            shape=batch,
        )
        self.action_spec = MultiCategorical(nvec=list(NVEC), shape=drives, dtype=torch.int64)
        self.reward_spec = Unbounded(shape=(num_worlds, 1), dtype=torch.float32)
        self.full_done_spec = done_spec(batch, None)

    def _set_seed(self, seed: int | None) -> None:
        self.world_keys = derive_keys(0 if seed is None else seed, STREAM_WORLD, self.num_worlds)
        self._state = initial_vector_state(self.num_worlds, self.config)

    def _output(self, outcome: Any | None) -> TensorDictBase:
        state, config = self._state, self.config
        zeros = torch.zeros(self.num_worlds, 1)
        flags = torch.zeros(self.num_worlds, 1, dtype=torch.bool)
        entries = {
            "cell": state.cell,
            "sensors": vector_sensors(state, config),
            "bump": state.bump,
            "collision": torch.zeros(self.num_worlds, len(DRIVES))
            if outcome is None
            else outcome.collision,
            "task_reward": zeros if outcome is None else outcome.task_reward.unsqueeze(1),
            "terminated": flags if outcome is None else outcome.terminated.unsqueeze(1),
            "truncated": flags.clone() if outcome is None else outcome.truncated.unsqueeze(1),
        }
        entries["done"] = entries["terminated"] | entries["truncated"]
        if outcome is not None:
            entries["reward"] = outcome.reward.unsqueeze(1)
        return TensorDict(entries, batch_size=self.batch_size)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDictBase:
        reset = None if tensordict is None else tensordict.get("_reset", None)
        mask = (
            torch.ones(self.num_worlds, dtype=torch.bool)
            if reset is None
            else reset.reshape(self.num_worlds)
        )
        self._state = reset_vector_worlds(
            self._state, mask, self.world_keys, self.config, self._layout
        )
        return self._output(None)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get("action")
        if action.shape != (self.num_worlds, len(DRIVES)):
            raise ValueError(
                f"the action vector has shape {tuple(action.shape)}: the two-drive world takes "
                f"[{self.num_worlds}, {len(DRIVES)}] (length {len(DRIVES)}: one value per "
                f"actuator, {', '.join(DRIVES)})"
            )
        self._state, outcome = step_vector_worlds(
            self._state, action.to(torch.int64), self.world_keys, self.config
        )
        return self._output(outcome)
