"""The options of the fast path's batch (``factorq_trainers.compiled.fast.ExperimentBatch``) and
their checks: the structure learner's (``StructureOptions``) and the sensor orders'
(``SensorOrders``), the argument checks, the cache-line-padded blocks the kernel writes, and the
structure learner's tables and state as the kernel reads them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch

from factorq_envs.grid_world import WorldConfig
from factorq_torch.base.validation import MAX_TABLE_ENTRIES, check_float, check_int
from factorq_torch.functional import (
    LIKELIHOODS,
    NOISY_ODDS,
    NOISY_PRIOR,
    PAIR_MODES,
    PREDICTIONS,
    REOPENINGS,
    candidate_log_prior,
    candidate_sets,
    competitor_mask,
    initial_activity,
    lgamma_tables,
)
from factorq_trainers.compiled.loader import _PREDICTION_CODES


@dataclass(frozen=True)
class StructureOptions:
    """The structure learner (``factorq_torch.structure.StructureLearner``) as Factor-Q's local
    value provider on the generic loop, with the bookkeeping of ``factorq dependencies``.

    ``orders`` ``[S, K]``: each experiment's sensor order
    (``factorq_envs.permutation.PermuteSensors``), replaced by ``orders_after`` from the first
    observation after the reset into run ``change_run`` (0: never). ``curve_every``: steps between
    two points of the per-experiment "all actuators right" curve. The other fields are the learner's
    arguments; the priors must be multiples of 1/1024 (the counts and priors then add exactly, so
    every ``lgamma`` argument is one of the tables' doubles).
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


@dataclass(frozen=True)
class SensorOrders:
    """A sensor order per experiment for any algorithm (``factorq_envs.permutation.PermuteSensors``
    on the compiled path): agent sensor ``j`` is world sensor ``orders[s, j]``, replaced by
    ``orders_after`` from the first observation after the reset into run ``change_run`` (0:
    never). ``StructureOptions`` carries its own."""

    orders: torch.Tensor
    orders_after: torch.Tensor | None = None
    change_run: int = 0


#: Bytes of a cache line. Each experiment's blocks that the kernel writes in its inner loop start
#: on a line of their own, so that two threads never write one line (false sharing).
CACHE_LINE = 64


def _padded_zeros(
    count: int, shape: tuple[int, ...], dtype: torch.dtype
) -> tuple[torch.Tensor, int]:
    """``(view, stride)``: zeros ``[count, *shape]`` as a view of a ``[count, stride]`` storage
    whose rows are whole cache lines (torch's CPU allocator aligns the storage itself to 64)."""
    per_line = CACHE_LINE // torch.empty((), dtype=dtype).element_size()
    numel = 1
    for extent in shape:
        numel *= extent
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


def _check_threads(threads: object) -> int:
    if threads is None:
        return torch.get_num_threads()
    return check_int("threads", threads, 1)


def structure_setup(
    options: StructureOptions | None,
    algorithm: str,
    world: WorldConfig,
    count: int,
    runs: int,
    episodes: int,
) -> tuple[dict, dict[str, torch.Tensor], dict[str, torch.Tensor], list]:
    """Check ``options`` of a batch of ``count`` experiments of ``runs`` x ``episodes`` episodes;
    return fq_batch's scalar fields, the learner's read-only tables, its state (``[S, ...]``
    tensors the kernel writes) and its candidate sets; without a learner
    ``({"learner": 0}, {}, {}, [])``."""
    if options is None:
        return {"learner": 0}, {}, {}, []
    if not isinstance(options, StructureOptions):
        raise TypeError(f"structure must be a StructureOptions, got {type(options).__name__}")
    if algorithm != "factor-q":
        raise ValueError(f"structure: the structure learner runs with factor-q, not {algorithm}")
    if options.prediction not in _PREDICTION_CODES:
        raise ValueError(
            f"structure.prediction={options.prediction!r}: the fast path runs "
            f"{tuple(_PREDICTION_CODES)} ({PREDICTIONS} on the modular path)"
        )
    if not isinstance(options.bayes_factor, (int, float)) or not (
        1 < options.bayes_factor < math.inf
    ):
        raise ValueError(f"structure.bayes_factor={options.bayes_factor!r} must be > 1")
    for name in ("reopen_factor", "noisy_reopen_factor"):
        if getattr(options, name) is not None:
            check_float(f"structure.{name}", getattr(options, name), 1.0, math.inf,
                        low_open=True, high_open=True)  # fmt: skip
    for name in ("prior_a", "prior_b"):
        value = getattr(options, name)
        if not (isinstance(value, (int, float)) and 0 < value < 2**20 and value * 1024 % 1 == 0):
            raise ValueError(
                f"structure.{name}={value!r}: the fast path needs a multiple of 1/1024 in "
                f"(0, 2**20)"
            )
    check_int("structure.window", options.window, 1)
    for name, known in (("likelihood", LIKELIHOODS), ("pairs", PAIR_MODES), ("reopen", REOPENINGS)):
        if getattr(options, name) not in known:
            raise ValueError(
                f"structure.{name}={getattr(options, name)!r} is unknown: choose one of {known}"
            )
    check_int("structure.change_run", options.change_run, 0, runs - 1)
    check_int("structure.curve_every", options.curve_every, 1)
    num_sensors, actuators = world.num_sensors, world.num_actuators
    sets = candidate_sets(num_sensors, options.max_parents)
    index_of = {frozenset(parents): index for index, parents in enumerate(sets)}
    orders = _check_orders("structure.orders", options.orders, count, num_sensors)
    after = orders if options.orders_after is None else options.orders_after
    after = _check_orders("structure.orders_after", after, count, num_sensors)
    truth = torch.full((count, 2, actuators), -2, dtype=torch.int64)
    dependency = world.dependency  # [A, K] in the world's order
    for phase, order in enumerate((orders, after)):
        for experiment in range(count):
            parents = dependency[:, order[experiment]]  # agent sensor j = world order[j]
            for actuator in range(actuators):
                members = frozenset(parents[actuator].nonzero().flatten().tolist())
                truth[experiment, phase, actuator] = index_of.get(members, -2)
    num_candidates, patterns = len(sets), 1 << min(options.max_parents, num_sensors)
    candidate_sensors = torch.full((num_candidates, 2), -1, dtype=torch.int64)
    for index, candidate in enumerate(sets):
        candidate_sensors[index, : len(candidate)] = torch.tensor(candidate, dtype=torch.int64)
    log_prior = candidate_log_prior(sets, options.prior)
    steps = runs * episodes * world.max_steps
    length = steps + 2  # n + 1 of every count stays inside
    log_bayes_factor = math.log(float(options.bayes_factor))
    pruned = options.pairs == "pruned" and options.max_parents >= 2 and num_sensors >= 2
    initial = initial_activity(sets)
    if not pruned:
        initial = torch.ones_like(initial)
    capacity = steps if pruned else 1  # every firing of an experiment (one per step)
    if capacity > MAX_TABLE_ENTRIES:
        raise ValueError(
            f"structure.pairs='pruned' keeps every firing of an experiment to rebuild an entering "
            f"pair: {steps} steps per experiment are past the cap of {MAX_TABLE_ENTRIES} (2**24): "
            f"use pairs='all' (--pairs all) or fewer runs, episodes or max_steps"
        )
    scored = torch.where(initial, log_prior, -math.inf)
    tables = {
        "candidate_sensors": candidate_sensors.contiguous(),
        "log_prior": log_prior.contiguous(),
        "competitors": competitor_mask(sets).to(torch.uint8).contiguous(),
        "lgamma_table": lgamma_tables(options.prior_a, options.prior_b, length).contiguous(),
        "noisy_lgamma_table": lgamma_tables(*NOISY_PRIOR, length).contiguous(),
        "orders": orders,
        "orders_after": after,
        "truth": truth,
        "initial_active": initial.to(torch.uint8).contiguous(),
        "all_candidates": torch.arange(num_candidates, dtype=torch.int16),
    }
    per_experiment = 8 * actuators * num_candidates * patterns
    counts, stride = _padded_zeros(count, (per_experiment,), torch.float64)
    curve_length = steps // options.curve_every + 1
    state = {
        "counts": counts,
        "committed": torch.full((count, actuators), -1, dtype=torch.int64),
        "samples": torch.zeros(count, actuators, dtype=torch.int64),
        "block_samples": torch.zeros(count, actuators, dtype=torch.int64),
        "reopened": torch.zeros(count, actuators, dtype=torch.int64),
        # over the initially active candidates (StructureLearner's first _refresh_cache)
        "map_cache": torch.full((count, actuators), int(scored.argmax()), dtype=torch.int64),
        "plausible": (scored >= scored.max() - log_bayes_factor)
        .to(torch.uint8)
        .expand(count, actuators, -1)
        .contiguous(),
        "right_since": torch.full((count, actuators), -1, dtype=torch.int64),
        "samples_at_change": torch.zeros(count, actuators, dtype=torch.int64),
        "wrong_commitments": torch.zeros(count, dtype=torch.int64),
        "noise_seen": torch.zeros(count, dtype=torch.int64),
        "change_tick": torch.full((count,), -1, dtype=torch.int64),
        "curve": torch.zeros(count, curve_length, dtype=torch.uint8),
        "active": initial.to(torch.uint8).expand(count, actuators, -1).contiguous(),
        "history_readings": torch.zeros(count, capacity, dtype=torch.int64),
        "history_action": torch.zeros(count, capacity, dtype=torch.uint8),
        "history_reward": torch.zeros(count, capacity, dtype=torch.float32),
        "history_length": torch.zeros(count, dtype=torch.int64),
        "history_start": torch.zeros(count, actuators, dtype=torch.int64),
        "block_start": torch.zeros(count, actuators, dtype=torch.int64),
        # the active candidates in increasing order, then padding (the kernel's loops)
        "active_list": torch.where(initial, torch.arange(num_candidates), num_candidates)
        .sort()
        .values.clamp(max=num_candidates - 1)
        .to(torch.int16)
        .expand(count, actuators, -1)
        .contiguous(),
        "active_count": torch.full((count, actuators), int(initial.sum()), dtype=torch.int64),
    }
    a, b = float(options.prior_a), float(options.prior_b)
    noisy_a, noisy_b = NOISY_PRIOR
    reopen_factor = float(
        options.bayes_factor if options.reopen_factor is None else options.reopen_factor
    )
    fields = {
        "learner": 1,
        "num_candidates": num_candidates,
        "learner_patterns": patterns,
        "prediction": _PREDICTION_CODES[options.prediction],
        "window": options.window,
        "change_run": options.change_run,
        "curve_every": options.curve_every,
        "curve_length": curve_length,
        "lgamma_length": length,
        "learner_stride": stride,
        "reopen_body": int(options.reopen == "body"),
        "likelihood_flip": int(options.likelihood == "flip"),
        "mixture": int(options.likelihood == "mixture"),
        "prune_pairs": int(pruned),
        "history_capacity": capacity,
        "log_bayes_factor": log_bayes_factor,
        "log_reopen_factor": math.log(reopen_factor),
        "log_noisy_reopen_factor": math.log(
            reopen_factor if options.noisy_reopen_factor is None else options.noisy_reopen_factor
        ),
        # as functional.beta_bernoulli_log_marginal computes it (Python's lgamma)
        "log_beta_prior": math.lgamma(a) + math.lgamma(b) - math.lgamma(a + b),
        # as functional.mixture_log_marginal computes them
        "log_noisy_beta_prior": math.lgamma(noisy_a)
        + math.lgamma(noisy_b)
        - math.lgamma(noisy_a + noisy_b),
        "log_mixture_total": math.log1p(NOISY_ODDS),
        "log_noisy_weight": math.log(NOISY_ODDS) - math.log1p(NOISY_ODDS),
    }
    return fields, tables, state, sets


def sensor_orders_setup(
    options: SensorOrders, world: WorldConfig, count: int, runs: int
) -> tuple[dict, dict[str, torch.Tensor], dict[str, torch.Tensor]]:
    """Check ``options`` of a batch of ``count`` experiments of ``runs`` runs; return fq_batch's
    fields, the orders as the kernel reads them and the state it writes (``change_tick``)."""
    if not isinstance(options, SensorOrders):
        raise TypeError(f"sensor_orders must be a SensorOrders, got {type(options).__name__}")
    check_int("sensor_orders.change_run", options.change_run, 0, runs - 1)
    orders = _check_orders("sensor_orders.orders", options.orders, count, world.num_sensors)
    after = orders if options.orders_after is None else options.orders_after
    after = _check_orders("sensor_orders.orders_after", after, count, world.num_sensors)
    state = {"change_tick": torch.full((count,), -1, dtype=torch.int64)}
    return {"change_run": options.change_run}, {"orders": orders, "orders_after": after}, state
