"""Hyperparameters of the tabular agents (SPEC section 3), validated where they enter."""

from __future__ import annotations

from dataclasses import dataclass

from factorq_torch.base.validation import check_float

ALGORITHMS = ("q-learning", "factor-q")
#: How a Factor-Q agent draws its exploratory actions: ``"uniform"`` over every actuator (the
#: paper) or ``"risk-aware"``, uniform over the actuators its local model does not call risky
#: (``functional.risk_mask``: ``rho_a >= -risk_threshold``; every actuator where all are).
EXPLORATIONS = ("uniform", "risk-aware")
#: Actuators of the paper's body (4 translations, each paired with its own proximity sensor), the
#: default of the agent's constructors; the body itself is declared in ``envs/body.py``
#: (``TRANSLATE``), which a test keeps in step with this number.
PAPER_NUM_ACTIONS = 4


@dataclass(frozen=True)
class AgentConfig:
    """Learning parameters shared by Q-learning and Factor-Q (defaults: the paper's).

    Args:
        epsilon: probability of a uniformly random action, in [0, 1].
        gamma: discount of future reward, in [0, 1).
        alpha: task learning rate (eqs. 1 and 4), in (0, 1].
        eta: margin by which the scaled local reward dominates the task reward (eq. 3), >= 0.
        g_min: floor of the normaliser G (eq. 3), > 0.
        risk_threshold: the local value, in local reward units (>= 0), beyond which an actuator
            is risky (``rho_a < -risk_threshold``) and a local value significant (``|rho_a| >
            risk_threshold``); 0.5: a collision of -1 more likely than not.
        risk_gate: eqs. 2-3 see only significant local values, the others as 0
            (``functional.significant_local``); False: the paper, every value counts.
        exploration: ``"uniform"`` (the paper) or ``"risk-aware"`` (``EXPLORATIONS``); Factor-Q
            only.
        arbitration: the task takes priority where its advantage outweighs any local future
            (``functional.arbitrated_normaliser``); False: the paper, eq. 3 always. Factor-Q only.
        local_span: the width of one step's local reward interval, read by ``arbitration`` (1:
            a collision of -1), >= 0.
    """

    epsilon: float = 0.01
    """Probability of a uniformly random (exploratory) action."""
    gamma: float = 0.9
    """Discount of future reward."""
    alpha: float = 0.2
    """Task learning rate (eqs. 1 and 4)."""
    eta: float = 0.1
    """Margin by which the scaled local reward dominates the task reward (eq. 3)."""
    g_min: float = 0.01
    """Floor of the normaliser G (eq. 3), so local reward decides in unvisited states."""
    risk_threshold: float = 0.5
    """Local value beyond which an actuator is risky / a local value significant (units of the
    local reward; 0.5: a collision of -1 more likely than not)."""
    risk_gate: bool = False
    """Eqs. 2-3 see only significant local values (|rho_a| > risk_threshold), the rest as 0."""
    exploration: str = "uniform"
    """Exploratory actions: uniform (the paper) or risk-aware (among the actuators not risky)."""
    arbitration: bool = False
    """The task takes priority where its advantage outweighs any local future (section 9)."""
    local_span: float = 1.0
    """Width of one step's local reward interval (1: a collision of -1), read by arbitration."""

    def __post_init__(self) -> None:
        check_float("epsilon", self.epsilon, 0.0, 1.0)
        check_float("gamma", self.gamma, 0.0, 1.0, high_open=True)
        check_float("alpha", self.alpha, 0.0, 1.0, low_open=True)
        check_float("eta", self.eta, 0.0, 1e6)
        check_float("g_min", self.g_min, 0.0, 1e6, low_open=True)
        check_float("risk_threshold", self.risk_threshold, 0.0, 1e6)
        if not isinstance(self.risk_gate, bool):
            raise TypeError(f"risk_gate must be a bool, got {self.risk_gate!r}")
        check_exploration(self.exploration)
        if not isinstance(self.arbitration, bool):
            raise TypeError(f"arbitration must be a bool, got {self.arbitration!r}")
        check_float("local_span", self.local_span, 0.0, 1e6)


def check_exploration(exploration: str) -> str:
    """Return ``exploration`` if it is one of ``EXPLORATIONS``, else raise a ValueError naming
    them."""
    if exploration not in EXPLORATIONS:
        raise ValueError(
            f"exploration={exploration!r} is unknown: choose one of {', '.join(EXPLORATIONS)}"
        )
    return exploration


def check_algorithm(algorithm: str) -> str:
    """Return ``algorithm`` if it is one of ``ALGORITHMS``, else raise a ValueError naming them."""
    if algorithm not in ALGORITHMS:
        raise ValueError(
            f"algorithm={algorithm!r} is unknown: choose one of {', '.join(ALGORITHMS)}"
        )
    return algorithm
