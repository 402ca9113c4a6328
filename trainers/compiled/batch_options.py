"""The options of the fast path's batch (``fast.ExperimentBatch``) and their checks, the
cache-line-padded blocks the kernel writes, and the structure learner's tables and state.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch

from factorq_envs.grid_world import WorldConfig
from factorq_torch import functional
from factorq_torch.base.validation import MAX_TABLE_ENTRIES, check_float, check_int
from factorq_torch.functional import LIKELIHOODS, NOISY_ODDS, NOISY_PRIOR, PAIR_MODES, REOPENINGS
from factorq_trainers.compiled.loader import _PREDICTION_CODES


@dataclass(frozen=True)
class SensorOrders:
    """A sensor order per experiment for any algorithm (``factorq_envs.permutation.PermuteSensors``
    on the compiled path): agent sensor ``j`` is world sensor ``orders[s, j]`` (``[S, K]``),
    replaced by ``orders_after`` from the first observation after the reset into run
    ``change_run`` (0: never)."""

    orders: torch.Tensor
    orders_after: torch.Tensor | None = None
    change_run: int = 0


@dataclass(frozen=True)
class StructureOptions:
    """The structure learner (``factorq_torch.structure.StructureLearner``) as Factor-Q's local
    value provider on the generic loop, with the bookkeeping of ``factorq dependencies``.

    ``orders``, ``orders_after``, ``change_run``: as ``SensorOrders``'. ``curve_every``: steps
    between two points of the per-experiment "all actuators right" curve. The other fields are the
    learner's arguments; the priors must be multiples of 1/1024 (the counts and priors then add
    exactly, so every ``lgamma`` argument is one of the tables' doubles).
    """

    orders: torch.Tensor
    max_parents: int = 2
    bayes_factor: float = 300.0
    window: int = 100
    prior_a: float = 0.25
    prior_b: float = 0.25
    prior: str = "sparse"
    prediction: str = "optimistic"
    reopen: str = "body"
    reopen_factor: float | None = None
    noisy_reopen_factor: float | None = None
    likelihood: str = "mixture"
    pairs: str = "pruned"
    orders_after: torch.Tensor | None = None
    change_run: int = 0
    curve_every: int = 10


#: Bytes of a cache line. Each experiment's blocks that the kernel writes in its inner loop start
#: on a line of their own, so that two threads never write one line (false sharing).
CACHE_LINE = 64


def _padded_zeros(
    count: int, shape: tuple[int, ...], dtype: torch.dtype
) -> tuple[torch.Tensor, int]:
    """``(view, stride)``: zeros ``[count, *shape]`` as a view of a ``[count, stride]`` storage
    whose rows are whole cache lines (torch's CPU allocator aligns the storage itself to 64)."""
    per_line = CACHE_LINE // torch.empty((), dtype=dtype).element_size()
    numel = math.prod(shape)
    stride = max(-(-numel // per_line) * per_line, per_line)
    return torch.zeros(count, stride, dtype=dtype)[:, :numel].unflatten(1, shape), stride


def _check_vector(name: str, value: Any, count: int | None) -> torch.Tensor:
    """A 1-d int64 CPU tensor of ``count`` entries (any count when None), made contiguous."""
    if not isinstance(value, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
    if value.dtype != torch.int64:
        raise TypeError(f"{name} must have dtype torch.int64, got {value.dtype}")
    if value.dim() != 1 or value.numel() == 0:
        raise ValueError(
            f"{name} must be a non-empty 1-d tensor [S], got shape {tuple(value.shape)}"
        )
    if count is not None and value.numel() != count:
        raise ValueError(f"{name} has {value.numel()} entries but periods has {count}")
    if value.device.type != "cpu":
        raise ValueError(f"{name} must be on the CPU, got device {value.device}")
    return value.detach().contiguous().clone()


def _check_orders(name: str, orders: Any, count: int, num_sensors: int) -> torch.Tensor:
    """``[count, K]`` int64, every row a permutation of ``range(K)``."""
    if not isinstance(orders, torch.Tensor) or orders.dtype != torch.int64:
        raise TypeError(f"{name} must be an int64 tensor [experiments, sensors]")
    if tuple(orders.shape) != (count, num_sensors):
        raise ValueError(f"{name} has shape {list(orders.shape)}, expected {[count, num_sensors]}")
    expected = torch.arange(num_sensors).expand(count, -1)
    if not torch.equal(orders.cpu().sort(dim=-1).values, expected):
        raise ValueError(f"{name}: every row must hold each of 0..{num_sensors - 1} once")
    return orders.detach().cpu().contiguous().clone()


def learner_setup(
    structure: StructureOptions | None,
    sensor_orders: SensorOrders | None,
    algorithm: str,
    world: WorldConfig,
    count: int,
    runs: int,
    episodes: int,
) -> tuple[dict, dict[str, torch.Tensor], dict[str, torch.Tensor], list]:
    """Check the structure learner's options (or the sensor orders alone) of a batch of ``count``
    experiments of ``runs`` x ``episodes`` episodes; return fq_batch's scalar fields, the
    read-only tables, the state the kernel writes (``[S, ...]`` tensors) and the candidate sets;
    with neither ``({"learner": 0}, {}, {}, [])``."""
    if structure is not None and sensor_orders is not None:
        raise ValueError("sensor_orders: give the orders in structure (StructureOptions)")
    options = sensor_orders if structure is None else structure
    if options is None:
        return {"learner": 0}, {}, {}, []
    name, kind = (
        ("sensor_orders", SensorOrders) if structure is None else ("structure", StructureOptions)
    )
    if not isinstance(options, kind):
        raise TypeError(f"{name} must be a {kind.__name__}, got {type(options).__name__}")
    num_sensors, actuators = world.num_sensors, world.num_actuators
    check_int(f"{name}.change_run", options.change_run, 0, runs - 1)
    orders = _check_orders(f"{name}.orders", options.orders, count, num_sensors)
    after = orders if options.orders_after is None else options.orders_after
    after = _check_orders(f"{name}.orders_after", after, count, num_sensors)
    fields: dict[str, Any] = {"learner": 0, "change_run": options.change_run}
    tables = {"orders": orders, "orders_after": after}
    state = {"change_tick": torch.full((count,), -1, dtype=torch.int64)}
    if structure is None:
        return fields, tables, state, []
    if algorithm != "factor-q":
        raise ValueError(f"structure: the structure learner runs with factor-q, not {algorithm}")
    if structure.prediction not in _PREDICTION_CODES:
        raise ValueError(
            f"structure.prediction={structure.prediction!r}: the fast path runs "
            f"{tuple(_PREDICTION_CODES)} ({functional.PREDICTIONS} on the modular path)"
        )
    for name in ("bayes_factor", "reopen_factor", "noisy_reopen_factor"):
        if name == "bayes_factor" or getattr(structure, name) is not None:
            check_float(f"structure.{name}", getattr(structure, name), 1.0, math.inf,
                        low_open=True, high_open=True)  # fmt: skip
    for name in ("prior_a", "prior_b"):
        value = getattr(structure, name)
        if not (isinstance(value, (int, float)) and 0 < value < 2**20 and value * 1024 % 1 == 0):
            raise ValueError(
                f"structure.{name}={value!r}: the fast path needs a multiple of 1/1024 in "
                f"(0, 2**20)"
            )
    check_int("structure.window", structure.window, 1)
    for name, known in (("likelihood", LIKELIHOODS), ("pairs", PAIR_MODES), ("reopen", REOPENINGS)):
        if getattr(structure, name) not in known:
            raise ValueError(
                f"structure.{name}={getattr(structure, name)!r} is unknown: choose one of {known}"
            )
    check_int("structure.curve_every", structure.curve_every, 1)
    sets = functional.candidate_sets(num_sensors, structure.max_parents)
    index_of = {frozenset(parents): index for index, parents in enumerate(sets)}
    truth = torch.full((count, 2, actuators), -2, dtype=torch.int64)
    dependency = world.dependency  # [A, K] in the world's order
    for phase, order in enumerate((orders, after)):
        for experiment in range(count):
            parents = dependency[:, order[experiment]]  # agent sensor j = world order[j]
            for actuator in range(actuators):
                members = frozenset(parents[actuator].nonzero().flatten().tolist())
                truth[experiment, phase, actuator] = index_of.get(members, -2)
    num_candidates, patterns = len(sets), 1 << min(structure.max_parents, num_sensors)
    candidate_sensors = torch.full((num_candidates, 2), -1, dtype=torch.int64)
    for index, candidate in enumerate(sets):
        candidate_sensors[index, : len(candidate)] = torch.tensor(candidate, dtype=torch.int64)
    log_prior = functional.candidate_log_prior(sets, structure.prior)
    steps = runs * episodes * world.max_steps
    length = steps + 2  # n + 1 of every count stays inside
    log_bayes_factor = math.log(float(structure.bayes_factor))
    pruned = structure.pairs == "pruned" and structure.max_parents >= 2 and num_sensors >= 2
    initial = (
        functional.initial_activity(sets) if pruned else torch.ones(len(sets), dtype=torch.bool)
    )
    capacity = steps if pruned else 1  # every firing of an experiment (one per step)
    if capacity > MAX_TABLE_ENTRIES:
        raise ValueError(
            f"structure.pairs='pruned' keeps every firing of an experiment to rebuild an entering "
            f"pair: {steps} steps per experiment are past the cap of {MAX_TABLE_ENTRIES} (2**24): "
            f"use pairs='all' (--pairs all) or fewer runs, episodes or max_steps"
        )
    scored = torch.where(initial, log_prior, -math.inf)
    tables.update(
        candidate_sensors=candidate_sensors,
        log_prior=log_prior.contiguous(),
        competitors=functional.competitor_mask(sets).to(torch.uint8).contiguous(),
        lgamma_table=functional.lgamma_tables(
            structure.prior_a, structure.prior_b, length
        ).contiguous(),
        noisy_lgamma_table=functional.lgamma_tables(*NOISY_PRIOR, length).contiguous(),
        truth=truth,
        initial_active=initial.to(torch.uint8).contiguous(),
        all_candidates=torch.arange(num_candidates, dtype=torch.int16),
    )
    per_experiment = 8 * actuators * num_candidates * patterns
    counts, stride = _padded_zeros(count, (per_experiment,), torch.float64)
    curve_length = steps // structure.curve_every + 1
    each, per_actuator, per_step = (count,), (count, actuators), (count, capacity)

    def full(shape: tuple, value: int = 0, dtype: torch.dtype = torch.int64) -> torch.Tensor:
        return torch.full(shape, value, dtype=dtype)

    def per_candidate(row: torch.Tensor, dtype: torch.dtype = torch.uint8) -> torch.Tensor:
        return row.to(dtype).expand(count, actuators, -1).contiguous()  # [C] -> [S, A, C]

    zeros = "samples block_samples reopened samples_at_change history_start block_start".split()
    # the active candidates in increasing order, then padding (the kernel's loops)
    active_list = torch.where(initial, torch.arange(num_candidates), num_candidates).sort().values
    state.update(
        counts=counts,
        **{name: full(per_actuator) for name in zeros},
        **{name: full(each) for name in ("wrong_commitments", "noise_seen", "history_length")},
        committed=full(per_actuator, -1),
        right_since=full(per_actuator, -1),
        # over the initially active candidates (StructureLearner's first _refresh_cache)
        map_cache=full(per_actuator, int(scored.argmax())),
        plausible=per_candidate(scored >= scored.max() - log_bayes_factor),
        curve=full((count, curve_length), dtype=torch.uint8),
        active=per_candidate(initial),
        history_readings=full(per_step),
        history_action=full(per_step, dtype=torch.uint8),
        history_reward=full(per_step, dtype=torch.float32),
        active_list=per_candidate(active_list.clamp(max=num_candidates - 1), torch.int16),
        active_count=full(per_actuator, int(initial.sum())),
    )
    reopen = structure.bayes_factor if structure.reopen_factor is None else structure.reopen_factor
    noisy = reopen if structure.noisy_reopen_factor is None else structure.noisy_reopen_factor

    def log_beta(a: float, b: float) -> float:  # as functional's log marginals (Python's lgamma)
        return math.lgamma(a) + math.lgamma(b) - math.lgamma(a + b)

    fields.update(
        learner=1,
        num_candidates=num_candidates,
        learner_patterns=patterns,
        prediction=_PREDICTION_CODES[structure.prediction],
        window=structure.window,
        curve_every=structure.curve_every,
        curve_length=curve_length,
        lgamma_length=length,
        learner_stride=stride,
        reopen_body=int(structure.reopen == "body"),
        likelihood_flip=int(structure.likelihood == "flip"),
        mixture=int(structure.likelihood == "mixture"),
        prune_pairs=int(pruned),
        history_capacity=capacity,
        log_bayes_factor=log_bayes_factor,
        log_reopen_factor=math.log(reopen),
        log_noisy_reopen_factor=math.log(noisy),
        log_beta_prior=log_beta(float(structure.prior_a), float(structure.prior_b)),
        log_noisy_beta_prior=log_beta(*NOISY_PRIOR),
        log_mixture_total=math.log1p(NOISY_ODDS),
        log_noisy_weight=math.log(NOISY_ODDS) - math.log1p(NOISY_ODDS),
    )
    return fields, tables, state, sets
