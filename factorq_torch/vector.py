"""Tabular Factor-Q acting on an action vector (simultaneous actuators, issue 40).

A body of ``J`` independent actuators, actuator ``j`` taking one of ``V_j`` values
(``nvec``) at every step, all of them firing together; the env returns one local reward per
actuator (``[..., J]``, never summed). ``VectorFactorQ`` holds, for ``S`` independent
experiments:

- the task table ``Q [S, N, M]`` over the cell and the **joint** action (``M = prod(nvec)``,
  ``factorq_torch.functional.joint_action_index`` order);
- one local table per **actuator value** ``rho [S, sum(nvec), P]`` with its visit counts: the
  expected local reward of setting actuator ``j`` to value ``v`` under the pattern of that
  value's parent sensors (``dependency`` ``[sum(nvec), K]``, the paper's factoring: the
  horizontal drive pushing west is decided by the west sensor);

and acts epsilon-greedily on ``C(s, a) = Q(s, a) + sum_j G_j rho_j(o, a_j)`` (eqs. 2-3 per
actuator, ``vector_normalisers`` and ``vector_combined_values``), updates the task table with
eq. 4's target ``r + gamma max_a' C(s', a')`` and each actuator's local table with **its own**
local reward (eq. 5 per actuator): the per-actuator assignment the paper's conclusion asks for.
``docs/decisions.md`` ("Simultaneous actuators") derives the combination.

The same class is both baselines of ``examples/action_vectors.py``: **flat Factor-Q** is one
actuator of ``M`` values whose local reward is the sum of the actuators' (eqs. 2-5 exactly as
the paper writes them, over the joint action), and **flat Q-learning** is ``local=False`` on
the state ``cell x sensor pattern`` with the conventional reward (eq. 1).

Example (two experiments, a 3x3 grid, the two-drive body's dependency):

    >>> from factorq_envs.vector_grid import drive_dependency
    >>> agent = VectorFactorQ(2, num_cells=9, nvec=(3, 3), dependency=drive_dependency())
    >>> cell = torch.tensor([0, 0]); sensors = torch.tensor([[1, 1, 0, 0]] * 2, dtype=torch.bool)
    >>> action = torch.tensor([[0, 2], [2, 0]])  # west + south bumps west; east + north, north
    >>> local = torch.tensor([[-1.0, 0.0], [0.0, -1.0]])  # one local reward per drive
    >>> agent.update(cell, sensors, action, torch.tensor([-1.0, -1.0]), local,
    ...              torch.tensor([3, 1]), sensors, torch.tensor([False, False]))
    >>> agent.rho[0, :, 1].tolist()  # experiment 0: only "horizontal west" under a west wall
    [-1.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    >>> agent.rho[1, :, 1].tolist()  # experiment 1: only "vertical north" under a north wall
    [0.0, 0.0, 0.0, -1.0, 0.0, 0.0]
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch

from factorq_torch.base.rng import STREAM_POLICY, STREAM_TASK_NETWORK, derive_keys, random_bits
from factorq_torch.base.validation import check_float, check_int
from factorq_torch.functional import (
    check_dependency,
    epsilon_greedy_from_bits,
    factorq_target,
    joint_action_index,
    joint_action_vector,
    local_patterns,
    project_local,
    q_learning_target,
    q_update,
    running_mean_update,
    vector_combined_values,
    vector_normalisers,
)
from factorq_torch.neural import BatchedMLP


class VectorFactorQ:
    """Tabular Factor-Q on an action vector, for ``S`` experiments (module docstring).

    Args:
        num_experiments: ``S``.
        num_cells: ``N``, the task states (a cell; for flat Q-learning, cell x sensor pattern).
        nvec: the values of each actuator (``J = len(nvec)`` actuators).
        dependency: bool ``[sum(nvec), K]``, the parent sensors of each actuator value (rows in
            ``nvec`` order); ``None`` only with ``local=False``.
        alpha, gamma, epsilon, eta, g_min: the paper's (SPEC section 3).
        seed: the policy's random streams (experiment ``i`` draws from key ``i``).
        local: the local tables and eqs. 2-3; ``False``: plain Q-learning on the joint action.
    """

    def __init__(
        self,
        num_experiments: int,
        num_cells: int,
        nvec: Sequence[int],
        dependency: torch.Tensor | None,
        *,
        alpha: float = 0.2,
        gamma: float = 0.9,
        epsilon: float = 0.01,
        eta: float = 0.1,
        g_min: float = 0.01,
        seed: int = 0,
        local: bool = True,
    ) -> None:
        self.num_experiments = check_int("num_experiments", num_experiments, 1)
        self.num_cells = check_int("num_cells", num_cells, 1)
        self.nvec = tuple(check_int(f"nvec[{j}]", v, 2) for j, v in enumerate(nvec))
        if not self.nvec:
            raise ValueError("nvec must name at least one actuator")
        self.num_joint = 1
        for values in self.nvec:
            self.num_joint *= values
        self.alpha = check_float("alpha", alpha, 0.0, 1.0, low_open=True)
        self.gamma = check_float("gamma", gamma, 0.0, 1.0, high_open=True)
        self.epsilon = check_float("epsilon", epsilon, 0.0, 1.0)
        self.eta = check_float("eta", eta, 0.0, float("inf"))
        self.g_min = check_float("g_min", g_min, 0.0, float("inf"))
        self.local = bool(local)
        entries = sum(self.nvec)
        self.q = torch.zeros(num_experiments, num_cells, self.num_joint)
        if self.local:
            if dependency is None:
                raise ValueError("VectorFactorQ with local=True needs a dependency")
            dependency = check_dependency(dependency)
            if dependency.shape[0] != entries:
                raise ValueError(
                    f"dependency has {dependency.shape[0]} rows but nvec={list(self.nvec)} has "
                    f"{entries} actuator values (one row each)"
                )
            self.dependency = dependency
            patterns = 1 << int(dependency.sum(dim=1).max())
            self.rho = torch.zeros(num_experiments, entries, patterns)
            self.kappa = torch.zeros(num_experiments, entries, patterns, dtype=torch.int64)
            # where actuator j's values start in the rows of rho: [J]
            self._offsets = torch.tensor([sum(self.nvec[:j]) for j in range(len(self.nvec))])
        self._keys = derive_keys(check_int("seed", seed, 0), STREAM_POLICY, num_experiments)
        self._draws = 0
        self._rows = torch.arange(num_experiments)

    # -- values and action ------------------------------------------------------------------

    def task_values(self, cell: torch.Tensor) -> torch.Tensor:
        """``Q(s, .)`` ``[S, M]`` over the joint action at ``cell`` ``[S]`` (the task table)."""
        return self.q[self._rows, cell]

    def update_task(self, cell: torch.Tensor, joint: torch.Tensor, target: torch.Tensor) -> None:
        """Eq. 4's (eq. 1's) step ``Q(s, a) <- Q(s, a) + alpha (target - Q(s, a))`` at
        ``(cell, joint)`` ``[S]`` each."""
        q_sa = self.q[self._rows, cell, joint]
        self.q[self._rows, cell, joint] = q_update(q_sa, target, self.alpha)

    def values(
        self, cell: torch.Tensor, sensors: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None, torch.Tensor]:
        """``(Q(s) [S, M], rho(o) [S, sum(nvec)], G [S, J], C(s) [S, M])`` at ``cell [S]``
        under ``sensors [S, K]`` (``rho`` and ``G`` None, ``C = Q`` with ``local=False``)."""
        q = self.task_values(cell)  # [S, M]
        if not self.local:
            return q, None, None, q
        rho = project_local(self.rho, sensors, self.dependency)  # [S, sum(nvec)]
        g = vector_normalisers(q, rho, self.nvec, self.eta, self.g_min)  # [S, J]
        return q, rho, g, vector_combined_values(q, rho, g, self.nvec)

    def act(self, cell: torch.Tensor, sensors: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Epsilon-greedy on ``C(s)`` over the joint action, ties broken at random:
        ``(action [S, J] int64 value indices, exploratory [S] bool)``."""
        with torch.no_grad():
            _, _, _, combined = self.values(cell, sensors)
        counter = 3 * self._draws
        self._draws += 1
        bits = [random_bits(self._keys, counter + i) for i in range(3)]
        joint, exploratory = epsilon_greedy_from_bits(combined, self.epsilon, *bits)
        return joint_action_vector(joint, self.nvec), exploratory

    # -- learning ---------------------------------------------------------------------------

    def update(
        self,
        cell: torch.Tensor,
        sensors: torch.Tensor,
        action: torch.Tensor,
        reward: torch.Tensor,
        local_reward: torch.Tensor | None,
        next_cell: torch.Tensor,
        next_sensors: torch.Tensor,
        terminated: torch.Tensor,
    ) -> None:
        """One transition per experiment: eq. 4 (eq. 1 with ``local=False``) on the task table
        at ``(cell, joint action)``, then eq. 5 on each actuator's table at the value it took
        with its own local reward ``local_reward [S, J]``.

        Args:
            cell, sensors: ``[S]``, ``[S, K]`` before the step.
            action: ``[S, J]`` the value each actuator took.
            reward: ``[S]`` the task reward (the conventional one with ``local=False``).
            local_reward: ``[S, J]`` one local reward per actuator (ignored with
                ``local=False``).
            next_cell, next_sensors, terminated: after the step (no bootstrap where
                ``terminated``).
        """
        joint = joint_action_index(action, self.nvec)  # [S]
        with torch.no_grad():
            _, _, _, c_next = self.values(next_cell, next_sensors)
        if self.local:
            target = factorq_target(reward, c_next, terminated, self.gamma)
        else:
            target = q_learning_target(reward, c_next, terminated, self.gamma)
        self.update_task(cell, joint, target)
        if not self.local or local_reward is None:
            return
        if local_reward.shape[-1] != len(self.nvec):
            raise ValueError(
                f"the local reward vector has length {local_reward.shape[-1]} but the agent has "
                f"{len(self.nvec)} actuators (nvec={list(self.nvec)}): one local reward each"
            )
        entry = self._offsets + action  # [S, J], the row of each actuator's value
        pattern = local_patterns(sensors, self.dependency).gather(1, entry)  # [S, J]
        rows = self._rows.unsqueeze(1).expand_as(entry)
        rho, kappa = running_mean_update(
            self.rho[rows, entry, pattern], self.kappa[rows, entry, pattern], local_reward
        )
        self.rho[rows, entry, pattern] = rho
        self.kappa[rows, entry, pattern] = kappa

    # -- saving -----------------------------------------------------------------------------

    def state_dict(self) -> dict[str, object]:
        """The tables and the action vector's shape they were learned for."""
        state: dict[str, object] = {"nvec": list(self.nvec), "q": self.q.clone()}
        if self.local:
            state.update(rho=self.rho.clone(), kappa=self.kappa.clone())
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Load tables saved by ``state_dict``; tables of another action vector (another length
        or other values) are refused in one error naming both sides, before anything loads."""
        saved = [int(v) for v in state["nvec"]]
        if saved != list(self.nvec):
            raise ValueError(
                f"the tables were saved for an action vector of length {len(saved)} "
                f"(nvec={saved}) but this agent's has length {len(self.nvec)} "
                f"(nvec={list(self.nvec)}): nothing was loaded"
            )
        tables = {"q": self.q}
        if self.local:
            tables.update(rho=self.rho, kappa=self.kappa)
        for name, table in tables.items():
            value = state[name]
            if not isinstance(value, torch.Tensor) or value.shape != table.shape:
                raise ValueError(
                    f"the saved {name!r} has shape {getattr(value, 'shape', None)} but this "
                    f"agent's is {tuple(table.shape)}: nothing was loaded"
                )
        for name, table in tables.items():
            table.copy_(state[name])


class NeuralVectorFactorQ(VectorFactorQ):
    """Neural Factor-Q on an action vector: the task values ``Q(s, .)`` over the joint action
    come from one network per experiment (``factorq_torch.neural.BatchedMLP``, the one-hot cell
    in, ``M`` joint values out, the output layer starting at 0 as the tables do), trained by one
    SGD step of learning rate ``learning_rate`` on ``0.5 (Q(s, a) - target)**2`` per transition
    with eq. 4's target; the local tables, eqs. 2-3 per actuator and eq. 5 per actuator are
    ``VectorFactorQ``'s.

    Args:
        num_experiments, num_cells, nvec, dependency: as ``VectorFactorQ``.
        hidden: the hidden widths of the task network.
        learning_rate: the SGD step (the task learning rate of the tables' ``alpha``).
        seed: the policy's streams and the networks' initial weights.
        **kwargs: ``gamma``, ``epsilon``, ``eta``, ``g_min`` as ``VectorFactorQ``.

    >>> from factorq_envs.vector_grid import drive_dependency
    >>> agent = NeuralVectorFactorQ(2, num_cells=9, nvec=(3, 3), dependency=drive_dependency())
    >>> agent.task_values(torch.tensor([0, 4])).shape  # every value starts at 0
    torch.Size([2, 9])
    """

    def __init__(
        self,
        num_experiments: int,
        num_cells: int,
        nvec: Sequence[int],
        dependency: torch.Tensor,
        *,
        hidden: Sequence[int] = (64,),
        learning_rate: float = 0.1,
        seed: int = 0,
        **kwargs: Any,
    ) -> None:
        super().__init__(num_experiments, 1, nvec, dependency, seed=seed, **kwargs)
        self.num_cells = check_int("num_cells", num_cells, 1)
        self.q = torch.zeros(0)  # no table: the network holds the task values
        keys = derive_keys(seed, STREAM_TASK_NETWORK, num_experiments)
        self.network = BatchedMLP(
            (num_experiments,), num_cells, self.num_joint, hidden=hidden, keys=keys,
            zero_output=True,
        )  # fmt: skip
        rate = check_float("learning_rate", learning_rate, 0.0, float("inf"), low_open=True)
        self.optimizer = torch.optim.SGD(self.network.parameters(), lr=rate)

    def task_values(self, cell: torch.Tensor) -> torch.Tensor:
        """``Q(s, .)`` ``[S, M]`` from each experiment's network at its ``cell``."""
        inputs = torch.nn.functional.one_hot(cell, self.num_cells).to(torch.float32)  # [S, N]
        return self.network(inputs)

    def update_task(self, cell: torch.Tensor, joint: torch.Tensor, target: torch.Tensor) -> None:
        """One SGD step on ``0.5 (Q(s, a) - target)**2`` summed over the experiments (each
        network sees only its own transition)."""
        q_sa = self.task_values(cell).gather(1, joint.unsqueeze(1)).squeeze(1)  # [S]
        loss = 0.5 * (q_sa - target.detach()).pow(2).sum()
        self.optimizer.zero_grad()
        loss.backward()
        self.optimizer.step()

    def state_dict(self) -> dict[str, object]:
        """Not offered: save ``network.state_dict()`` and the local tables instead."""
        raise NotImplementedError("NeuralVectorFactorQ: save network.state_dict() and rho, kappa")
