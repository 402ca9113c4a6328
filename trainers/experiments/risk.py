"""``risk``: torchrl's DQN alone against DQN + local risk (issue 26), side by side.

A command module (``/work/coord/COMMAND_PROTOCOL.md``): the runner owns options, the output
folder, resume and progress; this module declares the config, the units (one per world, method
and seed), what one unit runs and how the units are summarised.

Every unit trains torchrl's DQN recipe (``QValueActor``, ``EGreedyModule``, ``DQNLoss``,
``SoftUpdate``, ``Collector``, a ``ReplayBuffer``) on one world, with the same budget, network and
seed for every method; the methods differ only by the two lines of ``factorq_torch.risk``:

- ``dqn``: the recipe alone;
- ``dqn+risk-oracle``: plus ``LocalRisk`` over a ``LocalRewardTable`` given the env's true
  dependency, trained by ``LocalRiskLoss`` on every collected transition;
- ``dqn+risk-learned``: the same over a ``StructureLearner`` (told only the number of actuators
  and sensors);
- ``sb3-dqn`` / ``sb3-dqn+risk-oracle``: Stable-Baselines3's DQN on the gymnasium grid, alone and
  with ``factorq_torch.integrations.sb3`` (the ``sb3`` extra).

Every method reads the conventional reward (``SplitLocalReward(keep_reward=True)``: collisions
included), so DQN alone can learn to avoid collisions itself; the layer only adds
``local_reward``. Worlds: ``grid``, the dynamic FactoredGrid world (obstacles move every step);
``minigrid``, MiniGrid Dynamic-Obstacles (``size`` 8 by default; the ``minigrid`` extra).
highway-env waits for the Gymnasium-adapter issue.

Per unit: collisions during training, greedy collisions and success over ``eval_episodes`` greedy
episodes after training, the mean conventional return of the last 20% of training episodes, and
``steps_to_threshold``, the env steps until the success rate of the last 10 training episodes
first reaches ``success_threshold`` (None if never). The ``dqn+risk-*`` units also log what the
layer did in every training episode (``factorq_torch.risk.RiskSummary``: steps it penalised,
greedy choices it overrode, how often and how much each actuator was penalised), kept in the
results under ``risk_log`` and summarised in the report.

torchrl's INFO messages (its ``torchrl`` logger prints one per replay buffer it allocates) are
silenced while a unit runs, and its level restored after: the command's output is the report, and
anyone using torchrl keeps its defaults.
"""

from __future__ import annotations

import contextlib
import logging
import math
import statistics
import time
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from factorq_trainers.runner.options import option

if TYPE_CHECKING:
    import torch

    from factorq_torch.structure import StructureLearner
    from factorq_torch.tables import LocalRewardTable

Progress = Callable[[int], None]

NAME = "risk"
HELP = "torchrl's DQN (and SB3's) alone against DQN + local risk, side by side"
WORK_UNIT = "step"
WORLDS = ("grid", "minigrid")
METHODS = ("dqn", "dqn+risk-oracle", "dqn+risk-learned", "sb3-dqn", "sb3-dqn+risk-oracle")
TORCHRL_METHODS = METHODS[:3]


def _names(value: Any, field: str, allowed: tuple[str, ...]) -> tuple[str, ...]:
    if isinstance(value, str):
        value = tuple(part.strip() for part in value.split(",") if part.strip())
    value = tuple(value)
    unknown = [name for name in value if name not in allowed]
    if not value or unknown:
        raise ValueError(f"{field}={value!r}: choose one or more of {allowed}")
    return value


@dataclass(frozen=True)
class RiskConfig:
    """One budget for every method (module docstring).

    Args:
        worlds, methods, sb3_worlds: what runs (``WORLDS``, ``METHODS``; comma-separated text
            or a tuple).
        seeds, seed: seeds per (world, method), from ``seed`` on.
        steps: training env steps per unit.
        grid_size, grid_obstacles, minigrid_size: the worlds.
        hidden, lr, gamma, buffer_size, batch_size: the DQN recipe, the same for every method.
        learning_starts, train_every, tau: when it learns and how fast its target follows.
        eps_start, eps_end, exploration_fraction: its exploration schedule.
        eval_episodes: greedy episodes after training.
        success_threshold: the success rate of 10 episodes that counts as learned.
        out: the output directory.
    """

    worlds: tuple[str, ...] = option(("grid", "minigrid"), "Worlds: grid, minigrid.")
    methods: tuple[str, ...] = option(TORCHRL_METHODS, f"Methods, of {', '.join(METHODS)}.")
    sb3_worlds: tuple[str, ...] = option(("grid",), "Worlds the sb3-* methods run on.")
    seeds: int = option(3, "Seeds per (world, method).")
    seed: int = option(0, "First seed.")
    steps: int = option(3000, "Env steps of training per unit.")
    grid_size: int = option(6, "Side of the dynamic grid.")
    grid_obstacles: int = option(6, "Obstacles of the dynamic grid (they move every step).")
    minigrid_size: int = option(8, "Side of MiniGrid Dynamic-Obstacles.")
    hidden: int = option(64, "Width of the two hidden layers of the Q-network.")
    lr: float = option(1e-3, "Adam learning rate.")
    gamma: float = option(0.9, "Discount.")
    buffer_size: int = option(10_000, "Replay buffer capacity (transitions).")
    batch_size: int = option(64, "Minibatch size.")
    learning_starts: int = option(200, "Env steps before the first gradient step.")
    train_every: int = option(2, "Env steps per gradient step.")
    tau: float = option(0.02, "SoftUpdate's rate (target <- (1 - tau) target + tau net).")
    eps_start: float = option(1.0, "Initial epsilon.")
    eps_end: float = option(0.05, "Final epsilon.")
    exploration_fraction: float = option(0.3, "Fraction of the steps epsilon anneals over.")
    eval_episodes: int = option(10, "Greedy episodes after training.")
    success_threshold: float = option(0.8, "Success rate of 10 episodes that counts as learned.")
    out: str = option("results/risk", "Directory for the json, figure and report.")

    def __post_init__(self) -> None:
        object.__setattr__(self, "worlds", _names(self.worlds, "worlds", WORLDS))
        object.__setattr__(self, "methods", _names(self.methods, "methods", METHODS))
        object.__setattr__(self, "sb3_worlds", _names(self.sb3_worlds, "sb3_worlds", WORLDS))
        for name in ("seeds", "steps", "hidden", "buffer_size", "batch_size", "train_every"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name}={value!r} must be an integer >= 1")
        for name in ("seed", "learning_starts", "eval_episodes"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ValueError(f"{name}={value!r} must be an integer >= 0")
        if self.grid_size < 3 or self.minigrid_size < 5:
            raise ValueError("grid_size must be >= 3 and minigrid_size >= 5")
        for name, low, high in (
            ("lr", 0.0, 1.0),
            ("gamma", 0.0, 1.0),
            ("tau", 0.0, 1.0),
            ("eps_start", 0.0, 1.0),
            ("eps_end", 0.0, 1.0),
            ("exploration_fraction", 0.0, 1.0),
            ("success_threshold", 0.0, 1.0),
        ):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not low <= value <= high:
                raise ValueError(f"{name}={value!r} must be a number in [{low}, {high}]")
        if self.eps_end > self.eps_start:
            raise ValueError(f"eps_end={self.eps_end} must be <= eps_start={self.eps_start}")


CONFIG = RiskConfig


def units(config: RiskConfig) -> list[dict[str, Any]]:
    """One unit per (world, method, seed); sb3 methods only on ``sb3_worlds``.

    Args:
        config: the experiment.
    """
    found = []
    for world in config.worlds:
        for method in config.methods:
            if method.startswith("sb3") and world not in config.sb3_worlds:
                continue
            for index in range(config.seeds):
                seed = config.seed + index
                found.append(
                    {
                        "id": f"{world}/{method}/{seed}",
                        "world": world,
                        "method": method,
                        "seed": seed,
                    }
                )
    return found


# --------------------------------------------------------------------------------------------
# One unit: the torchrl recipe


def make_env(config: RiskConfig, world: str, seed: int) -> Any:  # a TransformedEnv (untyped)
    """The world as a torchrl env of batch ``[1]`` with ``local_reward`` beside the reward.

    Args:
        config: the experiment.
        world: ``"grid"`` or ``"minigrid"``.
        seed: the world's seed.
    """
    from torchrl.envs import TransformedEnv

    from factorq_envs import FactoredGridEnv, SplitLocalReward

    if world == "grid":
        base = FactoredGridEnv(
            size=config.grid_size,
            num_obstacles=config.grid_obstacles,
            obstacle_period=1,
            batch_size=(1,),
            seed=seed,
        )
    else:
        from factorq_envs.minigrid_torchrl import MiniGridEnv

        base = MiniGridEnv(config.minigrid_size, seeds=[seed])
    return TransformedEnv(base, SplitLocalReward(keep_reward=True))


def features(env: Any) -> tuple[Any, int]:
    """``observation`` ``[*B, N H + K]``: the (cell, heading) one-hot and the sensor bits, the
    information Q-learning's state holds, as a TensorDict module, and its width.

    Args:
        env: a ``make_env`` env.
    """
    import torch
    from tensordict.nn import TensorDictModule

    spec = env.observation_spec
    cells = int(spec["cell"].space.n)
    headings = int(spec["heading"].space.n) if "heading" in spec.keys() else 1

    class Features(torch.nn.Module):
        def forward(
            self, cell: torch.Tensor, sensors: torch.Tensor, heading: torch.Tensor | None = None
        ) -> torch.Tensor:
            position = cell if heading is None else cell * headings + heading
            one_hot = torch.nn.functional.one_hot(position, cells * headings).to(torch.float32)
            return torch.cat([one_hot, sensors.to(torch.float32)], dim=-1)

    in_keys = ["cell", "sensors"] + (["heading"] if headings > 1 else [])
    width = cells * headings + spec["sensors"].shape[-1]
    return TensorDictModule(Features(), in_keys=in_keys, out_keys=["observation"]), width


def provider(method: str, env: Any) -> LocalRewardTable | StructureLearner | None:
    """The local value provider of a ``dqn+risk-*`` method (None for plain DQN).

    Args:
        method: one of ``METHODS``.
        env: a ``make_env`` env (its base env's dependency).
    """
    from factorq_torch.structure import StructureLearner
    from factorq_torch.tables import LocalRewardTable

    dependency = env.base_env.dependency
    if method.endswith("risk-oracle"):
        return LocalRewardTable(1, dependency=dependency)
    if method.endswith("risk-learned"):
        actions, sensors = dependency.shape
        return StructureLearner(1, num_actions=actions, num_sensors=sensors)
    return None


class _Tally:
    """Training episodes of one world: collisions, returns, successes, steps to threshold."""

    def __init__(self, threshold: float) -> None:
        self.threshold, self.steps, self.collisions = threshold, 0, 0
        self.returns: list[float] = []
        self.successes: list[bool] = []
        self.current = 0.0
        self.steps_to_threshold: int | None = None

    def step(self, reward: float, collided: bool, done: bool, success: bool) -> None:
        self.steps += 1
        self.collisions += int(collided)
        self.current += reward
        if done:
            self.returns.append(self.current)
            self.successes.append(success)
            self.current = 0.0
            recent = self.successes[-10:]
            if (
                self.steps_to_threshold is None
                and len(recent) == 10
                and sum(recent) / 10 >= self.threshold
            ):
                self.steps_to_threshold = self.steps


def _step_flags(td: Any) -> tuple[list[float], list[bool], list[bool], list[bool]]:
    """Per world of one collected step: reward, collided, done, success (the goal reached)."""
    reward = td["next", "reward"].reshape(-1).tolist()
    collided = (td["next", "collision"] < 0).any(-1).reshape(-1)
    done = td["next", "done"].reshape(-1)
    success = td["next", "terminated"].reshape(-1) & ~collided
    return reward, collided.tolist(), done.tolist(), success.tolist()


def run_torchrl(
    config: RiskConfig, unit: dict[str, Any], progress: Progress | None = None
) -> dict[str, Any]:
    """torchrl's DQN recipe, plus the two lines of the local-risk layer for ``dqn+risk-*``.

    Args:
        config: the experiment.
        unit: one of ``units(config)``.
        progress: called with the env steps of each collected batch.
    """
    import torch
    from tensordict.nn import TensorDictSequential
    from torchrl.data import LazyTensorStorage, ReplayBuffer
    from torchrl.modules import MLP, EGreedyModule, QValueActor
    from torchrl.objectives import DQNLoss, SoftUpdate

    from factorq_torch.risk import RISK_MASK, LocalRisk, LocalRiskLoss, RiskSummary, with_local_risk

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=DeprecationWarning)
        from torchrl.collectors import Collector

    torch.manual_seed(unit["seed"])
    env = make_env(config, unit["world"], unit["seed"])
    spec = env.action_spec_unbatched
    encoder, width = features(env)
    network = MLP(in_features=width, out_features=int(spec.space.n), num_cells=[config.hidden] * 2)
    actor = QValueActor(
        TensorDictSequential(encoder, _module(network)), in_keys=["cell"], spec=spec
    )
    local = provider(unit["method"], env)
    acting = actor if local is None else with_local_risk(actor, local, env=env)  # line 1
    local_loss = None if local is None else LocalRiskLoss(local)  # line 2
    summary: RiskSummary | None = None  # what the layer did, per training episode (the logs)
    if local is not None:
        layer = next(module for module in acting.modules() if isinstance(module, LocalRisk))
        summary = RiskSummary(layer.actuator_names)
    risk_log: list[dict[str, Any]] = []
    annealing = max(1, round(config.exploration_fraction * config.steps))
    mask = None if local is None else RISK_MASK  # explore among the actions not called risky
    egreedy = EGreedyModule(
        spec,
        eps_init=config.eps_start,
        eps_end=config.eps_end,
        annealing_num_steps=annealing,
        action_mask_key=mask,
    )
    policy = TensorDictSequential(acting, egreedy)
    loss = DQNLoss(actor, action_space=spec, delay_value=True, loss_function="l2")
    loss.make_value_estimator(gamma=config.gamma)
    target = SoftUpdate(loss, tau=config.tau)
    optimizer = torch.optim.Adam(loss.parameters(), lr=config.lr)
    buffer = ReplayBuffer(
        storage=LazyTensorStorage(config.buffer_size), batch_size=config.batch_size
    )
    collector = Collector(
        env,
        policy,
        frames_per_batch=config.train_every,
        total_frames=config.steps,
        auto_register_policy_transforms=False,  # no recurrent state
    )
    tally = _Tally(config.success_threshold)
    started = time.perf_counter()
    for data in collector:  # [1, T]
        data = data.reshape(-1)
        for t in range(data.shape[0]):
            step = data[t : t + 1]
            if summary is not None:
                summary.update(step)
            for flags in zip(*_step_flags(step), strict=True):
                tally.step(*flags)
                if summary is not None and flags[2]:  # the episode is done
                    risk_log.append(summary.episode())
        egreedy.step(data.shape[0])
        if local_loss is not None:
            local_loss(data)  # eq. 5 on every transition once (the running means)
        buffer.extend(data)
        if tally.steps >= config.learning_starts:
            sample = buffer.sample()
            value = loss(sample)["loss"]
            optimizer.zero_grad()
            value.backward()
            optimizer.step()
            target.step()
        if progress is not None:
            progress(data.shape[0])
    collector.shutdown()
    wall = time.perf_counter() - started
    greedy = evaluate(config, unit, acting)
    result = _result(tally, greedy, wall)
    if summary is not None:
        result["risk_log"] = risk_log
    return result


def _module(network: torch.nn.Module) -> Any:
    from tensordict.nn import TensorDictModule

    return TensorDictModule(network, in_keys=["observation"], out_keys=["action_value"])


def evaluate(config: RiskConfig, unit: dict[str, Any], acting: Any) -> dict[str, int]:
    """Greedy episodes after training (torchrl's ``DETERMINISTIC`` exploration) on fresh worlds
    of the same kind: collisions and successes.

    Args:
        config: the experiment.
        unit: one of ``units(config)``.
        acting: the greedy policy (a tensordict module).
    """
    import torch
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    env = make_env(config, unit["world"], 10_000 + unit["seed"])
    collisions = successes = 0
    limit = 4 * (config.grid_size if unit["world"] == "grid" else config.minigrid_size) ** 2
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        for _ in range(config.eval_episodes):
            rollout = env.rollout(limit, acting, break_when_any_done=True)
            collided = (rollout["next", "collision"] < 0).any(-1)
            collisions += int(collided.sum())
            successes += int((rollout["next", "terminated"].squeeze(-1) & ~collided).any())
    return {"collisions": collisions, "successes": successes, "episodes": config.eval_episodes}


def _result(tally: _Tally, greedy: dict[str, int], wall: float) -> dict[str, Any]:
    tail = tally.returns[-max(1, len(tally.returns) // 5) :] if tally.returns else [math.nan]
    return {
        "train_collisions": tally.collisions,
        "episodes": len(tally.returns),
        "final_return": statistics.fmean(tail),
        "steps_to_threshold": tally.steps_to_threshold,
        "greedy_collisions": greedy["collisions"],
        "greedy_success": greedy["successes"] / max(1, greedy["episodes"]),
        "wall_s": wall,
    }


# --------------------------------------------------------------------------------------------
# One unit: Stable-Baselines3


def run_sb3(
    config: RiskConfig, unit: dict[str, Any], progress: Progress | None = None
) -> dict[str, Any]:
    """SB3's DQN on the gymnasium grid (``FactoredGrid-v0``), alone or as ``LocalRiskDQN`` with
    the oracle table (the ``sb3`` extra); the same budget and hyperparameters as the torchrl
    units.

    Args:
        config: the experiment.
        unit: one of ``units(config)`` (its world must be ``"grid"``).
        progress: called with the env steps of each callback.
    """
    import gymnasium
    from stable_baselines3 import DQN
    from stable_baselines3.common.callbacks import BaseCallback

    import factorq_envs  # noqa: F401  (registers FactoredGrid-v0)
    from factorq_envs.gymnasium_env import FactoredGridGym
    from factorq_torch.integrations.sb3 import LocalRiskDQN
    from factorq_torch.tables import LocalRewardTable

    if unit["world"] != "grid":
        raise ValueError("the sb3 methods run on the grid world only (sb3_worlds)")
    tally = _Tally(config.success_threshold)

    class Tally(BaseCallback):
        def _on_step(self) -> bool:
            for reward, done, info in zip(
                self.locals["rewards"], self.locals["dones"], self.locals["infos"], strict=True
            ):
                collided = bool((info["local_reward"] < 0).any())
                success = bool(done) and not info.get("TimeLimit.truncated", False)
                tally.step(float(reward), collided, bool(done), success and not collided)
            if progress is not None:
                progress(len(self.locals["infos"]))
            return True

    def grid_env(seed: int) -> gymnasium.Env:
        env = gymnasium.make(
            "FactoredGrid-v0",
            size=config.grid_size,
            num_obstacles=config.grid_obstacles,
            obstacle_period=1,
        )
        env.reset(seed=seed)
        return env

    env = grid_env(unit["seed"])
    settings: dict[str, Any] = dict(
        learning_rate=config.lr,
        buffer_size=config.buffer_size,
        learning_starts=config.learning_starts,
        batch_size=config.batch_size,
        tau=config.tau,
        gamma=config.gamma,
        train_freq=config.train_every,
        target_update_interval=1,  # with tau: SoftUpdate every gradient step, as torchrl's
        exploration_fraction=config.exploration_fraction,
        exploration_initial_eps=config.eps_start,
        exploration_final_eps=config.eps_end,
        policy_kwargs={"net_arch": [config.hidden, config.hidden]},
        seed=unit["seed"],
        verbose=0,
    )
    if unit["method"] == "sb3-dqn":
        model = DQN("MultiInputPolicy", env, **settings)
    else:
        grid = env.unwrapped
        assert isinstance(grid, FactoredGridGym)  # what FactoredGrid-v0 makes; for mypy
        provider = LocalRewardTable(1, dependency=grid.config.dependency)
        model = LocalRiskDQN("MultiInputPolicy", env, provider=provider, **settings)
    started = time.perf_counter()
    model.learn(config.steps, callback=Tally())
    wall = time.perf_counter() - started
    evaluation = grid_env(10_000 + unit["seed"])
    collisions = successes = 0
    for _ in range(config.eval_episodes):
        obs, _ = evaluation.reset()
        for _ in range(4 * config.grid_size**2):
            action, _ = model.predict(obs, deterministic=True)
            obs, _, terminated, truncated, info = evaluation.step(int(action))
            collided = bool((info["local_reward"] < 0).any())
            collisions += int(collided)
            if terminated or truncated:
                successes += int(terminated and not collided)
                break
    greedy = {"collisions": collisions, "successes": successes, "episodes": config.eval_episodes}
    return _result(tally, greedy, wall)


def work(config: RiskConfig, unit: dict[str, Any]) -> int:
    """The unit's share of the progress bar: its training env steps (what ``run_unit`` reports).

    Args:
        config: the experiment.
        unit: one of ``units(config)``.
    """
    return config.steps


@contextlib.contextmanager
def quiet_torchrl() -> Iterator[None]:
    """torchrl's logger at WARNING while the block runs (it prints an INFO line per replay buffer
    it allocates, to stdout by default), its own level restored after."""
    import torchrl  # noqa: F401  (its import sets the logger's level: before ours, not after)

    logger = logging.getLogger("torchrl")
    level = logger.level
    if logger.getEffectiveLevel() < logging.WARNING:
        logger.setLevel(logging.WARNING)
    try:
        yield
    finally:
        logger.setLevel(level)


def run_unit(
    config: RiskConfig, unit: dict[str, Any], progress: Progress | None = None
) -> dict[str, Any]:
    """Train and evaluate one (world, method, seed), without torchrl's INFO lines
    (``quiet_torchrl``).

    Args:
        config: the experiment.
        unit: one of ``units(config)``.
        progress: called with env steps done.
    """
    with quiet_torchrl():
        if unit["method"].startswith("sb3"):
            result = run_sb3(config, unit, progress)
        else:
            result = run_torchrl(config, unit, progress)
    return {**{key: unit[key] for key in ("world", "method", "seed")}, **result}


# --------------------------------------------------------------------------------------------
# Summary, report, figure (no torch)

METRICS = (
    "train_collisions",
    "greedy_collisions",
    "final_return",
    "greedy_success",
    "steps_to_threshold",
    "wall_s",
)


def _mean(values: list[float | None]) -> float | None:
    found = [v for v in values if v is not None and not (isinstance(v, float) and math.isnan(v))]
    return statistics.fmean(found) if found else None


#: What ``factorq sweep --command risk`` reports per configuration (``sweep_cells``): means
#: over seeds (the summary keeps no interval).
SWEEP_MEASURES = ("train_collisions", "greedy_collisions", "final_return", "greedy_success")


def sweep_cells(results: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Per world and method of a ``risk.json`` dict: the ``SWEEP_MEASURES``' means.

    Args:
        results: the dict of ``risk.json``.
    """
    return {
        f"{row['world']}/{row['method']}": {
            "world": row["world"],
            "algorithm": row["method"],
            **{measure: {"mean": row[measure], "ci95": None} for measure in SWEEP_MEASURES},
        }
        for row in results["rows"]
    }


def _difference(first: float | None, second: float | None) -> float | None:
    """``first - second``; ``None`` where a side has no finished episode to give a return."""
    return None if first is None or second is None else first - second


def summarise(config: RiskConfig, unit_results: list[dict[str, Any]]) -> dict[str, Any]:
    """Means over seeds per (world, method), and the ratios the issue's targets name.

    Args:
        config: the experiment.
        unit_results: ``run_unit``'s results.
    """
    groups: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for result in unit_results:
        groups.setdefault((result["world"], result["method"]), []).append(result)
    rows = []
    for (world, method), found in sorted(groups.items()):
        row: dict[str, Any] = {"world": world, "method": method, "seeds": len(found)}
        for metric in METRICS:
            row[metric] = _mean([r[metric] for r in found])
        row["reached"] = sum(r["steps_to_threshold"] is not None for r in found)
        rows.append(row)
    by = {(row["world"], row["method"]): row for row in rows}
    ratios = []
    for world in config.worlds:
        for base, with_risk in (
            ("dqn", "dqn+risk-oracle"),
            ("dqn", "dqn+risk-learned"),
            ("sb3-dqn", "sb3-dqn+risk-oracle"),
        ):
            if (world, base) in by and (world, with_risk) in by:
                alone, risk = by[world, base], by[world, with_risk]
                ratios.append(
                    {
                        "world": world,
                        "pair": f"{base} / {with_risk}",
                        "collision_ratio": alone["train_collisions"]
                        / max(risk["train_collisions"], 1e-9),
                        "return_gain": _difference(risk["final_return"], alone["final_return"]),
                    }
                )
        if (world, "dqn+risk-learned") in by and (world, "dqn+risk-oracle") in by:
            learned, oracle = by[world, "dqn+risk-learned"], by[world, "dqn+risk-oracle"]
            ratios.append(
                {
                    "world": world,
                    "pair": "learned / oracle collisions",
                    "collision_ratio": learned["train_collisions"]
                    / max(oracle["train_collisions"], 1e-9),
                    "return_gain": _difference(learned["final_return"], oracle["final_return"]),
                }
            )
    return {"rows": rows, "ratios": ratios, **risk_logs(unit_results)}


def risk_logs(unit_results: list[dict[str, Any]]) -> dict[str, Any]:
    """The layer's per-episode ``RiskSummary`` of every ``dqn+risk-*`` unit (``risk_log``, by
    unit id) and their totals per (world, method) over seeds (``risk_rows``): training episodes,
    steps, the share of steps it penalised an actuator, greedy choices it overrode per episode,
    and per actuator how often it was penalised and by how much on average."""
    log: dict[str, list[dict]] = {}
    groups: dict[tuple[str, str], list[dict]] = {}
    for result in unit_results:
        episodes = result.get("risk_log")
        if episodes is None:  # a method without the layer (or a unit kept before the log)
            continue
        log[f"{result['world']}/{result['method']}/{result['seed']}"] = episodes
        groups.setdefault((result["world"], result["method"]), []).extend(episodes)
    rows = []
    for (world, method), episodes in sorted(groups.items()):
        steps = sum(episode["steps"] for episode in episodes)
        counts: dict[str, int] = {}
        totals: dict[str, float] = {}
        for episode in episodes:
            for name, count in episode["penalised"].items():
                counts[name] = counts.get(name, 0) + count
                totals[name] = totals.get(name, 0.0) + count * episode["mean_penalty"][name]
        rows.append(
            {
                "world": world,
                "method": method,
                "episodes": len(episodes),
                "steps": steps,
                "penalised_share": sum(e["risky_steps"] for e in episodes) / max(steps, 1),
                "overrides_per_episode": sum(e["overrides"] for e in episodes)
                / max(len(episodes), 1),
                "penalised": counts,
                "mean_penalty": {
                    name: (totals[name] / counts[name] if counts[name] else 0.0) for name in counts
                },
            }
        )
    return {"risk_rows": rows, "risk_log": log}


def _cell(value: float | None, digits: int = 1) -> str:
    if value is None:
        return "-"
    return f"{value:,.{digits}f}"


def markdown(results: dict[str, Any]) -> str:
    """The table of means and the ratios.

    Args:
        results: the dict of ``risk.json``.
    """
    config = results["config"]
    lines = [
        f"DQN alone vs DQN + local risk: {config['steps']:,} env steps per unit, "
        f"{config['seeds']} seeds, means over seeds.",
        "",
        "| world | method | training collisions | greedy collisions | final return | greedy "
        "success | steps to threshold (reached) | wall s |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for row in results["rows"]:
        lines.append(
            f"| {row['world']} | {row['method']} | {_cell(row['train_collisions'])} | "
            f"{_cell(row['greedy_collisions'])} | {_cell(row['final_return'], 2)} | "
            f"{_cell(row['greedy_success'], 2)} | {_cell(row['steps_to_threshold'], 0)} "
            f"({row['reached']}/{row['seeds']}) | {_cell(row['wall_s'])} |"
        )
    if results["ratios"]:
        lines += [
            "",
            "| world | ratio | collisions | return difference |",
            "| --- | --- | ---: | ---: |",
        ]
        for ratio in results["ratios"]:
            lines.append(
                f"| {ratio['world']} | {ratio['pair']} | {ratio['collision_ratio']:.1f}x | "
                + ("-" if ratio["return_gain"] is None else f"{ratio['return_gain']:+.2f}")
                + " |"
            )
    lines += _risk_markdown(results)
    return "\n".join(lines) + "\n"


def _risk_markdown(results: dict[str, Any]) -> list[str]:
    """What the layer did (``risk_rows``), and the last training episode's summary line of each
    (world, method)'s first seed, as ``RiskSummary.line`` writes it."""
    rows = results.get("risk_rows") or []
    if not rows:
        return []
    lines = [
        "",
        "What the layer did in training (`RiskSummary` per episode; totals over seeds):",
        "",
        "| world | method | episodes | steps penalised | overrides per episode | penalised "
        "(times, mean penalty) |",
        "| --- | --- | ---: | ---: | ---: | --- |",
    ]
    for row in rows:
        hits = ", ".join(
            f"{name} x{count:,} ({row['mean_penalty'][name]:.2f})"
            for name, count in sorted(row["penalised"].items(), key=lambda item: -item[1])
            if count
        )
        lines.append(
            f"| {row['world']} | {row['method']} | {row['episodes']:,} | "
            f"{row['penalised_share']:.1%} | {row['overrides_per_episode']:.2f} | {hits or '-'} |"
        )
    log = results.get("risk_log") or {}
    last: dict[tuple[str, str], dict[str, Any]] = {}
    for unit_id, episodes in log.items():  # the first seed of each (world, method)
        world, method, _ = unit_id.rsplit("/", 2)
        if episodes and (world, method) not in last:
            last[world, method] = episodes[-1]
    if last:
        lines += ["", "Last training episode of the first seed:", ""]
        lines += [
            f"- {world} {method}: {_summary_line(summary)}"
            for (world, method), summary in last.items()
        ]
    return lines


def _summary_line(summary: dict[str, Any]) -> str:
    """``RiskSummary.line`` without importing torch (the report is drawn without it)."""
    hits = ", ".join(
        f"{name} x{count} ({summary['mean_penalty'][name]:.2f})"
        for name, count in summary["penalised"].items()
        if count
    )
    return (
        f"risk: {summary['risky_steps']}/{summary['steps']} steps penalised, "
        f"{summary['overrides']} overrides" + (f"; {hits}" if hits else "")
    )


def figure(results: dict[str, Any], path: Path) -> None:
    """Training collisions and final return per method, one panel pair per world.

    Args:
        results: the dict of ``risk.json``.
        path: the PNG to write.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    worlds = sorted({row["world"] for row in results["rows"]})
    fig, axes = plt.subplots(2, len(worlds), figsize=(4.5 * len(worlds), 6), squeeze=False)
    for column, world in enumerate(worlds):
        rows = [row for row in results["rows"] if row["world"] == world]
        labels = [row["method"] for row in rows]
        for line, (metric, title) in enumerate(
            (("train_collisions", "training collisions"), ("final_return", "final return"))
        ):
            axis = axes[line][column]
            axis.bar(range(len(rows)), [row[metric] or 0.0 for row in rows], color="tab:blue")
            axis.set_xticks(range(len(rows)), labels, rotation=30, ha="right", fontsize=8)
            axis.set_title(f"{world}: {title}", fontsize=9)
            if metric == "train_collisions":
                axis.set_yscale("log")
    fig.tight_layout()
    fig.savefig(path, dpi=100, format="png")  # the runner writes a temporary name first
    plt.close(fig)


def run(config: RiskConfig) -> dict[str, Any]:
    """All units here, summarised into the runner's envelope (no files).

    Args:
        config: the experiment.
    """
    import sys

    from factorq_trainers.runner import frame

    return frame.run_in_process(sys.modules[__name__], config)
