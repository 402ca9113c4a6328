"""Argument checks shared by every public entry point: one message format everywhere.

Errors name the argument, the value and the allowed range, e.g.
``ValueError: runs=0 is out of range: must be >= 1``.
"""

from __future__ import annotations

import math

#: Values one experiment's table may hold (``factorq_torch.tables``, the fast path). Kept here, free
#: of tensordict, so that the fast path and the config checks import it cheaply.
MAX_TABLE_ENTRIES = 1 << 24


def check_table_size(owner: str, what: str, entries: int) -> None:
    """Raise a ValueError when a table of ``entries`` values per experiment passes the cap."""
    if entries > MAX_TABLE_ENTRIES:
        raise ValueError(
            f"{owner}: {what} needs {entries} values per experiment, past the cap of "
            f"{MAX_TABLE_ENTRIES} (2**24): use fewer sensors or distractors"
        )


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
