"""Building, checking and loading the fast path's kernel (``_kernel.c``): the compiler, the cache
(``cache_dir``), the ABI (``fq_batch``'s layout, the kernel's codes, and the small entry points
the differential tests call: ``tests/kernel_probes.py``). Where no compiler works,
``is_available()`` is False and ``unavailable_reason()`` says why.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shlex
import shutil
import subprocess
import tempfile
import threading
import time
from pathlib import Path

import torch

from factorq_envs.grid_world import FactoredGrid, WorldConfig

#: The env-only mode of the kernel (benchmarks): uniformly random actions (the policy stream's
#: action draw), no learning, every action counted as exploratory.
RANDOM_WALK = "random-walk"

_ALGORITHM_CODES = {RANDOM_WALK: 0, "q-learning": 1, "factor-q": 2}
_SOURCE = Path(__file__).with_name("_kernel.c")
#: No FMA contraction, no fast-math (every float op rounds as torch's do) and no -march: one build
#: for every CPU of the architecture, measured no slower (docs/decisions.md, "Portable flags").
_FLAGS = ("-O3", "-std=c99", "-ffp-contract=off", "-fno-fast-math", "-fPIC", "-shared")
_ABI_VERSION = 10
#: The fields ``fq_check_experiment`` refuses, by code (1-based), and ``fq_advance``'s encoding.
_STATE_FIELDS = tuple(
    "cell run episode episode_step scatters policy_counter periods obstacle_pads heading ticks "
    "kappa episode_collisions committed samples counts change_tick history".split()
)
_CHECK_CODES = 64

#: The kernel's codes of ``StructureOptions.prediction`` (``"posterior"`` is modular only).
_PREDICTION_CODES = {"map": 0, "committed": 1, "optimistic": 2}
#: ``fq_batch``, as _kernel.c declares it: lines of a type and its fields, in order.
_LAYOUT = """
int64 algorithm num_experiments size num_obstacles max_steps runs episodes explore_threshold
void* periods world_keys policy_keys static_grid pad_of_cell q rho kappa grid obstacle_pads cell
void* episode_step scatters policy_counter run episode bump episode_collisions
void* episode_greedy_collisions episode_task_return steps collisions greedy_collisions task_return
float gamma alpha eta_factor g_min
int64 generic num_actuators num_sensors num_layout num_headings table_width
int64 sensor_noise_threshold actuator_noise_threshold
void* moves turns offsets permutation parent_weights heading ticks
int64 q_stride rho_stride kappa_stride grid_stride obstacle_stride
int64 learner num_candidates learner_patterns prediction window change_run curve_every
int64 curve_length lgamma_length learner_stride reopen_body likelihood_flip mixture prune_pairs
int64 history_capacity
double log_bayes_factor log_reopen_factor log_noisy_reopen_factor log_beta_prior
double log_noisy_beta_prior log_mixture_total log_noisy_weight
void* candidate_sensors log_prior competitors lgamma_table noisy_lgamma_table orders orders_after
void* truth initial_active all_candidates counts committed samples block_samples reopened
void* map_cache plausible right_since samples_at_change wrong_commitments noise_seen change_tick
void* curve active history_readings history_action history_reward history_length history_start
void* block_start active_list active_count
int64 risk_gate risk_explore
float risk_threshold
"""
_CTYPES: dict[str, type] = {"int64": ctypes.c_int64, "void*": ctypes.c_void_p}
_CTYPES.update(float=ctypes.c_float, double=ctypes.c_double)


class _Batch(ctypes.Structure):
    """The kernel's ``fq_batch`` (same field order and types; its size is checked on load)."""

    _fields_ = [
        (name, _CTYPES[kind])
        for kind, *names in map(str.split, _LAYOUT.strip().splitlines())
        for name in names
    ]


class _Unavailable(Exception):
    """The kernel cannot be built or loaded; the message says why."""


_lock = threading.Lock()
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
        raise _Unavailable(f"the compiled kernel {path} does not match loader.py (stale build?)")
    batch, float32 = ctypes.POINTER(_Batch), ctypes.c_float
    signatures = {  # name: (result, arguments)
        "fq_start": (None, [batch]),
        "fq_advance": (int64, [batch, int64, ctypes.POINTER(int64)]),
        "fq_check_experiment": (int64, [batch, int64]),
        "fq_combined_values": (None, [pointer, pointer, int64, float32, float32, pointer, pointer]),
        "fq_scatter": (None, [int64] * 5 + [pointer] * 4),
    }
    for name, (result, arguments) in signatures.items():
        function = getattr(library, name)
        function.restype, function.argtypes = result, arguments


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


def _pad_of_cell(size: int) -> torch.Tensor:
    """``[size * size]`` int32: each cell's index in the grid padded by a wall ring (``[P]``)."""
    cells = torch.arange(size * size)
    return ((cells // size + 1) * (size + 2) + cells % size + 1).to(torch.int32)


#: The generic loop's limits (bit masks of the sensors, stack arrays of the actuators).
MAX_KERNEL_SENSORS = 62
MAX_KERNEL_ACTUATORS = 32


def unsupported_reason(world: object) -> str | None:
    """Why the kernel cannot run ``world`` (a ``WorldConfig`` or a ``factorq_envs.protocol.World``),
    or None when it can: every body and layout of ``factorq_envs.grid_world.FactoredGrid`` (not a
    subclass: it may change the rules) up to ``MAX_KERNEL_SENSORS`` and ``MAX_KERNEL_ACTUATORS``."""
    if type(world) is FactoredGrid:
        world = world.config
    if not isinstance(world, WorldConfig):
        return (
            f"the world is {type(world).__name__}, and the kernel mirrors only "
            f"factorq_envs.grid_world.FactoredGrid"
        )
    if world.num_sensors > MAX_KERNEL_SENSORS:
        return f"{world.num_sensors} sensors, more than its {MAX_KERNEL_SENSORS}"
    if world.num_actuators > MAX_KERNEL_ACTUATORS:
        return f"{world.num_actuators} actuators, more than its {MAX_KERNEL_ACTUATORS}"
    return None
