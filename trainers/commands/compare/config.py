"""``factorq compare``'s config (``CompareConfig``, with Factor-DQN's ``FactorDQNConfig``): its
options and their checks."""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass, fields

from factorq_envs.regimes import REGIMES
from factorq_torch.base.config import AgentConfig
from factorq_torch.base.validation import check_float, check_hidden, check_names, check_threads
from factorq_torch.neural import ACTIVATIONS
from factorq_trainers.methods import experiment
from factorq_trainers.methods.dqn import METHODS, DQNConfig
from factorq_trainers.methods.experiment import ExperimentConfig
from factorq_trainers.runner.options import check_choices, option
from factorq_trainers.runner.outdir import checked_out

LOGGERS = ("csv", "tensorboard")
#: Fields that leave the numbers alone: a sweep's digest of a configuration leaves them out.
DIGEST_IGNORED = ("out", "threads", "logger")
#: Fields a sweep sets itself (``logger``: a sweep writes no per-episode logs).
SWEEP_RESERVED = ("seeds", "out", "logger")


@dataclass(frozen=True)
class FactorDQNConfig:
    """Neural Factor-Q's networks, optimiser and exploration (eqs. 2-4 use ``AgentConfig``'s
    gamma, alpha, eta and g_min). Why the local networks have no bias and tanh, and why
    ``epsilon`` is 0.05 rather than the paper's 0.01: ``docs/decisions.md`` (Factor-DQN)."""

    hidden: tuple[int, ...] = option(
        (64,), "Hidden layer widths of each experiment's task Q-network (input: the cell one-hot)."
    )
    activation: str = option(
        "relu", "Hidden activation of the task Q-network: tanh or relu.", choices=ACTIVATIONS
    )
    local_hidden: tuple[int, ...] = option(
        (8,), "Hidden layer widths of each actuator's local reward network (input: its sensor bit)."
    )
    local_bias: bool = option(
        False,
        "Biases in the local networks (False: nothing sensed predicts exactly 0; see neural.py).",
    )
    lr: float = option(1e-3, "Adam learning rate of the task Q-network.")
    local_lr: float = option(1e-2, "Adam learning rate of the local reward networks.")
    local_activation: str = option(
        "tanh", "Hidden activation of the local networks: tanh or relu.", choices=ACTIVATIONS
    )
    local_shared: bool = option(
        True,
        "One local network per experiment shared by its four actuators (else one per actuator).",
    )
    epsilon: float = option(
        0.05, "Exploration probability of FactorQPolicy (tabular Factor-Q: the paper's 0.01)."
    )

    def __post_init__(self) -> None:
        object.__setattr__(self, "hidden", check_hidden("hidden", self.hidden))
        object.__setattr__(self, "local_hidden", check_hidden("local_hidden", self.local_hidden))
        for name in ("local_bias", "local_shared"):
            if not isinstance(getattr(self, name), bool):
                raise TypeError(f"{name} must be a bool, got {getattr(self, name)!r}")
        check_choices(self)  # activation, local_activation
        check_float("lr", self.lr, 0.0, 1.0, low_open=True)
        check_float("local_lr", self.local_lr, 0.0, 1.0, low_open=True)
        check_float("epsilon", self.epsilon, 0.0, 1.0)


@dataclass(frozen=True)
class CompareConfig(experiment.WorldOptions):
    """The comparison: methods x worlds, ``seeds`` experiments each, ``steps`` env steps each."""

    seed: int = option(
        0, "Master seed: worlds, policies and network initialisations derive from it."
    )
    seeds: int = option(
        3, "Independent experiments per method and world; 95% intervals are across them."
    )
    steps: int = option(15_000, "Budget of env steps per experiment.")
    regimes: tuple[str, ...] = option(
        REGIMES, "Obstacle regimes to run: static, semi-dynamic, dynamic (comma-separated)."
    )
    methods: tuple[str, ...] = option(
        METHODS, "Methods to run: factor-q, q-learning, dqn, factor-dqn (comma-separated)."
    )
    out: str = option(
        "results/compare", "Directory for comparison.json, comparison.png, comparison.md and logs/."
    )
    logger: str = option(
        "csv",
        "Per-episode logs: csv (torchrl CSVLogger) or tensorboard (needs the tensorboard package).",
        choices=LOGGERS,
    )
    threads: int = option(1, "CPU threads for torch (1 is fastest on these tiny tensors).")
    agent: AgentConfig = option(
        AgentConfig(),
        "Tabular and Factor-DQN parameters: epsilon, gamma, alpha, eta, g_min (the paper's).",
    )
    dqn: DQNConfig = option(DQNConfig(), "DQN's hyperparameters (factorq_trainers.methods.dqn).")
    factor_dqn: FactorDQNConfig = option(
        FactorDQNConfig(), "Factor-DQN's networks and learning rates."
    )

    def __post_init__(self) -> None:
        object.__setattr__(self, "methods", check_names("methods", self.methods, METHODS))
        check_choices(self)  # logger
        if self.logger == "tensorboard" and importlib.util.find_spec("tensorboard") is None:
            raise ValueError(
                "logger='tensorboard' needs the tensorboard package, which is not installed: "
                "`pip install tensorboard` (the extra: `pip install -e '.[tensorboard]'`), "
                "or use logger='csv'"
            )
        object.__setattr__(self, "out", checked_out(self.out, files=True))  # claim() refuses one
        check_threads("threads", self.threads)
        for name, kind in (
            ("agent", AgentConfig),
            ("dqn", DQNConfig),
            ("factor_dqn", FactorDQNConfig),
        ):
            if not isinstance(getattr(self, name), kind):
                raise TypeError(f"{name} must be a {kind.__name__}, got {getattr(self, name)!r}")
        # ExperimentConfig validates seed, seeds, steps, regimes and the world, naming the option.
        object.__setattr__(self, "regimes", self.experiments.regimes)
        if "q-learning" in self.methods:  # its state holds the pattern of all sensors
            experiment.check_qlearning_table(self.experiments.world)

    @property
    def experiments(self) -> ExperimentConfig:
        return ExperimentConfig(**{f.name: getattr(self, f.name) for f in fields(ExperimentConfig)})
