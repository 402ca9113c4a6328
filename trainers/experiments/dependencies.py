"""``factorq dependencies``: Factor-Q that learns its own sensor-actuator pairing (issue 12).

Per *setting* (a body, a sensor layout, noise, a change), ``seeds`` experiments of ``runs`` x
``episodes`` episodes (task tables reset per run, local knowledge kept, SPEC section 4) for four
methods on the same worlds (common random numbers: the same world keys):

- ``learned``: ``factorq_torch.structure.StructureLearner`` as the local value provider, told
  nothing of the body, on the compiled path (``fast.StructureOptions``) or, with ``--path
  modular`` (or ``--prediction posterior``), through ``FactorQPolicy``, ``FactorQLoss`` and
  ``OnlineCollector`` (the modular torchrl path): the same numbers bit for bit. Every experiment
  receives its sensors in its own random order (``factorq_envs.permutation.PermuteSensors``),
  redrawn at run ``change_run`` in the ``change`` setting;
- ``oracle``: ``LocalRewardTable`` with the true dependency (the paper), on the compiled path;
- ``joint``: Factor-Q with one local table per actuator over the pattern of *all* sensors (the
  paper's footnote 2), compiled, where ``2**K`` entries fit (``tables.MAX_PARENTS``);
- ``q-learning``: compiled, where its table fits (``tables.MAX_TABLE_ENTRIES``);
- ``dqn`` (opt-in, ``--methods``): ``factorq_trainers.experiments.dqn`` on the oracle's step
  budget (``run_dqn``);
- ``gated`` (opt-in, ``--methods``): Factor-Q with ``factorq_torch.neural.
  GatedLocalRewardNetwork`` as the local value provider on the modular path, in the learner's
  sensor orders, its structure read out (``structure()``) at the end (``run_gated``).

The joint table and Q-learning receive the sensors in the learner's orders, changed at the same
moment (``fast.SensorOrders``); the oracle is told the true pairing at every moment, which is
the same as running it in the world's own order.

Structure metrics (``learned`` only), per experiment: the local samples (firings) per actuator
until it holds the right parents and keeps them to the end (the experiment's value: the largest
over its actuators; in the ``change`` setting counted from the change), wrong commitments
(commitments to a parent set other than the truth of that moment), the structural Hamming
distance at the end (parents missing or extra, an open actuator counting as "no parents").

Writes ``dependencies.json``, ``dependencies.png`` and ``dependencies.md`` to ``out``.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from factorq_envs.world import WORLD_PERIODS, WORLDS, WorldConfig
from factorq_torch.base.config import AgentConfig
from factorq_torch.base.rng import STREAM_POLICY, STREAM_WORLD
from factorq_torch.base.validation import (
    INT32_MAX,
    check_float,
    check_int,
    check_names,
    check_threads,
)
from factorq_trainers.analysis.stats import bootstrap_indices, interval, quantiles, wilson_ci
from factorq_trainers.experiments.experiment import MAX_SEED, check_world_options, experiment_keys
from factorq_trainers.runner import resources
from factorq_trainers.runner.options import option

NAME = "dependencies"
HELP = "learn which sensors each actuator depends on, against the oracle pairing"
DESCRIPTION = (
    "Run the structure learner against the oracle pairing, the full joint table and "
    "Q-learning on the settings; write dependencies.json, dependencies.png and dependencies.md "
    "to --out."
)
REPORT = "factorq_trainers.reports.dependencies"
#: The fields that leave the numbers alone (the compiled and modular paths agree bit for bit).
DIGEST_IGNORED = ("out", "threads", "path")
HINT = resources.DEPENDENCIES_HINT

#: The settings of the issue: name -> body options (the sensor order is drawn per experiment).
SETTINGS: dict[str, dict[str, Any]] = {
    "cross": {"body": "translate", "sensors": "cross"},
    "ring-24": {"body": "translate", "sensors": "ring", "num_distractors": 24},
    "heading": {"body": "heading", "sensors": "cross"},
    "noise-5": {"body": "translate", "sensors": "cross", "sensor_noise": 0.05},
    "noise-10": {"body": "translate", "sensors": "cross", "sensor_noise": 0.10},
    "change": {"body": "translate", "sensors": "cross"},
    # issue 27: noise with many sensors (8 ring sensors and 12 distractors: 20)
    "ring-12-noise-5": {
        "body": "translate",
        "sensors": "ring",
        "num_distractors": 12,
        "sensor_noise": 0.05,
    },
    "ring-12-noise-10": {
        "body": "translate",
        "sensors": "ring",
        "num_distractors": 12,
        "sensor_noise": 0.10,
    },
}
#: The setting that ``--body``, ``--sensors``, ``--distractors`` and ``--sensor-noise`` declare.
CUSTOM = "custom"
#: A setting's content: its body options with the defaults filled in, and whether the sensor
#: order is redrawn mid-experiment (the ``change`` preset).
SETTING_DEFAULTS = {
    "body": "translate",
    "sensors": "cross",
    "num_distractors": 0,
    "sensor_noise": 0.0,
}
METHODS = ("learned", "oracle", "joint", "q-learning", "dqn", "gated")
#: The methods with a policy stream of their own: their number fixes every method's keys
#: (``experiment_keys``), so a new method must not join them; the gated network takes the
#: learned structure's stream (the two learners under common random numbers).
KEYED_METHODS = ("learned", "oracle", "joint", "q-learning", "dqn")
#: The methods run by default: DQN is opt-in (``--methods``), see ``run_dqn``.
DEFAULT_METHODS = ("learned", "oracle", "joint", "q-learning")
METHOD_LABELS = {
    "learned": "learned structure",
    "oracle": "oracle pairing",
    "joint": "full joint table",
    "q-learning": "Q-learning",
    "dqn": "DQN",
    "gated": "gated network",
}
#: The gated network's training (``run_gated``): Adam's learning rate and the gates' L1 weight
#: (docs/decisions.md, "The neural variant": the paper's body read right after 2,000 steps).
GATED_LEARNING_RATE, GATED_L1 = 5e-2, 1e-3
#: Substream of the experiment key that draws the sensor orders (first, then after the change).
STREAM_ORDER = 7
#: The issue's thresholds: local samples per actuator.
SAMPLES_TARGET = 100
SAMPLES_TARGET_CHANGE = 200
#: The compiled path's priors are multiples of 1/PRIOR_DENOMINATOR (``fast.StructureOptions``).
PRIOR_DENOMINATOR, PRIOR_LIMIT = 1024, 2**20
#: Env steps between two points of the "right structure" curve.
CURVE_EVERY = 10


@dataclass(frozen=True)
class DependenciesConfig:
    """The structure-learning experiment; the defaults run in well under a minute on 2 cores."""

    seed: int = option(0, "Master seed: worlds, sensor orders and policies derive from it.")
    seeds: int = option(100, "Independent experiments per setting (and method).")
    settings: tuple[str, ...] = option(
        tuple(SETTINGS),
        "Settings to run: " + ", ".join(SETTINGS) + " (presets, comma-separated), or custom (the "
        "body options below; given alone, they run it instead of the presets).",
    )
    body: str | None = option(
        None, "Body of the custom setting: translate or heading (auto: the presets')."
    )
    sensors: str | None = option(
        None, "Sensor layout of the custom setting: cross or ring (auto: the presets')."
    )
    distractors: int | None = option(
        None, "Distractor sensor bits of the custom setting (auto: the presets')."
    )
    sensor_noise: float | None = option(
        None, "Probability that each sensor bit of the custom setting flips at each observation."
    )
    world: str = option("static", "World: static, semi-dynamic or dynamic.", choices=WORLDS)
    runs: int = option(10, "Runs per experiment (task tables reset at each).")
    episodes: int = option(1, "Episodes per run.")
    size: int = option(6, "Side of the square grid, in cells.")
    obstacles: int = option(4, "Number of single-cell obstacles.")
    max_steps: int = option(1_000, "Actions after which an episode is truncated.")
    layout_seed: int = option(0, "Seed of the static world's obstacle layout.")
    bayes_factor: float = option(300.0, "Posterior odds at which a parent set is committed to.")
    max_parents: int = option(2, "Largest candidate parent set (0, 1 or 2: pairs).")
    window: int = option(100, "Firings per actuator in the block the reopening test reads.")
    prior_a: float = option(
        0.25,
        "Beta(prior_a, prior_b) prior of every pattern's collision rate (with the mixture "
        "likelihood: of the clean population; flip: of the flip rate): prior_a (> 0; a multiple "
        "of 1/1024 on the compiled path).",
    )
    prior_b: float = option(
        0.25, "Beta(prior_a, prior_b) prior of every pattern's collision rate: prior_b (as a)."
    )
    candidate_prior: str = option(
        "sparse",
        "Prior over the candidate parent sets: size (no sensor, the single sensors and the pairs "
        "each a third), sparse (the pairs together 1/100 of that) or uniform.",
        choices=("size", "sparse", "uniform"),
    )
    likelihood: str = option(
        "mixture",
        "Likelihood of a parent set's data: mixture (each pattern's collision rate from a clean "
        "or a noisy population, whichever fits: noisy sensors), pattern (each pattern its own "
        "rate under the Beta prior) or flip (each pattern collides or not, the outcomes "
        "disagree at a flip rate learned per parent set).",
        choices=("flip", "pattern", "mixture"),
    )
    change_run: int = option(5, "Run at which the change setting redraws the sensor order.")
    prediction: str = option(
        "optimistic",
        "What an open actuator predicts: optimistic (the largest mean among the parent sets the "
        "evidence has not ruled out), map (its most probable parent set), posterior (the "
        "posterior-weighted mean; modular path only) or committed (nothing until it commits).",
        choices=("optimistic", "map", "posterior", "committed"),
    )
    reopen: str = option(
        "body",
        "What a reopening forgets: body (every actuator's counts: a body changes as a whole) or "
        "actuator (its own).",
        choices=("body", "actuator"),
    )
    reopen_factor: float | None = option(
        None,
        "Posterior odds of the change-point test at which a commitment is reopened (> 1; auto: "
        "the Bayes factor). Higher: fewer false reopenings under sensor noise, a changed body "
        "noticed later.",
    )
    path: str = option(
        "fast",
        "Where the learner runs: fast (the compiled kernel, where available) or modular.",
        choices=("fast", "modular"),
    )
    threads: int = option(2, "Threads of the compiled path.")
    methods: tuple[str, ...] = option(
        DEFAULT_METHODS,
        "Methods to run: " + ", ".join(METHODS) + " (comma-separated; dqn is slow: opt-in).",
    )
    out: str = option("results/dependencies", "Directory for the json, figure and report.")

    def __post_init__(self) -> None:
        check_int("seed", self.seed, 0, MAX_SEED)
        check_int("seeds", self.seeds, 1, INT32_MAX)
        settings = check_names("settings", self.settings, (*SETTINGS, CUSTOM))
        custom = [name for name in ("body", "sensors", "distractors", "sensor_noise")
                  if getattr(self, name) is not None]  # fmt: skip
        if custom and settings == tuple(SETTINGS):  # body options alone: their setting only
            settings = (CUSTOM,)
        if custom and CUSTOM not in settings:
            raise ValueError(
                f"settings: {', '.join(custom)} declare the setting {CUSTOM!r}: add it to "
                f"settings or leave settings out"
            )
        if CUSTOM in settings and not custom:
            raise ValueError(
                f"settings: {CUSTOM!r} needs body, sensors, distractors or sensor_noise"
            )
        object.__setattr__(self, "settings", settings)
        object.__setattr__(self, "methods", check_names("methods", self.methods, METHODS))
        check_int("runs", self.runs, 1, INT32_MAX)
        check_int("episodes", self.episodes, 1, INT32_MAX)
        check_int("max_parents", self.max_parents, 0)
        check_int("window", self.window, 1, INT32_MAX)
        check_threads("threads", self.threads)
        for name, choices in (
            ("prediction", ("optimistic", "map", "posterior", "committed")),
            ("path", ("fast", "modular")),
            ("reopen", ("body", "actuator")),
            ("candidate_prior", ("size", "sparse", "uniform")),
            ("likelihood", ("flip", "pattern", "mixture")),
        ):
            if getattr(self, name) not in choices:
                raise ValueError(
                    f"{name}={getattr(self, name)!r} is unknown: choose one of {choices}"
                )
        if not isinstance(self.bayes_factor, (int, float)) or not self.bayes_factor > 1:
            raise ValueError(
                f"bayes_factor={self.bayes_factor!r} must be > 1 (a commitment needs evidence "
                f"for the best candidate over the runner-up)"
            )
        if self.reopen_factor is not None:
            check_float(
                "reopen_factor", self.reopen_factor, 1.0, math.inf, low_open=True, high_open=True
            )
        for name in ("prior_a", "prior_b"):
            value = getattr(self, name)
            if (
                isinstance(value, bool)
                or not isinstance(value, (int, float))
                or not math.isfinite(value)
                or not value > 0
            ):
                raise ValueError(f"{name}={value!r} must be a finite number > 0")
            compiled = self.path == "fast" and self.prediction != "posterior"
            scaled = value * PRIOR_DENOMINATOR
            if compiled and (scaled != int(scaled) or not value < PRIOR_LIMIT):
                raise ValueError(
                    f"{name}={value!r}: the compiled path (--path fast) needs a multiple of "
                    f"1/{PRIOR_DENOMINATOR} below {PRIOR_LIMIT} (e.g. 0.0625); --path modular "
                    f"takes any finite value > 0"
                )
        from factorq_torch.structure import candidate_sets

        if "change" in self.settings:
            check_int("change_run", self.change_run, 1, self.runs - 1)
        for name in self.settings:
            world = self.world_of(name)
            candidate_sets(world.num_sensors, self.max_parents)  # the cap on the sets, named
            if not bool(world.dependency.any()):
                raise ValueError(
                    f"settings: {name!r} has a body without local rewards (no actuator can "
                    f"collide): there is no structure to learn"
                )

    def setting_options(self, setting: str) -> dict[str, Any]:
        """The body options of ``setting`` (a preset, or the custom one), defaults filled in."""
        if setting != CUSTOM:
            return {**SETTING_DEFAULTS, **SETTINGS[setting]}
        given = {
            "body": self.body,
            "sensors": self.sensors,
            "num_distractors": self.distractors,
            "sensor_noise": self.sensor_noise,
        }
        return {**SETTING_DEFAULTS, **{k: v for k, v in given.items() if v is not None}}

    def setting_stream(self, setting: str) -> int:
        """The seed of ``setting``'s sensor orders, from its content (its options and whether
        it changes), not its name or position: adding a setting changes no other's numbers,
        and two settings of the same content draw the same orders."""
        content = {**self.setting_options(setting), "change": setting == "change"}
        text = json.dumps(content, sort_keys=True)
        return int.from_bytes(hashlib.sha256(text.encode()).digest()[:8], "little") >> 1

    def world_of(self, setting: str) -> WorldConfig:
        options = self.setting_options(setting)
        renamed = {"num_distractors": "distractors"}
        body = {renamed.get(name, name): value for name, value in options.items()}
        return check_world_options(
            self.size, self.obstacles, self.max_steps, self.layout_seed, (self.world,), body
        )


CONFIG = DependenciesConfig


# --------------------------------------------------------------------------------------------
# One setting


def sensor_orders(
    seed: int, setting_stream: int, count: int, num_sensors: int, redraw: int
) -> torch.Tensor:
    """``[count, K]``: experiment ``i``'s sensor order (``redraw`` 0: the first, 1: after the
    change), drawn from its own generator seeded by ``(seed, setting_stream, i, redraw)``
    (``setting_stream``: ``DependenciesConfig.setting_stream``, from the setting's content)."""
    orders = []
    for index in range(count):
        generator = torch.Generator().manual_seed(
            hash((seed, STREAM_ORDER, setting_stream, index, redraw)) & (2**63 - 1)
        )
        orders.append(torch.randperm(num_sensors, generator=generator))
    return torch.stack(orders)


def _keys(config: DependenciesConfig, method: str) -> tuple[torch.Tensor, torch.Tensor]:
    labels = [(config.world, index) for index in range(config.seeds)]
    world_keys = experiment_keys(config.seed, STREAM_WORLD, labels)
    policy_keys = experiment_keys(config.seed, STREAM_POLICY, labels, KEYED_METHODS, method)
    return world_keys, policy_keys


def _learner_options(config: DependenciesConfig) -> dict[str, Any]:
    return {
        "max_parents": config.max_parents,
        "bayes_factor": config.bayes_factor,
        "window": config.window,
        "prior_a": config.prior_a,
        "prior_b": config.prior_b,
        "prior": config.candidate_prior,
        "prediction": config.prediction,
        "reopen": config.reopen,
        "reopen_factor": config.reopen_factor,
        "likelihood": config.likelihood,
    }


def run_learned(config: DependenciesConfig, setting: str) -> dict[str, Any]:
    """The learned structure with its structure metrics: on the compiled path where it runs
    (``fast.StructureOptions``), else on the modular torchrl path (``run_learned_modular``);
    both give the same numbers bit for bit (``tests/test_fast_structure.py``)."""
    from factorq_trainers.compiled import fast

    world = config.world_of(setting)
    if (
        config.path == "modular"
        or config.prediction == "posterior"
        or not fast.is_available()
        or fast.unsupported_reason(world) is not None
    ):
        return run_learned_modular(config, setting)
    return run_learned_fast(config, setting)


def run_learned_fast(config: DependenciesConfig, setting: str) -> dict[str, Any]:
    """``run_learned`` on the compiled path."""
    from factorq_trainers.compiled import fast

    world = config.world_of(setting)
    count, num_sensors = config.seeds, world.num_sensors
    world_keys, policy_keys = _keys(config, "learned")
    periods = torch.full((count,), WORLD_PERIODS[config.world], dtype=torch.int64)
    orders = sensor_orders(config.seed, config.setting_stream(setting), count, num_sensors, 0)
    change = setting == "change"
    options = fast.StructureOptions(
        orders=orders,
        orders_after=sensor_orders(
            config.seed, config.setting_stream(setting), count, num_sensors, 1
        )
        if change
        else None,
        change_run=config.change_run if change else 0,
        curve_every=CURVE_EVERY,
        **_learner_options(config),
    )
    batch = fast.ExperimentBatch(
        "factor-q",
        periods,
        world,
        AgentConfig(),
        config.runs,
        config.episodes,
        world_keys,
        policy_keys,
        threads=config.threads,
        structure=options,
    )
    while not batch.done:
        batch.advance(1 << 62)
    state = batch.learner_state()
    sets = batch._candidate_sets
    members = torch.zeros(len(sets), num_sensors, dtype=torch.bool)
    for index, parents in enumerate(sets):
        members[index, list(parents)] = True
    committed = state["committed"]
    structure = members[committed.clamp(min=0)] & (committed >= 0).unsqueeze(-1)
    truth = _permuted(world, options.orders_after if change else orders)
    steps = batch.metrics()["steps"].sum(dim=(1, 2))
    return _structure_result(
        config,
        setting,
        batch.metrics(),
        right_since=state["right_since"],
        samples_at_change=state["samples_at_change"],
        wrong_commitments=state["wrong_commitments"],
        structure=structure,
        truth=truth,
        reopened=state["reopened"],
        samples=state["samples"],
        curve=_fill_curve(state["curve"], steps),
        state=state,
    )


def _permuted(world: WorldConfig, orders: torch.Tensor) -> torch.Tensor:
    from factorq_envs.permutation import permuted_dependency

    return permuted_dependency(world.dependency, orders)


def _fill_curve(curve: torch.Tensor, steps: torch.Tensor) -> torch.Tensor:
    """``[S, points]`` bool: an experiment that has finished holds its last point; the points
    stop at the longest experiment's end."""
    curve = curve[:, : int(steps.max()) // CURVE_EVERY + 1]
    points = torch.arange(curve.shape[1]) * CURVE_EVERY
    last = (steps // CURVE_EVERY).clamp(max=curve.shape[1] - 1)  # [S]
    final = curve.gather(1, last.unsqueeze(1))  # [S, 1]
    return torch.where(points <= steps.unsqueeze(1), curve, final).bool()


def _structure_result(
    config,
    setting,
    metrics,
    *,
    right_since,
    samples_at_change,
    wrong_commitments,
    structure,
    truth,
    reopened,
    samples,
    curve,
    state,
) -> dict[str, Any]:
    right = (structure == truth).all(dim=-1)  # [S, A]
    final_right = right.all(dim=-1)
    since = right_since - (samples_at_change if setting == "change" else 0)
    since = since.clamp(min=0).to(torch.float64)
    until_right = torch.where(final_right, since.max(dim=-1).values, math.inf)
    hamming = (structure != truth).sum(dim=(1, 2))
    points = curve.shape[1]
    fraction = curve.float().mean(dim=0)
    return {
        "metrics": metrics,
        "samples_until_right": until_right.tolist(),
        "wrong_commitments": wrong_commitments.tolist(),
        "hamming_at_end": hamming.tolist(),
        "reopened": reopened.sum(dim=-1).tolist(),
        "samples_per_actuator": samples.tolist(),
        "curve": {
            "env_steps": [CURVE_EVERY * point for point in range(points)],
            "fraction_right": fraction.tolist(),
        },
        "_curve": curve,
        "_state": state,
    }


def run_learned_modular(config: DependenciesConfig, setting: str) -> dict[str, Any]:
    """``run_learned`` on the modular torchrl path: ``StructureLearner`` through
    ``FactorQPolicy``, ``FactorQLoss`` and ``OnlineCollector``."""
    from tensordict.nn import TensorDictSequential
    from torchrl.envs import Compose, TransformedEnv

    from factorq_envs.permutation import PermuteSensors, permuted_dependency
    from factorq_envs.transforms import SplitLocalReward
    from factorq_torch.collectors import OnlineCollector
    from factorq_torch.objectives import FactorQLoss
    from factorq_torch.policy import FactorQPolicy
    from factorq_torch.structure import StructureLearner
    from factorq_torch.tables import TaskQTable
    from factorq_trainers.experiments.experiment import make_env

    world, agent = config.world_of(setting), AgentConfig()
    count, num_sensors = config.seeds, world.num_sensors
    world_keys, policy_keys = _keys(config, "learned")
    periods = [WORLD_PERIODS[config.world]] * count
    orders = sensor_orders(config.seed, config.setting_stream(setting), count, num_sensors, 0)
    permute = PermuteSensors(orders)
    env = TransformedEnv(make_env(world, periods, world_keys), Compose(SplitLocalReward(), permute))
    task = TaskQTable(
        count, world.num_cells, num_headings=world.num_headings, num_actions=world.num_actuators
    )
    learner = StructureLearner(
        count, num_actions=world.num_actuators, num_sensors=num_sensors, **_learner_options(config)
    )
    policy = FactorQPolicy(count, keys=policy_keys, epsilon=agent.epsilon)
    loss = FactorQLoss(task, learner, gamma=agent.gamma, alpha=agent.alpha)
    collector = OnlineCollector(
        env,
        TensorDictSequential(task, learner, policy),
        loss,
        runs=config.runs,
        episodes=config.episodes,
    )
    truth = permuted_dependency(world.dependency, orders)  # [S, A, K]
    actuators = world.num_actuators
    right_since = torch.full((count, actuators), -1)  # samples when it last became right
    samples_at_change = torch.zeros(count, actuators, dtype=torch.int64)
    changed = torch.zeros(count, dtype=torch.bool)
    wrong_commitments = torch.zeros(count, dtype=torch.int64)
    previous = learner.committed.clone()
    steps = torch.zeros(count, dtype=torch.int64)
    max_steps = config.runs * config.episodes * world.max_steps
    curve = torch.zeros(count, max_steps // CURVE_EVERY + 1, dtype=torch.uint8)
    rows = torch.arange(count)
    for td in collector:
        active = td.get(("collector", "mask"))
        steps += active.to(torch.int64)
        if setting == "change":
            due = (collector.run_index >= config.change_run) & ~changed
            if bool(due.any()):
                new_orders = sensor_orders(
                    config.seed, config.setting_stream(setting), count, num_sensors, 1
                )
                permute.set_permutations(new_orders, due)
                truth[due] = permuted_dependency(world.dependency, new_orders)[due]
                samples_at_change[due] = learner.samples[due]
                changed |= due
        right = (learner.structure() == truth).all(dim=-1)  # [S, A]
        right_since = torch.where(
            right, torch.where(right_since < 0, learner.samples, right_since), -1
        )
        committed = learner.committed
        new_commit = (committed >= 0) & (committed != previous)
        wrong_commitments += (new_commit & ~right).sum(dim=-1)
        previous = committed.clone()
        point = active & (steps % CURVE_EVERY == 0)
        curve[rows[point], steps[point] // CURVE_EVERY] = right.all(dim=-1)[point].to(torch.uint8)
    metrics = {name: collector.metrics.get(name) for name in collector.metrics.keys()}
    state = {
        "committed": learner.committed.clone(),
        "samples": learner.samples.clone(),
        "block_samples": learner.block_samples.clone(),
        "reopened": learner.reopened.clone(),
        "map_cache": learner.map_cache.clone(),
        "plausible": learner.plausible_cache.to(torch.uint8),
        "right_since": right_since,
        "samples_at_change": samples_at_change,
        "wrong_commitments": wrong_commitments,
    }
    for prefix in ("", "block_"):
        for name in ("count", "successes", "reward_sum", "log_marginal"):
            state[prefix + name] = getattr(learner, prefix + name).clone()
    return _structure_result(
        config,
        setting,
        metrics,
        right_since=right_since,
        samples_at_change=samples_at_change,
        wrong_commitments=wrong_commitments,
        structure=learner.structure(),
        truth=truth,
        reopened=learner.reopened,
        samples=learner.samples,
        curve=_fill_curve(curve, steps),
        state=state,
    )


def run_compiled(config: DependenciesConfig, setting: str, method: str) -> dict[str, Any] | None:
    """The oracle, the joint table or Q-learning on the compiled path (``None``: does not fit
    or cannot run this setting; the reason is in ``skipped``)."""
    from factorq_trainers.compiled import fast

    world = config.world_of(setting)
    world_keys, policy_keys = _keys(config, method)
    periods = torch.full((config.seeds,), WORLD_PERIODS[config.world], dtype=torch.int64)
    dependency, algorithm = None, "factor-q"
    if method == "joint":
        dependency = torch.ones(world.num_actuators, world.num_sensors, dtype=torch.bool)
    if method == "q-learning":
        algorithm = "q-learning"
    orders = None
    if method in ("joint", "q-learning"):  # the sensors in the learner's orders, changed alike
        count, num_sensors = config.seeds, world.num_sensors
        change = setting == "change"
        orders = fast.SensorOrders(
            sensor_orders(config.seed, config.setting_stream(setting), count, num_sensors, 0),
            sensor_orders(config.seed, config.setting_stream(setting), count, num_sensors, 1)
            if change
            else None,
            config.change_run if change else 0,
        )
    metrics = fast.run_experiments(
        algorithm,
        periods,
        world,
        AgentConfig(),
        config.runs,
        config.episodes,
        world_keys,
        policy_keys,
        threads=config.threads,
        dependency=dependency,
        sensor_orders=orders,
    )
    return {"metrics": metrics}


def run_gated(config: DependenciesConfig, setting: str) -> dict[str, Any]:
    """Factor-Q with ``GatedLocalRewardNetwork`` (one network per experiment and actuator over
    all sensors, sigmoid gates under an L1 penalty, Adam) through ``FactorQPolicy``,
    ``FactorQLoss`` and ``OnlineCollector``, the sensors in the learner's orders (the change
    setting: redrawn at the same run). Its structure is read at the end (``structure()``: a
    sensor is a parent when flipping it moves the predicted local reward by a quarter of a
    collision), against the truth of that moment."""
    from tensordict.nn import TensorDictSequential
    from torchrl.envs import Compose, TransformedEnv

    from factorq_envs.permutation import PermuteSensors, permuted_dependency
    from factorq_envs.transforms import SplitLocalReward
    from factorq_torch.collectors import OnlineCollector
    from factorq_torch.neural import GatedLocalRewardNetwork
    from factorq_torch.objectives import FactorQLoss
    from factorq_torch.policy import FactorQPolicy
    from factorq_torch.tables import TaskQTable
    from factorq_trainers.experiments.experiment import make_env

    world, agent = config.world_of(setting), AgentConfig()
    count, num_sensors = config.seeds, world.num_sensors
    world_keys, policy_keys = _keys(config, "learned")  # common random numbers (KEYED_METHODS)
    orders = sensor_orders(config.seed, config.setting_stream(setting), count, num_sensors, 0)
    permute = PermuteSensors(orders)
    periods = [WORLD_PERIODS[config.world]] * count
    env = TransformedEnv(make_env(world, periods, world_keys), Compose(SplitLocalReward(), permute))
    task = TaskQTable(
        count, world.num_cells, num_headings=world.num_headings, num_actions=world.num_actuators
    )
    local = GatedLocalRewardNetwork(
        count,
        num_actions=world.num_actuators,
        num_sensors=num_sensors,
        l1=GATED_L1,
        seed=config.seed,
    )
    optimizer = torch.optim.Adam(local.parameters(), lr=GATED_LEARNING_RATE)
    collector = OnlineCollector(
        env,
        TensorDictSequential(
            task, local, FactorQPolicy(count, keys=policy_keys, epsilon=agent.epsilon)
        ),
        FactorQLoss(task, local, gamma=agent.gamma, alpha=agent.alpha),
        runs=config.runs,
        episodes=config.episodes,
        optimizer=optimizer,
    )
    truth = permuted_dependency(world.dependency, orders)
    changed = torch.zeros(count, dtype=torch.bool)
    for _ in collector:
        if setting == "change":
            due = (collector.run_index >= config.change_run) & ~changed
            if bool(due.any()):
                new_orders = sensor_orders(
                    config.seed, config.setting_stream(setting), count, num_sensors, 1
                )
                permute.set_permutations(new_orders, due)
                truth[due] = permuted_dependency(world.dependency, new_orders)[due]
                changed |= due
    structure = local.structure()  # [S, A, K]
    metrics = {name: collector.metrics.get(name) for name in collector.metrics.keys()}
    return {
        "metrics": metrics,
        "right_at_end": (structure == truth).all(dim=-1).all(dim=-1).tolist(),
        "hamming_at_end": (structure != truth).sum(dim=(1, 2)).tolist(),
    }


def _budget(config: DependenciesConfig, setting: str, runs: dict[str, dict[str, Any]]) -> int:
    """DQN's step budget: the oracle's mean env steps per experiment (else the learned
    structure's, else every episode at its longest)."""
    for method in ("oracle", "learned"):
        if method in runs:
            steps = runs[method]["metrics"]["steps"].sum(dim=(1, 2)).double().mean()
            return max(1, round(float(steps)))
    return config.runs * config.episodes * config.world_of(setting).max_steps


def run_dqn(config: DependenciesConfig, setting: str, budget: int) -> dict[str, Any]:
    """DQN (``experiments.dqn``, its default hyperparameters) on the setting's worlds for
    ``budget`` env steps per experiment (episodes as many as fit; DQN has no runs). It sees every
    sensor (``TaskQNetwork(with_proximity=True)``); the order does not matter to a network trained
    from scratch, so it runs without ``PermuteSensors``. Measured cost: 100 experiments of 1,400
    steps took 300 s on 2 loaded cores (docs/decisions.md), hence opt-in."""
    from factorq_trainers.experiments import dqn
    from factorq_trainers.experiments.experiment import ExperimentConfig

    options = config.setting_options(setting)
    experiments = ExperimentConfig(
        seed=config.seed,
        seeds=config.seeds,
        worlds=(config.world,),
        steps=budget,
        size=config.size,
        obstacles=config.obstacles,
        max_steps=config.max_steps,
        layout_seed=config.layout_seed,
        body=options["body"],
        sensors=options["sensors"],
        distractors=options.get("num_distractors", 0),
        sensor_noise=options.get("sensor_noise", 0.0),
    )
    traces = dqn.run(dqn.DQNConfig(), experiments)["traces"]
    episodes = min(len(trace["steps"]) for trace in traces)
    return {
        "totals": {
            "collisions": np.array([trace["total_collisions"] for trace in traces], float),
            "greedy": np.array([trace["total_greedy_collisions"] for trace in traces], float),
        },
        "budget": budget,
        "episodes": [len(trace["steps"]) for trace in traces],
        "collisions_per_episode": [
            float(np.mean([trace["collisions"][index] for trace in traces]))
            for index in range(episodes)
        ],
    }


def skipped_reason(config: DependenciesConfig, setting: str, method: str) -> str | None:
    """Why ``method`` does not run in ``setting`` (``None``: it runs)."""
    from factorq_torch.tables import MAX_PARENTS, MAX_TABLE_ENTRIES
    from factorq_trainers.compiled import fast

    world = config.world_of(setting)
    if method in ("learned", "gated"):
        return None
    if method == "dqn":
        if setting == "change":
            return (
                "DQN's env (factorq_trainers.experiments.dqn) cannot change the sensor order "
                "mid-experiment"
            )
        return None
    if not fast.is_available():
        return f"the compiled path is unavailable ({fast.unavailable_reason()})"
    if method == "joint" and world.num_sensors > MAX_PARENTS:
        return (
            f"a joint table over {world.num_sensors} sensors needs 2**{world.num_sensors} "
            f"entries per actuator, past the cap of 2**{MAX_PARENTS}"
        )
    if method == "q-learning":
        entries = (world.num_cells * world.num_headings << world.num_sensors) * world.num_actuators
        if entries > MAX_TABLE_ENTRIES:
            return f"its table needs {entries} values per experiment, past 2**24"
    return None


# --------------------------------------------------------------------------------------------
# Statistics


def _ratio(numerator: np.ndarray, denominator: np.ndarray, seed: int) -> dict[str, Any]:
    """Ratio of means with a paired bootstrap 95% interval over the seeds."""
    value = float(numerator.mean() / denominator.mean()) if denominator.mean() else math.inf
    if numerator.size < 2:
        return {"ratio": value, "ci": None}
    index = bootstrap_indices(seed, numerator.size)
    top, bottom = numerator[index].mean(axis=1), denominator[index].mean(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratios = np.where(bottom > 0, top / np.where(bottom > 0, bottom, 1), np.inf)
    return {"ratio": value, "ci": quantiles(ratios)}


def _percentile(values: np.ndarray, q: float) -> float | None:
    value = float(np.quantile(values, q, method="inverted_cdf"))
    return value if math.isfinite(value) else None


def summarise_setting(
    config: DependenciesConfig, setting: str, runs: dict[str, dict[str, Any]]
) -> dict[str, Any]:
    """Per method its totals; for ``learned`` the structure metrics and the ratios to the
    oracle."""
    summary: dict[str, Any] = {"methods": {}}
    totals = {}
    for method, result in runs.items():
        if method == "dqn":  # a step budget, no runs: its totals only
            collisions, greedy = result["totals"]["collisions"], result["totals"]["greedy"]
            summary["methods"][method] = {
                "collisions_per_experiment": float(collisions.mean()),
                "greedy_collisions_per_experiment": float(greedy.mean()),
                "steps_per_run": None,
                "step_budget": result["budget"],
                "episodes_per_experiment": float(np.mean(result["episodes"])),
                "collisions_per_episode": result["collisions_per_episode"],
            }
            continue
        metrics = result["metrics"]
        steps = metrics["steps"].to(torch.float64)  # [S, runs, episodes]
        collisions = metrics["collisions"].sum(dim=(1, 2)).double().numpy()
        greedy = metrics["greedy_collisions"].sum(dim=(1, 2)).double().numpy()
        per_run = steps.sum(dim=2).mean(dim=1).numpy()
        totals[method] = {"collisions": collisions, "greedy": greedy, "steps": per_run}
        summary["methods"][method] = {
            "collisions_per_experiment": float(collisions.mean()),
            "greedy_collisions_per_experiment": float(greedy.mean()),
            "steps_per_run": float(per_run.mean()),
            "collisions_per_episode": metrics["collisions"]
            .double()
            .flatten(1)
            .mean(dim=0)
            .tolist(),
        }
    gated = runs.get("gated")
    if gated is not None:
        summary["gated_structure"] = {
            "fraction_right_at_end": float(np.mean(gated["right_at_end"])),
            "hamming_at_end_mean": float(np.mean(gated["hamming_at_end"])),
        }
        if "oracle" in totals:
            mine, oracle = totals["gated"], totals["oracle"]
            summary["gated_against_oracle"] = {
                "collisions": _ratio(mine["collisions"], oracle["collisions"], config.seed),
                "greedy_collisions": _ratio(mine["greedy"], oracle["greedy"], config.seed),
                "learning_speed": _ratio(oracle["steps"], mine["steps"], config.seed),
            }
    learned = runs.get("learned")
    if learned is None:
        return summary
    until = np.asarray(learned["samples_until_right"], dtype=np.float64)
    target = SAMPLES_TARGET_CHANGE if setting == "change" else SAMPLES_TARGET
    summary["structure"] = {
        "samples_until_right_median": _percentile(until, 0.5),
        "samples_until_right_p90": _percentile(until, 0.9),
        "samples_target": target,
        "fraction_right_within_target": float((until <= target).mean()),
        "fraction_right_within_target_ci95": interval(*wilson_ci(until <= target)[1:]),
        "fraction_right_at_end": float(np.isfinite(until).mean()),
        "wrong_commitments_per_1000": 1000 * float(np.mean(learned["wrong_commitments"])),
        "hamming_at_end_mean": float(np.mean(learned["hamming_at_end"])),
        "reopened_per_experiment": float(np.mean(learned["reopened"])),
        "curve": learned["curve"],
    }
    if "oracle" in totals:
        mine, oracle = totals["learned"], totals["oracle"]
        summary["against_oracle"] = {
            "collisions": _ratio(mine["collisions"], oracle["collisions"], config.seed),
            "greedy_collisions": _ratio(mine["greedy"], oracle["greedy"], config.seed),
            # learning speed = 1 / steps per run: learned speed / oracle speed
            "learning_speed": _ratio(oracle["steps"], mine["steps"], config.seed),
        }
    return summary


# --------------------------------------------------------------------------------------------
# The experiment


def units(config: DependenciesConfig) -> list[dict[str, Any]]:
    """One unit per setting (its methods share worlds, and DQN's budget is the oracle's)."""
    return [{"id": setting, "setting": setting} for setting in config.settings]


def run_unit(
    config: DependenciesConfig,
    unit: dict[str, Any],
    progress: Callable[[int], None] | None = None,
) -> dict[str, Any]:
    """Every method of ``config`` in the unit's setting: its summary and the methods skipped."""
    setting = unit["setting"]
    runs: dict[str, dict[str, Any]] = {}
    skipped = {}
    for method in (method for method in METHODS if method in config.methods):
        reason = skipped_reason(config, setting, method)
        if reason is not None:
            skipped[method] = reason
            continue
        if method == "learned":
            runs[method] = run_learned(config, setting)
        elif method == "dqn":
            runs[method] = run_dqn(config, setting, _budget(config, setting, runs))
        elif method == "gated":
            runs[method] = run_gated(config, setting)
        else:
            runs[method] = run_compiled(config, setting, method)
    return {"summary": summarise_setting(config, setting, runs), "skipped": skipped}


def summarise(config: DependenciesConfig, outcomes: list[dict[str, Any]]) -> dict[str, Any]:
    """``dependencies.json``'s entries from the settings' units (in ``units`` order)."""
    results: dict[str, Any] = {"settings": {}, "skipped": {}, "methods": dict(METHOD_LABELS)}
    for setting, outcome in zip(config.settings, outcomes, strict=True):
        if outcome["skipped"]:
            results["skipped"][setting] = outcome["skipped"]
        results["settings"][setting] = outcome["summary"]
    return results


def estimate(config: DependenciesConfig) -> resources.Estimate:
    return resources.dependencies_estimate(config)


def run(config: DependenciesConfig) -> dict[str, Any]:
    """Every setting x method, here; the results (what ``dependencies.json`` holds)."""
    import sys

    from factorq_trainers.runner import frame

    return frame.run_in_process(sys.modules[__name__], config)
