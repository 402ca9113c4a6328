"""``CommittedStructureLearner``: the structure learner that predicts no local reward until it has
committed (issue 16).

``StructureLearner`` predicts an open actuator's local reward as the posterior-weighted running
mean over its candidate parent sets. In a body whose other actuators never collide (the heading
body: forward moves, the turns do not), that prediction is slightly negative for forward under
*every* sensor reading while the learner is open (the "no sensor" candidate's mean is the overall
collision rate), and eq. 3 lets the local term dominate: the greedy agent then turns in place
until the epsilon branch fires forward often enough to commit, which on MiniGrid takes longer
than the whole budget (measured, ``docs/decisions.md``). This variant predicts 0 for an open
actuator -- what an unvisited table entry predicts -- so the agent acts on its task values until
the evidence commits it, then exactly as ``StructureLearner`` (the committed candidate's running
mean). Counting, commitment and reopening are ``StructureLearner``'s, unchanged.

Example:
    >>> import torch
    >>> learner = CommittedStructureLearner(1, num_actions=2, num_sensors=2)
    >>> sensors = torch.tensor([[True, False]])
    >>> learner.update_running_mean(sensors, torch.tensor([0]), torch.tensor([[-1.0, 0.0]]))
    >>> learner.local_values(sensors)  # actuator 0 is open after one collision: no prediction
    tensor([[0., 0.]])
"""

from __future__ import annotations

import torch

from factorq_torch.structure import StructureLearner


class CommittedStructureLearner(StructureLearner):
    """``StructureLearner`` whose open actuators predict 0 (module docstring); same arguments."""

    def local_values(self, readings: torch.Tensor) -> torch.Tensor:
        """``[S, A]`` float32: the committed candidate's running mean, 0 while open."""
        values = super().local_values(readings)
        return torch.where(self.committed >= 0, values, torch.zeros_like(values))
