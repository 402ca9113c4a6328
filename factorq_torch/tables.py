"""Value tables as TensorDict modules: the task Q-table and Factor-Q's local reward tables.

Every table holds a leading dimension ``S``: one independent table per experiment of a batch, so
``S`` experiments (seeds, worlds) learn side by side in one module and nothing is shared across
the batch. A tensordict given to a table must have ``batch_size == [S]``.

- ``TaskQTable`` writes ``action_value`` ``[S, A]``: Factor-Q's task values ``Q(s, .)`` over cells,
  or Q-learning's values over (cell, proximity pattern) states (SPEC section 3).
- ``LocalRewardTable`` writes ``local_value`` ``[S, A]``: the projected local reward
  ``rho = (rho_0[o_0], ..., rho_3[o_3])`` of the current proximity reading, and owns eq. 5's
  running-mean update of ``rho`` and its visit counts ``kappa``.

A neural value provider that writes the same key can replace either table: the policies, the
losses and the collector only read ``action_value`` / ``local_value``.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from factorq_torch.base.validation import check_int
from factorq_torch.functional import qlearning_state, running_mean_update

NUM_ACTIONS = 4
#: Proximity patterns per cell: 4 binary sensors.
NUM_PATTERNS = 1 << NUM_ACTIONS


def check_batch(tensordict: TensorDictBase, num_experiments: int, owner: str) -> None:
    """Raise a ValueError unless ``tensordict.batch_size == [num_experiments]``."""
    if tuple(tensordict.batch_size) != (num_experiments,):
        raise ValueError(
            f"{owner} holds S={num_experiments} experiments but the tensordict has batch_size "
            f"{list(tensordict.batch_size)}: it must be [{num_experiments}] (one row per "
            f"experiment; build the env with batch_size=({num_experiments},))"
        )


def check_mask(mask: torch.Tensor | None, num_experiments: int, owner: str) -> torch.Tensor | None:
    """``mask`` as a bool ``[S]`` tensor (or ``None``); anything else raises a ValueError."""
    if mask is None:
        return None
    if not isinstance(mask, torch.Tensor) or mask.dtype != torch.bool:
        raise TypeError(f"{owner}: mask must be a bool tensor of shape [{num_experiments}]")
    mask = mask.reshape(-1) if mask.dim() == 2 and mask.shape[-1] == 1 else mask
    if tuple(mask.shape) != (num_experiments,):
        raise ValueError(
            f"{owner}: mask has shape {list(mask.shape)}, expected [{num_experiments}] "
            f"(one flag per experiment)"
        )
    return mask


def _check_entry(
    tensordict: TensorDictBase, key, shape: tuple, dtypes: tuple, owner: str
) -> torch.Tensor:
    """Read ``key`` and check its shape and dtype, naming both in the error."""
    value = tensordict.get(key, None)
    if value is None:
        raise KeyError(f"{owner} needs {key!r} in the tensordict; it has {list(tensordict.keys())}")
    if tuple(value.shape) != shape or value.dtype not in dtypes:
        raise ValueError(
            f"{owner}: {key!r} has shape {list(value.shape)} and dtype {value.dtype}, expected "
            f"shape {list(shape)} and dtype {' or '.join(str(d) for d in dtypes)}"
        )
    return value


class TaskQTable(TensorDictModuleBase):
    """Task values ``Q(s, .)`` of ``S`` experiments, one row of ``A`` actions per state.

    - Factor-Q (``with_proximity=False``): the state is the cell, ``table`` is ``[S, N, A]``.
    - Q-learning (``with_proximity=True``): the state is ``cell * 16 + proximity pattern``
      (``functional.qlearning_state``), ``table`` is ``[S, 16 N, A]``.

    ``table`` is an ``nn.Parameter`` (zeros), so a loss can update it by a gradient step.
    ``reset_task(mask)`` zeroes it (SPEC section 4: at the start of every run).

    Args:
        num_experiments: ``S``, the experiments of the batch.
        num_cells: ``N``, cells of the grid (``size**2``).
        with_proximity: add the proximity pattern to the state (Q-learning).
        num_actions: ``A`` (4 in the paper's world).
        device: where the table lives.

    Keys: reads ``cell`` ``[S]`` int64 (and ``proximity`` ``[S, 4]`` bool), writes
    ``action_value`` ``[S, A]`` float32.

    Example:
        >>> from tensordict import TensorDict
        >>> table = TaskQTable(2, num_cells=4)
        >>> with torch.no_grad():
        ...     table.table[1, 3] = torch.tensor([1.0, 2.0, 3.0, 4.0])
        >>> td = TensorDict(cell=torch.tensor([0, 3]), batch_size=[2])
        >>> table(td)["action_value"].tolist()
        [[0.0, 0.0, 0.0, 0.0], [1.0, 2.0, 3.0, 4.0]]
    """

    def __init__(
        self,
        num_experiments: int,
        num_cells: int,
        *,
        with_proximity: bool = False,
        num_actions: int = NUM_ACTIONS,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__()
        self.num_experiments = check_int("num_experiments", num_experiments, 1)
        self.num_cells = check_int("num_cells", num_cells, 1)
        self.num_actions = check_int("num_actions", num_actions, 1)
        self.with_proximity = bool(with_proximity)
        self.num_states = num_cells * NUM_PATTERNS if with_proximity else num_cells
        self.in_keys = ["cell", "proximity"] if with_proximity else ["cell"]
        self.out_keys = ["action_value"]
        self.table = torch.nn.Parameter(
            torch.zeros(num_experiments, self.num_states, num_actions, device=device)
        )

    def state_index(self, tensordict: TensorDictBase) -> torch.Tensor:
        """The row of each experiment's table, ``[S]`` int64 (validated)."""
        owner = type(self).__name__
        check_batch(tensordict, self.num_experiments, owner)
        cell = _check_entry(
            tensordict, "cell", (self.num_experiments,), (torch.int64, torch.int32), owner
        )
        if not self.with_proximity:
            return cell.to(torch.int64)
        proximity = _check_entry(
            tensordict, "proximity", (self.num_experiments, 4), (torch.bool,), owner
        )
        return qlearning_state(cell.to(torch.int64), proximity)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        state = self.state_index(tensordict)  # [S]
        index = state.view(-1, 1, 1).expand(-1, 1, self.num_actions)  # [S, 1, A]
        tensordict.set("action_value", self.table.gather(1, index).squeeze(1))  # [S, A]
        return tensordict

    @torch.no_grad()
    def reset_task(self, mask: torch.Tensor | None = None) -> None:
        """Zero the table of every experiment (or only where ``mask`` ``[S]`` is True)."""
        mask = check_mask(mask, self.num_experiments, "TaskQTable.reset_task")
        if mask is None:
            self.table.zero_()
        else:
            self.table.masked_fill_(mask.view(-1, 1, 1), 0.0)


class LocalRewardTable(TensorDictModuleBase):
    """Factor-Q's local reward tables ``rho_i[o_i]`` and visit counts ``kappa_i[o_i]`` (SPEC 3).

    One table per sensor/actuator pair ``i`` (proximity sensor ``i`` and the move in direction
    ``i``), indexed by the sensor's binary reading: ``rho`` ``[S, A, 2]`` float32 and ``kappa``
    ``[S, A, 2]`` int64, both buffers (eq. 5 is a running mean, not a gradient step). They are
    reset only by an explicit ``reset()`` (SPEC section 4: once per experiment).

    Keys: reads ``proximity`` ``[S, A]`` bool, writes ``local_value`` ``[S, A]`` float32 with
    ``local_value[s, i] = rho[s, i, proximity[s, i]]``.

    Example:
        >>> from tensordict import TensorDict
        >>> local = LocalRewardTable(1)
        >>> proximity = torch.tensor([[True, False, False, False]])  # a wall to the north
        >>> local.update_running_mean(proximity, torch.tensor([0]), torch.tensor([[-1.0, 0, 0, 0]]))
        >>> local(TensorDict(proximity=proximity, batch_size=[1]))["local_value"]
        tensor([[-1.,  0.,  0.,  0.]])
    """

    def __init__(
        self,
        num_experiments: int,
        *,
        num_actions: int = NUM_ACTIONS,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__()
        self.num_experiments = check_int("num_experiments", num_experiments, 1)
        self.num_actions = check_int("num_actions", num_actions, 1)
        self.in_keys = ["proximity"]
        self.out_keys = ["local_value"]
        shape = (num_experiments, num_actions, 2)
        self.register_buffer("rho", torch.zeros(shape, device=device))
        self.register_buffer("kappa", torch.zeros(shape, dtype=torch.int64, device=device))

    def _reading(self, proximity: torch.Tensor) -> torch.Tensor:
        """The sensor readings ``[S, A]`` bool as indices ``[S, A, 1]`` int64 into the tables."""
        return proximity.to(torch.int64).unsqueeze(-1)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        owner = type(self).__name__
        check_batch(tensordict, self.num_experiments, owner)
        proximity = _check_entry(
            tensordict, "proximity", (self.num_experiments, self.num_actions), (torch.bool,), owner
        )
        local_value = self.rho.gather(2, self._reading(proximity)).squeeze(2)  # [S, A]
        tensordict.set("local_value", local_value)
        return tensordict

    @torch.no_grad()
    def update_running_mean(
        self,
        proximity: torch.Tensor,
        action: torch.Tensor,
        local_reward: torch.Tensor,
        mask: torch.Tensor | None = None,
    ) -> None:
        """Eq. 5 for the fired actuator ``a``: ``kappa_a[o_a] += 1`` and ``rho_a[o_a]`` moves to
        the running mean of the local rewards ``r_L[a]`` seen there
        (``functional.running_mean_update``).

        Args:
            proximity: ``[S, A]`` bool, the readings *before* acting (under which ``a`` fired).
            action: ``[S]`` int64, the fired actuator.
            local_reward: ``[S, A]`` float, the local reward vector of the step.
            mask: ``[S]`` bool, update only these experiments (``None``: all).
        """
        batch = self.num_experiments
        mask = check_mask(mask, batch, "LocalRewardTable.update_running_mean")
        shapes = {"proximity": (proximity, (batch, self.num_actions)), "action": (action, (batch,))}
        shapes["local_reward"] = (local_reward, (batch, self.num_actions))
        for name, (value, shape) in shapes.items():
            if tuple(value.shape) != shape:
                raise ValueError(
                    f"LocalRewardTable.update_running_mean: {name} has shape "
                    f"{list(value.shape)}, expected {list(shape)}"
                )
        rows = torch.arange(batch, device=action.device)
        reading = proximity.gather(1, action.unsqueeze(1)).squeeze(1).to(torch.int64)  # [S], o_a
        reward = local_reward.gather(1, action.unsqueeze(1)).squeeze(1)  # [S], r_L[a]
        rho, kappa = self.rho[rows, action, reading], self.kappa[rows, action, reading]  # [S]
        new_rho, new_kappa = running_mean_update(rho, kappa, reward)
        if mask is not None:
            new_rho, new_kappa = (
                torch.where(mask, new_rho, rho),
                torch.where(mask, new_kappa, kappa),
            )
        self.rho[rows, action, reading] = new_rho
        self.kappa[rows, action, reading] = new_kappa

    @torch.no_grad()
    def reset(self, mask: torch.Tensor | None = None) -> None:
        """Zero ``rho`` and ``kappa`` of every experiment (or only where ``mask`` ``[S]``)."""
        mask = check_mask(mask, self.num_experiments, "LocalRewardTable.reset")
        if mask is None:
            self.rho.zero_()
            self.kappa.zero_()
        else:
            self.rho.masked_fill_(mask.view(-1, 1, 1), 0.0)
            self.kappa.masked_fill_(mask.view(-1, 1, 1), 0)
