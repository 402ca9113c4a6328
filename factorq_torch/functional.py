"""The paper's equations as pure, batched tensor functions (no TensorDict, inputs never mutated).

Shapes: ``A`` is the number of actions (4 in the paper's world) and ``...`` any leading batch
dimensions (experiments). Values are float tensors; actions are int64.

Floating-point order is part of the contract: sums over actions are written as explicit
left-to-right additions (``_left_sum``) and no step is fused, so the compiled fast path
(``trainers/compiled/_kernel.c``, which performs the same operations in the same order in float32)
produces bit-identical tables. Keep it that way when you edit.
"""

from __future__ import annotations

import itertools
import math
from array import array
from collections.abc import Sequence

import numpy as np
import torch
from torch.utils.weak import WeakIdKeyDictionary

from factorq_torch.base.indices import constant, scalar
from factorq_torch.base.rng import probability_threshold, randint_from_bits
from factorq_torch.base.validation import check_int


def sensor_pattern(readings: torch.Tensor) -> torch.Tensor:
    """Binary sensor readings as one integer: ``sum_i bit_i << i``.

    Shapes: ``[..., K]`` (bool or integer 0/1) -> ``[...]`` int64 in ``[0, 2**K)``.

    Args:
        readings: ``[..., K]`` sensor bits (bool, or integers 0/1).

    >>> sensor_pattern(torch.tensor([[True, False, False, True], [False] * 4]))
    tensor([9, 0])
    """
    count, device = readings.shape[-1], readings.device
    weights = constant(
        ("bit weights", count, device), lambda: 1 << torch.arange(count, device=device)
    )
    return (readings.to(torch.int64) * weights).sum(dim=-1)


def qlearning_state(cell: torch.Tensor, readings: torch.Tensor) -> torch.Tensor:
    """Q-learning's state index (SPEC section 3): ``cell * 2**K + sensor_pattern(readings)``.

    Shapes: ``cell [...]`` int64, ``readings [..., K]`` -> ``[...]`` int64 in ``[0, 2**K N)``.

    Args:
        cell: ``[...]`` int64 cell indices.
        readings: ``[..., K]`` sensor bits.

    >>> qlearning_state(torch.tensor([0, 3]), torch.tensor([[1, 1, 0, 0], [0, 0, 1, 0]]))
    tensor([ 3, 52])
    """
    return cell * (1 << readings.shape[-1]) + sensor_pattern(readings)


def check_dependency(dependency: object, num_sensors: int | None = None) -> torch.Tensor:
    """``dependency`` as a bool ``[A, K]`` tensor, else a TypeError / ValueError naming it.

    ``num_sensors``: the ``K`` it must have (``None``: any). Row ``a`` marks the parent sensors
    ``D(a)`` of actuator ``a``: those that decide its local reward.

    Args:
        dependency: the value to check (a bool tensor ``[A, K]``).
        num_sensors: the ``K`` it must have (``None``: any).
    """
    if not isinstance(dependency, torch.Tensor) or dependency.dtype != torch.bool:
        raise TypeError(
            f"dependency must be a bool tensor [actuators, sensors], got "
            f"{getattr(dependency, 'dtype', type(dependency).__name__)}"
        )
    if dependency.dim() != 2 or dependency.shape[0] < 1 or dependency.shape[1] < 1:
        raise ValueError(
            f"dependency has shape {list(dependency.shape)}: must be [actuators, sensors], both "
            f">= 1"
        )
    if num_sensors is not None and dependency.shape[1] != num_sensors:
        raise ValueError(
            f"dependency has shape {list(dependency.shape)}: it names {dependency.shape[1]} "
            f"sensors but there are {num_sensors}"
        )
    return dependency


#: Integers up to ``2**53`` are exact in float64: ``local_patterns`` sums bits by a float64
#: product up to this many sensors.
_EXACT_FLOAT64_BITS = 53


def parent_weights(dependency: torch.Tensor) -> torch.Tensor:
    """``[A, K]`` int64: ``2**r`` where sensor ``k`` is the ``r``-th parent of actuator ``a`` (in
    sensor order), 0 where it is no parent; ``local_patterns`` sums them over the set bits.

    Args:
        dependency: bool ``[A, K]``, actuator ``a``'s parent sensors in row ``a``.
    """
    ranks = dependency.to(torch.int64).cumsum(dim=-1) - 1  # [A, K]
    return torch.where(dependency, 1 << ranks.clamp(min=0), 0)


def local_patterns(readings: torch.Tensor, dependency: torch.Tensor) -> torch.Tensor:
    """The reading of each actuator's parent sensors as one integer ``o_D(a)``:
    ``sum_r readings[k_r] << r`` over the parents ``k_0 < k_1 < ...`` of ``a``.

    Shapes: ``readings [..., K]`` (bool), ``dependency [A, K]`` -> ``[..., A]`` int64 in
    ``[0, 2**|D(a)|)``. The paper's body (``dependency = eye(4)``): ``o_D(a) = readings[a]``.

    Args:
        readings: ``[..., K]`` sensor bits (bool).
        dependency: bool ``[A, K]``, the parents of each actuator.

    >>> dependency = torch.tensor([[True, False, True], [False, False, False]])
    >>> local_patterns(torch.tensor([True, False, True]), dependency)
    tensor([3, 0])
    """
    if readings.shape[-1] > _EXACT_FLOAT64_BITS:  # patterns past float64's exact integers
        weights = parent_weights(dependency)  # [A, K]
        return (readings.to(torch.int64).unsqueeze(-2) * weights).sum(dim=-1)
    # As a float64 product ``readings @ weights.T``: with at most 53 sensors every term and
    # partial sum is an integer below 2**53, exact in float64 whatever the summation order, and
    # the product is one matmul instead of a broadcast int64 [..., A, K] multiply and a sum over
    # a tiny last axis (4x faster on CPU at S = 4096).
    weights, columns = _pattern_tables(dependency)
    if columns is not None:  # one parent per actuator: the pattern is that sensor's bit
        if columns is _IDENTITY:  # actuator a's parent is sensor a
            return readings.to(torch.int64)
        return readings.index_select(-1, columns).to(torch.int64)
    return (readings.to(torch.float64) @ weights).to(torch.int64)


#: ``dependency -> (its version counter, weights, columns)``: ``parent_weights(dependency)`` as
#: float64 ``[K, A]`` and, when every actuator has exactly one parent, the parents ``[A]``
#: (int64; else None), built once per dependency tensor (about twenty small ops a step
#: otherwise) and rebuilt when the tensor is modified in place (its ``_version`` moves).
_PATTERN_TABLES = WeakIdKeyDictionary()


#: ``columns`` of a dependency whose actuator ``a``'s one parent is sensor ``a`` (``A = K``).
_IDENTITY = torch.empty(0, dtype=torch.int64)


def _pattern_tables(dependency: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
    """``(weights, columns)`` of ``dependency`` for ``local_patterns``, cached per tensor and
    version; ``columns`` (None: not one parent each) is only looked for on the CPU, where
    reading the dependency once is no synchronisation."""
    if dependency.requires_grad or dependency.device.type == "meta":
        return parent_weights(dependency).to(torch.float64).transpose(0, 1), None
    cached = _PATTERN_TABLES.get(dependency)
    if cached is None or cached[0] != dependency._version:
        weights = parent_weights(dependency).to(torch.float64).transpose(0, 1)
        columns = None
        if dependency.device.type == "cpu" and dependency.dim() == 2:
            if bool((dependency.sum(dim=-1) == 1).all()):
                columns = dependency.to(torch.int64).argmax(dim=-1)  # [A]
                if torch.equal(columns, torch.arange(dependency.shape[-1])):
                    columns = _IDENTITY
        cached = (dependency._version, weights, columns)
        _PATTERN_TABLES[dependency] = cached
    return cached[1], cached[2]


def project_local(
    rho: torch.Tensor, readings: torch.Tensor, dependency: torch.Tensor
) -> torch.Tensor:
    """The projection ``rho(o)`` of section 5.2 (SPEC section 3): ``rho(o)_a = rho_a[o_D(a)]``,
    each actuator's local reward table read at the pattern of its parent sensors.

    Shapes: ``rho [..., A, P]`` (``P >= 2**max_a |D(a)|``), ``readings [..., K]`` bool,
    ``dependency [A, K]`` bool -> ``[..., A]`` (leading dimensions broadcast). The paper's body:
    ``rho(o) = (rho_0[o_0], ..., rho_3[o_3])``.

    Args:
        rho: ``[..., A, P]`` the local reward tables.
        readings: ``[..., K]`` sensor bits (bool).
        dependency: bool ``[A, K]``, the parents of each actuator.
    """
    pattern = local_patterns(readings, dependency)  # [..., A]
    if rho.shape[:-2] != pattern.shape[:-1]:  # (torch.broadcast_shapes costs ~40 us in Python)
        leading = torch.broadcast_shapes(rho.shape[:-2], pattern.shape[:-1])
        rho = rho.expand(*leading, *rho.shape[-2:])
        pattern = pattern.expand(*leading, pattern.shape[-1])
    return rho.gather(-1, pattern.unsqueeze(-1)).squeeze(-1)


def _left_sum(x: torch.Tensor) -> torch.Tensor:
    """``x[..., 0] + x[..., 1] + ...`` in that order (``[..., A] -> [...]``)."""
    first, *rest = x.unbind(-1)
    total = first
    for column in rest:
        total = total + column
    return total


def _mean_of_others(x: torch.Tensor, excluded: torch.Tensor) -> torch.Tensor:
    """Mean of ``x[..., a]`` over ``a != excluded`` (``[..., A], [...] -> [...]``)."""
    where = excluded.unsqueeze(-1)
    others = x.scatter(-1, where, scalar(0.0, x).expand(where.shape))  # +0.0 at excluded
    return _left_sum(others) / scalar(x.shape[-1] - 1, x)


def normaliser(
    q: torch.Tensor, rho: torch.Tensor, eta: float = 0.1, g_min: float = 0.01
) -> torch.Tensor:
    """Eq. 3, the normalisation factor ``G`` that scales local to task reward.

    ``G = (Q(s, a_hat) - Q_bar) / (P_bar - rho[a_check]) * (1 + eta)`` with
    ``a_hat = argmax_a Q(s, a)``, ``Q_bar`` the mean of the other ``A - 1`` task values,
    ``a_check = argmin_a rho[a]`` and ``P_bar`` the mean of the other ``A - 1`` local values.
    When the denominator is 0 (``rho`` cannot tell actions apart) or ``G < g_min`` (e.g. an
    unvisited state, all ``Q`` equal), ``G = g_min``, so the local term still decides.

    Args:
        q: task values ``Q(s, .)``, ``[..., A]``.
        rho: projected local rewards ``rho(o)``, ``[..., A]``.
        eta: how much the local spread exceeds the task spread after scaling (paper: 0.1).
        g_min: the floor of ``G`` (SPEC: 0.01).

    Returns:
        ``G``, ``[...]``.
    """
    if q.shape == rho.shape and q.dtype == rho.dtype and q.device == rho.device:
        # Both halves in one pass over [Q, -rho] (the fewest small ops: a step of one agent is a
        # [1, A] row, where each op's dispatch, not its arithmetic, is the cost). max gives the
        # value and the first index holding it (argmax's, and -rho's is rho's first minimum);
        # negation is exact and rounding symmetric, so the mean of the others of -rho is -P_bar
        # and ``-rho[a_check] - (-P_bar)`` is ``P_bar - rho[a_check]`` bit for bit (up to the
        # sign of a zero, which the ``> 0`` test below does not see).
        both = torch.stack((q, rho.neg()))  # [2, ..., A]
        top, index = both.max(dim=-1)  # Q(s, a_hat), -rho[a_check]
        x, y = (top - _mean_of_others(both, index)).unbind(0)  # Q - Q_bar, P_bar - rho_min
    else:
        q_max, a_hat = q.max(dim=-1)  # [...]; which maximum is taken does not change Q_bar
        rho_min, a_check = rho.min(dim=-1)
        x = q_max - _mean_of_others(q, a_hat)
        y = _mean_of_others(rho, a_check) - rho_min
    # (the constants as cached 0-d tensors: the same values as Python numbers, fewer allocations)
    spread = y > scalar(0.0, y)
    g = x / torch.where(spread, y, scalar(1.0, y)) * scalar(1 + eta, x)  # (no 0 / 0: a gradient
    # stays finite). `g >= g_min` is False for NaN (inf / inf) too; an overflowed ratio is capped
    # at the largest finite value, so G stays finite for any finite input (never reached by real
    # tables).
    floor = scalar(g_min, g)
    g = torch.where(spread & (g >= floor), g, floor)
    return g.clamp_max(scalar(torch.finfo(g.dtype).max, g))


def combined_values(q: torch.Tensor, rho: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """Eq. 2, ``C(s) = Q(s) + G rho``: ``[..., A], [..., A], [...] -> [..., A]``.

    Values beyond the float range are capped at its ends (an identity for any real table), so the
    argmax is still defined when huge tables overflow.

    Args:
        q: ``[..., A]`` task values ``Q(s)``.
        rho: ``[..., A]`` local values ``rho(o)``.
        g: ``[...]`` eq. 3's normalisation factor ``G``.
    """
    largest = torch.finfo(q.dtype).max
    return (q + g.unsqueeze(-1) * rho).clamp(scalar(-largest, q), scalar(largest, q))


def arbitrated_normaliser(
    q: torch.Tensor, rho: torch.Tensor, g: torch.Tensor, gamma: float, local_span: float = 1.0
) -> torch.Tensor:
    """Arbitration (the paper's section 9): eq. 3's ``G``, or ``1`` where the task takes priority.

    ``[..., A], [..., A], [...] -> [...]``. The task takes priority in a state where one action
    ``a*`` beats every other under the conventional reward (task + local, summed: the reward
    structure's own exchange rate) *whatever local rewards follow*::

        (Q + rho)[a*] - max_{b != a*} (Q + rho)[b] > gamma * local_span / (1 - gamma)

    and eq. 2 would not choose it (``C(s)[a*]`` not above every other ``C(s)[b]``). There
    ``G = 1``: eq. 2 becomes ``C = Q + rho``, whose argmax is ``a*``, and eq. 4 bootstraps on
    its value. Everywhere else eq. 3's ``G`` stands, unchanged to the bit.

    Derivation. Under the conventional reward ``r_task + sum(r_L)`` the value of taking ``a`` and
    then following the policy is ``Q(s, a) + rho_a + gamma L(s')``: ``Q`` the task values (what
    Factor-Q's task table estimates), ``rho_a`` the expected local reward of this step (eq. 5),
    ``L(s')`` the discounted local return afterwards. With every step's local reward in an
    interval of width ``local_span`` (the paper: one collision, ``[-1, 0]``, width 1), any two
    actions' ``gamma L`` differ by at most ``gamma * local_span / (1 - gamma)`` (9 at the paper's
    ``gamma = 0.9``). So when ``a*``'s ``Q + rho`` beats every other's by more than that, its
    lower bound beats every other action's upper bound: ``a*`` is the better action for the task
    and the body together however the local future turns out, and taking it is a policy
    improvement step on the conventional reward. The rule reads only ``gamma`` and the local
    reward's span: nothing is tuned per world.

    In the paper's worlds it never fires: task values lie in ``[-1 / (1 - gamma), 0]`` there
    (rewards -1 per step, 0 on the goal step: ``[-10, 0]``, up to eq. 3's floor ``g_min``), and
    eq. 2 refuses ``a*`` only when ``a*`` carries a worse local value than some ``b``: against a
    certain collision (``rho = -1`` against 0) the margin needs a task advantage above
    ``9 + 1 = 10``. A task whose rewards are large against the local penalty (a goal worth 100
    collisions, ``factorq_envs.strike``) gets the margin, and the body strikes when the task
    needs it. docs/decisions.md, "Arbitration: when the task takes priority".

    Args:
        q: task values ``Q(s, .)``, ``[..., A]``.
        rho: local values ``rho(o)``, ``[..., A]`` (as eq. 2 sees them).
        g: eq. 3's ``G``, ``[...]``.
        gamma: the discount, in ``[0, 1)``.
        local_span: the width of one step's local reward interval (>= 0; 1 for a -1 collision).

    >>> q = torch.tensor([[70.0, 55.0, 55.0, 40.0], [-1.0, -2.0, -2.0, -3.0]])
    >>> rho = torch.tensor([[-1.0, 0.0, 0.0, 0.0], [-1.0, 0.0, 0.0, 0.0]])
    >>> arbitrated_normaliser(q, rho, torch.tensor([16.5, 0.6]), gamma=0.9)  # 14 > 9; 0 < 9
    tensor([1.0000, 0.6000])
    """
    if q.shape[-1] < 2:  # nothing to choose between
        return g
    margin = gamma * local_span / (1.0 - gamma)
    best = (q + rho).topk(2, dim=-1)  # [..., 2]
    dominant = best.indices[..., :1]  # [..., 1], a*
    priority = best.values[..., 0] - best.values[..., 1] > scalar(margin, q)
    combined = combined_values(q, rho, g)  # eq. 2 as it stands
    chosen = combined.gather(-1, dominant).squeeze(-1)
    others = combined.scatter(-1, dominant, scalar(-math.inf, combined).expand(dominant.shape))
    refused = chosen <= others.amax(dim=-1)  # eq. 2 does not choose a* outright
    return torch.where(priority & refused, scalar(1.0, g), g)


def risk_mask(rho: torch.Tensor, threshold: float = 0.5) -> torch.Tensor:
    """The actuators a local-risk layer does not call risky, ``[..., A]`` bool: ``rho_a >=
    -threshold`` (local reward units), every actuator of a state where none is left (never an
    empty choice).

    Args:
        rho: ``[..., A]`` local values ``rho(o)``.
        threshold: how negative ``rho_a`` may be (0.5: a collision more likely than not).
    """
    allowed = rho >= scalar(-threshold, rho)
    return allowed | ~allowed.any(dim=-1, keepdim=True)


def significant_local(rho: torch.Tensor, threshold: float = 0.5) -> torch.Tensor:
    """The local values eqs. 2-3 see under the risk gate: ``rho_a`` where ``|rho_a| >
    threshold``, else 0 (``[..., A] -> [..., A]``; docs/decisions.md, "The heading-noise stall").

    Eq. 3 scales *any* local spread above the task spread, so it ranks local values
    lexicographically: the least rewarded actuator is never the greedy choice, however small its
    deficit. That is the paper's intent for deterministic local rewards (0 or -1). A sensor that
    reads wrong makes ``rho_a(o) = -P(collision | o, a)`` a small probability in every pattern,
    and the lexicographic rule then forbids ``a`` wherever a riskless actuator exists (a heading
    body turns on the spot). The gate keeps the deterministic model the data support best:
    ``rho_a`` counts where the more probable outcome is the local reward (``|rho_a|`` above half
    the collision penalty: ``threshold = 0.5``, ``risk_mask``'s rule), and is 0 where the more
    probable outcome is nothing. Tables of 0 and -1 (the paper's noise-free worlds) are
    unchanged.

    Args:
        rho: ``[..., A]`` local values ``rho(o)``.
        threshold: the largest ``|rho_a|`` that counts as 0 (local reward units, >= 0).

    >>> significant_local(torch.tensor([-0.9, -0.02, 0.0, 0.7]))
    tensor([-0.9000,  0.0000,  0.0000,  0.7000])
    """
    return torch.where(rho.abs() > scalar(threshold, rho), rho, scalar(0.0, rho))


def safe_exploration_from_bits(allowed: torch.Tensor, action_bits: torch.Tensor) -> torch.Tensor:
    """The exploratory action drawn uniformly among the ``allowed`` actuators (``risk_mask``):
    the ``k``-th allowed one in index order, ``k = bits * n >> 32`` with ``n`` of them (the
    uniform draw of ``epsilon_greedy_from_bits`` when all are allowed, from the same bits).
    Shapes: ``[..., A] (bool, at least one True per row), [...] -> [...]`` (int64).

    Args:
        allowed: ``[..., A]`` bool, the actuators the local model does not call risky.
        action_bits: ``[...]`` int64 random words in ``[0, 2**32)``.
    """
    count = allowed.sum(dim=-1)
    k = randint_from_bits(action_bits, count)
    rank = allowed.cumsum(dim=-1) - 1
    return (allowed & (rank == k.unsqueeze(-1))).to(torch.int8).max(dim=-1).indices


#: ``local_risk_rows`` takes batches of at most this many values (rows x actions): there, a few
#: dozen float32 scalar operations cost less than the ~40 tensor ops of ``normaliser``,
#: ``combined_values`` and ``risk_mask`` (each a few microseconds of dispatch on a ``[1, A]``
#: row); the two take about as long at 64 values (16 rows of 4 actions), the tensor ops win past it.
ROW_KERNEL_VALUES = 32

#: The largest float32, as a Python float (exact).
_FLOAT32_MAX = float(np.finfo(np.float32).max)
#: ``local_risk_rows``' float32 constants (as Python floats) by ``(actions, eta, g_min,
#: mask_threshold)``.
_ROW_CONSTANTS: dict[tuple, tuple] = {}


def local_risk_rows(
    q: torch.Tensor,
    rho: torch.Tensor,
    eta: float = 0.1,
    g_min: float = 0.01,
    mask_threshold: float = 0.5,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
    """Eqs. 2-3 and the risk mask at once for a small batch: ``(C(s), G, allowed)``, bit for bit
    ``combined_values(q, rho, G)``, ``G = normaliser(q, rho, eta, g_min)`` and ``risk_mask(rho,
    mask_threshold)``; None where it does not apply (not a float32 CPU batch of at most
    ``ROW_KERNEL_VALUES`` values, ``q`` and ``rho`` of one shape, or a value that is not finite:
    the caller then uses those three functions, which are the definition).

    A fused op for the step of one agent: computed row by row, the same operations in the same
    order as ``normaliser``'s one pass over ``[Q, -rho]`` (per half the first maximum, the left
    sum of the others with ``+0.0`` in the maximum's place, divided by ``A - 1``), then ``G`` with
    its floor and cap, eq. 2 with its caps and the mask. Each float32 operation is computed on
    Python floats (the float32 values, exact in double) and rounded to float32 (``(float)`` in
    C, through a one-element ``array('f')``): for ``+``, ``-``, ``*`` and ``/`` of two float32
    numbers, double's correctly rounded result rounded again to float32 is the correctly
    rounded float32 result (53 >= 2 * 24 + 2 bits: the double rounding is innocuous, overflow
    to inf included), which is what torch's float32 ops give (IEEE 754, no fused multiply-add);
    the maxima, the mask and the finiteness check compare the same values.
    tests/test_functional.py compares the two bit for bit. About a twentieth of the time of the
    ~40 tensor ops on a ``[1, A]`` row (no numpy scalar, no tensor op but the outputs').

    Args:
        q: ``[..., A]`` task values ``Q(s)``.
        rho: ``[..., A]`` local values ``rho(o)``.
        eta, g_min: eq. 3's margin and floor of ``G``.
        mask_threshold: ``risk_mask``'s threshold.
    """
    if (
        q.dtype != torch.float32
        or rho.dtype != torch.float32
        or q.shape != rho.shape
        or q.dim() == 0
        or q.numel() > ROW_KERNEL_VALUES
        or not (q.is_cpu and rho.is_cpu)
        or q.numel() == 0
    ):
        return None
    actions, rows = q.shape[-1], q.dim() == 2  # ([B, A], one agent's step: no reshape)
    # the values as Python floats (float32 -> double, exact); a sum of at most 64 float32 values
    # is finite in double unless one is inf or NaN
    q_lists = (q if rows else q.reshape(-1, actions)).tolist()
    rho_lists = (rho if rows else rho.reshape(-1, actions)).tolist()
    if not math.isfinite(sum(map(sum, q_lists)) + sum(map(sum, rho_lists))):
        return None
    key = (actions, eta, g_min, mask_threshold)
    constants = _ROW_CONSTANTS.get(key)
    if constants is None:  # the arguments rounded to float32 (a few, reused)
        if len(_ROW_CONSTANTS) > 64:
            _ROW_CONSTANTS.clear()
        single = np.float32
        constants = _ROW_CONSTANTS[key] = (
            float(actions - 1),
            float(single(1 + eta)),
            float(single(g_min)),
            -float(single(mask_threshold)),
            range(1, actions),
        )
    others, factor, floor, limit, columns = constants
    largest, lowest = _FLOAT32_MAX, -_FLOAT32_MAX
    cell = array("f", (0.0,))  # rounds a double to float32 as (float) in C does

    def f32(value: float) -> float:
        cell[0] = value
        return cell[0]

    combined_rows, g_rows, allowed_rows = [], [], []
    for q_row, rho_row in zip(q_lists, rho_lists, strict=True):
        # each half's first maximum: Q's, then -rho's (rho's first minimum)
        q_best = rho_best = 0
        for a in columns:
            if q_row[a] > q_row[q_best]:
                q_best = a
            if rho_row[a] < rho_row[rho_best]:
                rho_best = a
        g = floor
        if others:  # (one action: 0 / 0 spreads, NaN, and G = g_min)
            spreads = []
            for half, best in ((q_row, q_best), ([-v for v in rho_row], rho_best)):
                total = 0.0 if best == 0 else half[0]  # Q - Q_bar, then P_bar - rho_min
                for a in columns:
                    total = f32(total + (0.0 if a == best else half[a]))
                spreads.append(f32(half[best] - f32(total / others)))
            x, y = spreads
            if y > 0.0:
                g = f32(f32(x / y) * factor)  # (inf / inf: NaN, below the floor's test)
                g = g if g >= floor else floor  # (False for NaN too)
                g = largest if g > largest else g
        g_rows.append(g)
        values = []
        for q_a, rho_a in zip(q_row, rho_row, strict=True):  # min(max(q + g rho, -M), M)
            value = f32(q_a + f32(g * rho_a))
            value = lowest if lowest > value else value  # max(value, -M), NaN kept
            values.append(largest if largest < value else value)  # min(value, M)
        combined_rows.append(values)
        allowed = [rho_a >= limit for rho_a in rho_row]  # (float32 -threshold, exact)
        allowed_rows.append(allowed if any(allowed) else [True] * actions)
    # the outputs as numpy arrays of the float32 values (exact), then wrapped
    combined = np.array(combined_rows, dtype=np.float32)
    g_array = np.array(g_rows, dtype=np.float32)
    allowed_array = np.array(allowed_rows, dtype=np.bool_)
    if not rows:  # (the batch's shape)
        combined, allowed_array = combined.reshape(q.shape), allowed_array.reshape(q.shape)
        g_array = g_array.reshape(q.shape[:-1])
    return torch.from_numpy(combined), torch.from_numpy(g_array), torch.from_numpy(allowed_array)


def q_learning_target(
    reward: torch.Tensor, q_next: torch.Tensor, terminated: torch.Tensor, gamma: float
) -> torch.Tensor:
    """Eq. 1's target ``r + gamma max_a' Q(s', a')``; ``r`` alone where ``terminated``.

    Truncated transitions still bootstrap: only ``terminated`` stops it.
    Shapes: ``[...], [..., A], [...] (bool) -> [...]``.

    Args:
        reward: ``[...]`` the rewards ``r``.
        q_next: ``[..., A]`` the next state's values ``Q(s')``.
        terminated: ``[...]`` bool, where the episode ended (no bootstrap).
        gamma: the discount.
    """
    bootstrap = reward + gamma * q_next.amax(dim=-1)
    return torch.where(terminated, reward, bootstrap)


def factorq_target(
    task_reward: torch.Tensor, c_next: torch.Tensor, terminated: torch.Tensor, gamma: float
) -> torch.Tensor:
    """Eq. 4's target ``r + gamma max_a' (Q(s', a') + G rho_a')``, with ``c_next = C(s')``.

    ``C(s')`` is eq. 2 at the next state with its own ``G`` and ``rho``; the raw task value would
    overestimate what the agent can get there (paper, 5.2.1). Same bootstrapping rule as eq. 1.
    Shapes: ``[...], [..., A], [...] (bool) -> [...]``.

    Args:
        task_reward: ``[...]`` the task rewards ``r``.
        c_next: ``[..., A]`` eq. 2's ``C(s')`` at the next state.
        terminated: ``[...]`` bool, where the episode ended (no bootstrap).
        gamma: the discount.
    """
    return q_learning_target(task_reward, c_next, terminated, gamma)


def q_update(q_sa: torch.Tensor, target: torch.Tensor, alpha: float) -> torch.Tensor:
    """Eqs. 1 and 4's update ``Q(s,a) <- (1 - alpha) Q(s,a) + alpha target``.

    Written as ``Q + alpha (target - Q)``: algebraically the same, and exactly (bit for bit) one
    SGD step of learning rate ``alpha`` on ``0.5 * (Q - target)**2``, which is how the losses
    apply it to tables and networks alike. Shapes broadcast.

    Args:
        q_sa: ``Q(s, a)``.
        target: eq. 1's or eq. 4's target.
        alpha: the learning rate.
    """
    return q_sa + alpha * (target - q_sa)


def running_mean_update(
    rho: torch.Tensor, kappa: torch.Tensor, reward: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Eq. 5 with the paper's ``alpha_L = 1 / kappa``: ``rho`` becomes the mean of all rewards seen.

    ``kappa <- kappa + 1``, ``rho <- rho + (r - rho) / kappa``. Shapes broadcast; ``kappa`` is an
    integer visit count. Returns the new ``(rho, kappa)``.

    Args:
        rho: the running means.
        kappa: their visit counts (integer).
        reward: the new rewards.
    """
    kappa = kappa + 1
    return rho + (reward - rho) / kappa, kappa


def running_mean_add(
    rho: torch.Tensor, kappa: torch.Tensor, step_sum: torch.Tensor, count: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Eq. 5 for ``n = count`` rewards at once (a minibatch hitting one entry ``n`` times):
    ``kappa <- kappa + n``, ``rho <- rho + sum_i (r_i - rho) / kappa``, with
    ``step_sum = sum_i (r_i - rho)``. The running mean of every reward seen (equal, up to
    rounding, to ``running_mean_update`` applied ``n`` times); with ``n = 1`` it *is*
    ``running_mean_update``, bit for bit. Where ``count == 0`` nothing changes. Shapes broadcast.

    Args:
        rho: the running means.
        kappa: their visit counts (integer).
        step_sum: ``sum_i (r_i - rho)`` of the new rewards of each entry.
        count: ``n``, the new rewards of each entry.

    >>> running_mean_add(torch.tensor([0.0]), torch.tensor([0]), torch.tensor([-2.0]),
    ...                  torch.tensor([4]))
    (tensor([-0.5000]), tensor([4]))
    """
    kappa = kappa + count
    stepped = rho + step_sum / kappa.clamp_min(scalar(1, kappa))  # (0-d constants: base.indices)
    return torch.where(count > scalar(0, count), stepped, rho), kappa


def running_mean_add_one(
    rho: np.float32, kappa: int, step_sum: np.float32
) -> tuple[np.float32, int]:
    """``running_mean_add`` of one reward (``count = 1``) on a float32 numpy scalar ``rho``
    and a Python int ``kappa``: bit for bit the tensor function's values (the same float32
    operations; ``kappa`` converted to float32 as torch's int64 / float32 division does). The
    tables' update of one transition, where a dozen tensor ops would cost more than the
    arithmetic (tests/test_functional.py compares the two).

    Args:
        rho: the running mean (float32).
        kappa: its visit count.
        step_sum: ``r - rho`` of the new reward (float32).
    """
    kappa = kappa + 1
    return rho + step_sum / np.float32(max(kappa, 1)), kappa


#: ``dependency -> (its version counter, parents)``: each actuator's parent sensors in order
#: (``local_pattern_of``), read once per dependency tensor and version.
_PARENT_LISTS = WeakIdKeyDictionary()


def local_pattern_of(readings: Sequence[bool], dependency: torch.Tensor, actuator: int) -> int:
    """``local_patterns(readings, dependency)[actuator]`` for one state's readings as Python
    booleans: ``sum_r readings[k_r] << r`` over the parents ``k_0 < k_1 < ...`` of ``actuator``
    (the parents read once per CPU dependency tensor and version).

    Args:
        readings: one state's ``K`` sensor bits.
        dependency: bool ``[A, K]``, the parents of each actuator.
        actuator: ``a``.

    >>> local_pattern_of([True, False, True], torch.tensor([[True, False, True]]), 0)
    3
    """
    cached = _PARENT_LISTS.get(dependency)
    if cached is None or cached[0] != dependency._version:
        parents = tuple(tuple(row.nonzero().flatten().tolist()) for row in dependency)
        cached = _PARENT_LISTS[dependency] = (dependency._version, parents)
    pattern = 0
    for rank, sensor in enumerate(cached[1][actuator]):
        if readings[sensor]:
            pattern |= 1 << rank
    return pattern


def greedy_action_from_bits(values: torch.Tensor, tie_bits: torch.Tensor) -> torch.Tensor:
    """``argmax_a values[..., a]``, ties broken uniformly at random by 32 random bits.

    The ``k``-th of the ``n`` maximal actions (in index order) is taken, ``k = bits * n >> 32``.
    Shapes: ``[..., A], [...] -> [...]`` (int64).

    Args:
        values: ``[..., A]`` action values.
        tie_bits: ``[...]`` int64 random words in ``[0, 2**32)``.
    """
    is_max = values == values.amax(dim=-1, keepdim=True)  # [..., A]
    count = is_max.sum(dim=-1)
    k = randint_from_bits(tie_bits, count)
    rank = is_max.cumsum(dim=-1) - 1  # rank of each maximal action among the maximal ones
    # the one action that is maximal with rank k (max's index of the single 1: argmax's)
    return (is_max & (rank == k.unsqueeze(-1))).to(torch.int8).max(dim=-1).indices


def epsilon_greedy_from_bits(
    values: torch.Tensor,
    epsilon: float,
    explore_bits: torch.Tensor,
    action_bits: torch.Tensor,
    tie_bits: torch.Tensor,
    allowed: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Epsilon-greedy on ``values`` given its random bits (the deterministic core).

    With probability ``epsilon`` (``explore_bits < epsilon * 2**32``) the action is uniform over
    the ``A`` actions (over the ``allowed`` ones if given: ``safe_exploration_from_bits``) and
    flagged exploratory (even if it happens to be greedy); otherwise it is the greedy action with
    random tie-breaking. Bits are int64 in ``[0, 2**32)``, shape ``[...]``.

    Args:
        values: ``[..., A]`` action values.
        epsilon: the exploration probability.
        explore_bits, action_bits, tie_bits: ``[...]`` int64 random words in ``[0, 2**32)``:
            explore or not, the uniform action, the tie-break.
        allowed: ``[..., A]`` bool, where exploration may go (``risk_mask``); None: everywhere
            (the paper).

    Returns:
        ``(action, exploratory)``: int64 ``[...]`` and bool ``[...]``.
    """
    exploratory = explore_bits < probability_threshold(epsilon)
    if allowed is None:
        random_action = randint_from_bits(action_bits, values.shape[-1])
    else:
        random_action = safe_exploration_from_bits(allowed, action_bits)
    action = torch.where(exploratory, random_action, greedy_action_from_bits(values, tie_bits))
    return action, exploratory


def epsilon_greedy(
    values: torch.Tensor, epsilon: float, generator: torch.Generator | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Epsilon-greedy selection with uniform random tie-breaking, drawing from ``generator``.

    The convenience form of ``epsilon_greedy_from_bits``: the three random words are drawn from
    the given ``torch.Generator`` (the library's own modules use per-experiment counter streams
    instead, see ``factorq_torch.base.rng``). Shapes: ``[..., A] -> ([...], [...])``.

    Args:
        values: ``[..., A]`` action values.
        epsilon: the exploration probability.
        generator: where the random words come from (``None``: torch's default).
    """
    shape = (3, *values.shape[:-1])
    bits = torch.randint(0, 1 << 32, shape, generator=generator, device=values.device)
    return epsilon_greedy_from_bits(values, epsilon, bits[0], bits[1], bits[2])


# --------------------------------------------------------------------------------------------
# Learned dependencies: the structure learner's math (factorq_torch.structure), shared
# with the compiled path. Float64 throughout; sums over the patterns of a candidate are explicit
# left-to-right additions (log_posterior_of), as the kernel performs them.

#: The largest candidate parent set (pairs): see ``factorq_torch.structure``.
MAX_CANDIDATE_PARENTS = 2
#: Sensors the learner accepts (patterns are computed in int64 bit masks).
MAX_SENSORS = 62
#: Priors over the candidate parent sets (``candidate_log_prior``).
PRIORS = ("size", "uniform", "sparse")
#: The ``"sparse"`` prior's mass of all pairs together, relative to "no sensor" and to all single
#: sensors together (docs/decisions.md, "Learned dependencies": measured 0.1, 0.01, 0.001).
SPARSE_PAIR_MASS = 0.01
#: What an actuator predicts before it commits (``factorq_torch.structure``): ``"optimistic"``,
#: the largest running mean among the plausible candidates (log posterior within
#: ``log(bayes_factor)`` of the best: a firing is avoided only when every structure the evidence
#: has not ruled out predicts a loss); ``"map"``, the running mean of its maximum a posteriori
#: candidate; ``"posterior"``, the posterior-weighted
#: running mean (modular path only: it needs ``exp``, whose float64 result the compiled path
#: cannot reproduce bit for bit); ``"committed"``, nothing (0, as an unvisited table entry).
PREDICTIONS = ("optimistic", "map", "posterior", "committed")
#: What a reopening forgets (``factorq_torch.structure``): ``"body"``, the counts of every
#: actuator of the experiment (a body changes as a whole); ``"actuator"``, its own only.
REOPENINGS = ("body", "actuator")
#: The likelihood of a candidate's data (``factorq_torch.structure``; docs/decisions.md, "Learned
#: dependencies with noisy sensors"): ``"pattern"``, every pattern its own Beta-Bernoulli rate
#: (``beta_bernoulli_log_marginal`` summed over the patterns); ``"flip"``, every pattern a label
#: (collides or not) that the outcome disagrees with at the candidate's flip rate, a Beta latent
#: integrated out (``flip_log_marginal``); ``"mixture"``, every pattern's rate from a clean
#: (sharp, ``Beta(prior_a, prior_b)``) or a noisy (soft, ``NOISY_PRIOR``) population, at the more
#: probable of the two (``mixture_log_marginal``).
LIKELIHOODS = ("pattern", "flip", "mixture")
#: The noisy population's Beta prior of a pattern's rate (``mixture_log_marginal``): a sensor
#: that is wrong a fraction of the time leaves a pattern's rate anywhere between 0 and 1.
NOISY_PRIOR = (2.0, 2.0)
#: Prior odds of the noisy population against the clean one, per pattern.
NOISY_ODDS = 0.25
#: ``log 2``: the price of one pattern's label under the ``"flip"`` likelihood (a fair coin).
LOG_TWO = math.log(2.0)


def beta_bernoulli_log_marginal(
    count: torch.Tensor, successes: torch.Tensor, prior_a: float = 1.0, prior_b: float = 1.0
) -> torch.Tensor:
    """``log p(y_1..y_n)`` of ``n`` Bernoulli outcomes with ``s`` successes under a rate drawn
    from ``Beta(a, b)``: ``log B(a + s, b + n - s) - log B(a, b)``, elementwise, in float64.

    ``B(x, y) = Gamma(x) Gamma(y) / Gamma(x + y)``; ``n = s = 0`` gives 0. Fractional ``s`` (and
    ``n``) are allowed (a fractional success). Shapes broadcast.

    Args:
        count: ``n``, the outcomes.
        successes: ``s``, the successes among them.
        prior_a, prior_b: the Beta prior of the rate.

    >>> beta_bernoulli_log_marginal(torch.tensor([2.0]), torch.tensor([1.0]))  # 1!1!/3! = 1/6
    tensor([-1.7918], dtype=torch.float64)
    """
    n = count if count.dtype == torch.float64 else count.to(torch.float64)
    s = successes if successes.dtype == torch.float64 else successes.to(torch.float64)
    a, b = float(prior_a), float(prior_b)
    log_beta_prior = math.lgamma(a) + math.lgamma(b) - math.lgamma(a + b)
    # the numbers as cached 0-d float64 tensors (base.indices.scalar): the same sums, a third of
    # the time on the few patterns one firing touches
    a_, b_, ab_ = scalar(a, n), scalar(b, n), scalar(a + b, n)
    return (
        torch.lgamma(a_ + s)
        + torch.lgamma(b_ + n - s)
        - torch.lgamma(ab_ + n)
        - scalar(log_beta_prior, n)
    )


def candidate_sets(num_sensors: int, max_parents: int = MAX_CANDIDATE_PARENTS) -> list[tuple]:
    """The candidate parent sets: ``()``, then ``(j,)`` for every sensor, then ``(j, k)``,
    ``j < k`` (with ``max_parents=2``), in that order.

    Args:
        num_sensors: ``K``, the sensors.
        max_parents: the largest set (1 or 2).
    """
    check_int("num_sensors", num_sensors, 1, MAX_SENSORS)
    if not isinstance(max_parents, int) or isinstance(max_parents, bool) or max_parents < 0:
        raise ValueError(f"max_parents={max_parents!r} must be an integer >= 0")
    if max_parents > MAX_CANDIDATE_PARENTS:
        raise ValueError(
            f"max_parents={max_parents} is past the cap of {MAX_CANDIDATE_PARENTS}: candidate "
            f"sets of {max_parents} sensors would be C({num_sensors}, {max_parents}) tables per "
            f"actuator and experiment"
        )
    sets: list[tuple] = []
    for size in range(min(max_parents, num_sensors) + 1):
        sets.extend(itertools.combinations(range(num_sensors), size))
    return sets


def candidate_log_prior(sets: list[tuple], prior: str = "size") -> torch.Tensor:
    """``[C]`` float64 log prior of the candidates: ``"size"``, every size of parent set has the
    same mass, uniform within a size; ``"uniform"``, every candidate the same; ``"sparse"``, as
    ``"size"`` but all pairs together have ``SPARSE_PAIR_MASS`` times the mass of a size (an
    actuator needs the evidence of a pair's second sensor before the pair competes).

    Args:
        sets: the candidates (``candidate_sets``).
        prior: one of ``PRIORS``.
    """
    if prior not in PRIORS:
        raise ValueError(f"prior={prior!r} is unknown: choose one of {PRIORS}")
    if prior == "uniform":
        return torch.full((len(sets),), -math.log(len(sets)), dtype=torch.float64)
    sizes = torch.tensor([len(s) for s in sets])
    per_size = torch.bincount(sizes).to(torch.float64)  # candidates of each size
    if prior == "size":
        return -torch.log(per_size[sizes]) - math.log(len(per_size))
    mass = torch.ones_like(per_size)  # of each size, before normalising
    mass[2:] = SPARSE_PAIR_MASS
    return torch.log(mass[sizes]) - torch.log(per_size[sizes]) - math.log(float(mass.sum()))


def competitor_mask(sets: list[tuple]) -> torch.Tensor:
    """``[C, C]`` bool: ``[c, c']`` True where ``c'`` competes with ``c`` for commitment: every
    other candidate but the strict supersets of ``c``; for "no sensor", the single sensors.
    (Vectorised: 529 candidates are 280,000 pairs, seconds as a Python loop.)

    Args:
        sets: the candidates (``candidate_sets``).
    """
    size = torch.tensor([len(parents) for parents in sets])
    width = 1 + max((max(parents) for parents in sets if parents), default=-1)
    members = torch.zeros(len(sets), width, dtype=torch.bool)
    for index, parents in enumerate(sets):
        members[index, list(parents)] = True
    outside = members.to(torch.int64) @ (~members).to(torch.int64).T  # [c, c']: c's not in c'
    strict_superset = (outside == 0) & (size[None, :] > size[:, None])
    mask = ~strict_superset & ~torch.eye(len(sets), dtype=torch.bool)
    mask[size == 0] = size == 1
    return mask


def posterior_weights(log_posterior: torch.Tensor, out: torch.Tensor | None = None) -> torch.Tensor:
    """``softmax`` over the last dimension (candidates): ``p(c | D)``, float64.

    Args:
        log_posterior: ``[..., C]`` log posterior of the candidates (up to a constant).
        out: where to write them (its shape), or None for a new tensor.
    """
    if out is None:
        return torch.softmax(log_posterior, dim=-1)
    return torch.softmax(log_posterior, dim=-1, out=out)


def log_posterior_of(log_prior: torch.Tensor | float, log_marginal: torch.Tensor) -> torch.Tensor:
    """``[..., C]`` float64: ``log p(c) + sum_p log p(D_p | c)`` of every candidate, from the log
    marginal of each of its patterns ``[..., C, P]``, summed left to right (the kernel's order:
    ``log_prior + (((m_0 + m_1) + m_2) + m_3)``).

    Args:
        log_prior: ``[C]`` (or a float) log prior of the candidates.
        log_marginal: ``[..., C, P]`` log marginal of each candidate's patterns.
    """
    first, *rest = log_marginal.unbind(-1)
    total = first
    for column in rest:
        total = total + column
    if not isinstance(log_prior, torch.Tensor):
        log_prior = scalar(float(log_prior), total)
    return log_prior + total


def lgamma_tables(prior_a: float, prior_b: float, length: int) -> torch.Tensor:
    """``[3, length]`` float64: ``lgamma(a + m)``, ``lgamma(b + m)``, ``lgamma((a + b) + m)`` for
    ``m = 0 .. length - 1``, by ``torch.lgamma`` (the compiled path looks them up instead of
    calling its C library's ``lgamma``, which differs from torch's in the last bit).

    Args:
        prior_a, prior_b: the Beta prior.
        length: the entries ``m`` of each table.
    """
    m = torch.arange(length, dtype=torch.float64)
    a, b = float(prior_a), float(prior_b)
    return torch.stack((torch.lgamma(a + m), torch.lgamma(b + m), torch.lgamma(a + b + m)))


def flip_log_marginal(
    count: torch.Tensor, successes: torch.Tensor, prior_a: float = 0.25, prior_b: float = 0.25
) -> torch.Tensor:
    """``[..., C]`` float64: ``log p(D, labels | c)`` of every candidate under the flip likelihood,
    from the counts of its patterns ``[..., C, P]`` (docs/decisions.md, "Learned dependencies with
    noisy sensors").

    Each pattern ``p`` of a candidate has a label ``z_p`` (collides or not; a fair coin a priori,
    ``log 2`` per visited pattern) and every outcome disagrees with its pattern's label with the
    candidate's flip rate ``epsilon ~ Beta(prior_a, prior_b)``, integrated out. With the labels
    that explain the data best (each pattern's majority: ``m_p = min(s_p, n_p - s_p)``
    disagreements) and ``m = sum_p m_p``, ``n = sum_p n_p``, ``v`` the visited patterns:

        log p(D, labels | c) = log B(a + m, b + n - m) - log B(a, b) - v log 2

    (``beta_bernoulli_log_marginal(n, m)``). Sums over the patterns run left to right, as the
    kernel adds them (exact for integral counts).

    Args:
        count: ``[..., C, P]`` the visits of each candidate's patterns.
        successes: ``[..., C, P]`` the collisions among them.
        prior_a, prior_b: the Beta prior of the flip rate.

    >>> # one pattern seen 4 times with 1 collision: m = 1, n = 4, v = 1, Beta(1, 1):
    >>> # B(2, 4) / B(1, 1) / 2 = (1! 3! / 5!) / 2 = 1/40
    >>> flip_log_marginal(torch.tensor([[[4.0, 0.0]]]), torch.tensor([[[1.0, 0.0]]]), 1.0, 1.0)
    tensor([[-3.6889]], dtype=torch.float64)
    """
    n = count.to(torch.float64)
    s = successes.to(torch.float64)
    disagreements = _left_sum(torch.minimum(s, n - s))
    total = _left_sum(n)
    labels = _left_sum((n > 0).to(torch.float64))
    return beta_bernoulli_log_marginal(total, disagreements, prior_a, prior_b) - labels * LOG_TWO


def mixture_log_marginal(
    count: torch.Tensor,
    successes: torch.Tensor,
    prior_a: float = 0.25,
    prior_b: float = 0.25,
    noisy_prior: tuple[float, float] = NOISY_PRIOR,
    noisy_odds: float = NOISY_ODDS,
) -> torch.Tensor:
    """``log p(D_p, level_p)`` of every pattern under the mixture likelihood, elementwise
    (docs/decisions.md, "Learned dependencies with noisy sensors"): the pattern's rate
    is drawn from the clean population ``Beta(prior_a, prior_b)`` (prior mass ``1 / (1 + odds)``)
    or the noisy one ``Beta(*noisy_prior)`` (``odds / (1 + odds)``); at the more probable level,

        max(BB_clean(n, s) - log(1 + odds), BB_noisy(n, s) + log(odds) - log(1 + odds))

    where ``n > 0``, and 0 for an unvisited pattern (no data: its level is not chosen). Float64,
    in this order (the kernel's).

    Args:
        count: ``n``, a pattern's visits.
        successes: ``s``, its collisions.
        prior_a, prior_b: the clean population's Beta prior.
        noisy_prior: the noisy population's Beta prior.
        noisy_odds: prior odds of the noisy population against the clean one.

    >>> # n = 2, s = 1 under Beta(1, 1) (clean) and Beta(2, 2) (noisy), odds 1:
    >>> # clean 1/6 * 1/2 = 1/12; noisy B(3, 3) / B(2, 2) = (1/30) / (1/6) = 1/5, * 1/2 = 1/10
    >>> mixture_log_marginal(torch.tensor([2.0]), torch.tensor([1.0]), 1.0, 1.0, (2.0, 2.0), 1.0)
    tensor([-2.3026], dtype=torch.float64)
    """
    log_total = math.log1p(noisy_odds)
    n = count if count.dtype == torch.float64 else count.to(torch.float64)
    s = successes if successes.dtype == torch.float64 else successes.to(torch.float64)
    # Both levels' beta_bernoulli_log_marginal at once, the operations in its order on a
    # leading [2] (clean, noisy) axis: one lgamma call and half the small ops of two calls (a
    # firing of a StructureLearner evaluates this on a few dozen patterns, twice).
    a, b = float(prior_a), float(prior_b)
    a_noisy, b_noisy = (float(value) for value in noisy_prior)
    shape = (2,) + (1,) * n.dim()

    def build() -> tuple[torch.Tensor, ...]:
        columns = [
            [a, a_noisy],
            [b, b_noisy],
            [a + b, a_noisy + b_noisy],
            [
                math.lgamma(a) + math.lgamma(b) - math.lgamma(a + b),
                math.lgamma(a_noisy) + math.lgamma(b_noisy) - math.lgamma(a_noisy + b_noisy),
            ],
            # clean - log(1 + odds) is clean + (-log(1 + odds)), exactly
            [-log_total, math.log(noisy_odds) - log_total],
        ]
        values = torch.tensor(columns, dtype=torch.float64, device=n.device)
        return values.reshape(5, *shape).unbind(0)

    key = ("mixture", a, b, a_noisy, b_noisy, float(noisy_odds), n.device, shape)
    prior_a_, prior_b_, prior_ab, log_beta_prior, level = constant(key, build)
    logs = torch.lgamma(torch.stack((prior_a_ + s, prior_b_ + n - s, prior_ab + n)))
    first, second, third = logs.unbind(0)  # [2, ...] each
    clean, noisy = (first + second - third - log_beta_prior + level).unbind(0)
    return torch.where(count > scalar(0, count), torch.maximum(clean, noisy), scalar(0.0, clean))


def has_minority(count: torch.Tensor, successes: torch.Tensor) -> torch.Tensor:
    """``[...]`` bool: whether a candidate's patterns ``[..., P]`` hold an outcome against their
    majority, ``sum_p min(s_p, n_p - s_p) > 0`` (docs/decisions.md, "Learned dependencies with
    noisy sensors", the noise gate).

    A clean pairing is deterministic (a collision world with sensors that read right: every
    visit of a pattern has the same outcome), so a *committed* candidate with a minority outcome
    in the data it was committed on shows that the sensors read wrong: the learner then tests for
    a change at ``noisy_reopen_factor``. Fractional rewards (modular path) count as minority
    outcomes too.

    Args:
        count: ``[..., P]`` the visits of each of a candidate's patterns.
        successes: ``[..., P]`` the collisions among them.

    >>> has_minority(torch.tensor([[3.0, 2.0], [3.0, 2.0]]), torch.tensor([[3.0, 0.0], [2.0, 0.0]]))
    tensor([False,  True])
    """
    n = count.to(torch.float64)
    s = successes.to(torch.float64)
    return (torch.minimum(s, n - s) > 0).any(dim=-1)


#: Which pair candidates a ``StructureLearner`` counts and scores (docs/decisions.md, "Learned
#: dependencies with noisy sensors", pair pruning): ``"all"``, every pair at every firing;
#: ``"pruned"``, a pair only while it is *active* (``pair_activity``), its counts rebuilt from the
#: actuator's stored firings when it enters (``rebuild_pair_counts``).
PAIR_MODES = ("all", "pruned")


def pair_members(sets: list[tuple]) -> torch.Tensor:
    """``[2, C]`` int64: for a pair ``(j, k)``, the candidate indices of its singles ``(j,)`` and
    ``(k,)``; for "no sensor" and a single, its own index twice (``pair_activity``).

    Args:
        sets: the candidates (``candidate_sets``).
    """
    index_of = {parents: index for index, parents in enumerate(sets)}
    members = torch.zeros(2, len(sets), dtype=torch.int64)
    for index, parents in enumerate(sets):
        if len(parents) == 2:
            members[0, index], members[1, index] = index_of[parents[:1]], index_of[parents[1:]]
        else:
            members[:, index] = index
    return members


def initial_activity(sets: list[tuple]) -> torch.Tensor:
    """``[C]`` bool: the candidates active before any data (after a reset or a reopening):
    "no sensor" and the singles. No pair: with no data "no sensor" explains every firing
    (``pair_activity``'s ``explained``), and a pair enters only once no candidate of at most one
    sensor does.

    Args:
        sets: the candidates (``candidate_sets``).
    """
    return torch.tensor([len(parents) < 2 for parents in sets], dtype=torch.bool)


def single_explains(
    count: torch.Tensor, successes: torch.Tensor, small: torch.Tensor
) -> torch.Tensor:
    """``[...]`` bool: whether a candidate of at most one sensor ("no sensor" or a single) has no
    outcome against its patterns' majority (``has_minority``) in the counts ``[..., C, P]``: it
    then explains every firing, and no pair can explain them better (``pair_activity``).

    Args:
        count: ``[..., C, P]`` the visits of every candidate's patterns.
        successes: ``[..., C, P]`` the collisions among them.
        small: ``[M]`` int64, the indices of the candidates of at most one sensor (``"no
            sensor"`` and the singles: ``arange(K + 1)`` in ``candidate_sets``' order).
    """
    return (~has_minority(count.index_select(-2, small), successes.index_select(-2, small))).any(
        dim=-1
    )


def pair_activity(
    log_posterior: torch.Tensor,
    committed: torch.Tensor,
    members: torch.Tensor,
    small: torch.Tensor,
    log_bayes_factor: float,
    explained: torch.Tensor | None = None,
) -> torch.Tensor:
    """``[..., C]`` bool: the candidates active after a firing (``"pruned"`` pairs).

    A candidate of at most one sensor is always active. While a candidate of at most one sensor
    explains every firing (``explained``, ``single_explains``: no outcome against its patterns'
    majority) a pair is active only when it is the committed candidate: a pair that explains the
    firings as well splits that candidate's patterns (with both outcomes seen, its two patterns are
    the outcomes themselves), and splitting a pattern whose outcomes all agree lowers its marginal
    (the rule of succession), while a pair with a mixed pattern pays for it; so no pair is needed.
    Otherwise a pair ``{j, k}`` is active when one of its singles is *plausible* (log posterior
    within ``log_bayes_factor`` of the best active candidate: the evidence has not ruled out that
    ``j`` matters), when it is itself plausible (a pair that explains the data better than its
    singles stays, even once they are ruled out by it), or when it is the committed candidate.
    ``log_posterior`` is that of the active candidates before the firing's entries (``-inf`` for the
    inactive ones, which are never plausible).

    Args:
        log_posterior: ``[..., C]`` float64, ``-inf`` where inactive.
        committed: ``[...]`` int64, the committed candidate (-1: open).
        members: ``[2, C]`` (``pair_members``).
        small: ``[C]`` bool, the candidates of at most one sensor.
        log_bayes_factor: ``log(bayes_factor)``.
        explained: ``[...]`` bool (``single_explains``), or None: never.
    """
    best = log_posterior.max(dim=-1, keepdim=True).values
    plausible = log_posterior >= best - scalar(log_bayes_factor, best)
    candidates = torch.arange(log_posterior.shape[-1], device=log_posterior.device)
    reasons = (
        plausible | plausible.index_select(-1, members[0]) | plausible.index_select(-1, members[1])
    )
    if explained is not None:
        reasons = reasons & ~explained.unsqueeze(-1)
    return small | reasons | (committed.unsqueeze(-1) == candidates)


def rebuild_pair_counts(
    readings: torch.Tensor,
    reward: torch.Tensor,
    block: torch.Tensor,
    first: torch.Tensor,
    second: torch.Tensor,
) -> tuple[torch.Tensor, ...]:
    """The counts of the pairs ``(first[m], second[m])`` over one actuator's stored firings, as
    counting them at every firing would have left them (``"pruned"`` pairs entering).

    The firings in order: ``readings`` ``[E]`` int64 (bit ``j`` is sensor ``j``), ``reward``
    ``[E]`` float64 (the actuator's local reward), ``block`` ``[E]`` bool (the firing is in the
    current block). Returns ``count``, ``successes``, ``reward_sum`` and their ``block_`` twins,
    each ``[M, 4]`` float64 (pattern ``x_first + 2 x_second``). Counts are integers (exact in any
    order); the success and reward sums are exact in any order when every reward is an integer
    (the collision world's 0 and -1), else added one firing at a time, oldest first, as the
    learner adds them.

    Args:
        readings: ``[E]`` int64 packed sensor bits of each firing.
        reward: ``[E]`` float64 local rewards.
        block: ``[E]`` bool, firings of the current block.
        first, second: ``[M]`` int64 sensors of each pair.
    """
    one = scalar(1, readings)
    pattern = ((readings.unsqueeze(0) >> first.unsqueeze(1)) & one) + (
        ((readings.unsqueeze(0) >> second.unsqueeze(1)) & one) << one
    )  # [M, E]
    success = (-reward).clamp(scalar(0.0, reward), scalar(1.0, reward))
    pairs = pattern.shape[0]
    results = []
    integral = bool((reward == reward.round()).all())
    for selected in (torch.ones_like(block), block):
        columns = selected.nonzero().flatten()
        where = pattern.index_select(1, columns)  # [M, E']
        values = (torch.ones_like(reward), success, reward)
        sums = []
        for index, value in enumerate(values):
            value = value.index_select(0, columns)
            total = torch.zeros(pairs, 4, dtype=torch.float64, device=readings.device)
            if index == 0 or integral:
                total.scatter_add_(1, where, value.expand(pairs, -1).contiguous())
            else:  # one firing at a time, oldest first: the learner's order of additions
                for e in range(value.numel()):
                    total.scatter_add_(1, where[:, e : e + 1], value[e].expand(pairs, 1))
            sums.append(total)
        results.extend(sums)
    return tuple(results)


# --------------------------------------------------------------------------------------------
# Action vectors (simultaneous actuators, issue 40): a body whose action is a vector of ``J``
# independent actuators, actuator ``j`` taking ``V_j`` values (``nvec``), ``M = prod(nvec)``
# joint actions. The task Q is over the joint action; the local tables are per actuator value;
# eqs. 2-3 are applied per actuator and the terms added (docs/decisions.md, "Simultaneous
# actuators: eqs. 2-3 per actuator"). With one actuator every function is the paper's.


def _check_nvec(nvec: Sequence[int]) -> tuple[int, ...]:
    values = tuple(check_int(f"nvec[{j}]", v, 2) for j, v in enumerate(nvec))
    if not values:
        raise ValueError("nvec must name at least one actuator")
    return values


def joint_action_index(action: torch.Tensor, nvec: Sequence[int]) -> torch.Tensor:
    """The joint action's index, mixed radix with actuator 0 the most significant digit:
    ``m = ((a_0 V_1 + a_1) V_2 + a_2) ...`` (row-major over ``nvec``).

    Shapes: ``[..., J]`` int64 -> ``[...]`` int64 in ``[0, prod(nvec))``.

    Args:
        action: ``[..., J]`` value indices, ``a_j`` in ``[0, nvec[j])``.
        nvec: the values of each actuator (its last dimension must be ``len(nvec)``).

    >>> joint_action_index(torch.tensor([[0, 0], [1, 2], [2, 1]]), (3, 3))
    tensor([0, 5, 7])
    """
    nvec = _check_nvec(nvec)
    if action.shape[-1] != len(nvec):
        raise ValueError(
            f"the action vector has length {action.shape[-1]} but nvec={list(nvec)} names "
            f"{len(nvec)} actuators"
        )
    index = torch.zeros(action.shape[:-1], dtype=torch.int64, device=action.device)
    for j, values in enumerate(nvec):
        index = index * values + action[..., j].to(torch.int64)
    return index


def joint_action_vector(index: torch.Tensor, nvec: Sequence[int]) -> torch.Tensor:
    """The inverse of ``joint_action_index``: ``[...]`` -> ``[..., J]`` int64.

    Args:
        index: ``[...]`` joint action indices in ``[0, prod(nvec))``.
        nvec: the values of each actuator.

    >>> joint_action_vector(torch.tensor([0, 5, 7]), (3, 3)).tolist()
    [[0, 0], [1, 2], [2, 1]]
    """
    nvec = _check_nvec(nvec)
    digits = []
    rest = index.to(torch.int64)
    for values in reversed(nvec):
        digits.append(rest % values)
        rest = rest // values
    return torch.stack(digits[::-1], dim=-1)


def actuator_mean_values(q: torch.Tensor, nvec: Sequence[int]) -> tuple[torch.Tensor, ...]:
    """Each actuator's mean task values: ``Qbar_j(s, v) = mean_{a : a_j = v} Q(s, a)``, the
    task value of actuator ``j``'s value ``v`` averaged over the other actuators' values.

    Shapes: ``q [..., M]`` (``M = prod(nvec)``, joint actions in ``joint_action_index`` order)
    -> ``J`` tensors ``[..., V_j]``. With one actuator, ``Qbar_0 = Q``.

    Args:
        q: ``[..., M]`` task values over the joint action.
        nvec: the values of each actuator.

    >>> q = torch.tensor([0.0, 1.0, 0.0, 3.0, 0.0, 0.0, 0.0, 0.0, 2.0])  # [a_0, a_1]: 3 x 3
    >>> [[round(x, 3) for x in m.tolist()] for m in actuator_mean_values(q, (3, 3))]
    [[0.333, 1.0, 0.667], [1.0, 0.333, 0.667]]
    """
    nvec = _check_nvec(nvec)
    lead = q.shape[:-1]
    grid = q.reshape(*lead, *nvec)  # [..., V_0, ..., V_{J-1}]
    first = len(lead)
    means = []
    for j in range(len(nvec)):
        others = tuple(first + i for i in range(len(nvec)) if i != j)
        means.append(grid.mean(dim=others) if others else grid)
    return tuple(means)


def split_actuator_values(rho: torch.Tensor, nvec: Sequence[int]) -> tuple[torch.Tensor, ...]:
    """``[..., sum(nvec)]`` per-actuator-value entries (actuator 0's values first) -> ``J``
    tensors ``[..., V_j]``.

    Args:
        rho: ``[..., sum(nvec)]`` one entry per actuator value.
        nvec: the values of each actuator.
    """
    nvec = _check_nvec(nvec)
    if rho.shape[-1] != sum(nvec):
        raise ValueError(
            f"the local values have {rho.shape[-1]} entries but nvec={list(nvec)} has "
            f"{sum(nvec)} actuator values"
        )
    return tuple(rho.split(list(nvec), dim=-1))


def vector_normalisers(
    q: torch.Tensor,
    rho: torch.Tensor,
    nvec: Sequence[int],
    eta: float = 0.1,
    g_min: float = 0.01,
) -> torch.Tensor:
    """Eq. 3 per actuator: ``G_j = (Q(s, a_hat) - Q_bar_j) / (P_bar_j - rho_j[a_check_j])
    * (1 + eta)``.

    ``a_hat = argmax_a Q(s, a)`` over the joint action (the first maximum in
    ``joint_action_index`` order); ``Q_bar_j`` the mean task value of the joint actions that set
    actuator ``j`` otherwise than ``a_hat`` does (the mean over ``v != a_hat_j`` of
    ``actuator_mean_values``); ``a_check_j = argmin_v rho_j[v]`` and ``P_bar_j`` the mean of
    actuator ``j``'s other ``V_j - 1`` local values. So ``G_j`` scales the spread of actuator
    ``j``'s local reward to the task spread that changing actuator ``j`` costs, each actuator in
    its own units; the floor is eq. 3's (``normaliser``). With one actuator it is the paper's
    ``G``. ``docs/decisions.md`` ("Simultaneous actuators") derives it, with the variants measured.

    Shapes: ``q [..., M]``, ``rho [..., sum(nvec)]`` -> ``[..., J]``.

    Args:
        q: ``[..., M]`` task values over the joint action.
        rho: ``[..., sum(nvec)]`` projected local rewards, actuator 0's values first.
        nvec: the values of each actuator.
        eta, g_min: as ``normaliser``.

    >>> q = torch.tensor([0.0, 1.0, 0.0, 3.0, 0.0, 0.0, 0.0, 0.0, 2.0])  # a_hat = (1, 0)
    >>> rho = torch.tensor([-1.0, 0.0, 0.0, 0.0, 0.0, 0.0])  # actuator 0's value 0 collides
    >>> vector_normalisers(q, rho, (3, 3))  # G_0 = (3 - 0.5) / 1 * 1.1; G_1: no spread, g_min
    tensor([2.7500, 0.0100])
    """
    q_max, a_hat = q.max(dim=-1)  # [...]
    hat = joint_action_vector(a_hat, nvec)  # [..., J]
    means = actuator_mean_values(q, nvec)
    locals_ = split_actuator_values(rho, nvec)
    floor = scalar(g_min, q)
    normalisers = []
    for j, (mean, local) in enumerate(zip(means, locals_, strict=True)):
        x = q_max - _mean_of_others(mean, hat[..., j])  # Q(s, a_hat) - Q_bar_j
        rho_min, a_check = local.min(dim=-1)
        y = _mean_of_others(local, a_check) - rho_min  # P_bar_j - rho_j[a_check_j]
        spread = y > scalar(0.0, y)
        g = x / torch.where(spread, y, scalar(1.0, y)) * scalar(1 + eta, x)
        g = torch.where(spread & (g >= floor), g, floor)
        normalisers.append(g.clamp_max(scalar(torch.finfo(g.dtype).max, g)))
    return torch.stack(normalisers, dim=-1)


def vector_combined_values(
    q: torch.Tensor, rho: torch.Tensor, g: torch.Tensor, nvec: Sequence[int]
) -> torch.Tensor:
    """Eq. 2 on an action vector: ``C(s, a) = Q(s, a) + sum_j G_j rho_j(o, a_j)``.

    Each actuator's local reward enters once, scaled by its own ``G_j``, for every joint action
    that sets it to that value: the local rewards stay separate (one per actuator) and add, as
    the actuators' collisions do. With one actuator it is ``combined_values``.

    Shapes: ``q [..., M]``, ``rho [..., sum(nvec)]``, ``g [..., J]`` -> ``[..., M]``.

    Args:
        q: ``[..., M]`` task values over the joint action.
        rho: ``[..., sum(nvec)]`` projected local rewards, actuator 0's values first.
        g: ``[..., J]`` the per-actuator normalisers (``vector_normalisers``).
        nvec: the values of each actuator.

    >>> q = torch.zeros(4)  # two actuators of two values: joint actions 00, 01, 10, 11
    >>> rho = torch.tensor([-1.0, 0.0, 0.0, -1.0])  # 0 collides at value 0, 1 at value 1
    >>> vector_combined_values(q, rho, torch.tensor([2.0, 3.0]), (2, 2))
    tensor([-2., -5.,  0., -3.])
    """
    nvec = _check_nvec(nvec)
    lead = q.shape[:-1]
    total = q.reshape(*lead, *nvec)
    for j, local in enumerate(split_actuator_values(rho, nvec)):
        term = g[..., j].unsqueeze(-1) * local  # [..., V_j]
        shape = [*lead] + [values if i == j else 1 for i, values in enumerate(nvec)]
        total = total + term.reshape(shape)
    largest = torch.finfo(q.dtype).max
    return total.reshape(*lead, -1).clamp(scalar(-largest, q), scalar(largest, q))
