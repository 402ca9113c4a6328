"""Argument checks shared by every public entry point: one message format everywhere.

Errors name the argument, the value and the allowed range, e.g.
``ValueError: runs=0 is out of range: must be >= 1``.
"""

from __future__ import annotations

import math


def is_int(value) -> bool:
    """An ``int`` that is not a ``bool``."""
    return isinstance(value, int) and not isinstance(value, bool)


def check_int(name: str, value, low: int, high: int | None = None, hint: str = "") -> int:
    """Return ``value`` if it is an int in ``[low, high]`` (``high=None``: no upper bound)."""
    if not is_int(value):
        raise TypeError(f"{name} must be an int, got {value!r} ({type(value).__name__})")
    if value < low or (high is not None and value > high):
        allowed = f">= {low}" if high is None else f"in [{low}, {high}]"
        raise ValueError(f"{name}={value} is out of range: must be {allowed}{hint}")
    return value


def check_float(
    name: str, value, low: float, high: float, *, low_open: bool = False, high_open: bool = False
) -> float:
    """Return ``value`` if it is a finite number in the interval (open ends as flagged)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise TypeError(f"{name} must be a number, got {value!r} ({type(value).__name__})")
    below = value <= low if low_open else value < low
    above = value >= high if high_open else value > high
    if not math.isfinite(value) or below or above:
        interval = f"{'(' if low_open else '['}{low}, {high}{')' if high_open else ']'}"
        raise ValueError(f"{name}={value} is out of range: must be in {interval}")
    return value


def check_names(name: str, value, allowed: tuple[str, ...] | list[str]) -> tuple[str, ...]:
    """``value`` (names, or one comma-separated string) as a tuple in ``allowed``'s order."""
    names = value.split(",") if isinstance(value, str) else list(value)
    names = [item.strip() if isinstance(item, str) else item for item in names]
    if not names:
        raise ValueError(f"{name} is empty: choose one or more of {', '.join(allowed)}")
    for item in names:
        if item not in allowed:
            raise ValueError(f"{name}: {item!r} is unknown: choose from {', '.join(allowed)}")
    duplicates = sorted({item for item in names if names.count(item) > 1})
    if duplicates:
        raise ValueError(f"{name}: {', '.join(duplicates)} given more than once")
    return tuple(item for item in allowed if item in names)


def check_device(name: str, device):
    """``device`` as a ``torch.device`` (``None`` stays ``None``), refused with one message when it
    is no device or names an accelerator this torch cannot use (e.g. ``cuda`` on a CPU build)."""
    if device is None:
        return None
    import torch  # the base layer's checks stay importable without torch for plain numbers

    try:
        device = torch.device(device)
    except (RuntimeError, TypeError) as error:
        raise ValueError(
            f"{name}={device!r} is not a torch device (e.g. cpu, cuda, cuda:1): {error}"
        ) from None
    if device.type == "cuda":
        if not torch.cuda.is_available():
            build = "a CPU-only build" if torch.version.cuda is None else "no visible GPU"
            raise ValueError(
                f"{name}={str(device)!r} but this torch ({torch.__version__}) has no CUDA "
                f"device ({build}): use {name}='cpu'"
            )
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise ValueError(
                f"{name}={str(device)!r} but only {torch.cuda.device_count()} CUDA device(s) "
                f"are visible"
            )
    elif device.type == "mps" and not torch.backends.mps.is_available():
        raise ValueError(f"{name}={str(device)!r} but MPS is not available here: use 'cpu'")
    return device
