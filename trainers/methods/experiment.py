"""What every experiment is built from (``paper``, ``compare``, ``transfer``, ``dependencies``
and ``methods.dqn`` assemble theirs from these pieces): ``experiment_keys`` (each experiment's
random stream key, the same whatever else is selected), ``check_world_options``, ``make_env``
(the batched ``FactoredGridEnv``), ``tabular_values`` and ``online_agent`` (Q-learning or
Factor-Q around tables or networks), ``ExperimentConfig`` and ``EpisodeRecorder`` (the
step-budget experiments of ``factorq compare`` and their per-episode records).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from factorq_envs.grid_world import WorldConfig, static_layout
from factorq_envs.regimes import REGIME_PERIODS, REGIMES
from factorq_torch.base import validation
from factorq_torch.base.config import AgentConfig
from factorq_torch.base.rng import derive_keys
from factorq_torch.base.validation import INT32_MAX, INT64_MAX, MAX_SIZE, check_int, check_names
from factorq_trainers.runner.options import option

if TYPE_CHECKING:  # torchrl and tensordict load only on the paths that step an env
    from tensordict import TensorDictBase

    from factorq_envs.torchrl_env import FactoredGridEnv

#: The largest seed a config accepts (keys are derived in 64-bit arithmetic).
MAX_SEED = 2**63 - 1
#: Per-episode records of ``EpisodeRecorder``.
EPISODE_FIELDS = (
    "steps",
    "collisions",
    "greedy_collisions",
    "task_return",
    "env_steps",
    "epsilon",
    "loss",
)
#: The per-episode fields that are floats (the others are whole counts).
FLOAT_FIELDS = ("task_return", "epsilon", "loss")


def experiment_keys(
    seed: int,
    stream: int,
    labels: Sequence[tuple[str, int]],
    variants: Sequence[str] = (),
    variant: str | None = None,
) -> torch.Tensor:
    """Keys ``[E]`` of ``stream`` for the experiments ``labels`` (``(world, seed index)`` each).

    Experiment (seed index ``i``, world ``w`` = index in ``REGIMES``) takes key number ``3 i + w``
    (every algorithm or method meets the same worlds: common random numbers), or, for one of
    several ``variants`` (algorithms, methods), number ``V (3 i + w) + v`` with ``v`` the index
    of ``variant``. Neither depends on what else is selected.
    """
    slots = []
    for world, index in labels:
        slot = len(REGIMES) * index + REGIMES.index(world)
        slots.append(slot if variant is None else len(variants) * slot + variants.index(variant))
    low = min(slots)  # a shard of late seeds derives only its own range of keys
    return derive_keys(seed, stream, max(slots) - low + 1, low)[torch.tensor(slots) - low]


#: The body options of a trainer's config (field name -> ``WorldConfig`` argument).
BODY_OPTIONS = {
    "body": "body",
    "sensors": "sensors",
    "distractors": "num_distractors",
    "sensor_permutation": "sensor_permutation",
    "sensor_noise": "sensor_noise",
    "actuator_noise": "actuator_noise",
}


def body_options(config: Any) -> dict[str, Any]:
    """The body options of a config that has ``BODY_OPTIONS``' fields, as config names."""
    return {name: getattr(config, name) for name in BODY_OPTIONS}


def check_world_options(
    size: int,
    obstacles: int,
    max_steps: int,
    layout_seed: int,
    worlds: Sequence[str],
    body: dict[str, Any] | None = None,
) -> WorldConfig:
    """The world of a trainer's config (obstacle period 0: it is set per experiment), with
    errors that name the options as the config spells them (``obstacles``, ``distractors``);
    checks that the static layout has a path when the static world is among ``worlds``.
    ``body``: the config's body options (``body_options``), default the paper's body."""
    # Upper bounds are those of the types the values reach (docs/decisions.md, "Hardening"); the
    # size is checked before the static layout, whose search grows with it.
    check_int("size", size, 2, MAX_SIZE)
    check_int("max_steps", max_steps, 1, INT64_MAX)
    permutation = (body or {}).get("sensor_permutation")
    if isinstance(permutation, int) and not isinstance(permutation, bool):  # a seed: int64 keys
        check_int("sensor_permutation", permutation, 0, MAX_SEED)
    check_int("layout_seed", layout_seed, 0, MAX_SEED)
    renames = {"num_obstacles": "obstacles", **{v: k for k, v in BODY_OPTIONS.items() if k != v}}
    try:
        world = WorldConfig(
            size=size,
            num_obstacles=obstacles,
            max_steps=max_steps,
            layout_seed=layout_seed,
            **{BODY_OPTIONS[name]: value for name, value in (body or {}).items()},
        )
        if "static" in worlds:
            static_layout(world)
    except (ValueError, TypeError) as error:
        message = str(error)
        for world_name, config_name in renames.items():
            message = message.replace(world_name, config_name)
        raise type(error)(message) from None
    return world


def body_of(world: Any) -> Any:
    """The config that declares the body's sizes (``num_cells``, ``num_sensors``, ...): a
    ``WorldConfig`` itself, else an ``factorq_envs.protocol.World``'s ``config``."""
    return world if isinstance(world, WorldConfig) else world.config


def check_qlearning_table(world: Any) -> None:
    """Refuse a Q-learning table past ``base.validation.MAX_TABLE_ENTRIES``: its state is the
    cell (x heading) x the pattern of all the body's sensors (``world``: a ``WorldConfig`` or a
    ``World``)."""
    world = body_of(world)
    validation.check_table_size(
        "q-learning",
        f"a Q-table of {world.num_cells} cells x {world.num_headings} headings x "
        f"2**{world.num_sensors} sensor patterns x {world.num_actuators} actions",
        (world.num_cells * world.num_headings << world.num_sensors) * world.num_actuators,
    )


def make_env(
    world: Any,
    periods: Sequence[int] | torch.Tensor,
    world_keys: torch.Tensor,
    *,
    device: torch.device | str | None = None,
    seed: int | None = None,
) -> FactoredGridEnv:
    """The batch's worlds: one ``FactoredGridEnv`` experiment per entry of ``periods``, each
    drawing its obstacles from its own ``world_keys`` entry (``experiment_keys``). ``world``: a
    ``WorldConfig`` (the paper's grid) or any ``factorq_envs.protocol.World``, passed whole
    (``FactoredGridEnv(world=...)``)."""
    from factorq_envs.torchrl_env import FactoredGridEnv  # torchrl: only on stepping paths

    return FactoredGridEnv(
        world=world,  # passed whole: a WorldConfig or a World
        obstacle_period=periods,
        batch_size=(len(periods),),
        seed=seed,
        device=device,
        # not a contiguous range of the world stream (key 3 i + w): given outright
        world_keys=world_keys,
    )


def tabular_values(
    algorithm: str, count: int, world: Any, device: torch.device | str | None = None
) -> tuple[Any, Any]:
    """The tables of ``count`` experiments of ``algorithm`` in ``world``'s body (a
    ``WorldConfig`` or an ``factorq_envs.protocol.World``): Q-learning's task table over cell (x
    heading) x the pattern of all sensors and no local table, or Factor-Q's task table over cells
    (x heading) and its local tables, given the body's true dependency (the oracle pairing, as in
    the paper)."""
    from factorq_torch.tables import LocalRewardTable, TaskQTable

    factorq = algorithm == "factor-q"
    dependency = world.dependency
    world = body_of(world)
    task = TaskQTable(
        count,
        world.num_cells,
        with_sensors=not factorq,
        num_sensors=world.num_sensors,
        num_headings=world.num_headings,
        num_actions=world.num_actuators,
        device=device,
        sparse_grad=True,  # SGD steps it; no dense [S, states, A] gradient per step
    )
    if not factorq:
        return task, None
    return task, LocalRewardTable(count, dependency=dependency, device=device)


def online_agent(
    env: Any,
    task: Any,
    local: Any,
    agent: AgentConfig,
    policy_keys: torch.Tensor,
    *,
    epsilon: float | None = None,
    device: torch.device | str | None = None,
) -> tuple[Any, Any, Any]:
    """``(env, policy, loss)`` of Q-learning (``local`` is ``None``) or Factor-Q around the value
    providers ``task`` and ``local`` (tables or networks: the rest is the same code).

    Factor-Q learns from the split reward, so its env is wrapped in ``SplitLocalReward``;
    ``epsilon`` overrides ``agent.epsilon``.
    """
    from tensordict.nn import TensorDictSequential
    from torchrl.envs import TransformedEnv

    from factorq_envs.transforms import SplitLocalReward
    from factorq_torch.objectives import FactorQLoss, TabularQLoss
    from factorq_torch.policy import EpsilonGreedyPolicy, FactorQPolicy

    count = policy_keys.numel()
    epsilon = agent.epsilon if epsilon is None else epsilon
    if local is None:
        chooser = EpsilonGreedyPolicy(
            count, keys=policy_keys, epsilon=epsilon, device=device, exploration=agent.exploration
        )
        loss = TabularQLoss(task, gamma=agent.gamma, alpha=agent.alpha)
        return env, TensorDictSequential(task, chooser), loss
    names = ("gamma", "eta", "g_min", "risk_threshold", "risk_gate", "arbitration", "local_span")
    shared = {name: getattr(agent, name) for name in names}  # eqs. 2-4's: policy and loss alike
    chooser = FactorQPolicy(
        count, keys=policy_keys, epsilon=epsilon, device=device, exploration=agent.exploration,
        **shared,
    )  # fmt: skip
    loss = FactorQLoss(task, local, alpha=agent.alpha, **shared)
    env = TransformedEnv(env, SplitLocalReward())
    return env, TensorDictSequential(task, local, chooser), loss


# --------------------------------------------------------------------------------------------
# Step-budget experiments (factorq compare, DQN)


#: The paper's world and body (SPEC section 1): the one place a world option's default is declared
#: (``WorldConfig``'s own); a command whose world differs names its own ``WorldConfig``.
PAPER_WORLD = WorldConfig()


@dataclass(frozen=True)
class WorldOptions:
    """The world and body options every grid command's config shares, their defaults
    ``PAPER_WORLD``'s. A config inherits them and checks them with ``checked_world``."""

    size: int = option(PAPER_WORLD.size, "Side of the square grid, in cells.")
    obstacles: int = option(PAPER_WORLD.num_obstacles, "Number of single-cell obstacles.")
    max_steps: int = option(PAPER_WORLD.max_steps, "Actions after which an episode is truncated.")
    layout_seed: int = option(
        PAPER_WORLD.layout_seed, "Seed of the static world's obstacle layout."
    )
    body: str = option(
        PAPER_WORLD.body,
        "Agent body: translate (the paper: moves N/W/S/E) or heading (forward, turn left/right).",
    )
    sensors: str = option(
        PAPER_WORLD.sensors,
        "Sensor layout: cross (the paper: 4 neighbours) or ring (8 neighbours).",
    )
    distractors: int = option(
        PAPER_WORLD.num_distractors,
        "Extra sensor bits that carry no information (fresh fair coins at every observation).",
    )
    sensor_permutation: int | None = option(
        None,
        "Seed of a random order in which the agent receives its sensors (default: layout order).",
    )
    sensor_noise: float = option(
        PAPER_WORLD.sensor_noise,
        "Probability that each sensor bit is flipped at each observation, in [0, 1].",
    )
    actuator_noise: float = option(
        PAPER_WORLD.actuator_noise,
        "Probability that another actuator fires than the chosen one, in [0, 1].",
    )

    def checked_world(self, regimes: Sequence[str] = ()) -> WorldConfig:
        """These options' world, checked (``check_world_options``; its static layout's path too
        when ``"static"`` is among ``regimes``)."""
        return check_world_options(
            self.size, self.obstacles, self.max_steps, self.layout_seed, regimes, body_options(self)
        )

    @property
    def world(self) -> WorldConfig:
        """The world of every experiment; the obstacle period is set per experiment."""
        return self.checked_world()


@dataclass(frozen=True)
class ExperimentConfig(WorldOptions):
    """Which experiments run, and their budget: ``seeds`` per world, ``steps`` env steps each."""

    seed: int = option(
        0, "Master seed: worlds, policies and network initialisations derive from it."
    )
    seeds: int = option(3, "Independent experiments per world (and method).")
    regimes: tuple[str, ...] = option(
        REGIMES, "Obstacle regimes to run: static, semi-dynamic, dynamic (comma-separated)."
    )
    steps: int = option(15_000, "Budget of env steps per experiment (episodes are as many as fit).")

    def __post_init__(self) -> None:
        check_int("seed", self.seed, 0, MAX_SEED)
        check_int("seeds", self.seeds, 1, INT32_MAX)
        object.__setattr__(self, "regimes", check_names("regimes", self.regimes, REGIMES))
        check_int("steps", self.steps, 1, INT32_MAX)
        self.checked_world(self.regimes)

    @property
    def num_experiments(self) -> int:
        return len(self.regimes) * self.seeds

    @property
    def periods(self) -> list[int]:
        """The obstacle period of every experiment of the batch."""
        return [REGIME_PERIODS[world] for world, _ in self.labels]

    @property
    def labels(self) -> list[tuple[str, int]]:
        """``(world, seed index)`` of every experiment of the batch, world-major."""
        return [(world, index) for world in self.regimes for index in range(self.seeds)]


class EpisodeRecorder:
    """Per-episode records of ``E`` experiments, fed one transition ``[E]`` at a time.

    ``update(td, epsilon, loss)`` reads ``("next", "bump")`` (a collision), ``exploratory``,
    ``("next", "done")`` and the task reward: ``("next", "reward")`` when ``("next",
    "local_reward")`` exists (the reward was split), else the conventional reward minus the sum of
    ``("next", "collision")``. ``epsilon`` and ``loss`` are per-experiment values of this step
    (``loss`` NaN where there was none); an episode records the epsilon at its end and the mean
    finite loss over its steps (``log_traces`` sends the records to a torchrl ``Logger``).

    ``totals`` counts collisions and greedy collisions over every step, including an episode left
    unfinished by the budget, and the *boxed-in* greedy collisions among them: those where all
    four sensors read an obstacle or wall before acting, so that every action collided (in the
    moving worlds a scatter can box the agent in; no policy avoids those).
    """

    def __init__(self, labels: Sequence[tuple[str, int]]) -> None:
        self.labels = list(labels)
        count = len(self.labels)
        self.env_steps = np.zeros(count, dtype=np.int64)
        self._sums = {name: np.zeros(count) for name in ("steps", "collisions", "greedy", "task")}
        self._loss_sum, self._loss_count = np.zeros(count), np.zeros(count)
        self.episodes: list[dict[str, list[float]]] = [
            {name: [] for name in EPISODE_FIELDS} for _ in range(count)
        ]
        self.totals = {
            "collisions": np.zeros(count, dtype=np.int64),
            "greedy_collisions": np.zeros(count, dtype=np.int64),
            "boxed_in_greedy_collisions": np.zeros(count, dtype=np.int64),
        }

    def update(
        self,
        td: TensorDictBase,
        epsilon: float | torch.Tensor | np.ndarray,
        loss: torch.Tensor | np.ndarray | None = None,
    ) -> None:
        next_td = td.get("next")
        collided = next_td.get("bump").any(dim=-1).cpu().numpy()  # [E]
        greedy = collided & ~td.get("exploratory").cpu().numpy()
        boxed_in = greedy & td.get("proximity").all(dim=-1).cpu().numpy()
        reward = next_td.get("reward").squeeze(-1)
        if next_td.get("local_reward", None) is None:
            reward = reward - next_td.get("collision").sum(dim=-1)
        done = next_td.get("done").squeeze(-1).cpu().numpy()
        sums = self._sums
        sums["steps"] += 1
        sums["collisions"] += collided
        sums["greedy"] += greedy
        sums["task"] += reward.cpu().numpy()
        self.env_steps += 1
        self.totals["collisions"] += collided
        self.totals["greedy_collisions"] += greedy
        self.totals["boxed_in_greedy_collisions"] += boxed_in
        if loss is not None:
            loss = loss.detach().cpu().numpy() if isinstance(loss, torch.Tensor) else loss
            finite = np.isfinite(loss)
            self._loss_sum += np.where(finite, loss, 0.0)
            self._loss_count += finite
        if not done.any():
            return
        epsilon = np.broadcast_to(
            epsilon.detach().cpu().numpy() if isinstance(epsilon, torch.Tensor) else epsilon,
            done.shape,
        )
        for row in np.flatnonzero(done).tolist():
            count = self._loss_count[row]
            record = {
                "steps": int(sums["steps"][row]),
                "collisions": int(sums["collisions"][row]),
                "greedy_collisions": int(sums["greedy"][row]),
                "task_return": float(sums["task"][row]),
                "env_steps": int(self.env_steps[row]),
                "epsilon": float(epsilon[row]),
                "loss": float(self._loss_sum[row] / count) if count else math.nan,
            }
            for name, value in record.items():
                self.episodes[row][name].append(value)
            for values in (*sums.values(), self._loss_sum, self._loss_count):
                values[row] = 0

    def traces(self) -> list[dict[str, Any]]:
        """One dict per experiment: the per-episode arrays, totals and label."""
        out = []
        for row, (world, index) in enumerate(self.labels):
            trace: dict[str, Any] = {"world": world, "seed_index": index}
            for name in EPISODE_FIELDS:
                dtype = np.float64 if name in FLOAT_FIELDS else np.int64
                trace[name] = np.asarray(self.episodes[row][name], dtype=dtype)
            for name, totals in (*self.totals.items(), ("env_steps", self.env_steps)):
                trace[f"total_{name}"] = int(totals[row])
            out.append(trace)
        return out


#: Logged names of the episode records that differ from their field names.
LOG_NAMES = {"steps": "path_length", "task_return": "return"}


def log_traces(logger: Any, traces: list[dict[str, Any]]) -> None:
    """Send ``EpisodeRecorder.traces()`` to ``logger`` (a torchrl ``Logger``): every finished
    episode's finite records under ``"{world}/seed_{i}/{name}"`` at step = its env steps."""
    for trace in traces:
        for episode in range(len(trace["steps"])):
            step = trace["env_steps"][episode].item()
            for name in EPISODE_FIELDS:
                value = trace[name][episode].item()
                if name != "env_steps" and math.isfinite(value):
                    tag = f"{trace['world']}/seed_{trace['seed_index']}/{LOG_NAMES.get(name, name)}"
                    logger.log_scalar(tag, value, step)
