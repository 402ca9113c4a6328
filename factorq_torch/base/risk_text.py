"""The one-line text of a local-risk episode summary, without torch (reports draw it without it).

``factorq_torch.risk.RiskSummary.line`` and ``factorq_trainers.commands.risk.report`` both use it.
"""

from __future__ import annotations

from typing import Any


def summary_line(summary: dict[str, Any]) -> str:
    """One log line of a ``RiskSummary.episode()`` summary (or its JSON form).

    Args:
        summary: ``steps``, ``risky_steps``, ``overrides``, and per actuator name ``penalised``
            (a count) and ``mean_penalty``.

    >>> summary_line({"steps": 9, "risky_steps": 2, "overrides": 1,
    ...               "penalised": {"forward": 2, "left": 0}, "mean_penalty": {"forward": -0.5}})
    'risk: 2/9 steps penalised, 1 overrides; forward x2 (-0.50)'
    """
    hits = ", ".join(
        f"{name} x{count} ({summary['mean_penalty'][name]:.2f})"
        for name, count in summary["penalised"].items()
        if count
    )
    return (
        f"risk: {summary['risky_steps']}/{summary['steps']} steps penalised, "
        f"{summary['overrides']} overrides" + (f"; {hits}" if hits else "")
    )
