"""``FactoredGridEnv``: ``S`` independent worlds as one batched torchrl env.

The world's rules live in a world (``factorq_envs.protocol.World``:
``factorq_envs.grid_world.FactoredGrid`` by default, any other world given as ``world=``); this
module only validates arguments, reads the specs from the world's config, holds the state of the
worlds in tensors and moves it in and out of TensorDicts.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Binary, Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from factorq_envs.grid_world import FactoredGrid, WorldConfig, static_layout, where_rows
from factorq_envs.protocol import check_world, optional_method
from factorq_torch.base import keys
from factorq_torch.base.rng import STREAM_WORLD, derive_keys
from factorq_torch.base.validation import check_device, check_seed, is_int

_INTEGER_DTYPES = (torch.int8, torch.int16, torch.int32, torch.int64, torch.uint8)


def _check_batch_size(batch_size: Any) -> torch.Size:
    """``None`` -> ``()``, an int ``n`` -> ``(n,)``, a sequence of positive ints as it is."""
    if batch_size is None:
        return torch.Size(())
    if is_int(batch_size):
        batch_size = (batch_size,)
    if not isinstance(batch_size, Sequence) or not all(is_int(d) for d in batch_size):
        raise TypeError(
            f"batch_size must be None, an int or a sequence of ints (e.g. (64,)), got "
            f"{batch_size!r} ({type(batch_size).__name__})"
        )
    if any(d < 1 for d in batch_size):
        raise ValueError(
            f"batch_size={tuple(batch_size)} is out of range: every dimension must be >= 1"
        )
    return torch.Size(batch_size)


def _check_periods(obstacle_period: Any, num_worlds: int) -> tuple[torch.Tensor, int]:
    """The period of every world ``[S]`` int64 and the one to record in the ``WorldConfig``.

    ``obstacle_period`` is an int (every world) or a sequence / 1-D integer tensor of length
    ``S`` (one per world, e.g. the paper's three worlds side by side in one batch).
    """
    if is_int(obstacle_period):
        if obstacle_period < 0:
            raise ValueError(
                f"obstacle_period={obstacle_period} is out of range: must be >= 0 "
                f"(0 static, k > 0 moving)"
            )
        return torch.full((num_worlds,), obstacle_period, dtype=torch.int64), obstacle_period
    if isinstance(obstacle_period, torch.Tensor):
        if obstacle_period.dtype not in _INTEGER_DTYPES or obstacle_period.dim() != 1:
            raise TypeError(
                f"obstacle_period as a tensor must be 1-D with an integer dtype, got shape "
                f"{tuple(obstacle_period.shape)} and dtype {obstacle_period.dtype}"
            )
        values = obstacle_period.tolist()
    elif isinstance(obstacle_period, Sequence) and all(is_int(p) for p in obstacle_period):
        values = list(obstacle_period)
    else:
        raise TypeError(
            f"obstacle_period must be an int or a sequence of ints (one per world), got "
            f"{obstacle_period!r} ({type(obstacle_period).__name__})"
        )
    if len(values) != num_worlds:
        raise ValueError(
            f"obstacle_period has {len(values)} entries: a sequence must hold one period per "
            f"world, {num_worlds} for this batch_size"
        )
    for index, period in enumerate(values):
        if period < 0:
            raise ValueError(
                f"obstacle_period[{index}]={period} is out of range: must be >= 0 "
                f"(0 static, k > 0 moving)"
            )
    # The config records one period only when the batch shares it; ``periods`` is the truth.
    shared = values[0] if len(set(values)) == 1 else 0
    return torch.tensor(values, dtype=torch.int64), shared


#: The arguments that describe the default world (a ``FactoredGrid``), with their defaults: with
#: ``world=`` they belong to that world's config and must be left out.
GRID_ARGUMENTS = {
    "size": 10,
    "num_obstacles": 10,
    "max_steps": 10_000,
    "layout_seed": 0,
    "body": "translate",
    "sensors": "cross",
    "num_distractors": 0,
    "sensor_permutation": None,
    "sensor_noise": 0.0,
    "actuator_noise": 0.0,
}


def check_no_grid_arguments(given: dict[str, Any], world: object) -> None:
    """Refuse grid arguments beside ``world=``: one ValueError naming them. ``given``: the
    constructor's arguments by name (its ``locals()``); only ``GRID_ARGUMENTS`` are read."""

    def differs(value: object, default: object) -> bool:
        if default is None or value is None:
            return value is not default
        try:
            return bool(value != default)
        except (TypeError, RuntimeError):
            return True

    extra = [name for name, default in GRID_ARGUMENTS.items() if differs(given[name], default)]
    if extra:
        raise ValueError(
            f"{', '.join(f'{name}={given[name]!r}' for name in extra)} describe the default "
            f"FactoredGrid: with world={type(world).__name__}(...) set them in the world's "
            f"config instead"
        )


def _keep_rows(stepping: torch.Tensor, new: torch.Tensor, kept: torch.Tensor) -> torch.Tensor:
    """``new`` in the worlds that stepped, ``kept`` in the others (``stepping`` ``[S]``): a bool
    map ``[S, N]`` by whole words (``world.where_rows``), anything else by ``torch.where``."""
    if new.dim() == 2 and new.dtype == torch.bool:
        return where_rows(stepping, new, kept)
    return torch.where(stepping.view(-1, *([1] * (new.dim() - 1))), new, kept)


def done_spec(batch: tuple[int, ...], device: torch.device | str | None) -> Composite:
    """The ``done`` / ``terminated`` / ``truncated`` flags ``[*batch, 1]`` bool of a batched env."""
    flag = Categorical(2, shape=(*batch, 1), dtype=torch.bool, device=device)
    return Composite(
        done=flag.clone(),
        terminated=flag.clone(),
        truncated=flag.clone(),
        shape=batch,
        device=device,
    )


class FactoredGridEnv(EnvBase):
    """``S`` independent worlds (SPEC sections 1-2), one per experiment of a batch: the paper's
    FactoredGrid by default, or any ``factorq_envs.protocol.World`` given as ``world``.

    Keyword Args:
        world: a ``WorldConfig`` (the grid's whole config: the same env as its fields given as
            the keywords below), or an ``factorq_envs.protocol.World`` (e.g.
            ``factorq_envs.corridor.Corridor(...)``, or a ``FactoredGrid``) whose rules, specs and
            body the env uses; ``None`` builds a ``FactoredGrid`` from the arguments below (size
            ... actuator_noise). With a world, those arguments are left out (refused, named).
        size: side of the square grid (>= 2).
        num_obstacles: single-cell obstacles, in ``[0, size**2 - 3]`` (at most ``(size - 1)**2``
            when a world is static, so that a path can exist).
        obstacle_period: 0 static, 10 semi-dynamic, 1 dynamic (scatter after every k-th action);
            an int for every world, or a sequence / 1-D tensor of one period per world.
        max_steps: actions after which an episode is truncated (>= 1).
        layout_seed: seed of the static layout, shared by every static world of the batch.
        batch_size: ``None`` / ``()`` for one world, ``(S,)`` (or any shape) for ``S`` worlds.
        device: where the state and the TensorDicts live (``None``: CPU tensors).
        seed: seed of the worlds' random streams; ``None`` means 0.
        experiment_offset: index of this batch's first world among all experiments: world ``i``
            gets the key of experiment ``experiment_offset + i``, so a batch of 1 at offset ``i``
            replays world ``i`` of a larger batch exactly.
        world_keys: int64 ``[S]``, the worlds' stream keys given outright (a trainer's keys,
            e.g. ``3 i + w`` of a mixed batch, that no ``seed`` / ``experiment_offset`` range
            describes); ``set_seed`` replaces them.
        body, sensors, num_distractors, sensor_permutation, sensor_noise, actuator_noise: the
            agent's body and sensors, as ``WorldConfig`` (defaults: the paper's). ``dependency``
            is the resulting ground truth, bool ``[actuators, sensors]``.

    Keys (``B`` = ``batch_size``, ``N = size**2``, in general ``config.num_cells``; ``K``,
    ``A`` and the headings are read from the world's config):

    - observation: ``cell`` ``[*B]`` int64 in ``[0, N)``; ``sensors`` ``[*B, K]`` bool, every
      sensor as the agent receives it (what the agents read; for the paper's body equal to
      ``proximity``); ``heading`` ``[*B]`` int64 (bodies with a heading only); ``proximity``
      ``[*B, 4]`` bool, the noise-free N, W, S, E neighbours (the grid's
      ``extra_observations``; another world publishes its own or none); ``bump`` ``[*B, A]`` bool;
      ``collision`` ``[*B, A]`` float32, the collision reward vector of the last action (-1 on
      the actuator that bumped; zeros after a reset), so that ``SplitLocalReward`` splits the
      reward without recomputing it (keys: ``factorq_torch.base.keys``);
    - action: ``action`` ``[*B]`` int64 in ``[0, A)`` (the paper's body: N, W, S, E);
    - reward: ``reward`` ``[*B, 1]`` float32, the conventional step + goal + sum(collision);
    - done: ``done``, ``terminated``, ``truncated`` ``[*B, 1]`` bool.

    The rules are called through ``world`` (an ``factorq_envs.protocol.World``). State (read and
    written by the fast path and checkpoints; worlds flattened to ``S``):
    ``world_state`` (the world's state, leading dim ``S``; ``S = 1`` when ``batch_size == ()``),
    ``world_keys`` ``[S]`` int64, ``periods`` ``[S]`` int64 (handed to the world's ``reset`` and
    ``step``), ``static_obstacles`` ``[N]`` bool (default world only), ``world_seed`` (the seed
    the keys came from), ``config`` (the world's config; a ``WorldConfig``'s
    ``obstacle_period`` is meaningful only when the batch shares one period).
    Randomness comes only from the worlds' counter streams, never from the global RNG.

    Example:
        >>> env = FactoredGridEnv(size=4, num_obstacles=2, obstacle_period=1, batch_size=(3,))
        >>> td = env.reset()
        >>> td["cell"], td["proximity"].shape
        (tensor([0, 0, 0]), torch.Size([3, 4]))
        >>> td["action"] = torch.tensor([0, 1, 2])  # north and west hit the wall
        >>> td = env.step(td)
        >>> td["next", "bump"][:, :2]
        tensor([[ True, False],
                [False,  True],
                [False, False]])
        >>> td["next", "reward"][:2].flatten()
        tensor([-2., -2.])
    """

    #: ``reset(td, restarts_terminated=True)`` is understood: the caller vouches that every world
    #: in ``"_reset"`` terminated at the last step (checked on the device), so a world that
    #: offers ``step_keeping_draws`` (the grid) restarts from the scatter that step drew, the
    #: same numbers without a second scatter (``OnlineCollector`` passes it when its counts
    #: show no truncated episode among the restarts).
    accepts_restarts_terminated = True
    #: ``reset(td, reset_mask=mask)`` is understood: the worlds to restart given as a keyword
    #: (bool ``[*B]``) instead of a ``"_reset"`` entry. The env's reset then reports every world,
    #: those left alone as the last step reported them (observation from the same state; that
    #: step's collision and done flags), so torchrl updates the tensordict with it instead of
    #: merging it entry by entry under the mask and checking the done flags by boolean indexing:
    #: the same entries (tested, every transition of a collector either way), about 0.2 ms less
    #: per partial reset at ``S = 300`` (``OnlineCollector`` uses it). Without a step since the
    #: last reset or state change, the worlds left alone report their state's status and no
    #: collision. Hence ``allow_done_after_reset``: a world left alone may be done (an episode
    #: that ended where the experiment finished); a restarted one never is (the start is not
    #: the goal, and ``max_steps >= 1``).
    accepts_reset_mask = True

    def __init__(
        self,
        *,
        size: int = 10,
        num_obstacles: int = 10,
        obstacle_period: int | Sequence[int] | torch.Tensor = 0,
        max_steps: int = 10_000,
        layout_seed: int = 0,
        batch_size: Sequence[int] | int | None = None,
        device: torch.device | str | None = None,
        seed: int | None = None,
        experiment_offset: int = 0,
        world_keys: torch.Tensor | None = None,
        body: str = "translate",
        sensors: str = "cross",
        num_distractors: int = 0,
        sensor_permutation: Sequence[int] | int | None = None,
        sensor_noise: float = 0.0,
        actuator_noise: float = 0.0,
        world: Any = None,  # a WorldConfig (the grid, whole) or a factorq_envs.protocol.World
    ) -> None:
        batch_size = _check_batch_size(batch_size)
        device = check_device("device", device)
        if not is_int(experiment_offset):
            raise TypeError(f"experiment_offset must be an int >= 0, got {experiment_offset!r}")
        if experiment_offset < 0:
            raise ValueError(f"experiment_offset={experiment_offset} is out of range: must be >= 0")
        num_worlds = math.prod(batch_size)
        periods, shared_period = _check_periods(obstacle_period, num_worlds)
        if isinstance(world, WorldConfig):  # the grid's config, passed whole
            check_no_grid_arguments(locals(), world)
            config = dataclasses.replace(world, obstacle_period=shared_period)
        elif world is not None:
            check_world(world)
            check_no_grid_arguments(locals(), world)  # the grid arguments, read by name
            super().__init__(device=device, batch_size=batch_size, allow_done_after_reset=True)
            self._setup(world, num_worlds, experiment_offset, periods, seed, world_keys)
            return
        else:
            # WorldConfig validates size, num_obstacles, max_steps and layout_seed with messages
            # that name the argument, its value and the allowed range.
            config = WorldConfig(
                size=size,
                num_obstacles=num_obstacles,
                obstacle_period=shared_period,
                max_steps=max_steps,
                layout_seed=layout_seed,
                body=body,
                sensors=sensors,
                num_distractors=num_distractors,
                sensor_permutation=sensor_permutation,
                sensor_noise=sensor_noise,
                actuator_noise=actuator_noise,
            )
        super().__init__(device=device, batch_size=batch_size, allow_done_after_reset=True)
        # Only static worlds need the layout: drawing it for a moving-only batch would waste
        # time and could refuse obstacle counts that moving worlds allow.
        if bool((periods == 0).any()):
            self.static_obstacles = static_layout(config).to(self.device)
        else:
            self.static_obstacles = torch.zeros(
                config.num_cells, dtype=torch.bool, device=self.device
            )
        world = FactoredGrid(config, self.static_obstacles)
        self._setup(world, num_worlds, experiment_offset, periods, seed, world_keys)

    def _setup(
        self,
        world: Any,
        num_worlds: int,
        experiment_offset: int,
        periods: torch.Tensor,
        seed: int | None,
        world_keys: torch.Tensor | None,
    ) -> None:
        """Everything after the world is known: state, specs, keys."""
        device = self.device
        # The world behind the factorq_envs.protocol.World interface: every rule goes through it.
        self.world = world
        self.config = world.config
        self.num_worlds = num_worlds
        self.experiment_offset = experiment_offset
        self.periods = periods.to(device)
        if callable(getattr(world, "to", None)):
            world.to(device)
        self._world_state = self.world.initial_state(num_worlds, device)
        self._kept_draws: tuple | None = None  # (state, draws, terminated) of the last step
        self._kept_output: tuple | None = None  # (state, collision, terminated, truncated)
        self._started = False  # set by the first reset (or by assigning world_state)
        self._make_specs()
        self._set_seed(seed)
        if world_keys is not None:
            if (
                not isinstance(world_keys, torch.Tensor)
                or world_keys.dtype != torch.int64
                or tuple(world_keys.shape) != (num_worlds,)
            ):
                raise ValueError(
                    f"world_keys must be an int64 tensor of shape [{num_worlds}] (one key per "
                    f"world), got {world_keys!r:.80}"
                )
            self.world_keys = world_keys.to(self.device)

    @property
    def world_state(self) -> Any:  # the world's NamedTuple
        """The worlds' state (the world's ``NamedTuple``, leading dim ``S``). Assigning it (a
        restored checkpoint, the fast path) counts as a reset: the env may be stepped from it."""
        return self._world_state

    @world_state.setter
    def world_state(self, value: Any) -> None:
        self._world_state = value
        self._started = True

    @property
    def dependency(self) -> torch.Tensor:
        """Ground truth bool ``[actuators, sensors]``: which of the sensors the agent receives
        decide each actuator's local reward (the world's ``dependency``). Tests and experiments
        read it; an agent gets it only in an explicit oracle mode."""
        return self.world.dependency.to(self.device)

    def _make_specs(self) -> None:
        batch, device, config = self.batch_size, self.device, self.config
        actuators = (*batch, config.num_actuators)
        # the collision entry's bounds: the world's local_reward_range (a world that pays),
        # else the grid's -1 / 0
        low, high = getattr(config, "local_reward_range", (-1.0, 0.0))
        entries = {
            keys.CELL: Categorical(config.num_cells, shape=batch, dtype=torch.int64, device=device),
            keys.SENSORS: Binary(
                n=config.num_sensors,
                shape=(*batch, config.num_sensors),
                dtype=torch.bool,
                device=device,
            ),
            keys.BUMP: Binary(
                n=config.num_actuators, shape=actuators, dtype=torch.bool, device=device
            ),
            keys.COLLISION: Bounded(
                low=low, high=high, shape=actuators, dtype=torch.float32, device=device
            ),
        }
        if config.num_headings > 1:
            entries[keys.HEADING] = Categorical(
                config.num_headings, shape=batch, dtype=torch.int64, device=device
            )
        # The world's extra entries (the grid's proximity): their widths read off one world.
        for name, value in self._extra_observations(self.world.initial_state(1), None).items():
            count = value.shape[-1]
            entries[name] = Binary(n=count, shape=(*batch, count), dtype=torch.bool, device=device)
        self.observation_spec = Composite(entries, shape=batch, device=device)
        self.action_spec = Categorical(
            config.num_actuators, shape=batch, dtype=torch.int64, device=device
        )
        self.reward_spec = Unbounded(shape=(*batch, 1), dtype=torch.float32, device=device)
        self.full_done_spec = done_spec(batch, device)

    # -- seeding -------------------------------------------------------------------------------

    def _extra_observations(
        self, state: Any, sensors: torch.Tensor | None
    ) -> dict[str, torch.Tensor]:
        """The world's optional extra observation entries ``{key: [S, n] bool}`` (none when it
        has no ``extra_observations``); ``sensors`` None: the world observes them itself."""
        extra = getattr(self.world, "extra_observations", None)
        if extra is None:
            return {}
        if sensors is None:
            sensors = self.world.observe(state, torch.zeros(state.cell.shape[0], dtype=torch.int64))
        return extra(state, sensors)

    def _set_seed(self, seed: int | None) -> None:
        """Re-derive the worlds' keys from ``seed`` (``None`` means 0) and rewind their streams."""
        if seed is None:
            seed = 0
        if not is_int(seed):
            raise TypeError(f"seed must be an int or None, got {seed!r} ({type(seed).__name__})")
        check_seed("seed", seed)  # [0, INT64_MAX]: 2**80 would wrap to 0 in the 64-bit keys
        self.world_seed = seed
        self.world_keys = derive_keys(
            seed, STREAM_WORLD, self.num_worlds, self.experiment_offset
        ).to(self.device)
        # A new seed starts its streams at the beginning, so set_seed + reset replays exactly.
        self._world_state = self.world.rewind(self._world_state)

    # -- reset and step ------------------------------------------------------------------------

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDictBase:
        """Start new episodes where ``"_reset"`` ``[*B, 1]`` is True, or where the keyword
        ``reset_mask`` ``[*B]`` is (``accepts_reset_mask``); everywhere without either."""
        reset = None if tensordict is None else tensordict.get("_reset", None)
        keyword = reset is None and kwargs.get("reset_mask") is not None
        if keyword:
            reset = kwargs["reset_mask"]
        if reset is None:
            mask = torch.ones(self.num_worlds, dtype=torch.bool, device=self.device)
        else:
            if (
                not isinstance(reset, torch.Tensor)
                or reset.dtype != torch.bool
                or reset.numel() != self.num_worlds
            ):
                raise ValueError(
                    f"reset_mask / '_reset' must be a bool tensor of batch_size "
                    f"{list(self.batch_size)} (one flag per world), got {reset!r:.80}"
                )
            mask = reset.reshape(self.num_worlds)  # [S]
        kept = self._kept_draws
        self._kept_draws = None
        previous = self._world_state
        if kwargs.get("restarts_terminated") and kept is not None and kept[0] is self._world_state:
            # Every world restarting here terminated at the last step (the caller says so,
            # checked on the device): its reset draws what that step drew (World docs).
            _, draws, terminated = kept
            message = "reset(restarts_terminated=True) restarts a world that did not terminate"
            torch._assert_async(~(mask & ~terminated).any(), message)
            state = self.world.reset(
                self.world_state, mask, self.world_keys, self.periods, draws=draws
            )
        else:
            state = self.world.reset(self.world_state, mask, self.world_keys, self.periods)
        self.world_state = state
        state = self.world_state
        last = self._kept_output
        self._kept_output = None
        if keyword and last is not None and last[0] is previous:
            # reset_mask: torchrl updates the caller's tensordict with all of this, so the worlds
            # left alone report what the last step reported (the merge under "_reset" keeps
            # exactly that): its collision and done flags (those of a world that did not step,
            # a finished experiment, are zeros); their observation comes from the same state.
            _, last_collision, last_terminated, last_truncated = last
            collision = last_collision.masked_fill(mask.unsqueeze(1), 0.0)
            alone = ~mask  # the worlds left alone
            terminated, truncated = last_terminated & alone, last_truncated & alone
        else:
            # Worlds left alone report their true status (a finished one stays done).
            terminated = state.cell == self.config.goal_cell
            truncated = ~terminated & (state.episode_step >= self.config.max_steps)
            collision = torch.zeros(self.num_worlds, self.config.num_actuators, device=self.device)
        return self._output(state, collision, terminated, truncated, reward=None)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        """One action per world: ``action`` ``[*B]`` -> the ``"next"`` TensorDict."""
        action = self._check_action(tensordict.get("action", None))  # [S]
        if not self._started:
            raise RuntimeError(
                "FactoredGridEnv.step was called before any reset: the worlds hold no episode "
                "yet (no obstacles, no position); call env.reset() first"
            )
        old = self.world_state
        keeping = getattr(self.world, "step_keeping_draws", None)
        draws = None
        if keeping is None:
            state, outcome = self.world.step(old, action, self.world_keys, self.periods)
        else:
            state, outcome, draws = keeping(old, action, self.world_keys, self.periods)
        reward, collision = outcome.reward, outcome.collision  # [S], [S, A]
        terminated, truncated = outcome.terminated, outcome.truncated  # [S]
        partial = tensordict.get("_step", None)
        if partial is not None:
            # torchrl's rollout steps only the worlds still running: the others keep their state.
            stepping = partial.reshape(self.num_worlds)  # [S]
            state = type(state)(
                *(_keep_rows(stepping, new, kept) for new, kept in zip(state, old, strict=True))
            )
            reward = torch.where(stepping, reward, 0.0)
            collision = torch.where(stepping.unsqueeze(1), collision, 0.0)
            terminated, truncated = terminated & stepping, truncated & stepping
        self.world_state = state
        # What a reset right after this step may reuse (reset(restarts_terminated=True)), and
        # what it reports for the worlds it leaves alone (reset(reset_mask=...)).
        self._kept_draws = None if draws is None else (state, draws, terminated)
        self._kept_output = (state, collision, terminated, truncated)
        return self._output(state, collision, terminated, truncated, reward)

    def _check_action(self, action: torch.Tensor | None) -> torch.Tensor:
        """The action as int64 ``[S]``; a missing, misshapen or out-of-range one raises here."""
        if action is None:
            raise ValueError("action is missing: step needs an 'action' entry")
        if action.dtype not in _INTEGER_DTYPES:
            raise TypeError(
                f"action must be an integer tensor (int64, values in "
                f"[0, {self.config.num_actuators - 1}]), "
                f"got dtype {action.dtype}"
            )
        if action.shape != self.batch_size:
            raise ValueError(
                f"action has shape {tuple(action.shape)}: must be batch_size "
                f"{tuple(self.batch_size)}, one action in [0, {self.config.num_actuators - 1}] "
                f"per world"
            )
        action = action.reshape(self.num_worlds).to(torch.int64)
        count = self.config.num_actuators
        if count & (count - 1) == 0:  # a power of two: outside [0, count) iff a bit of -count
            outside = (action & -count).any()  # is set (two's complement: negatives too)
        else:
            outside = ((action < 0) | (action >= count)).any()
        if action.device.type != "cpu":  # checked on the device: the step never waits for it
            message = f"action out of range: must be in [0, {count})"
            torch._assert_async(~outside, message)
            return action
        if bool(outside):
            out_of_range = (action < 0) | (action >= count)
            bad = action[out_of_range][0].item()
            names = ", ".join(f"{i} {name}" for i, name in enumerate(self.config.actuator_names))
            raise ValueError(f"action={bad} is out of range: must be in [0, {count - 1}] ({names})")
        return action

    def _output(
        self,
        state: Any,
        collision: torch.Tensor,
        terminated: torch.Tensor,
        truncated: torch.Tensor,
        reward: torch.Tensor | None,
    ) -> TensorDictBase:
        """The observation, reward and done entries of ``S`` worlds, shaped to ``batch_size``."""
        batch, config = self.batch_size, self.config
        actuators = (*batch, config.num_actuators)
        flag = (*batch, 1)
        sensors = self.world.observe(state, self.world_keys)  # [S, K]
        entries = {
            keys.CELL: state.cell.reshape(batch),
            keys.SENSORS: sensors.reshape(*batch, config.num_sensors),
            keys.BUMP: state.bump.reshape(actuators),
            keys.COLLISION: collision.reshape(actuators),
            "terminated": terminated.reshape(flag),
            "truncated": truncated.reshape(flag),
            "done": (terminated | truncated).reshape(flag),
        }
        if config.num_headings > 1:
            entries[keys.HEADING] = state.heading.reshape(batch)
        for name, value in self._extra_observations(state, sensors).items():
            entries[name] = value.reshape(*batch, value.shape[-1])
        if reward is not None:
            entries["reward"] = reward.reshape(flag)
        # The entries are built right here with the right shapes: skip TensorDict's checks,
        # which cost ~10x the construction itself on every step (DESIGN section 6).
        return TensorDict._new_unsafe(entries, batch_size=batch, device=self.device)

    def to(self, device: torch.device | str) -> FactoredGridEnv:
        """Move the specs (torchrl) and the worlds' state tensors to ``device``."""
        super().to(device)
        device = self.device
        state = self._world_state
        self._world_state = type(state)(*(tensor.to(device) for tensor in state))
        self.world_keys = self.world_keys.to(device)
        self.periods = self.periods.to(device)
        if hasattr(self, "static_obstacles"):
            self.static_obstacles = self.static_obstacles.to(device)
        if callable(getattr(self.world, "to", None)):
            self.world.to(device)
        return self

    # -- inspection ----------------------------------------------------------------------------

    def obstacle_map(self) -> torch.Tensor:
        """The current obstacles, a bool copy ``[*B, size, size]`` (``[r, c]`` = row r, col c;
        the world's ``obstacle_map``, shaped to the batch)."""
        obstacles = optional_method(self.world, "obstacle_map")(self.world_state)  # [S, ...]
        return obstacles.reshape(*self.batch_size, *obstacles.shape[1:])

    def render_rgb(self, index: int = 0) -> np.ndarray:
        """World ``index`` (flat, in ``[0, S)``) as an image ``uint8 [H, W, 3]``: walls, obstacles,
        the agent with its heading, the goal, the last collision (``factorq_envs.render``; the same
        picture as the gymnasium env's ``rgb_array``). ``RenderPixels`` writes it as ``pixels``."""
        if not is_int(index) or not 0 <= index < self.num_worlds:
            raise ValueError(f"index={index!r} is out of range: must be in [0, {self.num_worlds})")
        return optional_method(self.world, "render_rgb")(self.world_state, index)

    def render(self, index: int = 0) -> str:
        """A text picture of world ``index`` (flat index in ``[0, S)``): ``#`` wall,
        ``o`` obstacle, ``A`` agent, ``G`` goal."""
        if not is_int(index) or not 0 <= index < self.num_worlds:
            raise ValueError(f"index={index!r} is out of range: must be in [0, {self.num_worlds})")
        state = self.world_state
        return self.world.render(state, index)
