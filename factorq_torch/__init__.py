"""factorq_torch: the Factor-Q algorithm (and tabular Q-learning) for torchrl.

``functional`` holds one pure tensor function per equation of the paper; the other modules wrap
them as TensorDict modules, torchrl losses and an online collector. The public names are
importable from the package itself and load on first use, so ``import factorq_torch.base.rng``
(the fast path, the worlds) does not pay for torchrl::

    from factorq_torch import FactorQLoss, FactorQPolicy, LocalRewardTable, TaskQTable

The worlds are in ``factorq_envs`` (``FactoredGridEnv``, ``SplitLocalReward``, ``ExperimentIndex``,
``RenderPixels``, the gymnasium id ``"FactoredGrid-v0"``), which this package never imports.
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

#: public name -> the module that defines it (loaded on first access).
_LAZY = {
    "AgentConfig": "factorq_torch.base.config",
    "keys": "factorq_torch.base.keys",
    "functional": "factorq_torch.functional",
    "TaskQTable": "factorq_torch.tables",
    "LocalRewardTable": "factorq_torch.tables",
    "experiment_index": "factorq_torch.tables",
    "EpsilonGreedyPolicy": "factorq_torch.policy",
    "FactorQPolicy": "factorq_torch.policy",
    "FactorQLoss": "factorq_torch.objectives",
    "TabularQLoss": "factorq_torch.objectives",
    "tabular_optimizer": "factorq_torch.objectives",
    "OnlineCollector": "factorq_torch.collectors",
    "TaskQNetwork": "factorq_torch.neural",
    "LocalRewardNetwork": "factorq_torch.neural",
    "LocalRisk": "factorq_torch.risk",
    "LocalRiskLoss": "factorq_torch.risk",
    "RiskSummary": "factorq_torch.risk",
    "with_local_risk": "factorq_torch.risk",
    "find_local_risk": "factorq_torch.risk",
    "save_agent": "factorq_torch.artifacts",
    "load_agent": "factorq_torch.artifacts",
    "AgentFileError": "factorq_torch.artifacts",
}

__all__ = ["__version__", *_LAZY]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        module = importlib.import_module(_LAZY[name])
        value = module if module.__name__.endswith(f".{name}") else getattr(module, name)
        globals()[name] = value  # later look-ups skip this function
        return value
    raise AttributeError(f"module 'factorq_torch' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
