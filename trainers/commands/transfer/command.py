"""``factorq transfer``: a body model learned once, carried into a new task (the paper's section 9).

The paper's conclusion: the local model "relates to the agent and is independent of any particular
task", so "for a given embodiment, this would only have to be done once". Here it is done once and
carried: per seed, tabular Factor-Q with the oracle pairing learns its local tables (the *body
model*, ``rho`` and ``kappa`` of eq. 5) in a *source* task, and a fresh task table learns a
*target* task (another grid size, layout and obstacle regime) with that body model, against

- ``factor-q``: Factor-Q learning the target from scratch (the paper's agent),
- ``factor-q-body``: the same agent, starting from the source's body model (still learning it),
- ``q-learning``: the paper's baseline, for the absolute scale,

on the same worlds and policy streams (common random numbers). Measured per seed: collisions in
the first ``early`` episodes of the target (what the body model saves), and the steps per episode
and collisions over the last ``early`` (the final task performance, which it must not cost).

``--body-model PATH`` carries a body model saved with ``factorq_torch.artifacts.save_agent``
instead (``load_body_model``; ``train_body_model`` makes one). Runs on the compiled fast path where
it can, else on the modular torchrl path: the same numbers bit for bit (``run_batch``).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from factorq_envs.grid_world import WorldConfig
from factorq_envs.regimes import REGIME_PERIODS, REGIMES
from factorq_torch.base.config import EXPLORATIONS, AgentConfig
from factorq_torch.base.rng import STREAM_POLICY, STREAM_WORLD, substream_key
from factorq_torch.base.validation import INT32_MAX, check_int, check_names, check_threads
from factorq_trainers.analysis.stats import bootstrap_mean_ci, count_ratio, scalar_ci
from factorq_trainers.analysis.vocabulary import among
from factorq_trainers.commands.transfer.report import PAIRS
from factorq_trainers.compiled import fast
from factorq_trainers.methods import experiment
from factorq_trainers.methods.experiment import MAX_SEED, PAPER_WORLD, experiment_keys
from factorq_trainers.runner.kept import COUNT, FRACTION, NON_NEGATIVE, TEXT
from factorq_trainers.runner.options import check_choices, option

NAME = "transfer"
HELP = "a body model learned once and carried into a new task, against learning from scratch"
DESCRIPTION = (
    "Learn Factor-Q's local tables (the body model) in a source task, then learn a target task "
    "with them against Factor-Q and Q-learning from scratch; write transfer.json, transfer.png "
    "and transfer.md to --out."
)
METHODS = among(
    "factor-q", "factor-q-body", "q-learning", "factor-q-learned", "factor-q-learned-body"
)
#: What runs unless ``--methods`` says otherwise (the learned structure runs on the torchrl path
#: only, minutes where the rest takes seconds: opt-in).
DEFAULT_METHODS = METHODS[:3]
#: The issue's target: the body model's collisions in the first ``early`` episodes of the target
#: at most a fifth of a fresh Factor-Q's.
TARGET_RATIO = 5.0
#: Substream of the source task's keys (the target's are the streams themselves).
SOURCE_SUBSTREAM = 1

#: A unit's result (``run_unit``), what a kept one must hold (``runner.kept``'s schema).
UNIT_RESULT = {
    "early_collisions": [COUNT],
    "late_collisions": [COUNT],
    "late_steps": [NON_NEGATIVE],
    "late_truncated": [FRACTION],
    "collisions_per_episode": [NON_NEGATIVE],
    "path": TEXT,
    "body_from": TEXT,
}


#: The default target: a larger, more crowded grid than the paper's, with another layout.
TARGET_WORLD = WorldConfig(size=14, num_obstacles=20, layout_seed=1)


@dataclass(frozen=True)
class TransferConfig(experiment.WorldOptions):
    """The target task is the world options (``size``, ``obstacles``, ``layout_seed``, the body)
    in each of ``regimes``; the source task shares the body and ``max_steps``."""

    size: int = option(TARGET_WORLD.size, "Side of the target grid, in cells.")
    obstacles: int = option(TARGET_WORLD.num_obstacles, "Obstacles of the target grid.")
    layout_seed: int = option(TARGET_WORLD.layout_seed, "Seed of the target's static layout.")
    regimes: tuple[str, ...] = option(
        REGIMES, "Obstacle regimes of the target: static, semi-dynamic, dynamic (comma-separated)."
    )
    episodes: int = option(100, "Episodes of the target task per seed (one run).")
    early: int = option(20, "The first (and last) episodes the collisions are counted over.")
    source_size: int = option(PAPER_WORLD.size, "Side of the source grid (the paper's).")
    source_obstacles: int = option(PAPER_WORLD.num_obstacles, "Obstacles of the source grid.")
    source_layout_seed: int = option(PAPER_WORLD.layout_seed, "Seed of the source's static layout.")
    source_regime: str = option("static", "Obstacle regime of the source task.", choices=REGIMES)
    source_episodes: int = option(200, "Episodes of the source task per seed (one run).")
    body_model: str | None = option(
        None,
        "A body model saved with factorq_torch.artifacts.save_agent (a LocalRewardTable of 1 or "
        "--seeds experiments) to carry instead of learning one in the source task.",
    )
    exploration: str = option(
        "risk-aware",
        "Factor-Q's exploratory actions: risk-aware (among the actuators its local model does not "
        "call risky) or uniform (the paper's: exploration then walks into known risks, which no "
        "body model can save). Q-learning explores uniformly.",
        choices=EXPLORATIONS,
    )
    methods: tuple[str, ...] = option(
        DEFAULT_METHODS,
        "Methods: "
        + ", ".join(METHODS)
        + " (factor-q-learned, factor-q-learned-body: the structure learner, told "
        "nothing of the pairing, on the torchrl path only: slow, opt-in).",
    )
    seed: int = option(0, "Master seed: worlds and policies derive from it.")
    seeds: int = option(20, "Independent experiments per (method, regime).")
    path: str = option(
        "fast",
        "Where it runs: fast (the compiled kernel, where available) or modular (torchrl).",
        choices=("fast", "modular"),
    )
    threads: int = option(1, "Threads of the compiled path.")
    out: str = option("results/transfer", "Directory for the json, figure and report.")

    def __post_init__(self) -> None:
        check_int("seed", self.seed, 0, MAX_SEED)
        check_int("seeds", self.seeds, 1, 100_000)
        object.__setattr__(self, "regimes", check_names("regimes", self.regimes, REGIMES))
        object.__setattr__(self, "methods", check_names("methods", self.methods, METHODS))
        check_int("episodes", self.episodes, 1, INT32_MAX)
        check_int("early", self.early, 1, self.episodes, f" (episodes={self.episodes})")
        check_int("source_episodes", self.source_episodes, 1, INT32_MAX)
        check_threads("threads", self.threads)
        check_choices(self)  # source_regime, exploration, path: as argparse does
        for world in ("target_world", "source_world"):
            getattr(self, world)  # both checked now, naming the options

    @property
    def target_world(self) -> WorldConfig:
        return self.checked_world(self.regimes)

    @property
    def source_world(self) -> WorldConfig:
        try:
            return experiment.check_world_options(
                self.source_size,
                self.source_obstacles,
                self.max_steps,
                self.source_layout_seed,
                (self.source_regime,),
                experiment.body_options(self),
            )
        except (ValueError, TypeError) as error:
            message = str(error)
            for name in ("size", "obstacles", "layout_seed"):
                message = message.replace(f"{name}=", f"source_{name}=", 1)
            raise type(error)(message) from None

    def agent(self, method: str) -> AgentConfig:
        """The paper's agent; Factor-Q with ``exploration``."""
        return AgentConfig(exploration="uniform" if method == "q-learning" else self.exploration)


CONFIG = TransferConfig


# --------------------------------------------------------------------------------------------
# Running one batch of experiments


def run_batch(
    config: TransferConfig,
    algorithm: str,
    world: WorldConfig,
    regime: str,
    episodes: int,
    *,
    source: bool = False,
    body: dict[str, torch.Tensor] | None = None,
    progress: Callable[[int], None] | None = None,
    learned: bool = False,
) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor] | None, str]:
    """``seeds`` experiments of ``algorithm`` for one run of ``episodes`` in ``world`` with
    ``regime``'s obstacle period, Factor-Q's local model starting from ``body`` when given: the
    oracle's tables (``rho``, ``kappa`` ``[seeds, A, 2**parents]``) or, with ``learned``, a
    ``StructureLearner``'s whole state (its evidence; on the torchrl path only). Returns the
    per-episode metrics ``[seeds, 1, episodes]``, Factor-Q's local model at the end (else None)
    and the path it ran on."""
    # World and policy keys [seeds]: the same for every method (common random numbers); the
    # source task's on their own substream.
    labels = [(regime, index) for index in range(config.seeds)]
    keys = [experiment_keys(config.seed, s, labels) for s in (STREAM_WORLD, STREAM_POLICY)]
    if source:
        keys = [substream_key(key, SOURCE_SUBSTREAM) for key in keys]
    world_keys, policy_keys = keys
    periods = torch.full((config.seeds,), REGIME_PERIODS[regime], dtype=torch.int64)
    agent = config.agent(algorithm)
    fast_path = config.path == "fast" and fast.is_available()
    if fast_path and not learned and fast.unsupported_reason(world) is None:
        batch = fast.ExperimentBatch(
            algorithm, periods, world, agent, 1, episodes, world_keys, policy_keys,
            threads=config.threads,
        )  # fmt: skip
        if body is not None:
            state = batch.state_dict()
            state["rho"], state["kappa"] = body["rho"].clone(), body["kappa"].clone()
            batch.load_state_dict(state)
        metrics = batch.run(progress)
        tables = batch.tables() if algorithm == "factor-q" else None
        local = None if tables is None else {name: tables[name] for name in ("rho", "kappa")}
        return metrics, local, "fast"
    from factorq_torch.collectors import OnlineCollector

    task, table = experiment.tabular_values(algorithm, config.seeds, world)
    if table is not None:  # Factor-Q: the oracle's table or the learner, from ``body`` if given
        table = _local_model(config, world, learned, body)
    env, policy, loss = experiment.online_agent(
        experiment.make_env(world, periods, world_keys), task, table, agent, policy_keys
    )
    on_episodes = None if progress is None else (lambda done, _experiments: progress(done))
    collector = OnlineCollector(env, policy, loss, runs=1, episodes=episodes, progress=on_episodes)
    result = collector.run()
    metrics = {name: result.get(name).clone() for name in result.keys()}
    if table is None:
        return metrics, None, "modular"
    kept = table.state_dict() if learned else {"rho": table.rho, "kappa": table.kappa}
    return metrics, {name: value.clone() for name, value in kept.items()}, "modular"


def _local_model(
    config: TransferConfig, world: WorldConfig, learned: bool, state: dict | None = None
) -> Any:
    """Factor-Q's local model of every seed in ``world``'s body, loaded with ``state`` (a
    ``run_batch`` local model) when given: a ``LocalRewardTable`` ``[seeds]`` on the oracle
    pairing, or with ``learned`` a ``StructureLearner`` told nothing of it."""
    from factorq_torch.structure import StructureLearner
    from factorq_torch.tables import LocalRewardTable

    if learned:
        actuators, sensors = world.num_actuators, world.num_sensors
        local = StructureLearner(config.seeds, num_actions=actuators, num_sensors=sensors)
    else:
        local = LocalRewardTable(config.seeds, dependency=world.dependency)
    if state is not None:  # the learner's whole state, or the table's rho and kappa
        local.load_state_dict({**local.state_dict(), **state})
    return local


def train_body_model(config: TransferConfig, learned: bool = False) -> Any:
    """The body model of every seed, learned by Factor-Q in the source task: the oracle's table or,
    with ``learned``, a ``StructureLearner`` (``_local_model``; ``save_agent`` writes either)."""
    return _local_model(config, config.source_world, learned, _source_body(config, learned))


def _source_body(config: TransferConfig, learned: bool) -> dict[str, torch.Tensor]:
    """Factor-Q's local model (``run_batch``'s) at the end of the source task."""
    _, local, _ = run_batch(
        config, "factor-q", config.source_world, config.source_regime, config.source_episodes,
        source=True, learned=learned,
    )  # fmt: skip
    assert local is not None
    return local


def load_body_model(config: TransferConfig) -> dict[str, torch.Tensor]:
    """``--body-model``'s tables for every seed, checked against the target's body (one
    ``AgentFileError`` line naming the file and both bodies otherwise)."""
    from factorq_torch.artifacts import AgentFileError, load_agent
    from factorq_torch.tables import LocalRewardTable

    world = config.target_world
    probe = experiment.make_env(world, [0], torch.zeros(1, dtype=torch.int64))
    module = load_agent(str(config.body_model), env=probe)
    if not isinstance(module, LocalRewardTable):
        raise AgentFileError(
            f"body model {config.body_model} is a {type(module).__name__}: factorq transfer "
            f"carries a LocalRewardTable"
        )
    if not torch.equal(module.dependency.cpu(), world.dependency.cpu()):
        raise AgentFileError(
            f"body model {config.body_model} pairs actuators and sensors as "
            f"{module.dependency.int().tolist()}; the target body's dependency is "
            f"{world.dependency.int().tolist()}"
        )
    held = module.rho.shape[0]
    if held not in (1, config.seeds):
        raise AgentFileError(
            f"body model {config.body_model} holds {held} experiments: give one, or seeds={held}"
        )
    return {
        name: getattr(module, name).detach().expand(config.seeds, -1, -1).clone()
        for name in ("rho", "kappa")
    }


# --------------------------------------------------------------------------------------------
# The command protocol


def prepare(config: TransferConfig) -> None:
    """A ``--body-model`` is read and checked before any work."""
    if config.body_model is not None:
        load_body_model(config)


def units(config: TransferConfig) -> list[dict[str, Any]]:
    """One unit per (method, regime)."""
    return [
        {"id": f"{method}-{regime}", "method": method, "regime": regime}
        for method in config.methods
        for regime in config.regimes
    ]


def work(config: TransferConfig, unit: dict[str, Any]) -> int:
    """The progress bar's share of a unit: its episodes (the source's included)."""
    method = unit["method"]
    carried_file = method == "factor-q-body" and config.body_model is not None
    source = config.source_episodes if method in PAIRS and not carried_file else 0
    return config.seeds * (config.episodes + source)


def run_unit(
    config: TransferConfig, unit: dict[str, Any], progress: Callable[[int], None] | None = None
) -> dict[str, Any]:
    """The unit's method in its regime: per-seed measures and the per-episode collision curve."""
    method, regime = unit["method"], unit["regime"]
    learned = method.startswith("factor-q-learned")
    body, body_from = None, "none"
    if method == "factor-q-body" and config.body_model is not None:
        body, body_from = load_body_model(config), "file"
    elif method in PAIRS:
        body, body_from = _source_body(config, learned), "source task"
        if progress is not None:
            progress(config.seeds * config.source_episodes)
    algorithm = "q-learning" if method == "q-learning" else "factor-q"
    metrics, _, path = run_batch(
        config, algorithm, config.target_world, regime, config.episodes, body=body,
        progress=progress, learned=learned,
    )  # fmt: skip
    collisions = metrics["collisions"][:, 0].to(torch.int64)  # [seeds, episodes]
    steps = metrics["steps"][:, 0].to(torch.int64)
    early = config.early
    late = slice(config.episodes - early, config.episodes)
    return {
        "early_collisions": collisions[:, :early].sum(dim=1).tolist(),
        "late_collisions": collisions[:, late].sum(dim=1).tolist(),
        "late_steps": steps[:, late].double().mean(dim=1).tolist(),
        "late_truncated": (steps[:, late] >= config.max_steps).double().mean(dim=1).tolist(),
        "collisions_per_episode": collisions.double().mean(dim=0).tolist(),
        "path": path,
        "body_from": body_from,
    }


def _stat(values: list[float], seed: int) -> dict[str, Any]:
    mean, low, high = scalar_ci(values, lambda samples: bootstrap_mean_ci(samples, seed))
    data = np.asarray(values, dtype=np.float64)
    return {
        "mean": mean,
        "ci95": None if low is None else [low, high],
        "median": float(np.median(data)),
        "range": [float(data.min()), float(data.max())],
    }


def summarise(config: TransferConfig, unit_results: list[dict[str, Any]]) -> dict[str, Any]:
    """Per regime: each method's measures over the seeds, and the body model against a fresh
    Factor-Q (the ratio of mean early collisions, the final steps side by side)."""
    results: dict[str, dict[str, Any]] = {regime: {} for regime in config.regimes}
    paths, body_from = set(), "none"
    for unit, outcome in zip(units(config), unit_results, strict=True):
        paths.add(outcome["path"])
        if outcome["body_from"] != "none":
            body_from = outcome["body_from"]
        results[unit["regime"]][unit["method"]] = {
            **{
                name: _stat(outcome[name], config.seed)
                for name in ("early_collisions", "late_collisions", "late_steps", "late_truncated")
            },
            "collisions_per_episode": outcome["collisions_per_episode"],
        }
    against: dict[str, Any] = {}
    for (carried, fresh_method), regime in itertools.product(PAIRS.items(), config.regimes):
        methods = results[regime]
        if fresh_method in methods and carried in methods:
            fresh, body = methods[fresh_method], methods[carried]
            early = fresh["early_collisions"]["mean"], body["early_collisions"]["mean"]
            against.setdefault(carried, {})[regime] = {
                "early_collisions_ratio": count_ratio(*early),
                "target_met": bool(early[0] > 0 and early[0] >= TARGET_RATIO * early[1]),
                "late_steps_fresh": fresh["late_steps"]["mean"],
                "late_steps_body": body["late_steps"]["mean"],
            }
    return {
        "results": results,
        "body_against_fresh": against,
        "path": "/".join(sorted(paths)),
        "body_from": body_from,
        "target_ratio": TARGET_RATIO,
    }
