"""The fused fast path: whole experiments (SPEC section 4) advanced by a small compiled C kernel.

The kernel (``_kernel.c``, plain C99) performs exactly the operations of ``factorq_envs.world`` and
``factorq_torch.functional`` in the same float32 order, with the same counter-based random streams
(``factorq_torch.base.rng``), so its metrics and tables equal the modular torch path and the slow
reference (``tests/reference.py``) bit for bit. It runs one experiment at a time for many steps
(its tables stay in the L1/L2 cache) and leaves Python only once per ``advance`` call.

The kernel is compiled on first use with the system C compiler (``cc``, ``gcc`` or ``clang``;
``FACTORQ_CC`` overrides) and cached under ``$FACTORQ_CACHE_DIR``, else
``$XDG_CACHE_HOME/factorq_torch``, else ``~/.cache/factorq_torch``. Where no compiler works,
``is_available()`` is False and ``unavailable_reason()`` says why; callers fall back to the
modular torchrl path.

>>> from factorq_envs.world import WorldConfig
>>> from factorq_torch.base.config import AgentConfig
>>> from factorq_torch.base.rng import STREAM_POLICY, STREAM_WORLD, derive_keys
>>> if is_available():
...     metrics = run_experiments(
...         "factor-q", torch.tensor([0, 1]), WorldConfig(size=5, num_obstacles=3), AgentConfig(),
...         runs=2, episodes=3, world_keys=derive_keys(0, STREAM_WORLD, 2),
...         policy_keys=derive_keys(0, STREAM_POLICY, 2))
...     print(tuple(metrics["steps"].shape))
... else:
...     print((2, 2, 3))
(2, 2, 3)
"""

from __future__ import annotations

import ctypes
import hashlib
import math
import os
import platform
import shlex
import shutil
import subprocess
import tempfile
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor, wait
from dataclasses import dataclass
from pathlib import Path

import torch

from factorq_envs.world import NUM_ACTIONS, FactoredGrid, WorldConfig, static_layout
from factorq_torch.base.config import ALGORITHMS, AgentConfig
from factorq_torch.base.keys import EPISODE_METRICS
from factorq_torch.base.rng import probability_threshold
from factorq_torch.base.validation import MAX_PARENTS, check_float, check_int, check_table_size
from factorq_torch.functional import (
    LIKELIHOODS,
    NOISY_ODDS,
    NOISY_PRIOR,
    PREDICTIONS,
    REOPENINGS,
    candidate_log_prior,
    candidate_sets,
    check_dependency,
    competitor_mask,
    lgamma_tables,
    parent_weights,
)

#: The env-only mode of the kernel (benchmarks): uniformly random actions (the policy stream's
#: action draw), no learning, every action counted as exploratory.
RANDOM_WALK = "random-walk"

_ALGORITHM_CODES = {RANDOM_WALK: 0, "q-learning": 1, "factor-q": 2}
_SOURCE = Path(__file__).with_name("_kernel.c")
#: No FMA contraction and no fast-math: every float operation must round exactly as torch's
#: separate ops do. -march=native is left out (measured no faster; keeps the cache portable).
_FLAGS = ("-O3", "-std=c99", "-ffp-contract=off", "-fno-fast-math", "-fPIC", "-shared")
_ABI_VERSION = 7
#: The fields ``fq_check_experiment`` refuses, by code (1-based), and ``fq_advance``'s encoding.
_STATE_FIELDS = (
    "cell",
    "run",
    "episode",
    "episode_step",
    "scatters",
    "policy_counter",
    "periods",
    "obstacle_pads",
    "heading",
    "ticks",
    "kappa",
    "episode_collisions",
    "committed",
    "samples",
    "counts",
    "change_tick",
)
_CHECK_CODES = 64


# --------------------------------------------------------------------------------------------
# Building and loading the kernel


#: The structure learner's pointers in fq_batch, in order (read-only ones first).
_LEARNER_POINTERS = (
    "candidate_sensors",
    "log_prior",
    "competitors",
    "lgamma_table",
    "noisy_lgamma_table",
    "orders",
    "orders_after",
    "truth",
    "counts",
    "committed",
    "samples",
    "block_samples",
    "reopened",
    "map_cache",
    "plausible",
    "right_since",
    "samples_at_change",
    "wrong_commitments",
    "change_tick",
    "curve",
)
#: The kernel's codes of ``StructureOptions.prediction`` (``"posterior"`` is modular only).
_PREDICTION_CODES = {"map": 0, "committed": 1, "optimistic": 2}


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
    likelihood: str = "mixture"
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


class _Batch(ctypes.Structure):
    """The kernel's ``fq_batch`` (same field order and types; its size is checked on load)."""

    _fields_ = (
        [
            (name, ctypes.c_int64)
            for name in (
                "algorithm",
                "num_experiments",
                "size",
                "num_obstacles",
                "max_steps",
                "runs",
                "episodes",
                "explore_threshold",
            )
        ]
        + [
            (name, ctypes.c_void_p)
            for name in (
                "periods",
                "world_keys",
                "policy_keys",
                "static_grid",
                "pad_of_cell",
                "q",
                "rho",
                "kappa",
                "grid",
                "obstacle_pads",
                "cell",
                "episode_step",
                "scatters",
                "policy_counter",
                "run",
                "episode",
                "bump",
                "episode_collisions",
                "episode_greedy_collisions",
                "episode_task_return",
                "steps",
                "collisions",
                "greedy_collisions",
                "task_return",
            )
        ]
        + [(name, ctypes.c_float) for name in ("gamma", "alpha", "eta_factor", "g_min")]
        + [
            (name, ctypes.c_int64)
            for name in (
                "generic",
                "num_actuators",
                "num_sensors",
                "num_layout",
                "num_headings",
                "table_width",
                "sensor_noise_threshold",
                "actuator_noise_threshold",
            )
        ]
        + [
            (name, ctypes.c_void_p)
            for name in (
                "moves",
                "turns",
                "offsets",
                "permutation",
                "parent_weights",
                "heading",
                "ticks",
            )
        ]
        + [(f"{name}_stride", ctypes.c_int64) for name in ("q", "rho", "kappa", "grid", "obstacle")]
        + [
            (name, ctypes.c_int64)
            for name in (
                "learner",
                "num_candidates",
                "learner_patterns",
                "prediction",
                "window",
                "change_run",
                "curve_every",
                "curve_length",
                "lgamma_length",
                "learner_stride",
                "reopen_body",
                "likelihood_flip",
                "mixture",
            )
        ]
        + [
            (name, ctypes.c_double)
            for name in (
                "log_bayes_factor",
                "log_reopen_factor",
                "log_beta_prior",
                "log_noisy_beta_prior",
                "log_mixture_total",
                "log_noisy_weight",
            )
        ]
        + [(name, ctypes.c_void_p) for name in _LEARNER_POINTERS]
    )


class _Unavailable(Exception):
    """The kernel cannot be built or loaded; the message says why."""


_lock = threading.Lock()
_executor: ThreadPoolExecutor | None = None
_executor_workers = 0
_library: ctypes.CDLL | None = None
_reason: str | None = None
_build_info: dict = {}


def cache_dir() -> Path:
    """Where compiled kernels are kept (``FACTORQ_CACHE_DIR``, ``XDG_CACHE_HOME``, ``~/.cache``)."""
    if os.environ.get("FACTORQ_CACHE_DIR"):
        return Path(os.environ["FACTORQ_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "factorq_torch"


def _compiler() -> list[str]:
    """The compiler command: ``FACTORQ_CC`` (may carry arguments) or the first of cc, gcc, clang."""
    override = os.environ.get("FACTORQ_CC")
    if override is not None:
        command = shlex.split(override)
        if not command or shutil.which(command[0]) is None:
            raise _Unavailable(f"FACTORQ_CC={override!r} is not an executable C compiler")
        return command
    for name in ("cc", "gcc", "clang"):
        if shutil.which(name):
            return [name]
    raise _Unavailable("no C compiler found (looked for cc, gcc, clang; set FACTORQ_CC)")


def _build() -> tuple[ctypes.CDLL, dict]:
    """Compile (or find in the cache) and load the kernel: ``(library, info)`` with the info of
    ``build_info()``; raise ``_Unavailable`` on failure."""
    compiler = _compiler()
    try:
        version = subprocess.run(
            [*compiler, "--version"], capture_output=True, text=True, timeout=60, check=True
        ).stdout
    except (OSError, subprocess.SubprocessError) as error:
        raise _Unavailable(f"C compiler {' '.join(compiler)!r} does not run: {error}") from error
    source = _SOURCE.read_bytes()
    # Everything the binary depends on: a change in any of them builds a new file.
    identity = "\0".join(
        [hashlib.sha256(source).hexdigest(), " ".join(compiler), " ".join(_FLAGS), version]
        + [platform.system(), platform.machine(), str(_ABI_VERSION)]
    )
    digest = hashlib.sha256(identity.encode()).hexdigest()[:20]
    directory = cache_dir()
    path = directory / f"_kernel-{digest}.so"
    compile_seconds = None
    if not path.exists():
        try:
            directory.mkdir(parents=True, exist_ok=True)
        except OSError as error:
            raise _Unavailable(f"cannot create the kernel cache {directory}: {error}") from error
        # Build under a unique name, then rename: concurrent builders (pytest workers) never see
        # a half-written file, and the last rename wins with identical content.
        try:
            handle, temporary = tempfile.mkstemp(
                prefix=f"{path.stem}-", suffix=".tmp", dir=directory
            )
        except OSError as error:
            raise _Unavailable(f"cannot write to the kernel cache {directory}: {error}") from error
        os.close(handle)
        try:
            start = time.perf_counter()
            result = subprocess.run(
                [*compiler, *_FLAGS, str(_SOURCE), "-o", temporary],
                capture_output=True,
                text=True,
                timeout=300,
            )
            compile_seconds = time.perf_counter() - start
            if result.returncode != 0:
                raise _Unavailable(
                    f"compiling {_SOURCE.name} with {' '.join(compiler)!r} failed "
                    f"(exit {result.returncode}): {result.stderr.strip()[-2000:]}"
                )
            os.chmod(temporary, 0o755)  # mkstemp made it private; a shared cache is readable
            os.replace(temporary, path)
        except (OSError, subprocess.SubprocessError) as error:
            raise _Unavailable(f"compiling {_SOURCE.name} failed: {error}") from error
        finally:
            if os.path.exists(temporary):
                os.unlink(temporary)
    try:
        library = ctypes.CDLL(str(path))
    except OSError as error:
        raise _Unavailable(f"loading the compiled kernel {path} failed: {error}") from error
    _declare(library, path)
    info = {"path": str(path), "compiled": compile_seconds is not None}
    info["seconds"] = compile_seconds or 0.0
    return library, info


def _declare(library: ctypes.CDLL, path: Path) -> None:
    """Check the kernel's ABI and declare its functions' argument types."""
    int64, pointer = ctypes.c_int64, ctypes.c_void_p
    library.fq_abi_version.restype = int64
    library.fq_batch_size.restype = int64
    if library.fq_abi_version() != _ABI_VERSION or library.fq_batch_size() != ctypes.sizeof(_Batch):
        raise _Unavailable(f"the compiled kernel {path} does not match fast.py (stale build?)")
    batch = ctypes.POINTER(_Batch)
    library.fq_start.argtypes = [batch]
    library.fq_start.restype = None
    library.fq_advance.argtypes = [batch, int64, ctypes.POINTER(int64)]
    library.fq_advance.restype = int64
    library.fq_check_experiment.argtypes = [batch, int64]
    library.fq_check_experiment.restype = int64
    library.fq_combined_values.argtypes = [pointer, pointer, int64, ctypes.c_float]
    library.fq_combined_values.argtypes += [ctypes.c_float, pointer, pointer]
    library.fq_combined_values.restype = None
    library.fq_scatter.argtypes = [int64] * 5 + [pointer] * 4
    library.fq_scatter.restype = None


def _load() -> ctypes.CDLL | None:
    """The loaded kernel, building it on the first call; None (with ``_reason``) if impossible."""
    global _library, _reason
    with _lock:
        if _library is None and _reason is None:
            try:
                _library, info = _build()
                _build_info.update(info)
            except _Unavailable as error:
                _reason = str(error)
        return _library


def is_available() -> bool:
    """Whether the compiled kernel can be used here (builds it on the first call)."""
    return _load() is not None


def unavailable_reason() -> str | None:
    """Why the kernel cannot be used, or None when it can."""
    _load()
    return _reason


def build_info() -> dict:
    """``path`` of the loaded kernel, whether this process ``compiled`` it, and in how many
    ``seconds`` (empty when unavailable)."""
    _load()
    return dict(_build_info)


def _require() -> ctypes.CDLL:
    library = _load()
    if library is None:
        raise RuntimeError(f"the factorq_torch fast path is unavailable: {_reason}")
    return library


def kernel_combined_values(
    q: torch.Tensor, rho: torch.Tensor, eta: float, g_min: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """The kernel's eq. 2-3 on rows of ``q``, ``rho`` ``[n, 4]`` float32: ``(G [n], C [n, 4])``.

    For differential tests against ``functional.normaliser`` and ``functional.combined_values``.
    """
    library = _require()
    q = q.detach().to(torch.float32).contiguous().view(-1, NUM_ACTIONS)
    rho = rho.detach().to(torch.float32).contiguous().view(-1, NUM_ACTIONS)
    if q.shape != rho.shape:
        raise ValueError(f"q {tuple(q.shape)} and rho {tuple(rho.shape)} must have one shape")
    g = torch.empty(q.shape[0], dtype=torch.float32)
    out = torch.empty_like(q)
    eta_factor, rows = 1 + eta, q.shape[0]
    library.fq_combined_values(
        q.data_ptr(), rho.data_ptr(), rows, eta_factor, g_min, g.data_ptr(), out.data_ptr()
    )
    return g, out


def kernel_scatter(
    size: int, num_obstacles: int, key: int, scatter_index: int, agent: int
) -> torch.Tensor:
    """The kernel's obstacle scatter for one world: ``[size * size]`` bool.

    For differential tests against ``factorq_envs.world.scatter_obstacles``.
    """
    library = _require()
    WorldConfig(size=size, num_obstacles=num_obstacles)  # validates the pair
    num_cells, width = size * size, size + 2
    cells = torch.arange(num_cells)
    pad_of_cell = ((cells // size + 1) * width + cells % size + 1).to(torch.int32)
    grid = torch.empty(width * width, dtype=torch.uint8)
    pads = torch.empty(max(num_obstacles, 1), dtype=torch.int32)
    blocked = torch.empty(num_cells, dtype=torch.uint8)
    library.fq_scatter(
        size,
        num_obstacles,
        key,
        scatter_index,
        agent,
        pad_of_cell.data_ptr(),
        grid.data_ptr(),
        pads.data_ptr(),
        blocked.data_ptr(),
    )
    return blocked.bool()


#: The generic loop's limits (bit masks of the sensors, stack arrays of the actuators).
MAX_KERNEL_SENSORS = 62
MAX_KERNEL_ACTUATORS = 32


def unsupported_reason(world) -> str | None:
    """Why the kernel cannot run ``world``, or None when it can (every body and layout of
    ``factorq_envs.body`` up to ``MAX_KERNEL_SENSORS`` sensors and ``MAX_KERNEL_ACTUATORS``
    actuators).

    ``world`` is a ``WorldConfig`` or an ``factorq_envs.protocol.World``: the kernel mirrors only
    ``factorq_envs.world``'s ``FactoredGrid``, so any other world (a foreign one, or a subclass that
    may change its rules) is refused here and runs on the modular path."""
    if type(world) is FactoredGrid:
        world = world.config
    if not isinstance(world, WorldConfig):
        return (
            f"the world is {type(world).__name__}, and the kernel mirrors only "
            f"factorq_envs.world.FactoredGrid"
        )
    if world.num_sensors > MAX_KERNEL_SENSORS:
        return f"{world.num_sensors} sensors, more than its {MAX_KERNEL_SENSORS}"
    if world.num_actuators > MAX_KERNEL_ACTUATORS:
        return f"{world.num_actuators} actuators, more than its {MAX_KERNEL_ACTUATORS}"
    return None


def _pool(workers: int) -> ThreadPoolExecutor:
    """A process-wide pool of at least ``workers`` helper threads (kept between calls: starting
    threads on every ``advance`` costs more than short chunks of work)."""
    global _executor, _executor_workers
    with _lock:
        if _executor is None or _executor_workers < workers:
            if _executor is not None:
                _executor.shutdown(wait=False)
            _executor = ThreadPoolExecutor(workers, thread_name_prefix="factorq-fast")
            _executor_workers = workers
        return _executor


def _wait_uninterrupted(futures: list) -> None:
    """Wait until every future is done, whatever interrupts arrive meanwhile (a second Ctrl-C
    must not skip the wait either); the futures' own errors are left to their callers."""
    pending = list(futures)
    while pending:
        try:
            wait(pending)
        except KeyboardInterrupt:
            pass
        pending = [future for future in pending if not future.done()]


# --------------------------------------------------------------------------------------------
# Argument checks


#: Bytes of a cache line. Each experiment's blocks that the kernel writes in its inner loop start
#: on a line of their own, so that two threads never write one line (false sharing).
CACHE_LINE = 64


def _padded_zeros(count: int, shape: tuple[int, ...], dtype: torch.dtype):
    """``(view, stride)``: zeros ``[count, *shape]`` as a view of a ``[count, stride]`` storage
    whose rows are whole cache lines (torch's CPU allocator aligns the storage itself to 64)."""
    per_line = CACHE_LINE // torch.empty((), dtype=dtype).element_size()
    numel = 1
    for extent in shape:
        numel *= extent
    stride = max(-(-numel // per_line) * per_line, per_line)
    return torch.zeros(count, stride, dtype=dtype)[:, :numel].unflatten(1, shape), stride


def _check_vector(name: str, value, count: int | None) -> torch.Tensor:
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


def _check_orders(name: str, orders, count: int, num_sensors: int) -> torch.Tensor:
    """``[count, K]`` int64, every row a permutation of ``range(K)``."""
    if not isinstance(orders, torch.Tensor) or orders.dtype != torch.int64:
        raise TypeError(f"{name} must be an int64 tensor [experiments, sensors]")
    if tuple(orders.shape) != (count, num_sensors):
        raise ValueError(f"{name} has shape {list(orders.shape)}, expected {[count, num_sensors]}")
    expected = torch.arange(num_sensors).expand(count, -1)
    if not torch.equal(orders.cpu().sort(dim=-1).values, expected):
        raise ValueError(f"{name}: every row must hold each of 0..{num_sensors - 1} once")
    return orders.detach().cpu().contiguous().clone()


def _check_threads(threads) -> int:
    if threads is None:
        return torch.get_num_threads()
    return check_int("threads", threads, 1)


# --------------------------------------------------------------------------------------------
# The batch


class ExperimentBatch:
    """S independent experiments of one algorithm, state in tensors, advanced by the C kernel.

    Experiment ``i`` is ``runs`` x ``episodes`` episodes of ``algorithm`` in a world with obstacle
    period ``periods[i]``, drawing from ``world_keys[i]`` and ``policy_keys[i]`` (from
    ``rng.derive_keys``); it gives the same numbers alone or in any batch, whatever the thread
    count and however ``advance`` is chunked. ``algorithm`` is ``"q-learning"``, ``"factor-q"`` or
    ``RANDOM_WALK`` (env only, for benchmarks). Not safe to advance from two threads at once.
    """

    def __init__(
        self,
        algorithm: str,
        periods: torch.Tensor,
        world: WorldConfig,
        agent: AgentConfig,
        runs: int,
        episodes: int,
        world_keys: torch.Tensor,
        policy_keys: torch.Tensor,
        threads: int | None = None,
        dependency: torch.Tensor | None = None,
        structure: StructureOptions | None = None,
        sensor_orders: SensorOrders | None = None,
    ) -> None:
        if algorithm not in _ALGORITHM_CODES:
            choices = ", ".join((*ALGORITHMS, RANDOM_WALK))
            raise ValueError(f"algorithm={algorithm!r} is unknown: choose one of {choices}")
        if not isinstance(world, WorldConfig):
            raise TypeError(f"world must be a WorldConfig, got {type(world).__name__}")
        if not isinstance(agent, AgentConfig):
            raise TypeError(f"agent must be an AgentConfig, got {type(agent).__name__}")
        unsupported = unsupported_reason(world)
        if unsupported is not None:
            raise ValueError(f"world: the fast path cannot run this world: {unsupported}")
        periods = _check_vector("periods", periods, None)
        if bool((periods < 0).any()):
            raise ValueError(
                f"periods must be >= 0 (0 static, k > 0 moving), got {periods.min().item()}"
            )
        count = periods.numel()
        self.algorithm = algorithm
        self.world = world
        self.agent = agent
        self.runs = check_int("runs", runs, 1)
        self.episodes = check_int("episodes", episodes, 1)
        self.threads = _check_threads(threads)
        self._library = _require()
        world_keys = _check_vector("world_keys", world_keys, count)
        policy_keys = _check_vector("policy_keys", policy_keys, count)

        size, num_cells = world.size, world.num_cells
        width = size + 2
        cells = torch.arange(num_cells)
        pad_of_cell = ((cells // size + 1) * width + cells % size + 1).to(torch.int32)  # [N]
        static_grid = torch.ones(width * width, dtype=torch.uint8)  # [P], the wall ring is 1
        static_grid[pad_of_cell.long()] = 0
        if bool((periods == 0).any()) and world.num_obstacles:
            static_grid[pad_of_cell.long()] = static_layout(world).to(torch.uint8)
        # The body as data (factorq_envs.body): the paper's body runs the specialised loop.
        # ``dependency`` (bool [A, K]) replaces the world's true one in Factor-Q's local tables,
        # e.g. the full joint table over all sensors (factorq_trainers.experiments.dependencies);
        # only in the generic loop.
        generic = not world.is_paper_body or dependency is not None or structure is not None
        generic = generic or sensor_orders is not None
        num_actuators, num_sensors = world.num_actuators, world.num_sensors
        positions = num_cells * world.num_headings
        num_states = positions << num_sensors if algorithm == "q-learning" else positions
        if algorithm == "q-learning":
            check_table_size(
                "ExperimentBatch", f"a Q-table of {num_states} states", num_states * num_actuators
            )
        if algorithm == RANDOM_WALK:
            num_states = 0
        if dependency is None:
            dependency = world.dependency
        else:
            dependency = check_dependency(dependency, world.num_sensors)
            if dependency.shape[0] != world.num_actuators:
                raise ValueError(
                    f"dependency has {dependency.shape[0]} actuators, the body has "
                    f"{world.num_actuators}"
                )
        parents = int(dependency.sum(dim=1).max())
        check_int("parents of an actuator (dependency)", parents, 0, MAX_PARENTS)
        table_width = 1 << parents
        offsets = world._tables["offsets"]  # [4, L, 2]
        body_tensors = {
            "moves": world._tables["moves"].to(torch.int64).contiguous(),
            "turns": world._tables["turns"].to(torch.int64).contiguous(),
            "offsets": (offsets[..., 0] * width + offsets[..., 1]).contiguous(),  # [4, L]
            "permutation": world._tables["permutation"].to(torch.int64).contiguous(),
            "parent_weights": parent_weights(dependency).contiguous(),  # [A, K]
        }
        experiment_shape = (count, self.runs, self.episodes)

        def zeros(*shape, dtype=torch.int64):
            return torch.zeros(shape, dtype=dtype)

        # Written in the kernel's inner loop: one cache-line-aligned block per experiment.
        q, q_stride = _padded_zeros(count, (num_states, num_actuators), torch.float32)
        rho, rho_stride = _padded_zeros(count, (num_actuators, table_width), torch.float32)
        kappa, kappa_stride = _padded_zeros(count, (num_actuators, table_width), torch.int64)
        grid, grid_stride = _padded_zeros(count, (width * width,), torch.uint8)
        obstacle_pads, obstacle_stride = _padded_zeros(count, (world.num_obstacles,), torch.int32)

        # Every tensor the kernel reads or writes, by its fq_batch field name.
        self._tensors: dict[str, torch.Tensor] = {
            "periods": periods,  # [S]
            "world_keys": world_keys,  # [S]
            "policy_keys": policy_keys,  # [S]
            "static_grid": static_grid,  # [P]
            "pad_of_cell": pad_of_cell,  # [N]
            "q": q,  # [S, states, actuator]
            "rho": rho,  # [S, actuator, pattern of its parents]
            "kappa": kappa,
            "grid": grid,  # [S, P]
            "obstacle_pads": obstacle_pads,  # [S, K]
            "cell": zeros(count),
            "episode_step": zeros(count),
            "scatters": zeros(count),
            "policy_counter": zeros(count),
            "run": zeros(count),
            "episode": zeros(count),
            "bump": zeros(count, num_actuators, dtype=torch.uint8),
            "heading": zeros(count),
            "ticks": zeros(count),
            "episode_collisions": zeros(count),
            "episode_greedy_collisions": zeros(count),
            "episode_task_return": zeros(count, dtype=torch.float32),
            "steps": zeros(*experiment_shape),
            "collisions": zeros(*experiment_shape),
            "greedy_collisions": zeros(*experiment_shape),
            "task_return": zeros(*experiment_shape, dtype=torch.float32),
        }
        if structure is not None and sensor_orders is not None:
            raise ValueError("sensor_orders: give the orders in structure (StructureOptions)")
        learner_fields = self._structure(structure, algorithm, world, count)
        if sensor_orders is not None:
            learner_fields.update(self._sensor_orders(sensor_orders, world, count))
        self._body = body_tensors  # read-only; kept alive for the kernel's pointers
        pointers = {
            name: tensor.data_ptr()
            for name, tensor in (
                *self._tensors.items(),
                *body_tensors.items(),
                *self._learner_tables.items(),
            )
        }
        self._batch = _Batch(
            algorithm=_ALGORITHM_CODES[algorithm],
            num_experiments=count,
            size=size,
            num_obstacles=world.num_obstacles,
            max_steps=world.max_steps,
            runs=self.runs,
            episodes=self.episodes,
            explore_threshold=probability_threshold(agent.epsilon),
            gamma=agent.gamma,
            alpha=agent.alpha,
            eta_factor=1 + agent.eta,
            g_min=agent.g_min,
            generic=int(generic),
            num_actuators=num_actuators,
            num_sensors=num_sensors,
            num_layout=world.layout.num_sensors,
            num_headings=world.num_headings,
            table_width=table_width,
            sensor_noise_threshold=probability_threshold(world.sensor_noise),
            actuator_noise_threshold=probability_threshold(world.actuator_noise),
            q_stride=q_stride,
            rho_stride=rho_stride,
            kappa_stride=kappa_stride,
            grid_stride=grid_stride,
            obstacle_stride=obstacle_stride,
            **learner_fields,
            **pointers,
        )
        self._library.fq_start(ctypes.byref(self._batch))

    def _structure(
        self, options: StructureOptions | None, algorithm: str, world: WorldConfig, count: int
    ) -> dict:
        """Check ``options``, allocate the learner's state (in ``self._tensors``) and read-only
        tables (in ``self._learner_tables``); return fq_batch's scalar fields."""
        self.structure = options
        self._learner_tables: dict[str, torch.Tensor] = {}
        if options is None:
            return {"learner": 0}
        if not isinstance(options, StructureOptions):
            raise TypeError(f"structure must be a StructureOptions, got {type(options).__name__}")
        if algorithm != "factor-q":
            raise ValueError(
                f"structure: the structure learner runs with factor-q, not {algorithm}"
            )
        if options.prediction not in _PREDICTION_CODES:
            raise ValueError(
                f"structure.prediction={options.prediction!r}: the fast path runs "
                f"{tuple(_PREDICTION_CODES)} ({PREDICTIONS} on the modular path)"
            )
        if not isinstance(options.bayes_factor, (int, float)) or not (
            1 < options.bayes_factor < math.inf
        ):
            raise ValueError(f"structure.bayes_factor={options.bayes_factor!r} must be > 1")
        if options.reopen_factor is not None:
            check_float(
                "structure.reopen_factor",
                options.reopen_factor,
                1.0,
                math.inf,
                low_open=True,
                high_open=True,
            )
        for name in ("prior_a", "prior_b"):
            value = getattr(options, name)
            if (
                not isinstance(value, (int, float))
                or not (0 < value < 2**20)
                or (value * 1024 != int(value * 1024))
            ):
                raise ValueError(
                    f"structure.{name}={value!r}: the fast path needs a multiple of 1/1024 in "
                    f"(0, 2**20)"
                )
        check_int("structure.window", options.window, 1)
        if options.likelihood not in LIKELIHOODS:
            raise ValueError(
                f"structure.likelihood={options.likelihood!r} is unknown: choose one of "
                f"{LIKELIHOODS}"
            )
        if options.reopen not in REOPENINGS:
            raise ValueError(
                f"structure.reopen={options.reopen!r} is unknown: choose one of {REOPENINGS}"
            )
        check_int("structure.change_run", options.change_run, 0, self.runs - 1)
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
        for index, parents in enumerate(sets):
            candidate_sensors[index, : len(parents)] = torch.tensor(parents, dtype=torch.int64)
        log_prior = candidate_log_prior(sets, options.prior)
        steps = self.runs * self.episodes * world.max_steps
        length = steps + 2  # n + 1 of every count stays inside
        self._learner_tables = {
            "candidate_sensors": candidate_sensors.contiguous(),
            "log_prior": log_prior.contiguous(),
            "competitors": competitor_mask(sets).to(torch.uint8).contiguous(),
            "lgamma_table": lgamma_tables(options.prior_a, options.prior_b, length).contiguous(),
            "noisy_lgamma_table": lgamma_tables(*NOISY_PRIOR, length).contiguous(),
            "orders": orders,
            "orders_after": after,
            "truth": truth,
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
            "map_cache": torch.full((count, actuators), int(log_prior.argmax()), dtype=torch.int64),
            "plausible": (log_prior >= log_prior.max() - math.log(float(options.bayes_factor)))
            .to(torch.uint8)
            .expand(count, actuators, -1)
            .contiguous(),
            "right_since": torch.full((count, actuators), -1, dtype=torch.int64),
            "samples_at_change": torch.zeros(count, actuators, dtype=torch.int64),
            "wrong_commitments": torch.zeros(count, dtype=torch.int64),
            "change_tick": torch.full((count,), -1, dtype=torch.int64),
            "curve": torch.zeros(count, curve_length, dtype=torch.uint8),
        }
        self._tensors.update(state)
        self._candidate_sets = sets
        a, b = float(options.prior_a), float(options.prior_b)
        noisy_a, noisy_b = NOISY_PRIOR
        return {
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
            "log_bayes_factor": math.log(float(options.bayes_factor)),
            "log_reopen_factor": math.log(
                float(
                    options.bayes_factor if options.reopen_factor is None else options.reopen_factor
                )
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

    def _sensor_orders(self, options: SensorOrders, world: WorldConfig, count: int) -> dict:
        """Check ``options``; keep its orders for the kernel; return fq_batch's fields."""
        if not isinstance(options, SensorOrders):
            raise TypeError(f"sensor_orders must be a SensorOrders, got {type(options).__name__}")
        check_int("sensor_orders.change_run", options.change_run, 0, self.runs - 1)
        orders = _check_orders("sensor_orders.orders", options.orders, count, world.num_sensors)
        after = orders if options.orders_after is None else options.orders_after
        after = _check_orders("sensor_orders.orders_after", after, count, world.num_sensors)
        self._learner_tables.update(orders=orders, orders_after=after)
        self._tensors["change_tick"] = torch.full((count,), -1, dtype=torch.int64)
        return {"change_run": options.change_run}

    def learner_state(self) -> dict[str, torch.Tensor]:
        """The structure learner's state and bookkeeping (copies): ``committed``, ``samples``,
        ``block_samples``, ``reopened``, ``map_cache``, ``right_since``, ``samples_at_change``
        ``[S, A]``; ``wrong_commitments``, ``change_tick`` ``[S]``; ``curve`` ``[S, points]``;
        the counts as ``count``, ``successes``, ``reward_sum``, ``log_marginal`` and their
        ``block_`` twins ``[S, A, C, P]``; ``truth`` ``[S, 2, A]`` (candidate indices)."""
        if self.structure is None:
            raise RuntimeError("this batch runs no structure learner")
        names = ("count", "successes", "reward_sum", "log_marginal")
        # the learner's own state: the pointers after its counts (committed ... curve)
        own = _LEARNER_POINTERS[_LEARNER_POINTERS.index("counts") + 1 :]
        state = {name: self._tensors[name].clone() for name in own}
        shape = (self.num_experiments, 8, self.world.num_actuators, self._batch.num_candidates)
        counts = self._tensors["counts"].reshape(*shape, self._batch.learner_patterns)
        for index, name in enumerate((*names, *("block_" + name for name in names))):
            state[name] = counts[:, index].clone()
        state["truth"] = self._learner_tables["truth"].clone()
        return state

    @property
    def num_experiments(self) -> int:
        return self._batch.num_experiments

    @property
    def done(self) -> bool:
        """All experiments have finished their runs x episodes."""
        return bool((self._tensors["run"] >= self.runs).all())

    @property
    def experiments_finished(self) -> int:
        """Experiments that have finished all their runs x episodes."""
        return int((self._tensors["run"] >= self.runs).sum())

    @property
    def episodes_completed(self) -> int:
        """Episodes finished so far, summed over the experiments."""
        run, episode = self._tensors["run"], self._tensors["episode"]
        return int((run * self.episodes + episode).sum())

    @property
    def total_steps(self) -> int:
        """Env steps taken so far, summed over the experiments (one policy decision per step)."""
        return int(self._tensors["policy_counter"].sum())

    def advance(self, max_steps: int) -> int:
        """Run each unfinished experiment for up to ``max_steps`` more env steps (stopping early
        at its end); return the number of episodes completed in this call (all experiments)."""
        check_int("max_steps", max_steps, 0)
        if max_steps == 0 or self.done:
            return 0
        next_experiment = ctypes.c_int64(0)
        arguments = (ctypes.byref(self._batch), max_steps, ctypes.byref(next_experiment))
        threads = min(self.threads, self.num_experiments)
        if threads == 1:
            return self._checked([self._library.fq_advance(*arguments)])
        # ctypes releases the GIL during the call: each thread takes whole experiments from the
        # shared counter until none is left (results never depend on who ran what).
        pool = _pool(threads - 1)
        helpers = [pool.submit(self._library.fq_advance, *arguments) for _ in range(threads - 1)]
        try:
            completed = self._library.fq_advance(*arguments)
            results = [completed, *(helper.result() for helper in helpers)]
        except BaseException:
            # An interrupt (Ctrl-C) or an error here must not unwind while a helper still runs
            # the kernel on this batch: leaving would free the batch (and the shared counter)
            # under it, a crash. Wait for them (each finishes its current chunk), then raise.
            _wait_uninterrupted(helpers)
            raise
        return self._checked(results)

    def _checked(self, results: list[int]) -> int:
        """The episodes completed, or the kernel's refusal of a state out of range (ValueError)."""
        refused = [result for result in results if result < 0]
        if refused:
            experiment, code = divmod(-refused[0] - 1, _CHECK_CODES)
            field = _STATE_FIELDS[code - 1] if 0 < code <= len(_STATE_FIELDS) else f"code {code}"
            raise ValueError(
                f"the fast kernel refused experiment {experiment}: its {field} is out of range "
                f"(the state was loaded from a bad checkpoint or edited)"
            )
        return sum(results)

    def metrics(self) -> dict[str, torch.Tensor]:
        """Per-episode ``steps``, ``collisions``, ``greedy_collisions`` (int64) and
        ``task_return`` (float32), each ``[S, runs, episodes]``; zeros where not yet played."""
        return {name: self._tensors[name].clone() for name in EPISODE_METRICS}

    def tables(self) -> dict[str, torch.Tensor]:
        """The learned tables: ``q`` ``[S, states, 4]``, ``rho`` ``[S, 4, 2]`` (float32) and
        ``kappa`` ``[S, 4, 2]`` (int64; indexed by actuator, then sensor value)."""
        return {name: self._tensors[name].clone() for name in ("q", "rho", "kappa")}

    def state_dict(self) -> dict[str, torch.Tensor]:
        """Everything needed to resume exactly: tables, world state, stream positions, counters,
        partial metrics, and the batch's identity (periods and keys, checked on load)."""
        state = {
            name: tensor.clone()
            for name, tensor in self._tensors.items()
            if name not in ("static_grid", "pad_of_cell", "grid", "obstacle_pads", "bump")
        }
        pads = self._tensors["pad_of_cell"].long()
        state["obstacles"] = self._tensors["grid"][:, pads].bool()  # [S, N]
        state["bump"] = self._tensors["bump"].bool()  # [S, 4]
        return state

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        """Restore a ``state_dict`` of a batch built with the same arguments."""
        expected = self.state_dict()
        missing = sorted(set(expected) - set(state))
        unexpected = sorted(set(state) - set(expected))
        if missing or unexpected:
            raise KeyError(f"state_dict mismatch: missing {missing}, unexpected {unexpected}")
        for name, reference in expected.items():
            value = state[name]
            if not isinstance(value, torch.Tensor):
                raise TypeError(f"state[{name!r}] must be a tensor, got {type(value).__name__}")
            if value.shape != reference.shape or value.dtype != reference.dtype:
                raise ValueError(
                    f"state[{name!r}] has shape {tuple(value.shape)} and dtype {value.dtype}, "
                    f"expected {tuple(reference.shape)} and {reference.dtype}"
                )
        for name in ("periods", "world_keys", "policy_keys"):
            if not torch.equal(state[name], expected[name]):
                raise ValueError(f"state[{name!r}] belongs to a different batch")
        obstacles = state["obstacles"]  # [S, N]
        counts = obstacles.sum(dim=1)
        if bool((counts != self.world.num_obstacles).any()):
            raise ValueError(
                f"state['obstacles'] must hold num_obstacles={self.world.num_obstacles} per world"
            )
        if bool((state["cell"] < 0).any()) or bool((state["cell"] >= self.world.num_cells).any()):
            raise ValueError(f"state['cell'] must be in [0, {self.world.num_cells})")
        # In place: the kernel holds these tensors' data pointers.
        for name, tensor in self._tensors.items():
            if name in state and name not in ("bump",):
                tensor.copy_(state[name])
        pads = self._tensors["pad_of_cell"].long()
        grid = self._tensors["grid"]
        grid[:, pads] = obstacles.to(torch.uint8)
        cells = obstacles.nonzero()[:, 1].view(self.num_experiments, self.world.num_obstacles)
        self._tensors["obstacle_pads"].copy_(pads[cells])
        self._tensors["bump"].copy_(state["bump"])


def run_experiments(
    algorithm: str,
    periods: torch.Tensor,
    world: WorldConfig,
    agent: AgentConfig,
    runs: int,
    episodes: int,
    world_keys: torch.Tensor,
    policy_keys: torch.Tensor,
    *,
    threads: int | None = None,
    progress: Callable[[int], object] | None = None,
    dependency: torch.Tensor | None = None,
    structure: StructureOptions | None = None,
    sensor_orders: SensorOrders | None = None,
) -> dict[str, torch.Tensor]:
    """Run S experiments to the end (see ``ExperimentBatch``) and return their ``metrics()``.

    ``progress(n)`` is called with the number of episodes completed since its last call;
    ``dependency`` replaces the world's in Factor-Q's local tables (``ExperimentBatch``).
    """
    batch = ExperimentBatch(
        algorithm,
        periods,
        world,
        agent,
        runs,
        episodes,
        world_keys,
        policy_keys,
        threads,
        dependency=dependency,
        structure=structure,
        sensor_orders=sensor_orders,
    )
    # Chunks only matter for progress reports (results do not depend on them).
    chunk = 20_000 if progress is not None else 1 << 62
    while not batch.done:
        completed = batch.advance(chunk)
        if progress is not None and completed:
            progress(completed)
    return batch.metrics()
