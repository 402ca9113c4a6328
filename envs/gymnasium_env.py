"""The FactoredGrid world, or any ``factorq_envs.protocol.World``, as a gymnasium env (one world,
numpy in and out).

Registered as ``"FactoredGrid-v0"`` on ``import factorq_envs``. It runs the same pure functions as
the torchrl env (the world's ``reset``, ``step``, ``observe``) on tensors of one world, and draws
from the same counter streams: ``reset(seed=s)`` gives the trajectories of
``FactoredGridEnv(seed=s)`` for the same actions and the same world.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import gymnasium
import numpy as np
import torch
from gymnasium import spaces

from factorq_envs.grid_world import FactoredGrid, WorldConfig, static_layout
from factorq_envs.gym_spaces import FlagSpace, IndexSpace, register_if_torchrl_loaded
from factorq_envs.protocol import check_world, optional_method
from factorq_torch.base.rng import STREAM_WORLD, derive_keys
from factorq_torch.base.validation import check_int


class FactoredGridGym(gymnasium.Env):
    """One FactoredGrid world (SPEC sections 1-2), or any ``factorq_envs.protocol.World``, for
    gymnasium.

    Args:
        world: a ``WorldConfig`` (the grid's whole config: the same env as its fields given as
            the keywords below), or an ``factorq_envs.protocol.World`` (e.g.
            ``factorq_envs.corridor.Corridor(...)``) whose rules, spaces and body the env uses;
            ``None`` builds a ``FactoredGrid`` from the arguments below (size ... actuator_noise).
            With a world, those arguments are left out (refused, named). The spaces are
            read from its config (``cell``: ``Discrete(num_cells)``, ``sensors``:
            ``MultiBinary(num_sensors)``, ``heading`` when ``num_headings > 1``, ``bump``:
            ``MultiBinary(num_actuators)``, the world's extra observations; action
            ``Discrete(num_actuators)``). The index entries are ``IndexSpace`` and the flags
            ``FlagSpace`` (``factorq_envs.gym_spaces``): torchrl's ``GymEnv`` reads them as a
            categorical ``cell`` and bool sensors, so ``SplitLocalReward`` and the tables take
            ``GymEnv("FactoredGrid-v0")`` with no transform.
        size, num_obstacles, obstacle_period, max_steps, layout_seed: as ``WorldConfig``
            (``obstacle_period``: 0 static, 10 semi-dynamic, 1 dynamic).
        body, sensors, num_distractors, sensor_permutation, sensor_noise, actuator_noise: the
            body and its sensors, as ``WorldConfig`` (observation ``sensors`` ``[K]``, and
            ``heading`` for a body with a heading; ``Discrete(A)`` actions).
        render_mode: ``None``, ``"ansi"`` (``render()`` returns the text picture) or
            ``"rgb_array"`` (``render()`` returns ``uint8 [H, W, 3]``, ``factorq_envs.render``:
            walls, obstacles, the agent with its heading, the goal, the last collision in red; what
            gymnasium's ``RecordVideo`` and SB3's ``make_vec_env`` ask for).

    Spaces (the paper's body): observation ``Dict(cell=Discrete(N), sensors=MultiBinary(4),
    proximity=MultiBinary(4), bump=MultiBinary(4), collision=Box(-1, 0, (4,)))`` with
    ``N = size**2``; action ``Discrete(4)``
    (0 north, 1 west, 2 south, 3 east). The reward is
    the conventional step + goal + sum(collision); ``info`` holds ``"local_reward"`` (float32
    ``[4]``, the collision vector) and ``"task_reward"`` (step + goal, a float32 scalar, so that
    torchrl's ``GymEnv(..., info_dict_reader)`` can read both). Episodes end inside the
    env: ``terminated`` at the goal, ``truncated`` after ``max_steps`` actions. Never seeded,
    the world's stream starts from seed 0.

    Example:
        >>> import factorq_envs
        >>> env = gymnasium.make("FactoredGrid-v0", size=3, num_obstacles=0)
        >>> observation, info = env.reset(seed=0)
        >>> int(observation["cell"]), observation["proximity"].tolist()
        (0, [1, 1, 0, 0])
        >>> observation, reward, terminated, truncated, info = env.step(0)  # north: the wall
        >>> reward, float(info["task_reward"]), info["local_reward"].tolist()
        (-2.0, -1.0, [-1.0, 0.0, 0.0, 0.0])
    """

    metadata = {"render_modes": ["ansi", "rgb_array"], "render_fps": 4}

    def __init__(
        self,
        size: int = 10,
        num_obstacles: int = 10,
        obstacle_period: int = 0,
        max_steps: int = 10_000,
        layout_seed: int = 0,
        render_mode: str | None = None,
        body: str = "translate",
        sensors: str = "cross",
        num_distractors: int = 0,
        sensor_permutation: Sequence[int] | int | None = None,
        sensor_noise: float = 0.0,
        actuator_noise: float = 0.0,
        world: Any = None,  # a WorldConfig (the grid, whole) or a factorq_envs.protocol.World
    ) -> None:
        if world is not None:
            from factorq_envs.torchrl_env import (
                check_no_grid_arguments,  # the one list of grid arguments
            )

            check_no_grid_arguments(locals(), world)  # the grid arguments, read by name
        if isinstance(world, WorldConfig):  # the grid's config, passed whole
            check_int("obstacle_period", obstacle_period, 0, hint=" (0 static, k > 0 moving)")
            config = dataclasses.replace(world, obstacle_period=obstacle_period)
        elif world is not None:
            check_world(world)
            check_int("obstacle_period", obstacle_period, 0, hint=" (0 static, k > 0 moving)")
            self._setup(world, obstacle_period, render_mode)
            return
        else:
            config = WorldConfig(
                size=size,
                num_obstacles=num_obstacles,
                obstacle_period=obstacle_period,
                max_steps=max_steps,
                layout_seed=layout_seed,
                body=body,
                sensors=sensors,
                num_distractors=num_distractors,
                sensor_permutation=sensor_permutation,
                sensor_noise=sensor_noise,
                actuator_noise=actuator_noise,
            )
        if obstacle_period == 0:
            static_obstacles = static_layout(config)
        else:
            static_obstacles = torch.zeros(config.num_cells, dtype=torch.bool)
        self._setup(FactoredGrid(config, static_obstacles), obstacle_period, render_mode)

    def _setup(self, world: Any, obstacle_period: int, render_mode: str | None) -> None:
        """Spaces and state, read from ``world`` (an ``factorq_envs.protocol.World``)."""
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(
                f"render_mode={render_mode!r} is not supported: must be None or one of "
                f"{self.metadata['render_modes']}"
            )
        self.render_mode = render_mode
        # The world behind the factorq_envs.protocol.World interface: every rule goes through it.
        self.world = world
        self.config = config = world.config
        self.periods = torch.tensor([obstacle_period], dtype=torch.int64)  # [1]
        self.world_state = self.world.initial_state(1)
        self._collision = np.zeros(config.num_actuators, dtype=np.float32)
        # IndexSpace and FlagSpace: torchrl's GymEnv reads a categorical cell and bool flags
        # (factorq_envs.gym_spaces), Gymnasium and SB3 a Discrete and a MultiBinary
        register_if_torchrl_loaded()
        # the collision entry's bounds: the world's local_reward_range (a world that pays),
        # else the grid's -1 / 0
        low, high = getattr(config, "local_reward_range", (-1.0, 0.0))
        entries = {
            "cell": IndexSpace(config.num_cells),
            "sensors": FlagSpace(config.num_sensors),
            "bump": FlagSpace(config.num_actuators),
            # the collision vector (as FactoredGridEnv's), so that torchrl's GymEnv composes with
            # SplitLocalReward; info["local_reward"] keeps it for gymnasium users
            "collision": spaces.Box(float(low), float(high), (config.num_actuators,), np.float32),
        }
        if config.num_headings > 1:
            entries["heading"] = IndexSpace(config.num_headings)
        for name, value in self._extra_observations(None).items():
            entries[name] = FlagSpace(value.shape[-1])
        self.observation_space = spaces.Dict(entries)
        self.action_space = spaces.Discrete(config.num_actuators)
        self._seed_world(0)

    def _extra_observations(self, sensors: torch.Tensor | None) -> dict:
        """The world's optional extra entries ``{key: [1, n] bool}`` (the grid's proximity)."""
        extra = getattr(self.world, "extra_observations", None)
        if extra is None:
            return {}
        if sensors is None:
            sensors = self.world.observe(self.world_state, torch.zeros(1, dtype=torch.int64))
        return extra(self.world_state, sensors)

    @property
    def static_obstacles(self) -> torch.Tensor:
        """The static layout ``[N]`` of the default world (zeros when it moves)."""
        return self.world.static_obstacles

    def _seed_world(self, seed: int) -> None:
        """The world's key from ``seed`` (as ``FactoredGridEnv``), its stream rewound."""
        self.world_keys = derive_keys(seed, STREAM_WORLD, 1)  # [1]
        self.world_state = self.world.rewind(self.world_state)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, Any], dict[str, Any]]:
        super().reset(seed=seed)
        if seed is not None:
            self._seed_world(seed)
        self._collision = np.zeros(self.config.num_actuators, dtype=np.float32)
        start_all = torch.ones(1, dtype=torch.bool)
        self.world_state = self.world.reset(
            self.world_state, start_all, self.world_keys, self.periods
        )
        # the step's info keys, zero at a reset (torchrl's info_dict_reader reads both alike)
        info = {
            "local_reward": np.zeros(self.config.num_actuators, dtype=np.float32),
            "task_reward": np.float32(0.0),
        }
        return self._observation(), info

    def step(self, action: Any) -> tuple[dict[str, Any], float, bool, bool, dict[str, Any]]:
        if isinstance(action, np.ndarray) and action.shape == ():
            action = action.item()
        count = self.config.num_actuators
        if isinstance(action, bool | np.bool_) or not isinstance(action, int | np.integer):
            raise TypeError(
                f"action must be an int in [0, {count - 1}], got {action!r} "
                f"({type(action).__name__})"
            )
        if not 0 <= action < count:
            names = ", ".join(f"{i} {name}" for i, name in enumerate(self.config.actuator_names))
            raise ValueError(
                f"action={action} is out of range: must be in [0, {count - 1}] ({names})"
            )
        action_tensor = torch.tensor([int(action)], dtype=torch.int64)  # [1]
        self.world_state, outcome = self.world.step(
            self.world_state, action_tensor, self.world_keys, self.periods
        )
        self._collision = outcome.collision[0].numpy().copy()  # [A] float32
        info = {
            "local_reward": self._collision.copy(),
            "task_reward": np.float32(outcome.task_reward[0]),  # with a dtype, for torchrl
        }
        return (
            self._observation(),
            float(outcome.reward[0]),
            bool(outcome.terminated[0]),
            bool(outcome.truncated[0]),
            info,
        )

    def _observation(self) -> dict[str, Any]:
        state = self.world_state
        sensors = self.world.observe(state, self.world_keys)  # [1, K]
        observation = {
            "cell": np.int64(state.cell[0]),
            "sensors": sensors[0].numpy().astype(np.int8),
            "bump": state.bump[0].numpy().astype(np.int8),
            "collision": self._collision.copy(),
        }
        if self.config.num_headings > 1:
            observation["heading"] = np.int64(state.heading[0])
        for name, value in self._extra_observations(sensors).items():
            observation[name] = value[0].numpy().astype(np.int8)
        return observation

    def obstacle_map(self) -> np.ndarray:
        """The current obstacles, a bool copy ``[size, size]`` (the world's ``obstacle_map``)."""
        return optional_method(self.world, "obstacle_map")(self.world_state)[0].cpu().numpy()

    def render(self) -> str | np.ndarray | None:
        """The text picture (``render_mode="ansi"``: ``#`` wall, ``o`` obstacle, ``A`` agent,
        ``G`` goal) or the image (``"rgb_array"``, ``uint8 [(size + 2) 16, (size + 2) 16, 3]``)."""
        state = self.world_state
        if self.render_mode == "rgb_array":
            return self.render_rgb()
        if self.render_mode != "ansi":
            return None
        return self.world.render(state, 0)

    def render_rgb(self) -> np.ndarray:
        """The world as an image, ``uint8 [H, W, 3]`` (the world's ``render_rgb``)."""
        return optional_method(self.world, "render_rgb")(self.world_state, 0)


#: The ``info`` entries torchrl reads from ``FactoredGridGym`` (``torchrl_info_reader``).
INFO_KEYS = ("task_reward",)


def torchrl_info_reader() -> Any:  # torchrl's reader (untyped)
    """torchrl's ``default_info_dict_reader`` for the step's ``task_reward`` with its spec
    declared (a float32 scalar per env), so torchrl need not infer it from a first step.
    ``local_reward`` is left out: the ``collision`` observation carries it, and
    ``SplitLocalReward`` writes ``local_reward`` itself.

    Example:
        >>> from torchrl.envs import GymEnv
        >>> env = GymEnv("FactoredGrid-v0", size=3, num_obstacles=0)
        >>> env = env.set_info_dict_reader(torchrl_info_reader())
        >>> env.rollout(2)["next", "task_reward"].shape
        torch.Size([2])
    """
    import torch
    from torchrl.data import Unbounded
    from torchrl.envs.libs.gym import default_info_dict_reader

    spec = {key: Unbounded(shape=(), dtype=torch.float32) for key in INFO_KEYS}
    return default_info_dict_reader(list(INFO_KEYS), spec=spec)
