"""``factorq paper``'s config (``PaperConfig``): its options and their checks."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from factorq_envs.regimes import REGIMES
from factorq_torch.base import validation
from factorq_torch.base.config import ALGORITHMS, AgentConfig
from factorq_torch.base.validation import INT32_MAX, check_int, check_names, check_threads
from factorq_trainers.methods import experiment
from factorq_trainers.methods.experiment import MAX_SEED, check_qlearning_table
from factorq_trainers.runner.options import check_choices, option
from factorq_trainers.runner.outdir import checked_out

#: Fields that leave the numbers alone (tested: backends, devices, threads and shards give
#: identical results): a sweep's digest of a configuration leaves them out.
DIGEST_IGNORED = ("out", "threads", "backend", "device", "shard_seeds")
#: Experiment drivers: the compiled kernel, the modular torchrl path, or the first available.
BACKENDS = ("auto", "fast", "modular")


@dataclass(frozen=True)
class PaperConfig(experiment.WorldOptions):
    """The paper's experiment (SPEC section 4); defaults reproduce it with 100 seeds."""

    seed: int = option(0, "Master seed: every random number of the experiment derives from it.")
    seeds: int = option(
        100, "Independent experiments per cell (world x algorithm); CIs are across them."
    )
    first_seed: int = option(
        0, "Index of the first seed: a run of seeds first_seed .. first_seed + seeds - 1 (a shard)."
    )
    shard_seeds: int = option(
        100,
        "Seeds per unit of work (an algorithm's experiments of shard_seeds seeds in every world): "
        "a finished unit is kept in OUT/units/ and a resumed run does not rerun it; the numbers "
        "do not depend on it.",
    )
    runs: int = option(
        10, "Runs per experiment (task tables reset each run; Factor-Q's local tables carry over)."
    )
    episodes: int = option(200, "Episodes per run.")
    regimes: tuple[str, ...] = option(
        REGIMES, "Obstacle regimes to run: static, semi-dynamic, dynamic (comma-separated)."
    )
    methods: tuple[str, ...] = option(
        ALGORITHMS, "Methods to run: q-learning, factor-q (comma-separated)."
    )
    epsilon: float = option(0.01, "Probability of a uniformly random (exploratory) action.")
    gamma: float = option(0.9, "Discount of future reward, in [0, 1).")
    alpha: float = option(0.2, "Task learning rate (eqs. 1 and 4), in (0, 1].")
    eta: float = option(0.1, "Margin by which scaled local reward dominates task reward (eq. 3).")
    g_min: float = option(0.01, "Floor of the normaliser G (eq. 3), > 0.")
    out: str = option("results/paper", "Directory for results.json, figure3.png and report.md.")
    threads: int | None = option(
        None,
        "CPU threads for the experiments (default: all available, the compiled path's workers; the "
        "modular path runs 1 torch thread per process, fastest for its small tensors); results do "
        "not depend on it.",
    )
    backend: str = option(
        "auto",
        "Experiment driver: fast (compiled), modular (torchrl), auto (fast if it is available).",
        choices=BACKENDS,
    )
    device: str = option("cpu", "Torch device (the fast backend runs on cpu only).")

    def __post_init__(self) -> None:
        check_int("seed", self.seed, 0, MAX_SEED)
        for name, low in (("seeds", 1), ("first_seed", 0), ("shard_seeds", 1), ("runs", 1)):
            check_int(name, getattr(self, name), low, INT32_MAX)
        check_int("episodes", self.episodes, 1, INT32_MAX)
        object.__setattr__(self, "regimes", check_names("regimes", self.regimes, REGIMES))
        world = self.checked_world(self.regimes)
        object.__setattr__(self, "methods", check_names("methods", self.methods, ALGORITHMS))
        _ = self.agent  # AgentConfig validates epsilon, gamma, alpha, eta and g_min
        if "q-learning" in self.methods:  # its state holds the pattern of all sensors
            check_qlearning_table(world)
        if self.threads is not None:
            check_threads("threads", self.threads)
        check_choices(self)  # backend
        try:
            kind = torch.device(self.device).type
        except (RuntimeError, TypeError):
            kind = None  # check_device says why
        if self.backend == "fast" and kind not in (None, "cpu"):
            raise ValueError(f"device={self.device!r} is not supported by backend 'fast' (cpu)")
        # The device must exist here: refused now, not once the run began.
        validation.check_device("device", self.device, allow_meta=False, optional=False)
        object.__setattr__(self, "out", checked_out(self.out))

    @property
    def agent(self) -> AgentConfig:
        """The learning parameters, validated."""
        return AgentConfig(
            epsilon=self.epsilon, gamma=self.gamma, alpha=self.alpha, eta=self.eta, g_min=self.g_min
        )

    @property
    def cells(self) -> list[tuple[str, str]]:
        """The selected ``(world, algorithm)`` cells, in canonical order."""
        return [(world, algorithm) for world in self.regimes for algorithm in self.methods]
