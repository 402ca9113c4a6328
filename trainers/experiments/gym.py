"""Factor-Q on a declared Gymnasium world against DQN: ``factorq gym`` (issue 25), a command
module of the runner (``/work/coord`` protocol: ``NAME``, ``CONFIG``, ``units``, ``run_unit``,
``summarise``, ``markdown``, ``figure``).

Every method trains one experiment per unit (``(method, seed)``) for the same env-step budget on
the same worlds (common random numbers: seed ``i`` meets the same env seed under every method):

- ``dqn``: ``factorq_trainers.experiments.dqn``'s torchrl DQN (``DQNLoss``, target network, replay,
  annealed epsilon) on the world's own observation (highway: ``Kinematics``), with the
  hyperparameters highway-env's documentation uses for SB3's DQN (``HIGHWAY_DQN``);
- ``factor-q-oracle``: neural Factor-Q: the task values from a network on the same observation
  (trained online by ``FactorQLoss`` with Adam), the local values from ``LocalRewardTable`` on
  the declared oracle dependency and the binary sensors (eq. 5);
- ``factor-q-learned``: the same with ``StructureLearner(prediction="committed")`` told only
  ``A`` and ``K``: it must find the dependency itself (its structure at the end is reported
  against the oracle);
- ``sb3-dqn`` (optional extra ``sb3``; skipped in the defaults): Stable-Baselines3's DQN with
  the same documented hyperparameters, on the same observation.

**Measures** per unit: crashes during training (per 1,000 env steps), the greedy policy's crash
rate and return over ``eval_episodes`` episodes after training (fresh env seeds, exploration
off), training env steps until the mean return of the last ``window`` finished episodes first
reaches ``threshold``, env steps per second of training, and curves (cumulative crashes, mean
return of the last ``window`` episodes) at ``curve_points`` points. The return is the
conventional reward summed (highway's own reward).

**Intervals** over seeds (``factorq_trainers.analysis.stats``): Wilson's for the greedy crash
rate (a proportion), the BCa bootstrap of the mean for the other measures and the curves' bands
(bounded or positive: its bounds stay between the seeds). The report and figure are
``factorq_trainers.reports.gym``.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, TypedDict

import numpy as np

from factorq_torch.base.validation import check_float, check_int, check_names
from factorq_trainers.analysis.stats import (
    bootstrap_mean_ci,
    finite_or_none,
    interval,
    scalar_ci,
    wilson_ci,
)
from factorq_trainers.runner.options import option

if TYPE_CHECKING:
    import torch

    from factorq_envs.declared_env import DeclaredEnv
    from factorq_envs.gymnasium_adapter import FactorQEnv

NAME = "gym"
REPORT = "factorq_trainers.reports.gym"
WORK_UNIT = "step"
HELP = (
    "Factor-Q (oracle and learned dependencies) against DQN on a declared Gymnasium world "
    "(highway-fast-v0, MiniGrid): crashes and return for the same env-step budget."
)

METHODS = ("dqn", "factor-q-oracle", "factor-q-learned", "sb3-dqn")
DEFAULT_METHODS = ("dqn", "factor-q-oracle", "factor-q-learned")


class DQNSettings(TypedDict):
    """``HIGHWAY_DQN``'s entries: ``DQNConfig``'s names (``experiments.dqn``)."""

    hidden: tuple[int, ...]
    lr: float
    buffer_size: int
    learning_starts: int
    batch_size: int
    gamma: float
    train_every: int
    target_update_interval: int
    exploration_fraction: float


#: highway-env's documented SB3 DQN (its README and scripts/sb3_highway_dqn.py): MlpPolicy
#: [256, 256], learning rate 5e-4, buffer 15,000, learning starts 200, batch 32, gamma 0.8,
#: a gradient step every env step, target update every 50, exploration over 70% of the budget.
HIGHWAY_DQN = DQNSettings(
    hidden=(256, 256),
    lr=5e-4,
    buffer_size=15_000,
    learning_starts=200,
    batch_size=32,
    gamma=0.8,
    train_every=1,
    target_update_interval=50,
    exploration_fraction=0.7,
)
FACTOR_Q_EPSILON = 0.05  # Factor-DQN's (docs/decisions.md): constant, no annealing
FACTOR_Q_LR = 1e-3


@dataclass(frozen=True)
class WorldSpec:
    """A declared world as the experiment runs it."""

    make: str  # "module:function", seed -> FactorQEnv
    observation: str  # the entry the networks read
    threshold: float  # the default return threshold
    extra: str  # what prepare() imports
    label: str


WORLDS = {
    "highway": WorldSpec(
        "factorq_envs.highway:make_highway",
        "observation",
        20.0,
        "highway",
        "highway-fast-v0",
    ),
    "minigrid-8x8": WorldSpec(
        f"{__name__}:make_minigrid_8x8",  # this module, wherever the runner puts it
        "image",
        0.5,
        "minigrid",
        "MiniGrid-Dynamic-Obstacles-8x8-v0 (nodeath)",
    ),
}


def make_minigrid_8x8(seed: int) -> FactorQEnv:
    """MiniGrid Dynamic-Obstacles 8x8 with the "nodeath" semantics (``WORLDS["minigrid-8x8"]``).

    Args:
        seed: the env seed.
    """
    from factorq_envs.minigrid_adapter import make_minigrid

    return make_minigrid(8, "nodeath", seed=seed)


@dataclass(frozen=True)
class GymConfig:
    """The experiment. The defaults (3 seeds x 1,000 steps x 3 methods: at most 10,350 env
    steps with the greedy episodes) are about 2-3 minutes of highway's own stepping on 2 idle
    cores at its 35-45 env steps/s per core, plus the learning
    (``docs/tutorials/highway.md``: not yet measured on an idle machine)."""

    world: str = option("highway", "The declared world.", choices=tuple(WORLDS))
    seed: int = option(0, "Master seed: env seeds, policies and networks derive from it.")
    seeds: int = option(3, "Independent experiments per method.")
    methods: tuple[str, ...] = option(
        DEFAULT_METHODS, "Methods (comma-separated): " + ", ".join(METHODS) + "."
    )
    steps: int = option(1_000, "Training env steps per experiment, the same for every method.")
    eval_episodes: int = option(5, "Greedy episodes after training.")
    window: int = option(5, "Finished episodes in the mean return of the curves and threshold.")
    threshold: float | None = option(
        None, "Return threshold for 'steps to threshold' (default: the world's)."
    )
    curve_points: int = option(20, "Points of the curves in the figure.")
    out: str = option("results/gym", "Directory for the json, figure and report.")

    def __post_init__(self) -> None:
        if self.world not in WORLDS:
            raise ValueError(f"world={self.world!r}: choose one of {', '.join(WORLDS)}")
        check_int("seed", self.seed, 0, 2**31 - 1)
        check_int("seeds", self.seeds, 1, 1_000)
        object.__setattr__(self, "methods", check_names("methods", self.methods, METHODS))
        check_int("steps", self.steps, 10, 10**8)
        check_int("eval_episodes", self.eval_episodes, 1, 10_000)
        check_int("window", self.window, 1, 10_000)
        if self.threshold is not None:
            check_float("threshold", self.threshold, -math.inf, math.inf)
        check_int("curve_points", self.curve_points, 1, 1_000)

    @property
    def spec(self) -> WorldSpec:
        """The declared world (``WORLDS[world]``)."""
        return WORLDS[self.world]

    @property
    def return_threshold(self) -> float:
        """``threshold``, else the world's default."""
        return self.spec.threshold if self.threshold is None else self.threshold


CONFIG = GymConfig


def prepare(config: GymConfig) -> None:
    """The world's extra (and SB3 when asked for) installed, else one ModuleNotFoundError.

    Args:
        config: the experiment.
    """
    from factorq_envs.gymnasium_adapter import require_extra

    modules = {"highway": "highway_env", "minigrid": "minigrid"}
    extra = config.spec.extra
    require_extra(modules[extra], f"factorq-torch[{extra}]")
    if "sb3-dqn" in config.methods:
        require_extra("stable_baselines3", "factorq-torch[sb3]")


def units(config: GymConfig) -> list[dict[str, Any]]:
    """One unit per method and seed: ``{"id", "method", "seed_index"}``.

    Args:
        config: the experiment.
    """
    return [
        {"id": f"{method}-seed{index}", "method": method, "seed_index": index}
        for method in config.methods
        for index in range(config.seeds)
    ]


def work(config: GymConfig, unit: dict[str, Any]) -> int:
    """A unit's training env steps (what ``run_unit`` reports to ``progress``).

    Args:
        config: the experiment.
        unit: one of ``units(config)``.
    """
    return config.steps


# --------------------------------------------------------------------------------------------
# Seeds and envs


def _env_seed(config: GymConfig, index: int, evaluation: bool = False) -> int:
    """The env seed of experiment ``index`` (the same for every method)."""
    from factorq_torch.base.rng import STREAM_WORLD, derive_keys

    offset = index + (config.seeds if evaluation else 0)
    return int(derive_keys(config.seed, STREAM_WORLD, 1, offset)[0]) & 0x7FFFFFFF


def _keys(config: GymConfig, unit: dict[str, Any], stream: int) -> torch.Tensor:
    from factorq_torch.base.rng import derive_keys

    slot = METHODS.index(unit["method"]) * config.seeds + unit["seed_index"]
    return derive_keys(config.seed, stream, 1, slot)


def _maker(config: GymConfig) -> Callable[[int], FactorQEnv]:
    import importlib

    module, function = config.spec.make.split(":")
    return getattr(importlib.import_module(module), function)


def _torchrl_env(config: GymConfig, seed: int) -> DeclaredEnv:
    from factorq_envs.declared_env import declared_torchrl_env

    return declared_torchrl_env(_maker(config), [seed], exclude=_excluded(config))


def _excluded(config: GymConfig) -> list[str]:
    return ["mission", "direction"] if config.world.startswith("minigrid") else []


# --------------------------------------------------------------------------------------------
# The networks and agents


def observation_network(
    count: int,
    key: str,
    shape: Sequence[int],
    actions: int,
    hidden: Sequence[int],
    keys: torch.Tensor,
    zero_output: bool,
) -> Any:  # a tensordict module (tensordict: untyped)
    """``S`` MLPs on an observation entry: ``key`` ``[..., S, *shape]`` -> ``action_value``
    ``[..., S, A]`` (the entry flattened, as float32; MiniGrid's image divided by 10: its
    indices are below 11).

    Args:
        count: ``S``, the MLPs (one per experiment).
        key: the observation entry they read.
        shape: the entry's shape per experiment.
        actions: ``A``, the outputs.
        hidden: the hidden layers' widths.
        keys: ``[S]`` seeds of their initial weights (``BatchedMLP``).
        zero_output: start with a zero output layer (every value 0).
    """
    import torch
    from tensordict.nn import TensorDictModuleBase

    from factorq_torch.neural import BatchedMLP

    size = math.prod(shape)
    scale = 0.1 if key == "image" else 1.0

    class ObservationQNetwork(TensorDictModuleBase):
        def __init__(self) -> None:
            super().__init__()
            self.in_keys, self.out_keys = [key], ["action_value"]
            self.mlp = BatchedMLP(
                (count,), size, actions, hidden=hidden, keys=keys, zero_output=zero_output
            )

        def forward(self, tensordict: Any) -> Any:
            value = tensordict.get(key)
            x = value.reshape(*value.shape[: value.dim() - len(shape)], size)
            tensordict.set("action_value", self.mlp(x.to(torch.float32) * scale))
            return tensordict

    return ObservationQNetwork()


class Recorder:
    """Crashes, returns and curves of one training experiment.

    Args:
        config: the experiment (its ``steps``, ``window``, threshold and ``curve_points``).
    """

    def __init__(self, config: GymConfig) -> None:
        self.config = config
        self.step = 0
        self.crashes = 0
        self.episode_return = 0.0
        self.returns: list[float] = []
        self.reached: int | None = None
        self.every = max(1, config.steps // config.curve_points)
        self.curve_steps: list[int] = []
        self.curve_crashes: list[int] = []
        self.curve_return: list[float | None] = []

    def update(self, crashed: bool, reward: float, done: bool) -> None:
        """Count one env step.

        Args:
            crashed: the step collided.
            reward: its conventional reward.
            done: it ended the episode.
        """
        self.step += 1
        self.crashes += int(crashed)
        self.episode_return += reward
        if done:
            self.returns.append(self.episode_return)
            self.episode_return = 0.0
            recent = self.returns[-self.config.window :]
            enough = len(recent) == self.config.window
            if self.reached is None and enough and _mean(recent) >= self.config.return_threshold:
                self.reached = self.step
        if self.step % self.every == 0 or self.step == self.config.steps:
            self.curve_steps.append(self.step)
            self.curve_crashes.append(self.crashes)
            recent = self.returns[-self.config.window :]
            self.curve_return.append(_mean(recent) if recent else None)

    def result(self) -> dict[str, Any]:
        """The unit's training measures and curves (JSON)."""
        return {
            "crashes": self.crashes,
            "crashes_per_1000": 1000.0 * self.crashes / max(1, self.step),
            "episodes": len(self.returns),
            "steps_to_threshold": self.reached,
            "curve_steps": self.curve_steps,
            "curve_crashes": self.curve_crashes,
            "curve_return": self.curve_return,
        }


def _mean(values: Sequence[float]) -> float:
    return float(sum(values) / len(values))


def _transition(td: Any) -> tuple[bool, float, bool]:
    """(crashed, conventional reward, done) of a ``[1]`` transition (split or not)."""
    nxt = td.get("next")
    reward = float(nxt.get("reward").sum())
    local = nxt.get("local_reward", None)
    if local is not None:  # the reward was split: put the collision back
        reward += float(local.sum())
    return bool(nxt.get("bump").any()), reward, bool(nxt.get("done").any())


def run_unit(
    config: GymConfig, unit: dict[str, Any], progress: Callable[[int], None] | None = None
) -> dict[str, Any]:
    """Train and evaluate one unit (one method, one seed): ``Recorder.result()`` with the greedy
    measures, ``wall_s`` and ``steps_per_s`` (and the structures, for Factor-Q).

    Args:
        config: the experiment.
        unit: one of ``units(config)``.
        progress: called with env steps done, every 100.
    """
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny networks: more threads only wait on each other
    try:
        method = unit["method"]
        runner = {
            "dqn": _run_dqn,
            "factor-q-oracle": _run_factor_q,
            "factor-q-learned": _run_factor_q,
            "sb3-dqn": _run_sb3,
        }[method]
        return runner(config, unit, progress or (lambda steps: None))
    finally:
        torch.set_num_threads(threads)


def _tick(progress: Callable[[int], None], step: int, total: int) -> None:
    if step % 100 == 0 or step == total:
        progress(100 if step % 100 == 0 else step % 100)


def _env_and_task_network(
    config: GymConfig, unit: dict[str, Any], *, zero_output: bool
) -> tuple[DeclaredEnv, Any]:
    """The unit's env (its own env seed) and a task Q-network on the world's observation, with
    highway-env's documented hidden layers: what every torchrl method of a unit starts from."""
    from factorq_torch.base.rng import STREAM_TASK_NETWORK

    env = _torchrl_env(config, _env_seed(config, unit["seed_index"]))
    key = config.spec.observation
    network = observation_network(
        1,
        key,
        tuple(env.observation_spec[key].shape[1:]),
        env.num_actions,
        HIGHWAY_DQN["hidden"],
        _keys(config, unit, STREAM_TASK_NETWORK),
        zero_output=zero_output,
    )
    return env, network


def _run_dqn(
    config: GymConfig, unit: dict[str, Any], progress: Callable[[int], None]
) -> dict[str, Any]:
    import torch

    from factorq_torch.base.rng import STREAM_POLICY
    from factorq_trainers.experiments.dqn import DQNConfig, _gradient_step, dqn_agent

    settings = DQNConfig(**HIGHWAY_DQN)
    env, q_network = _env_and_task_network(config, unit, zero_output=False)
    torch.manual_seed(int(_keys(config, unit, STREAM_POLICY)[0]) & 0x7FFFFFFF)
    agent = dqn_agent(q_network, env.num_actions, settings, config.steps)
    key = config.spec.observation
    stored = [key, ("next", key), "action", ("next", "reward"), ("next", "done")]
    stored.append(("next", "terminated"))
    recorder = Recorder(config)
    started = time.perf_counter()
    td = env.reset()
    for step in range(1, config.steps + 1):
        with torch.no_grad():
            td = env.step(agent.policy(td))
        recorder.update(*_transition(td))
        agent.buffer.extend(td.select(*stored).unsqueeze(0))
        if step >= settings.learning_starts and step % settings.train_every == 0:
            _gradient_step(agent, settings.batch_size)
        td = env.step_mdp(td)
        if bool(td.get("done").any()):
            td.set("_reset", td.get("done"))
            td = env.reset(td)
        _tick(progress, step, config.steps)
    wall = time.perf_counter() - started
    env.close()
    result = recorder.result()
    result.update(_evaluate(config, unit, agent.value_network), wall_s=wall)
    result["steps_per_s"] = config.steps / wall
    return result


def _run_factor_q(
    config: GymConfig, unit: dict[str, Any], progress: Callable[[int], None]
) -> dict[str, Any]:
    import torch

    from factorq_torch.base.config import AgentConfig
    from factorq_torch.base.rng import STREAM_POLICY
    from factorq_torch.collectors import OnlineCollector
    from factorq_torch.structure import StructureLearner
    from factorq_torch.tables import LocalRewardTable
    from factorq_trainers.experiments.experiment import online_agent

    base, task = _env_and_task_network(config, unit, zero_output=True)
    oracle = base.dependency
    if unit["method"] == "factor-q-oracle":
        if oracle is None:
            raise ValueError(
                f"factor-q-oracle needs a world that declares its oracle: {config.world}"
            )
        local = LocalRewardTable(1, dependency=oracle)
    else:  # an open actuator predicts no local reward (docs/decisions.md, MiniGrid)
        local = StructureLearner(
            1, num_actions=base.num_actions, num_sensors=base.num_sensors, prediction="committed"
        )
    agent = AgentConfig(gamma=HIGHWAY_DQN["gamma"])
    env, policy, loss = online_agent(
        base, task, local, agent, _keys(config, unit, STREAM_POLICY), epsilon=FACTOR_Q_EPSILON
    )
    optimizer = torch.optim.Adam(task.parameters(), lr=FACTOR_Q_LR)
    collector = OnlineCollector(
        env, policy, loss, runs=1, episodes=config.steps, optimizer=optimizer
    )
    recorder = Recorder(config)
    started = time.perf_counter()
    for step, td in enumerate(collector, start=1):
        recorder.update(*_transition(td))
        _tick(progress, step, config.steps)
        if step >= config.steps:
            break
    wall = time.perf_counter() - started
    collector.shutdown()
    result = recorder.result()
    result.update(_evaluate(config, unit, policy), wall_s=wall)
    result["steps_per_s"] = config.steps / wall
    declaration = base.declaration
    if oracle is not None:  # the declared names and oracle, for a summary without torch
        result["oracle"] = oracle.to(torch.int64).tolist()
        result["actuator_names"] = list(base.config.actuator_names)
        result["sensor_names"] = list(declaration.sensor_names) or [
            f"s{k}" for k in range(base.num_sensors)
        ]
    if isinstance(local, StructureLearner):
        learned = local.structure()[0]  # [A, K]
        result["structure"] = learned.to(torch.int64).tolist()
        if oracle is not None:  # a world without one: the structure alone
            result["agrees_with_oracle"] = (learned == oracle).all(dim=-1).tolist()
    return result


def _evaluate(config: GymConfig, unit: dict[str, Any], policy: Any) -> dict[str, Any]:
    """The greedy policy (exploration off) for ``eval_episodes`` episodes on fresh env seeds."""
    import torch
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    crashes, returns = 0, []
    for episode in range(config.eval_episodes):
        seed = _env_seed(config, unit["seed_index"] * config.eval_episodes + episode, True)
        env = _torchrl_env(config, seed)
        td, total, crashed = env.reset(), 0.0, False
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            while True:
                td = env.step(policy(td))
                hit, reward, done = _transition(td)
                total += reward
                crashed |= hit
                if done:
                    break
                td = env.step_mdp(td)
        env.close()
        crashes += int(crashed)
        returns.append(total)
    return {"greedy_crash_rate": crashes / config.eval_episodes, "greedy_return": _mean(returns)}


def _run_sb3(
    config: GymConfig, unit: dict[str, Any], progress: Callable[[int], None]
) -> dict[str, Any]:
    """SB3's DQN with the documented hyperparameters on the world's own observation; crashes
    and returns read from the adapter's ``info`` by a recording wrapper."""
    import gymnasium
    import torch
    from stable_baselines3 import DQN

    recorder = Recorder(config)

    class Record(gymnasium.Wrapper):
        def step(self, action: Any) -> Any:
            out = self.env.step(action)
            observation, reward, terminated, truncated, info = out
            recorder.update(bool(info["collided"]), float(reward), terminated or truncated)
            _tick(progress, recorder.step, config.steps)
            return out

    def make(seed: int) -> gymnasium.Env:
        env = _maker(config)(seed)
        return gymnasium.wrappers.FilterObservation(env, [config.spec.observation])

    torch.manual_seed(_env_seed(config, unit["seed_index"]))
    env = Record(gymnasium.wrappers.FlattenObservation(make(_env_seed(config, unit["seed_index"]))))
    settings = HIGHWAY_DQN
    model = DQN(
        "MlpPolicy",
        env,
        policy_kwargs={"net_arch": list(settings["hidden"])},
        learning_rate=settings["lr"],
        buffer_size=settings["buffer_size"],
        learning_starts=settings["learning_starts"],
        batch_size=settings["batch_size"],
        gamma=settings["gamma"],
        train_freq=settings["train_every"],
        gradient_steps=1,
        target_update_interval=settings["target_update_interval"],
        exploration_fraction=settings["exploration_fraction"],
        seed=_env_seed(config, unit["seed_index"]),
        device="cpu",
    )
    started = time.perf_counter()
    model.learn(total_timesteps=config.steps)
    wall = time.perf_counter() - started
    crashes, returns = 0, []
    for episode in range(config.eval_episodes):
        seed = _env_seed(config, unit["seed_index"] * config.eval_episodes + episode, True)
        evaluation = gymnasium.wrappers.FlattenObservation(make(seed))
        observation, _ = evaluation.reset()
        total, crashed, done = 0.0, False, False
        while not done:
            action, _ = model.predict(observation, deterministic=True)
            observation, reward, terminated, truncated, info = evaluation.step(int(action))
            total += float(reward)
            crashed |= bool(info["collided"])
            done = terminated or truncated
        crashes += int(crashed)
        returns.append(total)
    result = recorder.result()
    result.update(
        greedy_crash_rate=crashes / config.eval_episodes,
        greedy_return=_mean(returns),
        wall_s=wall,
        steps_per_s=config.steps / wall,
    )
    return result


# --------------------------------------------------------------------------------------------
# Results (no torch below)

MEASURES = (
    "crashes_per_1000",
    "greedy_crash_rate",
    "greedy_return",
    "steps_to_threshold",
    "steps_per_s",
)


#: The measures that are proportions (per seed in [0, 1]): Wilson's interval.
PROPORTIONS = ("greedy_crash_rate",)
CURVES = ("curve_crashes", "curve_return")


def _stat(values: list[float | None], seed: int, proportion: bool = False) -> dict[str, Any]:
    """Mean over the seeds that have a value, its 95% interval (Wilson's for a proportion, the
    BCa bootstrap's otherwise: neither leaves the possible range) and how many seeds have one."""
    present = [v for v in values if v is not None]
    if not present:
        return {"mean": None, "ci95": None, "n": 0}
    method = wilson_ci if proportion else functools.partial(bootstrap_mean_ci, seed=seed)
    mean, low, high = scalar_ci(present, method)
    return {"mean": mean, "ci95": interval(low, high), "n": len(present)}


def _band(rows: list[list[float | None]], seed: int) -> dict[str, list[float | None]]:
    """A curve's mean over seeds at each point and its 95% BCa bootstrap band, over the seeds
    with a value there (``None``: no seed has one; no band from a single seed). One bootstrap
    per set of seeds present (the return is missing before a seed's first episode)."""
    points = max(len(row) for row in rows)
    values = np.full((len(rows), points), np.nan)
    for index, row in enumerate(rows):
        values[index, : len(row)] = [np.nan if value is None else value for value in row]
    mean, low, high = (np.full(points, np.nan) for _ in range(3))
    present = ~np.isnan(values)  # [seeds, points]
    for pattern in {tuple(column) for column in present.T.tolist()}:
        seeds = np.array(pattern, dtype=bool)
        if not seeds.any():
            continue
        columns = (present.T == seeds).all(axis=1)
        centre, band_low, band_high = bootstrap_mean_ci(values[seeds][:, columns], seed)
        mean[columns] = centre
        if band_low is not None and band_high is not None:
            low[columns], high[columns] = band_low, band_high
    return {
        name: [finite_or_none(value) for value in array]
        for name, array in (("mean", mean), ("low", low), ("high", high))
    }


def summarise(config: GymConfig, unit_results: list[dict[str, Any]]) -> dict[str, Any]:
    """Per method: each measure's mean and 95% interval over seeds (Wilson for the greedy crash
    rate, else the BCa bootstrap), the curves of every seed and their mean and band over seeds,
    and (learned dependencies) how many seeds' learner agrees with the oracle per actuator.

    Args:
        config: the experiment.
        unit_results: ``run_unit``'s results, in ``units(config)`` order.
    """
    by_method: dict[str, list[dict[str, Any]]] = {}
    for unit, result in zip(units(config), unit_results, strict=True):
        by_method.setdefault(unit["method"], []).append(result)
    methods = {}
    for method, results in by_method.items():
        entry: dict[str, Any] = {
            name: _stat([r[name] for r in results], config.seed, name in PROPORTIONS)
            for name in MEASURES
        }
        entry["curves"] = {name: [r[name] for r in results] for name in ("curve_steps", *CURVES)}
        entry["bands"] = {name: _band(entry["curves"][name], config.seed) for name in CURVES}
        entry["reached"] = sum(r["steps_to_threshold"] is not None for r in results)
        entry["wall_s"] = sum(r["wall_s"] for r in results)
        if "structure" in results[0]:
            entry["structures"] = [r["structure"] for r in results]
        if "agrees_with_oracle" in results[0]:
            entry["agrees_with_oracle"] = [
                sum(r["agrees_with_oracle"][a] for r in results)
                for a in range(len(results[0]["agrees_with_oracle"]))
            ]
        methods[method] = entry
    out: dict[str, Any] = {
        "methods": methods,
        "world": config.spec.label,
        "threshold": config.return_threshold,
    }
    declared = next((r for r in unit_results if "oracle" in r), None)
    if declared is not None:
        out["sensors"] = declared["sensor_names"]
        out["actuators"] = declared["actuator_names"]
        out["oracle"] = declared["oracle"]
    return out


def run(config: GymConfig, progress: Callable[[int], None] | None = None) -> dict[str, Any]:
    """Every unit here, summarised into the runner's envelope (no files).

    Args:
        config: the experiment.
        progress: called with env steps done.
    """
    import sys

    from factorq_trainers.runner import frame

    return frame.run_in_process(sys.modules[__name__], config, progress)
