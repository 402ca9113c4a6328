"""Constant index tensors, built once per shape and device (a step would otherwise rebuild them).

``row_starts(S, stride)`` is ``arange(S) * stride``: where row ``i`` of a ``[S, stride]`` tensor
starts in its flattened storage. The online step of ``S`` experiments indexes each experiment's
own row of a table that way, in every layer (the worlds' obstacle maps, the task and local
tables), so the constant lives here, below them all. The tensors are shared: never write them.
"""

from __future__ import annotations

import torch

#: ``(batch, stride, device, column) -> tensor``; a handful of shapes per process.
_ROW_STARTS: dict = {}
_MOST_CACHED = 32


def row_starts(
    batch: int, stride: int, device: torch.device | str | None = None, column: bool = False
) -> torch.Tensor:
    """``arange(batch) * stride`` int64 ``[batch]`` (``[batch, 1]`` with ``column``), cached.

    >>> row_starts(3, 10).tolist(), row_starts(2, 5, column=True).tolist()
    ([0, 10, 20], [[0], [5]])
    """
    device = torch.device("cpu" if device is None else device)
    key = (batch, stride, device, column)
    starts = _ROW_STARTS.get(key)
    if starts is None:
        if len(_ROW_STARTS) >= _MOST_CACHED:
            _ROW_STARTS.clear()
        starts = torch.arange(batch, device=device) * stride
        _ROW_STARTS[key] = starts = starts.unsqueeze(1) if column else starts
    return starts
