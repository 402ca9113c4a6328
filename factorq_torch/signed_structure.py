"""Learned dependencies for local rewards of either sign: one structure learner per sign.

``StructureLearner`` reads a firing's local reward as a cost, the Bernoulli outcome
``clip(-r, 0, 1)``: a local reward above 0 counts as nothing happened, so it cannot learn what
pays. ``SignedStructureLearner`` gives each sign its own channel, two ``StructureLearner``s told
the same ``A`` and ``K``:

- ``costs`` learns from ``min(r, 0)``: which sensors decide a loss (a collision);
- ``pays`` learns from ``-max(r, 0)``: which sensors decide a gain (an item collected), read as a
  cost of the same size, so every rule of the learner (candidates, likelihood, commitment,
  reopening) applies unchanged.

The local value is ``costs(o) - pays(o)``: each channel's running mean of its own rewards, the
gain's sign restored. The structure (``structure``) is the union of both channels' parents.

Why two channels rather than one "a local reward that is not 0" event (measured in
docs/decisions.md, "Local rewards of either sign"): one channel counts a gain and a loss as the
same event, so for an actuator whose losses are common (walls) and gains rare (items), the
single sensor of the losses explains nearly every event and is committed to before the gains
have made the pair's case; the pattern "nothing sensed" then holds the rare gains, its running
mean is a small positive number, and eqs. 2-3 make any positive difference absolute (a paying
actuator is always greedy). Per sign, each channel's outcome is deterministic given its own
sensor. And the learner's ``"optimistic"`` prediction stays right for both: ``costs`` predicts a
loss only where every plausible structure predicts one; ``pays``, reading gains as costs,
predicts a gain only where every plausible structure predicts one (a firing is sought, as it is
avoided, only on the evidence of every structure not yet ruled out).

Keys: reads ``sensors`` ``[S, K]`` bool, writes ``local_value`` ``[S, A]`` float32.

>>> learner = SignedStructureLearner(1, num_actions=1, num_sensors=2, bayes_factor=10.0)
>>> for step in range(40):  # sensor 0 sees a wall (-1), sensor 1 an item (+1)
...     reading = torch.tensor([[step % 3 == 1, step % 3 == 2]])
...     reward = torch.tensor([[-1.0 if step % 3 == 1 else 1.0 if step % 3 == 2 else 0.0]])
...     learner.update_running_mean(reading, torch.tensor([0]), reward)
>>> learner.structure().int().tolist()
[[[1, 1]]]
>>> readings = ([True, False], [False, True], [False, False])  # a wall, an item, nothing
>>> [learner.local_values(torch.tensor([reading])).item() for reading in readings]
[-1.0, 1.0, 0.0]
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from factorq_torch.base import keys
from factorq_torch.structure import StructureLearner


def split_signs(local_reward: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(min(r, 0), -max(r, 0))``: the costs and the gains read as costs (both ``<= 0``, no
    ``-0.0``)."""
    zero = torch.zeros((), dtype=local_reward.dtype, device=local_reward.device)
    costs = torch.where(local_reward < 0, local_reward, zero)
    gains = torch.where(local_reward > 0, -local_reward, zero)
    return costs, gains


class SignedStructureLearner(TensorDictModuleBase):
    """Two ``StructureLearner``s, one per sign of the local reward (module docstring).

    Args:
        num_experiments: ``S``.
        num_actions, num_sensors: ``A`` and ``K``, as ``StructureLearner``.
        **options: every other ``StructureLearner`` option, given to both channels.
    """

    def __init__(
        self, num_experiments: int, *, num_actions: int, num_sensors: int, **options: Any
    ) -> None:
        super().__init__()
        self.costs = StructureLearner(
            num_experiments, num_actions=num_actions, num_sensors=num_sensors, **options
        )
        self.pays = StructureLearner(
            num_experiments, num_actions=num_actions, num_sensors=num_sensors, **options
        )
        self.num_experiments = self.costs.num_experiments
        self.num_actions, self.num_sensors = num_actions, num_sensors
        self.in_keys = list(self.costs.in_keys)
        self.out_keys = [keys.LOCAL_VALUE]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        costs = self.costs(tensordict).get(keys.LOCAL_VALUE)
        gains = self.pays(tensordict).get(keys.LOCAL_VALUE)
        tensordict.set(keys.LOCAL_VALUE, costs - gains)
        return tensordict

    def local_values(self, readings: torch.Tensor) -> torch.Tensor:
        """``rho(o)`` ``[S, A]`` of the online step's readings ``[S, K]``."""
        return self.costs.local_values(readings) - self.pays.local_values(readings)

    def update_running_mean(
        self,
        readings: torch.Tensor,
        action: torch.Tensor,
        local_reward: torch.Tensor,
        mask: torch.Tensor | None = None,
    ) -> None:
        """Each channel counts the firing with its own part of ``local_reward`` (``split_signs``);
        the arguments as ``StructureLearner.update_running_mean``."""
        costs, gains = split_signs(local_reward)
        self.costs.update_running_mean(readings, action, costs, mask)
        self.pays.update_running_mean(readings, action, gains, mask)

    def structure(self) -> torch.Tensor:
        """``[S, A, K]`` bool: the parents either channel committed to."""
        return self.costs.structure() | self.pays.structure()

    def is_committed(self) -> torch.Tensor:
        """``[S, A]`` bool: both channels of the actuator have committed."""
        return self.costs.is_committed() & self.pays.is_committed()

    def reset(self, mask: torch.Tensor | None = None) -> None:
        """Forget both channels (every experiment, or only where ``mask`` ``[S]``)."""
        self.costs.reset(mask)
        self.pays.reset(mask)
