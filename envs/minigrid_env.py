"""``MiniGridEnv``: ``S`` MiniGrid Dynamic-Obstacles worlds as one torchrl env (see
``factorq_envs.minigrid`` for the observation, the rewards and the collision semantics)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict
from torchrl.data import Binary, Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from factorq_envs.body import HEADING
from factorq_envs.grid import done_spec
from factorq_envs.minigrid import VIEW_SIZE, dependency, make_minigrid
from factorq_torch.base import keys
from factorq_torch.base.validation import check_int


class MiniGridEnv(EnvBase):
    """``S`` MiniGrid worlds as one torchrl env of ``batch_size=(S,)`` (module docstring).

    Args:
        size, semantics, layout, with_image: as ``make_minigrid``.
        seeds: one seed per world: its first reset is ``reset(seed=seeds[i])`` and every later
            episode continues MiniGrid's own generator, so a seed replays the same episodes under
            the same actions.
        device: where the tensors are returned.

    Keys: ``cell`` ``[S]``, ``heading`` ``[S]``, ``sensors`` ``[S, K]`` bool, ``bump`` ``[S, 3]``
    bool, ``collision`` ``[S, 3]`` float32, [``image`` ``[S, 7, 7, 3]`` uint8], ``reward``
    ``[S, 1]`` (MiniGrid's), ``done`` / ``terminated`` / ``truncated`` ``[S, 1]``. A ``_reset``
    ``[S, 1]`` restarts only the marked worlds; a ``_step`` ``[S, 1]`` steps only the marked ones.

    Example (not a doctest: MiniGrid is an optional extra)::

        env = MiniGridEnv(5, seeds=[0, 1])
        td = env.reset()  # td["sensors"] [2, 3] bool; td["heading"] [3, 3] (facing east)
    """

    def __init__(
        self,
        size: int,
        semantics: str = "minigrid",
        *,
        layout: str = "front3",
        with_image: bool = False,
        seeds: Sequence[int] = (0,),
        device: torch.device | str | None = None,
    ) -> None:
        seeds = [check_int("seeds", seed, 0) for seed in seeds]
        if not seeds:
            raise ValueError("seeds is empty: give one seed per world")
        super().__init__(device=device, batch_size=(len(seeds),))
        self.envs = [
            make_minigrid(size, semantics, layout=layout, with_image=with_image) for _ in seeds
        ]
        self.size, self.semantics, self.layout = size, semantics, layout
        self.with_image = bool(with_image)
        self.seeds = seeds
        self._started = [False] * len(seeds)
        first = self.envs[0]
        self.num_cells, self.num_sensors = first.num_cells, first.num_sensors
        self.num_actions = first.num_actions
        self.max_steps: int = first.unwrapped.max_steps  # type: ignore[attr-defined]  # MiniGridEnv's
        self._last: list[dict[str, Any]] = [first.observation_space.sample() for _ in seeds]
        self._make_specs()

    @property
    def dependency(self) -> torch.Tensor:
        """The ground truth ``[3, K]`` (``dependency``); an agent gets it only as the oracle."""
        return dependency(self.layout)

    def _make_specs(self) -> None:
        batch, device = self.batch_size, self.device
        actuators = (*batch, self.num_actions)
        entries = {
            keys.CELL: Categorical(self.num_cells, shape=batch, dtype=torch.int64, device=device),
            keys.HEADING: Categorical(
                HEADING.num_headings, shape=batch, dtype=torch.int64, device=device
            ),
            keys.SENSORS: Binary(
                n=self.num_sensors,
                shape=(*batch, self.num_sensors),
                dtype=torch.bool,
                device=device,
            ),
            keys.BUMP: Binary(n=self.num_actions, shape=actuators, dtype=torch.bool, device=device),
            keys.COLLISION: Bounded(
                low=-1.0, high=0.0, shape=actuators, dtype=torch.float32, device=device
            ),
        }
        if self.with_image:
            entries["image"] = Bounded(
                low=0,
                high=255,
                shape=(*batch, VIEW_SIZE, VIEW_SIZE, 3),
                dtype=torch.uint8,
                device=device,
            )
        self.observation_spec = Composite(entries, shape=batch, device=device)
        self.action_spec = Categorical(
            self.num_actions, shape=batch, dtype=torch.int64, device=device
        )
        self.reward_spec = Unbounded(shape=(*batch, 1), dtype=torch.float32, device=device)
        self.full_done_spec = done_spec(batch, device)

    def _set_seed(self, seed: int | None) -> None:
        """Seed world ``i`` with ``seed + i`` at its next reset."""
        seed = 0 if seed is None else check_int("seed", seed, 0)
        self.seeds = [seed + i for i in range(len(self.envs))]
        self._started = [False] * len(self.envs)

    def _mask(self, tensordict, key: str) -> list[bool]:
        flags = None if tensordict is None else tensordict.get(key, None)
        if flags is None:
            return [True] * len(self.envs)
        return flags.reshape(-1).tolist()

    def _reset(self, tensordict=None, **kwargs):
        for i, go in enumerate(self._mask(tensordict, "_reset")):
            if go:
                seed = None if self._started[i] else self.seeds[i]
                self._last[i], _ = self.envs[i].reset(seed=seed)
                self._started[i] = True
        false = [False] * len(self.envs)
        return self._output(None, false, false)

    def _step(self, tensordict):
        action = tensordict.get("action").reshape(-1).tolist()
        stepping = self._mask(tensordict, "_step")
        count = len(self.envs)
        rewards, terminated, truncated = [0.0] * count, [False] * count, [False] * count
        for i in range(count):
            if not stepping[i]:
                continue
            obs, rewards[i], terminated[i], truncated[i], _ = self.envs[i].step(action[i])
            self._last[i] = obs
        return self._output(rewards, terminated, truncated)

    def _output(self, rewards, terminated, truncated):
        batch, device = self.batch_size, self.device
        last = self._last

        def stack(name, dtype):
            return torch.as_tensor(np.stack([obs[name] for obs in last]), dtype=dtype)

        entries = {
            keys.CELL: torch.tensor([obs[keys.CELL] for obs in last], dtype=torch.int64),
            keys.HEADING: torch.tensor([obs[keys.HEADING] for obs in last], dtype=torch.int64),
            keys.SENSORS: stack(keys.SENSORS, torch.bool),
            keys.BUMP: stack(keys.BUMP, torch.bool),
            keys.COLLISION: stack(keys.COLLISION, torch.float32),
        }
        if self.with_image:
            entries["image"] = stack("image", torch.uint8)
        term = torch.tensor(terminated, dtype=torch.bool).unsqueeze(-1)
        trunc = torch.tensor(truncated, dtype=torch.bool).unsqueeze(-1)
        entries.update(terminated=term, truncated=trunc, done=term | trunc)
        if rewards is not None:
            entries["reward"] = torch.tensor(rewards, dtype=torch.float32).unsqueeze(-1)
        return TensorDict(entries, batch_size=batch).to(device)

    def close(self, *, raise_if_closed: bool = True) -> None:
        for env in self.envs:
            env.close()
        super().close(raise_if_closed=raise_if_closed)
