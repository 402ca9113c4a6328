"""``factorq dependencies``' settings, methods and config (``DependenciesConfig``): the named
presets, the custom setting the body options declare, and the checks of every option.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass
from typing import Any

from factorq_envs.grid_world import WorldConfig
from factorq_envs.regimes import REGIMES
from factorq_torch.base import validation
from factorq_torch.base.config import EXPLORATIONS, AgentConfig
from factorq_torch.base.validation import INT32_MAX, check_float, check_int, check_names
from factorq_trainers.analysis.vocabulary import among
from factorq_trainers.methods.experiment import MAX_SEED, PAPER_WORLD, check_world_options
from factorq_trainers.runner.options import check_choices, option

#: The fields that leave the numbers alone (the compiled and modular paths agree bit for bit);
#: read by ``factorq sweep`` from the config's module.
DIGEST_IGNORED = ("out", "threads", "path")

#: The settings of the issue: name -> body options (the sensor order is drawn per experiment).
SETTINGS: dict[str, dict[str, Any]] = {
    "cross": {"body": "translate", "sensors": "cross"},
    "ring-24": {"body": "translate", "sensors": "ring", "num_distractors": 24},
    "heading": {"body": "heading", "sensors": "cross"},
    "noise-5": {"body": "translate", "sensors": "cross", "sensor_noise": 0.05},
    "noise-10": {"body": "translate", "sensors": "cross", "sensor_noise": 0.10},
    "change": {"body": "translate", "sensors": "cross"},
    # noise with many sensors (8 ring sensors and 12 distractors: 20)
    "ring-12-noise-5": {
        "body": "translate", "sensors": "ring", "num_distractors": 12, "sensor_noise": 0.05
    },
    "ring-12-noise-10": {
        "body": "translate", "sensors": "ring", "num_distractors": 12, "sensor_noise": 0.10
    },
}  # fmt: skip
#: The setting that ``--body``, ``--sensors``, ``--distractors`` and ``--sensor-noise`` declare.
CUSTOM = "custom"
#: A setting's content: its body options with the defaults filled in, and whether the sensor
#: order is redrawn mid-experiment (the ``change`` preset).
SETTING_DEFAULTS = {
    name: getattr(PAPER_WORLD, name)
    for name in ("body", "sensors", "num_distractors", "sensor_noise")
}
#: The structure experiment's grid: smaller than the paper's (6x6, 4 obstacles, 1,000 steps),
#: so that 100 experiments of every setting run in seconds and an actuator fires its first 100
#: times within a few runs (docs/decisions.md, "Learned dependencies").
STRUCTURE_WORLD = WorldConfig(size=6, num_obstacles=4, max_steps=1_000)
METHODS = among(
    "factor-q-learned", "factor-q", "factor-q-joint", "q-learning", "dqn", "factor-q-gated"
)
#: The methods with a policy stream of their own: their number fixes every method's keys
#: (``experiment_keys``), so a new method must not join them; the gated network takes the
#: learned structure's stream (the two learners under common random numbers).
KEYED_METHODS = ("factor-q-learned", "factor-q", "factor-q-joint", "q-learning", "dqn")
#: The methods run by default: DQN is opt-in (``--methods``), see ``run_dqn``.
DEFAULT_METHODS = ("factor-q-learned", "factor-q", "factor-q-joint", "q-learning")
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
    regimes: tuple[str, ...] = option(
        ("static",),
        "Obstacle regimes: " + ", ".join(REGIMES) + " (comma-separated); every setting runs in "
        "each.",
    )
    runs: int = option(10, "Runs per experiment (task tables reset at each).")
    episodes: int = option(1, "Episodes per run.")
    size: int = option(STRUCTURE_WORLD.size, "Side of the square grid, in cells.")
    obstacles: int = option(STRUCTURE_WORLD.num_obstacles, "Number of single-cell obstacles.")
    max_steps: int = option(
        STRUCTURE_WORLD.max_steps, "Actions after which an episode is truncated."
    )
    layout_seed: int = option(
        STRUCTURE_WORLD.layout_seed, "Seed of the static world's obstacle layout."
    )
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
    pairs: str = option(
        "pruned",
        "Which pair candidates are counted: pruned (a pair only while one of its sensors, or the "
        "pair itself, is plausible, its counts rebuilt from the stored firings when it enters: "
        "the same counts, a fraction of the work with many sensors) or all (every pair at every "
        "firing).",
        choices=("all", "pruned"),
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
    noisy_reopen_factor: float | None = option(
        10000.0,
        "The change-point test's odds once a commitment rested on data with an outcome against "
        "its pattern's majority (noisy sensors: the collision rate of a pattern then drifts with "
        "the policy, no change of structure). auto: --reopen-factor's.",
    )
    risk_gate: str = option(
        "off",
        "on: Factor-Q (learned, oracle, joint, gated) sees only significant local values in eqs. "
        "2-3 (|rho_a| > 0.5: a collision more likely than not), the rest as 0, the fix of the "
        "heading-noise stall (docs/decisions.md). off: the paper's eqs. 2-3.",
        choices=("off", "on"),
    )
    exploration: str = option(
        "uniform",
        "Factor-Q's exploratory actions (learned, oracle, joint, gated): uniform (the paper) or "
        "risk-aware (uniform among the actuators its local model does not call risky, rho_a >= "
        "-0.5). Q-learning and DQN always explore uniformly.",
        choices=EXPLORATIONS,
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
        object.__setattr__(self, "regimes", check_names("regimes", self.regimes, REGIMES))
        object.__setattr__(self, "methods", check_names("methods", self.methods, METHODS))
        check_int("runs", self.runs, 1, INT32_MAX)
        check_int("episodes", self.episodes, 1, INT32_MAX)
        check_int("max_parents", self.max_parents, 0)
        check_int("window", self.window, 1, INT32_MAX)
        validation.check_threads("threads", self.threads)
        check_choices(self)
        if not isinstance(self.bayes_factor, (int, float)) or not self.bayes_factor > 1:
            raise ValueError(
                f"bayes_factor={self.bayes_factor!r} must be > 1 (a commitment needs evidence "
                f"for the best candidate over the runner-up)"
            )
        for name in ("reopen_factor", "noisy_reopen_factor"):
            if getattr(self, name) is not None:
                check_float(name, getattr(self, name), 1.0, math.inf, low_open=True, high_open=True)
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
        from factorq_torch.functional import candidate_sets

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

    def agent_of(self, method: str) -> AgentConfig:
        """The learning parameters of ``method``: the paper's, with ``risk_gate`` and
        ``exploration`` for the Factor-Q methods (Q-learning and DQN have no local model)."""
        if method in ("q-learning", "dqn"):
            return AgentConfig()
        return AgentConfig(risk_gate=self.risk_gate == "on", exploration=self.exploration)

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

    @property
    def regime(self) -> str:
        """The obstacle regime of a unit's config (``command.units`` gives each its own)."""
        if len(self.regimes) != 1:
            raise ValueError(f"regimes: a unit runs one regime, not {', '.join(self.regimes)}")
        return self.regimes[0]

    def body_of(self, setting: str) -> dict[str, Any]:
        """``setting_options`` as a config names them (``distractors``: ``WorldOptions``')."""
        options = self.setting_options(setting)
        return {"distractors" if k == "num_distractors" else k: v for k, v in options.items()}

    def world_of(self, setting: str) -> WorldConfig:
        body = self.body_of(setting)
        return check_world_options(
            self.size, self.obstacles, self.max_steps, self.layout_seed, self.regimes, body
        )
