"""``PermuteSensors``: a sensor order per experiment, which may be redrawn mid-experiment.

``WorldConfig.sensor_permutation`` gives every experiment of a batch the same order, fixed for the
whole experiment. The structure-learning experiment (``factorq dependencies``) needs
one order per experiment and a body that changes while the agent learns ("the permutation is
redrawn at run 5"). This transform is that hook, kept outside the world: it reorders the
``sensors`` entry the env writes, ``sensors[s, j] <- sensors[s, permutations[s, j]]``, on every
step and reset, and ``set_permutations(permutations, mask)`` changes the order of some
experiments from the next observation on. The world, its random streams and everything else it
writes are untouched, so an agent that does not read ``sensors`` through an order (the oracle, a
table over all sensors) sees the same world with or without it.

The true dependency of experiment ``s`` after the transform is ``dependency[:, permutations[s]]``
(``permuted_dependency``).
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.envs.transforms import Transform

from factorq_torch.base import keys


def permuted_dependency(dependency: torch.Tensor, permutations: torch.Tensor) -> torch.Tensor:
    """``[S, A, K]`` bool: the dependency each experiment's agent faces, ``dependency[:, p]``."""
    return dependency[:, permutations].permute(1, 0, 2)


class PermuteSensors(Transform):
    """Reorder ``sensors`` ``[S, K]`` per experiment (module docstring).

    Args:
        permutations: ``[S, K]`` int64, row ``s`` a permutation of ``range(K)``.
        sensors_key: the entry to reorder.

    Example:
        >>> from torchrl.envs import TransformedEnv
        >>> from factorq_envs.torchrl_env import FactoredGridEnv
        >>> base = FactoredGridEnv(size=3, num_obstacles=0, batch_size=(1,))
        >>> env = TransformedEnv(base, PermuteSensors(torch.tensor([[1, 2, 3, 0]])))
        >>> base.reset()["sensors"].tolist(), env.reset()["sensors"].tolist()
        ([[True, True, False, False]], [[True, False, False, True]])
    """

    def __init__(self, permutations: torch.Tensor, sensors_key: str = keys.SENSORS) -> None:
        super().__init__(in_keys=[sensors_key], out_keys=[sensors_key])
        self.sensors_key = sensors_key
        self.register_buffer("permutations", self._check(permutations).clone())

    @staticmethod
    def _check(permutations: torch.Tensor) -> torch.Tensor:
        if not isinstance(permutations, torch.Tensor) or permutations.dim() != 2:
            raise ValueError("permutations must be an int64 tensor [experiments, sensors]")
        ordered = permutations.sort(dim=-1).values
        expected = torch.arange(permutations.shape[-1]).expand_as(permutations)
        if not torch.equal(ordered.cpu(), expected):
            raise ValueError("every row of permutations must hold each of 0..K-1 once")
        return permutations.to(torch.int64)

    def set_permutations(self, permutations: torch.Tensor, mask: torch.Tensor) -> None:
        """Experiments where ``mask`` ``[S]`` is True take ``permutations`` ``[S, K]``'s rows."""
        permutations = self._check(permutations).to(self.permutations.device)
        self.permutations[mask] = permutations[mask]

    def _permute(self, tensordict: TensorDictBase) -> TensorDictBase:
        sensors = tensordict.get(self.sensors_key, None)  # [S, K]
        if sensors is not None:
            tensordict.set(self.sensors_key, sensors.gather(-1, self.permutations))
        return tensordict

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        return self._permute(next_tensordict)

    def _reset(
        self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase
    ) -> TensorDictBase:
        return self._permute(tensordict_reset)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        return self._permute(tensordict)
