"""The one method vocabulary of every command and report.

A method's name means the same agent, drawn with the same label, in every command's
``--methods``, results file, kept unit and report. The grammar:

- ``q-learning``, ``dqn``, ``sb3-dqn``: the baselines (a tabular Q, torchrl's DQN, SB3's DQN);
- ``factor-q``: tabular Factor-Q on the dependencies the world declares (the paper's agent: the
  "oracle" pairing), ``factor-dqn`` its neural form;
- a suffix says where the dependencies come from or what is carried: ``-learned`` (the structure
  learner, told only the number of actuators and sensors), ``-posterior`` (its open prediction),
  ``-joint`` (the full joint table over every sensor), ``-gated`` (a gated network),
  ``-body`` (a body model learned in another task and carried in);
- ``+risk``: a DQN with the local-risk layer (``factorq_torch.risk.LocalRisk``), on the declared
  dependencies unless ``-learned``.

Each command's ``METHODS`` is built with ``among`` (docs/decisions.md, "One method vocabulary").
"""

from __future__ import annotations

from typing import Any

#: Every method, by name: its label in reports and figures.
METHODS: dict[str, str] = {
    "q-learning": "Q-learning",
    "factor-q": "Factor-Q",
    "factor-q-learned": "Factor-Q, learned dependencies",
    "factor-q-posterior": "Factor-Q, learned, posterior prediction",
    "factor-q-joint": "Factor-Q, full joint table",
    "factor-q-gated": "Factor-Q, gated network",
    "factor-q-body": "Factor-Q, carried body model",
    "factor-q-learned-body": "Factor-Q, learned dependencies, carried body model",
    "dqn": "DQN",
    "dqn-image": "DQN (MiniGrid image)",
    "factor-dqn": "neural Factor-Q",
    "factor-dqn-learned": "neural Factor-Q, learned dependencies",
    "dqn+risk": "DQN + local risk",
    "dqn+risk-learned": "DQN + local risk, learned dependencies",
    "sb3-dqn": "SB3 DQN",
    "sb3-dqn+risk": "SB3 DQN + local risk",
}


def among(*names: str) -> tuple[str, ...]:
    """``names`` (a command's methods, in its order), each checked against ``METHODS``."""
    unknown = [name for name in names if name not in METHODS]
    if unknown:
        raise ValueError(f"methods not in the vocabulary (analysis/vocabulary.py): {unknown}")
    return names


def label(name: str) -> str:
    """The label of method ``name`` (its name itself where it is not in the vocabulary: a report
    drawn from an edited file still draws)."""
    return METHODS.get(name, name)


def recorded_label(results: dict[str, Any], name: str) -> str:
    """The label a results file recorded for method ``name`` (its ``"methods"``, name -> label,
    as the run wrote them: ``minigrid``, ``dependencies``), else ``name`` itself."""
    recorded = results.get("methods")
    return str(recorded.get(name, name)) if isinstance(recorded, dict) else name
