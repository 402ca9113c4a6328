"""Value tables as TensorDict modules: the task Q-table and Factor-Q's local reward tables.

Every table holds a leading dimension ``S``: one independent table per experiment of a batch, so
``S`` experiments (seeds, worlds) learn side by side in one module and nothing is shared across
the batch. A tensordict given to a table holds transitions of any batch shape ``[*B]``, each with
its experiment index (``keys.EXPERIMENT``; absent: ``arange(S)`` over a ``[S]`` batch, 0 when
``S = 1``, see ``experiment_index``).

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

import math
from typing import Any

import numpy as np
import torch
from tensordict import NestedKey, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch.autograd.graph import increment_version

from factorq_torch.base import keys
from factorq_torch.base.config import PAPER_NUM_ACTIONS
from factorq_torch.base.indices import row_starts, scalar
from factorq_torch.base.validation import (
    MAX_PARENTS,
    check_device,
    check_finite,
    check_indices,
    check_int,
    check_same_device,
    check_table_size,
)
from factorq_torch.functional import (
    ROW_KERNEL_VALUES,
    check_dependency,
    local_pattern_of,
    local_patterns,
    project_local,
    qlearning_state,
    running_mean_add,
    running_mean_add_one,
)

#: The paper's body: 4 actuators and 4 sensors (the defaults; other bodies pass theirs).
NUM_ACTIONS = PAPER_NUM_ACTIONS  # the default body (base.config)
#: Parent sensors one actuator's local table may be indexed by (2**16 entries).


def check_batch(tensordict: TensorDictBase, num_experiments: int, owner: str) -> None:
    """Raise a ValueError unless ``tensordict.batch_size == [num_experiments]``."""
    if tuple(tensordict.batch_size) != (num_experiments,):
        raise ValueError(
            f"{owner} holds S={num_experiments} experiments but the tensordict has batch_size "
            f"{list(tensordict.batch_size)}: it must be [{num_experiments}] (one row per "
            f"experiment; build the env with batch_size=({num_experiments},))"
        )


def experiment_index(tensordict: TensorDictBase, num_experiments: int, owner: str) -> torch.Tensor:
    """The experiment of every transition, int64 ``[*B]`` for a tensordict of batch ``[*B]``.

    Read from ``keys.EXPERIMENT`` when present (values in ``[0, S)``); absent, it is
    ``arange(S)`` over a ``[S]`` batch (broadcast over the trailing dimensions of ``[S, *T]``,
    a rollout of a ``[S]`` env) and 0 everywhere when ``S = 1``. Anything else is a ValueError
    naming the batch and the remedy, raised here, where the transitions enter.

    Args:
        tensordict: the transitions, batch ``[*B]``.
        num_experiments: ``S``, the experiments the table holds.
        owner: the caller's name, for the error message.
    """
    batch = tuple(tensordict.batch_size)
    index = tensordict.get(keys.EXPERIMENT, None)
    if index is not None:
        return check_experiment(index, batch, num_experiments, owner)
    if batch == (num_experiments,):
        return torch.arange(num_experiments, device=tensordict.device)
    if num_experiments == 1:
        return torch.zeros(batch, dtype=torch.int64, device=tensordict.device)
    if batch and batch[0] == num_experiments:
        rows = torch.arange(num_experiments, device=tensordict.device)
        return rows.view(-1, *([1] * (len(batch) - 1))).expand(batch)
    raise ValueError(
        f"{owner} holds S={num_experiments} experiments but the tensordict has batch_size "
        f"{list(batch)} and no {keys.EXPERIMENT!r} entry: give each transition its experiment "
        f"index under {keys.EXPERIMENT!r} (factorq_envs.transforms.ExperimentIndex writes it), "
        f"or use "
        f"batch_size [{num_experiments}] / [{num_experiments}, T] (build the env with "
        f"batch_size=({num_experiments},))"
    )


def check_experiment(
    index: torch.Tensor, batch: tuple, num_experiments: int, owner: str
) -> torch.Tensor:
    """``index`` as int64 ``batch`` with values in ``[0, S)``, else a ValueError naming it."""
    if tuple(index.shape) == (*batch, 1):
        index = index.squeeze(-1)
    if tuple(index.shape) != tuple(batch) or index.is_floating_point() or index.is_complex():
        raise ValueError(
            f"{owner}: {keys.EXPERIMENT!r} has shape {list(index.shape)} and dtype "
            f"{index.dtype}, expected integer experiment indices of shape {list(batch)}"
        )
    index = index.to(torch.int64)
    if index.numel() and bool(((index < 0) | (index >= num_experiments)).any()):
        raise ValueError(
            f"{owner}: {keys.EXPERIMENT!r} holds indices outside [0, {num_experiments}): the "
            f"module holds S={num_experiments} experiments"
        )
    return index


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


def table_rows(
    table: torch.Tensor, experiment: torch.Tensor | None, state: torch.Tensor
) -> torch.Tensor:
    """``table[experiment, state]`` ``[*B, A]`` of a ``[S, states, A]`` table (no gradient) for
    int64 indices ``[*B]``, by one ``index_select`` of whole rows on the flattened table: the
    same values as the advanced indexing, 2-3x faster on CPU where the rows are not in cache
    (measured in the README loop at S = 4096; a ``gather`` along the states, fewer ops, was 4x
    slower there). ``experiment`` None: the online step, ``state`` ``[S]`` and experiment ``i``
    reading its own table (the row offsets cached, ``row_starts``). A state outside
    ``[0, states)`` raises IndexError like the indexing does (``experiment`` must be in range:
    ``experiment_index`` checks it)."""
    count, states, width = table.shape
    starts = row_starts(count, states, state.device) if experiment is None else experiment * states
    inside = (state >= 0) & (state < states)
    flat = torch.where(inside, starts + state, -1).reshape(-1)
    return table.detach().reshape(-1, width).index_select(0, flat).reshape(*state.shape, width)


def is_online(tensordict: TensorDictBase, num_experiments: int) -> bool:
    """Whether ``tensordict`` is the online step of ``S`` experiments: batch ``[S]``, entry ``i``
    experiment ``i`` (no ``keys.EXPERIMENT`` entry)."""
    return tuple(tensordict.batch_size) == (num_experiments,) and (
        tensordict.get(keys.EXPERIMENT, None) is None
    )


def check_firing(
    owner: str,
    readings: torch.Tensor,
    action: torch.Tensor,
    local_reward: torch.Tensor,
    num_actions: int,
    device: torch.device,
) -> None:
    """What a local learner's update reads (``LocalRewardTable``, ``StructureLearner``): bool
    ``readings``, integer actions in ``[0, num_actions)``, finite local rewards, all on the
    learner's ``device``; errors name the argument, the first experiment and its value (shapes
    are the caller's to check)."""
    if readings.dtype != torch.bool:
        raise TypeError(f"{owner}: readings must be bool sensor readings, got {readings.dtype}")
    if action.dtype not in (torch.int64, torch.int32):
        raise TypeError(f"{owner}: action must be integer action indices, got {action.dtype}")
    for name, value in (("readings", readings), ("action", action), ("local_reward", local_reward)):
        check_same_device(owner, name, value, device)
    check_indices(owner, "action", action, num_actions)
    check_finite(owner, "local_reward", local_reward, cause="the env or a transform gave it")


def _check_entry(
    tensordict: TensorDictBase, key: NestedKey, shape: tuple, dtypes: tuple, owner: str
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


def _check_loaded(owner: str, state_dict: dict, prefix: str, floats: tuple, counts: tuple) -> None:
    """Refuse a state dict whose tables hold NaN or infinite values (``floats``) or negative
    counts (``counts``), before anything is loaded: a table loaded so would be refused only at
    its first use, far from the file or the code that made it."""
    for name in floats:
        value = state_dict.get(prefix + name)
        if isinstance(value, torch.Tensor):
            check_finite(f"{owner}.load_state_dict", repr(prefix + name), value, cause=_LOADED)
    for name in counts:
        value = state_dict.get(prefix + name)
        if isinstance(value, torch.Tensor) and value.numel() and value.device.type != "meta":
            if bool((value < 0).any()):
                raise ValueError(
                    f"{owner}.load_state_dict: {prefix + name!r} holds negative counts "
                    f"(first: {int(value[value < 0][0])}): {_LOADED}"
                )


#: What a bad loaded table means.
_LOADED = "the state was saved from a diverged run or edited; nothing was loaded"

#: The signs a ``LocalRewardTable`` may be declared to hold: ``"either"`` (the default: any local
#: reward), ``"negative"`` (costs only, ``<= 0``: the paper's collisions) or ``"positive"`` (pays
#: only, ``>= 0``).
SIGNS = ("either", "negative", "positive")


def check_sign(owner: str, sign: str, values: torch.Tensor, what: str) -> None:
    """Refuse ``values`` holding a local reward of the sign a table declared ``sign`` does not
    take: one ValueError naming the declared sign and what was seen (both signs, when both
    are there). ``"either"`` takes anything."""
    if sign == "either" or values.numel() == 0 or values.device.type == "meta":
        return
    positive, negative = values[values > 0], values[values < 0]
    wrong = positive if sign == "negative" else negative
    if wrong.numel() == 0:
        return
    seen = []
    if positive.numel():
        seen.append(f"a positive local reward ({float(positive.max()):+g})")
    if negative.numel():
        seen.append(f"a negative local reward ({float(negative.min()):+g})")
    takes = "<= 0, costs only" if sign == "negative" else ">= 0, pays only"
    raise ValueError(
        f"{owner}: the table was declared sign={sign!r} (local rewards {takes}), but "
        f"{what} holds {' and '.join(seen)}: declare sign='either' for a body whose local "
        f"rewards take both signs"
    )


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
        with_sensors: add the pattern of all sensors to the state (Q-learning).
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
        device = check_device("device", device)
        self.num_cells = check_int("num_cells", num_cells, 1)
        self.num_actions = check_int("num_actions", num_actions, 1)
        self.num_sensors = check_int("num_sensors", num_sensors, 0, 62)
        self.num_headings = check_int("num_headings", num_headings, 1)
        self.with_sensors = bool(with_sensors)
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

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs) -> None:  # type: ignore[no-untyped-def]
        _check_loaded(type(self).__name__, state_dict, prefix, ("table",), ())
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def state_index(self, tensordict: TensorDictBase) -> torch.Tensor:
        """The row of each transition's table, ``[*B]`` int64 (validated)."""
        owner = type(self).__name__
        batch = tuple(tensordict.batch_size)
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
        learning = torch.is_grad_enabled() and self.table.requires_grad
        experiment = None  # the online step without gradient: no index tensor to build
        if learning or not is_online(tensordict, self.num_experiments):
            experiment = experiment_index(tensordict, self.num_experiments, type(self).__name__)
        state = self.state_index(tensordict)  # [*B]
        try:
            if learning and self.sparse_grad:
                values = _RowsWithSparseGrad.apply(self.table, experiment, state)  # [*B, A]
            elif learning:  # a dense gradient through the indexing (a negative state is sent
                # past the end: the indexing would wrap it around)
                values = self.table[experiment, torch.where(state >= 0, state, self.num_states)]
            else:
                values = table_rows(self.table, experiment, state)  # [*B, A]
        except IndexError:
            raise ValueError(self._misfit(state)) from None
        tensordict.set(keys.ACTION_VALUE, values)
        return tensordict

    def _misfit(self, state: torch.Tensor) -> str:
        """The message for a state outside the table: the first such transition's cell (floor
        division keeps a negative cell negative), past the end (an env larger than
        ``num_cells``) or negative (a bad index)."""
        outside = (state < 0) | (state >= self.num_states)
        first = int(state.reshape(-1)[outside.reshape(-1)][0])
        cell = first // ((1 << self.num_sensors) if self.with_sensors else 1) // self.num_headings
        where = int(outside.reshape(-1).nonzero()[0, 0])
        if cell < 0:
            return (
                f"TaskQTable: {keys.CELL!r} holds cell {cell} (transition {where} first): a "
                f"table of num_cells={self.num_cells} holds cells 0 to {self.num_cells - 1}"
            )
        return (
            f"TaskQTable was built for num_cells={self.num_cells} but received cell "
            f"{cell} (transition {where} first): the env has more cells (size**2) than the "
            f"table; build TaskQTable(..., num_cells=size**2) of the env"
        )

    @torch.no_grad()
    def reset_task(self, mask: torch.Tensor | None = None) -> None:
        """Zero the table of every experiment (or only where ``mask`` ``[S]`` is True)."""
        mask = check_mask(mask, self.num_experiments, "TaskQTable.reset_task")
        if mask is None:
            self.table.zero_()
        else:
            self.table.masked_fill_(mask.view(-1, 1, 1), 0.0)


class _RowsWithSparseGrad(torch.autograd.Function):
    """``table[experiment, state]`` ``[*B, A]`` whose backward is a sparse COO gradient of
    ``table``'s shape holding the rows read: the entries a dense gradient would hold (duplicates
    summed), the same floats, without materialising the zeros."""

    @staticmethod
    def forward(
        ctx: Any, table: torch.Tensor, experiment: torch.Tensor, state: torch.Tensor
    ) -> torch.Tensor:
        ctx.save_for_backward(experiment, state)
        ctx.table_shape = table.shape
        return table_rows(table, experiment, state)

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[torch.Tensor, None, None]:
        experiment, state = ctx.saved_tensors
        indices = torch.stack((experiment.reshape(-1), state.reshape(-1)))  # [2, M]
        gradient = torch.sparse_coo_tensor(
            indices,
            grad.reshape(-1, grad.shape[-1]).contiguous(),
            ctx.table_shape,
            check_invariants=False,  # indices were checked by the forward's indexing
        ).coalesce()  # the online step reads one row per experiment: nothing to sum
        return gradient, None, None


#: Why eq. 5 can overflow: ``r - rho`` of two finite float32 numbers of opposite signs
#: exceeds float32's range when they are beyond half of it.
_OVERFLOW = (
    "a local reward beyond half float32's range (|r| > 1.7e38) overflows r - rho; "
    "the table is unchanged"
)


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
        sign: the local rewards it takes (``SIGNS``): ``"either"`` (default, any sign: a body
            that pays and costs), ``"negative"`` (``<= 0``) or ``"positive"`` (``>= 0``); a
            reward of the other sign, fed to ``update_running_mean`` or held by a loaded
            ``rho``, is refused naming both (``check_sign``).

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
        sign: str = "either",
    ) -> None:
        super().__init__()
        self.num_experiments = check_int("num_experiments", num_experiments, 1)
        device = check_device("device", device)
        if not isinstance(sign, str) or sign not in SIGNS:
            raise ValueError(f"sign={sign!r} is unknown: choose one of {', '.join(SIGNS)}")
        self.sign = sign
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
        readings = _check_entry(
            tensordict,
            self.sensors_key,
            (*tensordict.batch_size, self.num_sensors),
            (torch.bool,),
            owner,
        )
        if is_online(tensordict, self.num_experiments):
            local_value = project_local(self.rho, readings, self.dependency)  # [S, A]
        else:  # rho_a[o_D(a)] of each transition's experiment (project_local, gathered)
            experiment = experiment_index(tensordict, self.num_experiments, owner)  # [*B]
            pattern = local_patterns(readings, self.dependency)  # [*B, A]
            actuators = torch.arange(self.num_actions, device=pattern.device)
            local_value = self.rho[experiment.unsqueeze(-1), actuators, pattern]  # [*B, A]
        tensordict.set(keys.LOCAL_VALUE, local_value)
        return tensordict

    def local_values(self, readings: torch.Tensor) -> torch.Tensor:
        """``rho(o)`` ``[S, A]`` of the online step's readings ``[S, K]`` (bool, checked by the
        caller): what ``forward`` writes for a ``[S]`` batch, without the tensordict
        (``project_local``; ``StructureLearner.local_values`` is its counterpart). A few
        experiments on the CPU are read by ``_local_values_read``, the same entries."""
        rho = self.rho
        if (
            readings.is_cpu
            and rho.is_cpu
            and rho.dtype in (torch.float32, torch.float64)
            and not rho.requires_grad
            and readings.shape == (self.num_experiments, self.num_sensors)
            and self.num_experiments * self.num_actions <= ROW_KERNEL_VALUES
        ):
            return self._local_values_read(rho, readings)
        return project_local(rho, readings, self.dependency)

    def _local_values_read(self, rho: torch.Tensor, readings: torch.Tensor) -> torch.Tensor:
        """``project_local(rho, readings, dependency)`` of a few experiments on the CPU, read
        through numpy: ``rho[s, a, o_D(a)]`` at flat indices computed once per reading
        (``local_pattern_of``, the mirror of ``local_patterns``; a copy of the same entries,
        so the same numbers: tests/test_tables.py compares the two) and per dependency (its
        tensor and version), where project_local's dozen tensor ops cost more than the read
        (the layer reads it at every step of one agent)."""
        dependency = self.dependency
        state = (dependency, dependency._version, rho.shape)
        memo: tuple[tuple, dict[bytes, np.ndarray]] | None = self.__dict__.get("_read_index")
        if memo is None or memo[0][0] is not dependency or memo[0][1:] != state[1:]:
            memo = self.__dict__["_read_index"] = (state, {})
        key = readings.numpy().tobytes()
        index = memo[1].get(key)
        if index is None:
            actions, width = self.num_actions, rho.shape[-1]
            index = np.array(
                [
                    (row * actions + a) * width + local_pattern_of(reading, dependency, a)
                    for row, reading in enumerate(readings.tolist())
                    for a in range(actions)
                ],
                dtype=np.intp,
            )
            if len(memo[1]) >= 1 << 16:  # (at most 2**K readings per experiment)
                memo[1].clear()
            memo[1][key] = index
        return torch.from_numpy(rho.numpy().reshape(-1)[index].reshape(readings.shape[0], -1))

    @torch.no_grad()
    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs) -> None:  # type: ignore[no-untyped-def]
        _check_loaded(type(self).__name__, state_dict, prefix, ("rho",), ("kappa",))
        rho = state_dict.get(prefix + "rho")
        if isinstance(rho, torch.Tensor):
            owner = f"{type(self).__name__}.load_state_dict"
            check_sign(owner, self.sign, rho, f"the loaded {prefix + 'rho'!r}")
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def update_running_mean(
        self,
        readings: torch.Tensor,
        action: torch.Tensor,
        local_reward: torch.Tensor,
        mask: torch.Tensor | None = None,
        experiment: torch.Tensor | None = None,
    ) -> None:
        """Eq. 5 for the fired actuator ``a``: ``kappa_a[o] += 1`` and ``rho_a[o]`` moves to the
        running mean of the local rewards ``r_L[a]`` seen there, ``o = o_D(a)``
        (``functional.running_mean_update``).

        Any batch ``[*B]`` of transitions is taken. Where ``n`` transitions of a batch hit the
        same entry ``(experiment, a, o)``, they are added at once:
        ``kappa += n``, ``rho += sum_i (r_i - rho) / kappa``, which is the running mean of every
        reward seen (equal, up to rounding, to adding them one by one). With one transition
        per entry (``n = 1``, e.g. one step of ``S`` experiments) this is exactly eq. 5.

        Args:
            readings: ``[*B, K]`` bool, the sensors *before* acting (under which ``a`` fired).
            action: ``[*B]`` int64, the chosen actuator.
            local_reward: ``[*B, A]`` float, the local reward vector of the step.
            mask: ``[*B]`` bool, update only these transitions (``None``: all).
            experiment: ``[*B]`` int64, each transition's experiment (``None``: ``arange(S)``
                over a ``[S]`` batch, 0 when ``S = 1``; see ``experiment_index``).
        """
        owner = "LocalRewardTable.update_running_mean"
        if self.sign != "either" and isinstance(local_reward, torch.Tensor):
            check_sign(owner, self.sign, local_reward, "local_reward")
        batch = tuple(readings.shape[:-1])
        if readings.dim() < 1 or readings.shape[-1] != self.num_sensors:
            raise ValueError(
                f"{owner}: readings has shape {list(readings.shape)}, expected "
                f"[..., {self.num_sensors}]"
            )
        shapes = {"action": (action, batch)}
        shapes["local_reward"] = (local_reward, (*batch, self.num_actions))
        for name, (value, shape) in shapes.items():
            if tuple(value.shape) != shape:
                raise ValueError(
                    f"{owner}: {name} has shape {list(value.shape)}, expected {list(shape)}"
                )
        if (
            mask is None
            and experiment is None
            and batch == (self.num_experiments,)
            and self._update_online(readings, action, local_reward)
        ):
            return
        check_firing(owner, readings, action, local_reward, self.num_actions, self.rho.device)
        distinct = False  # whether the transitions' experiments are known to differ
        patterns_per_table = self.rho.shape[-1]
        if experiment is None:
            if batch == (self.num_experiments,):  # experiment i's tables start at row_starts[i]
                table_starts = row_starts(
                    self.num_experiments, self.num_actions * patterns_per_table, action.device
                )
                distinct = True
            elif self.num_experiments == 1:
                experiment = torch.zeros(batch, dtype=torch.int64, device=action.device)
            else:
                raise ValueError(
                    f"{owner}: action has shape {list(batch)} but the table holds "
                    f"S={self.num_experiments} experiments: pass experiment=[*B] indices"
                )
        else:
            experiment = check_experiment(experiment, batch, self.num_experiments, owner)
        if mask is not None:
            if not isinstance(mask, torch.Tensor) or mask.dtype != torch.bool:
                raise TypeError(f"{owner}: mask must be a bool tensor of shape {list(batch)}")
            mask = mask.squeeze(-1) if tuple(mask.shape) == (*batch, 1) else mask
            if tuple(mask.shape) != batch:
                raise ValueError(
                    f"{owner}: mask has shape {list(mask.shape)}, expected {list(batch)}"
                )
        action = action.reshape(-1)  # [M]
        patterns = local_patterns(readings.reshape(-1, self.num_sensors), self.dependency)
        reading = patterns.gather(1, action.unsqueeze(1)).squeeze(1)  # [M], o_D(a)
        rewards = local_reward.reshape(-1, self.num_actions)
        reward = rewards.gather(1, action.unsqueeze(1)).squeeze(1)  # [M], r_L[a]
        if not distinct:
            assert experiment is not None  # for mypy: every branch but the distinct one sets it
            table_starts = experiment.reshape(-1) * (self.num_actions * patterns_per_table)
        width = scalar(patterns_per_table, action)  # (0-d constants: base.indices.scalar)
        entry = table_starts + (action * width + reading)  # [M], into rho / kappa
        rho_flat, kappa_flat = self.rho.view(-1), self.kappa.view(-1)
        rho, kappa = rho_flat.index_select(0, entry), kappa_flat.index_select(0, entry)  # [M]
        step = reward - rho  # r_L[a] - rho_a[o]
        if mask is None:
            visits = torch.ones_like(kappa)
        else:
            mask = mask.reshape(-1)
            step, visits = torch.where(mask, step, scalar(0.0, step)), mask.to(torch.int64)
        # Sums per entry (n transitions on one entry add n visits and their n steps). One
        # transition per experiment (the online step) hits distinct entries: the sums are the
        # transitions' own (``0.0 + step``, as index_add_ into zeros computes it: -0.0 -> 0.0).
        if distinct:
            count, total = visits, step + scalar(0.0, step)
        else:
            count = torch.zeros_like(kappa_flat).index_add_(0, entry, visits)[entry]  # [M]
            total = torch.zeros_like(rho_flat).index_add_(0, entry, step)[entry]  # [M]
        new_rho, new_kappa = running_mean_add(rho, kappa, total, count)  # eq. 5, n at once
        check_finite(owner, "the running mean (eq. 5)", new_rho, cause=_OVERFLOW)
        rho_flat.index_copy_(0, entry, new_rho)  # every transition of an entry writes the same
        kappa_flat.index_copy_(0, entry, new_kappa)  # value

    def _update_online(
        self, readings: torch.Tensor, action: torch.Tensor, local_reward: torch.Tensor
    ) -> bool:
        """``update_running_mean`` of one transition per experiment (the online step, no mask)
        on a small CPU table, read and written through numpy: the same entries and values
        (``local_pattern_of``, ``running_mean_add_one``), without the dozens of tensor ops of
        the batched update. False (nothing written) where it does not apply: another dtype or
        device, a large batch, an action out of range or a local reward that is not finite (the
        tensor path then runs, and names what is wrong)."""
        rho, kappa, actions = self.rho, self.kappa, self.num_actions
        if (
            readings.dtype != torch.bool
            or action.dtype not in (torch.int64, torch.int32)
            or local_reward.dtype != torch.float32
            or rho.dtype != torch.float32
            or kappa.dtype != torch.int64
            or local_reward.numel() > ROW_KERNEL_VALUES
            or rho.device.type != "cpu"
            or any(value.device.type != "cpu" for value in (readings, action, local_reward))
            or local_reward.requires_grad
            or rho.requires_grad
            or not (rho.is_contiguous() and kappa.is_contiguous())
        ):
            return False
        fired = action.tolist()
        rewards = local_reward.numpy()  # [S, A]
        if not all(0 <= a < actions for a in fired) or not all(
            map(math.isfinite, rewards.reshape(-1).tolist())
        ):
            return False
        sensors = readings.tolist()
        rho_flat, kappa_flat = rho.view(-1).numpy(), kappa.view(-1).numpy()
        table, width, zero = actions * rho.shape[-1], rho.shape[-1], np.float32(0.0)
        updates = []
        with np.errstate(over="ignore", invalid="ignore"):  # an overflow is refused below
            for row, (a, reading) in enumerate(zip(fired, sensors, strict=True)):
                entry = row * table + a * width + local_pattern_of(reading, self.dependency, a)
                old = rho_flat[entry]  # eq. 5, as the batched update computes it for n = 1
                new, visits = running_mean_add_one(
                    old, int(kappa_flat[entry]), rewards[row, a] - old + zero
                )
                updates.append((entry, new, visits))
        if not all(math.isfinite(new) for _, new, _ in updates):
            return False  # nothing written: the tensor path refuses it, naming the experiment
        for entry, new, visits in updates:
            rho_flat[entry], kappa_flat[entry] = new, visits
        increment_version(rho)  # written as by index_copy_: in place, seen by autograd
        increment_version(kappa)
        return True

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
