"""Constant index tensors, built once per shape and device (a step would otherwise rebuild them).

``constant(key, build)`` builds such a tensor once; ``row_starts(S, stride)`` is
``arange(S) * stride``: where row ``i`` of a ``[S, stride]`` tensor
starts in its flattened storage. The online step of ``S`` experiments indexes each experiment's
own row of a table that way, in every layer (the worlds' obstacle maps, the task and local
tables), so the constant lives here, below them all. The tensors are shared: never write them.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

import torch

T = TypeVar("T")

#: ``key -> value`` of ``constant``: a handful of shapes and devices per process.
_CONSTANTS: dict = {}
_MOST_CACHED = 64


def constant(key: tuple, build: Callable[[], T]) -> T:
    """``build()``, built once per ``key`` and then shared: the constant tensors a step would
    otherwise rebuild (index offsets, lookup tables). Never write what it returns.

    >>> constant(("doc", 3), lambda: torch.arange(3)) is constant(("doc", 3), lambda: None)
    True
    """
    value = _CONSTANTS.get(key)
    if value is None:
        if len(_CONSTANTS) >= _MOST_CACHED:  # shapes of another run: drop the old ones
            _CONSTANTS.clear()
        value = _CONSTANTS[key] = build()
    return value


def row_starts(
    batch: int, stride: int, device: torch.device | str | None = None, column: bool = False
) -> torch.Tensor:
    """``arange(batch) * stride`` int64 ``[batch]`` (``[batch, 1]`` with ``column``), cached.

    >>> row_starts(3, 10).tolist(), row_starts(2, 5, column=True).tolist()
    ([0, 10, 20], [[0], [5]])
    """
    device = torch.device("cpu" if device is None else device)

    def build() -> torch.Tensor:
        starts = torch.arange(batch, device=device) * stride
        return starts.unsqueeze(1) if column else starts

    return constant(("row_starts", batch, stride, device, column), build)


def scalar(value: float, like: torch.Tensor) -> torch.Tensor:
    """``value`` as a 0-d tensor of ``like``'s dtype and device, cached: an op between a small
    tensor and a Python number wraps the number in a new tensor at every call (3-5 us each on a
    ``[1, A]`` row, more than the arithmetic), while a 0-d operand computes the same values (the
    number is cast to the tensor's dtype either way, and a 0-d tensor does not promote it).

    >>> x = torch.tensor([1.0, 2.0])
    >>> torch.equal(x * scalar(1.1, x), x * 1.1), scalar(1.1, x) is scalar(1.1, x)
    (True, True)
    """
    dtype, device = like.dtype, like.device
    return constant(
        ("scalar", value, dtype, device), lambda: torch.tensor(value, dtype=dtype, device=device)
    )
