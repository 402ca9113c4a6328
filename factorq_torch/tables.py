"""Value tables as TensorDict modules: the task Q-table and Factor-Q's local reward tables.

Every table holds a leading dimension ``S``: one independent table per experiment of a batch, so
``S`` experiments (seeds, worlds) learn side by side in one module and nothing is shared across
the batch. A tensordict given to a table must have ``batch_size == [S]``.

- ``TaskQTable`` writes ``action_value`` ``[S, A]``: Factor-Q's task values ``Q(s, .)`` over cells
  (x headings), or Q-learning's values over (cell (x heading), pattern of all sensors) states
  (SPEC section 3).
- ``LocalRewardTable`` writes ``local_value`` ``[S, A]``: the projected local reward
  ``rho(o)_a = rho_a[o_D(a)]`` of the current sensor reading (``functional.project_local``, each
  actuator's table indexed by the pattern of its parent sensors ``D(a)`` given by ``dependency``;
  the paper: ``rho = (rho_0[o_0], ..., rho_3[o_3])``), and owns eq. 5's running-mean update of
  ``rho`` and its visit counts ``kappa``.

**Size caps.** A table of one experiment holds at most ``MAX_TABLE_ENTRIES`` (2**24) values: a
Q-learning state space of cells x headings x ``2**K`` sensor patterns grows fast (ring + 4
distractors: 100 x 4096 states x 4 actions = 1.6 M), and past the cap a batch of 100 experiments
would need tens of GB. An actuator may have at most ``MAX_PARENTS`` (16) parent sensors.

A neural value provider that writes the same key can replace either table: the policies, the
losses and the collector only read ``action_value`` / ``local_value``.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from factorq_torch.base import keys
from factorq_torch.base.validation import (  # MAX_TABLE_ENTRIES: re-exported
    MAX_TABLE_ENTRIES,  # noqa: F401
    check_int,
    check_table_size,
)
from factorq_torch.functional import (
    check_dependency,
    local_patterns,
    project_local,
    qlearning_state,
    running_mean_update,
)

#: The paper's body: 4 actuators and 4 sensors (the defaults; other bodies pass theirs).
NUM_ACTIONS = 4
#: Proximity patterns per cell of the paper's body: 4 binary sensors.
NUM_PATTERNS = 1 << NUM_ACTIONS
#: Parent sensors one actuator's local table may be indexed by (2**16 entries).
MAX_PARENTS = 16


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

    - Factor-Q (``with_sensors=False``): the state is the cell (x the heading when
      ``num_headings > 1``), ``table`` is ``[S, N H, A]``.
    - Q-learning (``with_sensors=True``): the state is ``(cell H + heading) 2**K + pattern`` of
      all ``K`` sensors (``functional.qlearning_state``), ``table`` is ``[S, 2**K N H, A]``.

    ``table`` is an ``nn.Parameter`` (zeros), so a loss can update it by a gradient step.
    ``reset_task(mask)`` zeroes it (SPEC section 4: at the start of every run). A table past
    ``MAX_TABLE_ENTRIES`` values per experiment is refused.

    Args:
        num_experiments: ``S``, the experiments of the batch.
        num_cells: ``N``, cells of the grid (``size**2``).
        with_sensors: add the pattern of all sensors to the state (Q-learning);
            ``with_proximity`` is its older name.
        num_sensors: ``K`` (4 in the paper's body).
        num_headings: ``H``, 1 without a heading, 4 with one (read from ``heading``).
        num_actions: ``A`` (4 in the paper's body).
        sensors_key: where the sensors are read (``keys.SENSORS``).
        device: where the table lives.
        sparse_grad: give ``table`` a sparse gradient (one row ``[A]`` per experiment, the
            state it read) instead of a dense ``[S, states, A]`` one: the same update through
            ``objectives.tabular_optimizer`` (plain SGD takes sparse gradients), bit for bit, at
            a cost independent of the table's size (Q-learning at S = 16384: a dense gradient
            of 100 M values per step). Optimizers without sparse support (Adam) need False.

    Keys: reads ``cell`` ``[S]`` int64 (``heading`` ``[S]`` int64, ``sensors`` ``[S, K]`` bool),
    writes ``action_value`` ``[S, A]`` float32.

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
        with_sensors: bool = False,
        with_proximity: bool = False,
        num_sensors: int = NUM_ACTIONS,
        num_headings: int = 1,
        num_actions: int = NUM_ACTIONS,
        sensors_key: str = keys.SENSORS,
        device: torch.device | str | None = None,
        sparse_grad: bool = False,
    ) -> None:
        super().__init__()
        self.sparse_grad = bool(sparse_grad)
        self.num_experiments = check_int("num_experiments", num_experiments, 1)
        self.num_cells = check_int("num_cells", num_cells, 1)
        self.num_actions = check_int("num_actions", num_actions, 1)
        self.num_sensors = check_int("num_sensors", num_sensors, 0, 62)
        self.num_headings = check_int("num_headings", num_headings, 1)
        self.with_sensors = bool(with_sensors or with_proximity)
        self.with_proximity = self.with_sensors  # the older name
        self.sensors_key = sensors_key
        positions = num_cells * num_headings
        self.num_states = positions << num_sensors if self.with_sensors else positions
        what = (
            f"a Q-table of {num_cells} cells x {num_headings} headings"
            + (f" x 2**{num_sensors} sensor patterns" if self.with_sensors else "")
            + f" x {num_actions} actions"
        )
        check_table_size(type(self).__name__, what, self.num_states * num_actions)
        self.in_keys = [keys.CELL]
        if num_headings > 1:
            self.in_keys.append(keys.HEADING)
        if self.with_sensors:
            self.in_keys.append(sensors_key)
        self.out_keys = [keys.ACTION_VALUE]
        self.table = torch.nn.Parameter(
            torch.zeros(num_experiments, self.num_states, num_actions, device=device)
        )

    def state_index(self, tensordict: TensorDictBase) -> torch.Tensor:
        """The row of each experiment's table, ``[S]`` int64 (validated)."""
        owner = type(self).__name__
        batch = (self.num_experiments,)
        check_batch(tensordict, self.num_experiments, owner)
        integers = (torch.int64, torch.int32)
        state = _check_entry(tensordict, keys.CELL, batch, integers, owner).to(torch.int64)
        if self.num_headings > 1:
            heading = _check_entry(tensordict, keys.HEADING, batch, integers, owner)
            state = state * self.num_headings + heading.to(torch.int64)
        if not self.with_sensors:
            return state
        readings = _check_entry(
            tensordict, self.sensors_key, (*batch, self.num_sensors), (torch.bool,), owner
        )
        return qlearning_state(state, readings)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        state = self.state_index(tensordict)  # [S]
        if self.sparse_grad and torch.is_grad_enabled() and self.table.requires_grad:
            values = _RowsWithSparseGrad.apply(self.table, state)
        else:
            index = state.view(-1, 1, 1).expand(-1, 1, self.num_actions)  # [S, 1, A]
            values = self.table.gather(1, index).squeeze(1)
        tensordict.set(keys.ACTION_VALUE, values)  # [S, A]
        return tensordict

    @torch.no_grad()
    def reset_task(self, mask: torch.Tensor | None = None) -> None:
        """Zero the table of every experiment (or only where ``mask`` ``[S]`` is True)."""
        mask = check_mask(mask, self.num_experiments, "TaskQTable.reset_task")
        if mask is None:
            self.table.zero_()
        else:
            self.table.masked_fill_(mask.view(-1, 1, 1), 0.0)


class _RowsWithSparseGrad(torch.autograd.Function):
    """``table[s, state[s]]`` ``[S, A]`` (the values of a gather) whose backward is a sparse COO
    gradient of ``table``'s shape with the rows read: the entries a dense gradient would hold,
    the same floats, without materialising the zeros."""

    @staticmethod
    def forward(ctx, table: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(state)
        ctx.table_shape = table.shape
        index = state.view(-1, 1, 1).expand(-1, 1, table.shape[2])
        return table.gather(1, index).squeeze(1)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        (state,) = ctx.saved_tensors
        rows = torch.arange(state.shape[0], device=state.device)
        # One entry per experiment, rows ascending: coalesced by construction.
        gradient = torch.sparse_coo_tensor(
            torch.stack((rows, state)),
            grad.contiguous(),
            ctx.table_shape,
            is_coalesced=True,
            check_invariants=False,
        )
        return gradient, None


class LocalRewardTable(TensorDictModuleBase):
    """Factor-Q's local reward tables ``rho_a[o_D(a)]`` and visit counts ``kappa_a[o_D(a)]``.

    One table per actuator ``a``, indexed by the pattern ``o_D(a)`` of its parent sensors
    ``D(a)`` (row ``a`` of ``dependency``; ``functional.local_patterns``): ``2**|D(a)|`` entries
    (the paper: one sensor, 2 entries). Stored as ``rho`` ``[S, A, P]`` float32 and ``kappa``
    ``[S, A, P]`` int64 with ``P = 2**max_a |D(a)|`` (an actuator with fewer parents uses the
    first ``2**|D(a)|``), both buffers (eq. 5 is a running mean, not a gradient step). They are
    reset only by an explicit ``reset()`` (SPEC section 4: once per experiment).

    Args:
        num_experiments: ``S``.
        dependency: bool ``[A, K]``, the parents of each actuator (the oracle's
            ``env.dependency``); default the paper's pairing ``eye(num_actions)``.
        num_actions: ``A`` when ``dependency`` is not given.
        sensors_key: where the sensors are read (``keys.SENSORS``).
        device: where the tables live.

    Keys: reads ``sensors`` ``[S, K]`` bool, writes ``local_value`` ``[S, A]`` float32 with
    ``local_value[s, a] = rho[s, a, o_D(a)]`` (``functional.project_local``).

    Example:
        >>> from tensordict import TensorDict
        >>> local = LocalRewardTable(1)
        >>> sensors = torch.tensor([[True, False, False, False]])  # a wall to the north
        >>> local.update_running_mean(sensors, torch.tensor([0]), torch.tensor([[-1.0, 0, 0, 0]]))
        >>> local(TensorDict(sensors=sensors, batch_size=[1]))["local_value"]
        tensor([[-1.,  0.,  0.,  0.]])
    """

    def __init__(
        self,
        num_experiments: int,
        *,
        dependency: torch.Tensor | None = None,
        num_actions: int = NUM_ACTIONS,
        sensors_key: str = keys.SENSORS,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__()
        self.num_experiments = check_int("num_experiments", num_experiments, 1)
        if dependency is None:
            dependency = torch.eye(check_int("num_actions", num_actions, 1), dtype=torch.bool)
        dependency = check_dependency(dependency)
        parents = int(dependency.sum(dim=1).max())
        if parents > MAX_PARENTS:
            raise ValueError(
                f"dependency gives an actuator {parents} parent sensors: at most {MAX_PARENTS} "
                f"(a table of 2**{MAX_PARENTS} entries) are allowed"
            )
        self.num_actions, self.num_sensors = dependency.shape
        self.sensors_key = sensors_key
        self.in_keys = [sensors_key]
        self.out_keys = [keys.LOCAL_VALUE]
        self.register_buffer("dependency", dependency.to(device=device).clone())
        shape = (num_experiments, self.num_actions, 1 << parents)
        self.register_buffer("rho", torch.zeros(shape, device=device))
        self.register_buffer("kappa", torch.zeros(shape, dtype=torch.int64, device=device))

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        owner = type(self).__name__
        check_batch(tensordict, self.num_experiments, owner)
        readings = _check_entry(
            tensordict,
            self.sensors_key,
            (self.num_experiments, self.num_sensors),
            (torch.bool,),
            owner,
        )
        local_value = project_local(self.rho, readings, self.dependency)  # [S, A]
        tensordict.set(keys.LOCAL_VALUE, local_value)
        return tensordict

    @torch.no_grad()
    def update_running_mean(
        self,
        readings: torch.Tensor,
        action: torch.Tensor,
        local_reward: torch.Tensor,
        mask: torch.Tensor | None = None,
    ) -> None:
        """Eq. 5 for the fired actuator ``a``: ``kappa_a[o] += 1`` and ``rho_a[o]`` moves to the
        running mean of the local rewards ``r_L[a]`` seen there, ``o = o_D(a)``
        (``functional.running_mean_update``).

        Args:
            readings: ``[S, K]`` bool, the sensors *before* acting (under which ``a`` fired).
            action: ``[S]`` int64, the chosen actuator.
            local_reward: ``[S, A]`` float, the local reward vector of the step.
            mask: ``[S]`` bool, update only these experiments (``None``: all).
        """
        batch = self.num_experiments
        mask = check_mask(mask, batch, "LocalRewardTable.update_running_mean")
        shapes = {"readings": (readings, (batch, self.num_sensors)), "action": (action, (batch,))}
        shapes["local_reward"] = (local_reward, (batch, self.num_actions))
        for name, (value, shape) in shapes.items():
            if tuple(value.shape) != shape:
                raise ValueError(
                    f"LocalRewardTable.update_running_mean: {name} has shape "
                    f"{list(value.shape)}, expected {list(shape)}"
                )
        rows = torch.arange(batch, device=action.device)
        patterns = local_patterns(readings, self.dependency)  # [S, A]
        reading = patterns.gather(1, action.unsqueeze(1)).squeeze(1)  # [S], o_D(a)
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
