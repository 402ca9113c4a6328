"""Argument checks shared by every public entry point: one message format everywhere.

Errors name the argument, the value and the allowed range, e.g.
``ValueError: runs=0 is out of range: must be >= 1``.
"""

from __future__ import annotations

import collections
import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, TypeGuard

if TYPE_CHECKING:
    import torch

#: The largest value of a C ``int64_t`` (and of a torch int64 tensor entry).
INT64_MAX = 2**63 - 1
#: The largest value of a C ``int``: the cap of every count (seeds, runs, episodes, steps, buffer
#: sizes), so that the kernel's index products of counts stay far inside int64.
INT32_MAX = 2**31 - 1
#: The most threads any entry point starts (libgomp aborts and the kernel's thread pool runs out
#: of memory far above it; no machine this runs on has more cores).
MAX_THREADS = 256
#: The largest grid side: the padded cell index ``(size + 2)**2`` is a C int32 in the kernel with
#: a wide margin, and the static layout's reachability search takes about a second at this size.
MAX_SIZE = 1024
#: Values one experiment's table may hold (``factorq_torch.tables``, the fast path). Kept here, free
#: of tensordict, so that the fast path and the config checks import it cheaply.
MAX_TABLE_ENTRIES = 1 << 24
#: Parent sensors one actuator's local table may have (a table of ``2**MAX_PARENTS`` entries).
MAX_PARENTS = 16


def check_table_size(owner: str, what: str, entries: int) -> None:
    """Raise a ValueError when a table of ``entries`` values per experiment passes the cap."""
    if entries > MAX_TABLE_ENTRIES:
        raise ValueError(
            f"{owner}: {what} needs {entries} values per experiment, past the cap of "
            f"{MAX_TABLE_ENTRIES} (2**24): use fewer sensors or distractors"
        )


#: The widest hidden layer a network may ask for (far past any use; keeps allocations sane).
MAX_WIDTH = 65_536


def check_hidden(name: str, value: Any) -> tuple[int, ...]:
    """Hidden layer widths (one int, or a sequence such as ``(64, 64)``) as a tuple of ints in
    ``[1, MAX_WIDTH]``; errors name ``name`` (``hidden width=0 is out of range ...``)."""
    if is_int(value):
        value = (value,)
    if isinstance(value, str) or not isinstance(value, Sequence):
        raise TypeError(
            f"{name} must be a sequence of layer widths such as (64, 64), got {value!r}"
        )
    for width in value:
        check_int(f"{name} width", width, 1, MAX_WIDTH)
    return tuple(value)


def is_int(value: object) -> TypeGuard[int]:
    """An ``int`` that is not a ``bool``."""
    return isinstance(value, int) and not isinstance(value, bool)


def check_int(name: str, value: object, low: int, high: int | None = None, hint: str = "") -> int:
    """Return ``value`` if it is an int in ``[low, high]`` (``high=None``: no upper bound)."""
    if not is_int(value):
        raise TypeError(f"{name} must be an int, got {value!r} ({type(value).__name__})")
    if value < low or (high is not None and value > high):
        allowed = f">= {low}" if high is None else f"in [{low}, {high}]"
        raise ValueError(f"{name}={value} is out of range: must be {allowed}{hint}")
    return value


def check_seed(name: str, value: object) -> int:
    """A seed in the documented range ``[0, INT64_MAX]`` (keys are derived in 64 bits: past it
    a seed would silently equal a smaller one, ``2**80`` the same as 0)."""
    return check_int(name, value, 0, INT64_MAX)


def check_threads(name: str, value: object) -> int:
    """A thread count in ``[1, MAX_THREADS]``."""
    return check_int(name, value, 1, MAX_THREADS)


def check_float(
    name: str,
    value: object,
    low: float,
    high: float,
    *,
    low_open: bool = False,
    high_open: bool = False,
) -> float:
    """Return ``value`` if it is a finite number in the interval (open ends as flagged)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise TypeError(f"{name} must be a number, got {value!r} ({type(value).__name__})")
    if isinstance(value, int) and abs(value) > 2**1023:  # float(value) would raise OverflowError
        shown = f"{str(value)[:12]}... ({len(str(abs(value)))} digits)"
        interval = f"{'(' if low_open else '['}{low}, {high}{')' if high_open else ']'}"
        raise ValueError(f"{name}={shown} is out of range: must be in {interval}")
    below = value <= low if low_open else value < low
    above = value >= high if high_open else value > high
    if not math.isfinite(value) or below or above:
        interval = f"{'(' if low_open else '['}{low}, {high}{')' if high_open else ']'}"
        raise ValueError(f"{name}={value} is out of range: must be in {interval}")
    return value


def check_names(name: str, value: Any, allowed: tuple[str, ...] | list[str]) -> tuple[str, ...]:
    """``value`` (names, or one comma-separated string) as a tuple in ``allowed``'s order."""
    names = value.split(",") if isinstance(value, str) else list(value)
    names = [item.strip() if isinstance(item, str) else item for item in names]
    if not names:
        raise ValueError(f"{name} is empty: choose one or more of {', '.join(allowed)}")
    for item in names:
        if item not in allowed:
            raise ValueError(f"{name}: {item!r} is unknown: choose from {', '.join(allowed)}")
    counts = collections.Counter(names)  # linear: a checkpoint's config may hold 10**6 names
    duplicates = sorted(item for item, count in counts.items() if count > 1)
    if duplicates:
        raise ValueError(f"{name}: {', '.join(duplicates)} given more than once")
    return tuple(item for item in allowed if item in names)


def check_device(
    name: str, value: Any, *, allow_meta: bool = True, optional: bool = True
) -> torch.device | None:
    """``value`` as a ``torch.device`` that exists on this machine (``None`` stays ``None``).

    Checked by allocating an empty tensor there, so a missing CUDA, MPS or other backend (or a
    ``cuda:N`` past the device count) is one line where it enters (a module's constructor, a
    trainer's config) rather than a traceback once the run has begun. ``meta`` (shapes only) is
    fine for modules, which can be traced there, and refused with ``allow_meta=False`` (a run:
    nothing could be computed). ``optional=False`` refuses ``None`` as no device.
    """
    if value is None and optional:
        return None
    import torch  # the base layer's checks stay importable without torch for plain numbers

    try:
        device = torch.device(value)
    except (RuntimeError, TypeError):
        raise ValueError(
            f"{name}={value!r} is not a torch device (e.g. cpu, cuda, cuda:1)"
        ) from None
    if device.type == "meta":
        if allow_meta:
            return device
        raise ValueError(
            f"{name}={value!r} holds no data (meta tensors have shapes only): use cpu or an "
            f"accelerator"
        )
    try:
        torch.empty(0, device=device)
    except Exception as error:  # torch raises RuntimeError, AssertionError, ... per backend
        text = str(error).strip()
        reason = text.splitlines()[0].split(". ")[0].rstrip(".") if text else type(error).__name__
        if len(reason) > 100:
            reason = reason[:97] + "..."
        raise ValueError(
            f"{name}={value!r} is not available on this machine ({reason}): use {name}='cpu'"
        ) from None
    return device


def check_finite(
    owner: str, name: str, values: torch.Tensor, *, cause: str | None = None
) -> torch.Tensor:
    """Return ``values`` (a tensor ``[S, ...]``) if every entry is finite, else raise a
    ValueError naming ``owner``, the key and the first experiment (leading index) at fault.

    Cheap enough to stay on. On the CPU the sum of the values decides at once when it is finite
    (a NaN or an infinity makes every sum NaN or infinite; two ops and a memory read, no
    synchronisation), and only a sum that is not (bad values, or finite ones whose sum
    overflows) is checked entry by entry; on an accelerator it is a device-side assert
    (``torch._assert_async``) so that it never stalls the step with a device-to-host copy; on
    ``meta`` there is no data. A NaN or infinite value fed to a policy or a loss would otherwise
    spread silently through argmax ties and targets. The CPU error names the first bad value;
    ``cause`` replaces the default remedy (a diverged table or network).
    """
    import torch

    if not values.is_floating_point() or values.device.type == "meta":
        return values
    if values.device.type != "cpu":
        finite = torch.isfinite(values).all()
        torch._assert_async(finite, f"{owner}: {name} holds NaN or infinite values")
        return values
    if math.isfinite(values.sum().item()) or bool(torch.isfinite(values).all()):
        return values
    cause = cause or "a table or network diverged or was loaded from a bad state"
    where, value = _first(values, ~torch.isfinite(values))
    raise ValueError(
        f"{owner}: {name} holds NaN or infinite values{where}: {cause} (first: {value})"
    )


def _first(values: torch.Tensor, bad: torch.Tensor) -> tuple[str, object]:
    """`` (experiment i first)`` (the first experiment, leading index, holding a ``bad`` entry;
    empty for a 0-d tensor) and that experiment's first bad value."""
    if not values.dim():
        return "", values.item()
    rows, flags = values.reshape(values.shape[0], -1), bad.reshape(values.shape[0], -1)
    experiment = int(flags.any(dim=1).nonzero()[0, 0])
    return f" (experiment {experiment} first)", rows[experiment][flags[experiment]][0].item()


def check_indices(
    owner: str, name: str, values: torch.Tensor, high: int, *, what: str = "values"
) -> torch.Tensor:
    """Return ``values`` (an integer tensor ``[S, ...]``) if every entry is in ``[0, high)``,
    else raise a ValueError naming ``owner``, the key, the first experiment at fault and its
    value (a raw torch index error, or a silent read of another experiment's row, otherwise).

    As ``check_finite``: on the CPU one ``aminmax`` decides (the entries are read once), and
    only a batch out of range is searched; on an accelerator a device-side assert, no host
    synchronisation; nothing to check on ``meta``.
    """
    import torch

    if values.numel() == 0 or values.device.type == "meta":
        return values
    if values.device.type != "cpu":
        inside = ((values >= 0) & (values < high)).all()
        torch._assert_async(inside, f"{owner}: {name} holds {what} outside [0, {high})")
        return values
    low_seen, high_seen = torch.aminmax(values)
    if int(low_seen) >= 0 and int(high_seen) < high:
        return values
    where, value = _first(values, (values < 0) | (values >= high))
    raise ValueError(f"{owner}: {name} holds {what} outside [0, {high}){where}: {value}")


def check_same_device(
    owner: str, name: str, value: torch.Tensor, device: torch.device | str
) -> None:
    """Raise a ValueError naming the key when ``value`` is not on ``device`` (torch's own error
    names neither the key nor the remedy)."""
    if value.device != device:
        raise ValueError(
            f"{owner}: {name} is on {value.device} but the tables are on {device}: move the "
            f"tensordict there (td.to({str(device)!r}))"
        )
