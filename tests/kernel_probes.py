"""The compiled kernel's small entry points, called through ctypes for differential tests: its
eqs. 2-3 (``fq_combined_values``) against ``factorq_torch.functional``, its obstacle scatter
(``fq_scatter``) against ``factorq_envs.grid_world.scatter_obstacles``. Only tests call them, so
they live here, beside ``reference.py``; the kernel declares both (``loader._declare``)."""

from __future__ import annotations

import torch

from factorq_envs.grid_world import NUM_ACTIONS, WorldConfig
from factorq_torch.base.validation import INT64_MAX, check_int
from factorq_trainers.compiled.loader import _pad_of_cell, _require


def kernel_combined_values(
    q: torch.Tensor, rho: torch.Tensor, eta: float, g_min: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """The kernel's eq. 2-3 on rows of ``q``, ``rho`` ``[n, 4]`` float32: ``(G [n], C [n, 4])``,
    for differential tests against ``functional.normaliser`` and ``functional.combined_values``."""
    library = _require()
    q = q.detach().to(torch.float32).contiguous().view(-1, NUM_ACTIONS)
    rho = rho.detach().to(torch.float32).contiguous().view(-1, NUM_ACTIONS)
    if q.shape != rho.shape:
        raise ValueError(f"q {tuple(q.shape)} and rho {tuple(rho.shape)} must have one shape")
    g, out, rows = torch.empty(q.shape[0], dtype=torch.float32), torch.empty_like(q), q.shape[0]
    library.fq_combined_values(
        q.data_ptr(), rho.data_ptr(), rows, 1 + eta, g_min, g.data_ptr(), out.data_ptr()
    )
    return g, out


def kernel_scatter(
    size: int, num_obstacles: int, key: int, scatter_index: int, agent: int
) -> torch.Tensor:
    """The kernel's obstacle scatter for one world, ``[size * size]`` bool, for differential
    tests against ``factorq_envs.grid_world.scatter_obstacles``."""
    library = _require()
    WorldConfig(size=size, num_obstacles=num_obstacles)  # validates the pair
    # ctypes wraps ints into int64 silently (a key of 2**64 would be key 0): keys are int64 bit
    # patterns (``rng.derive_keys``), the counter and the cell are indices
    check_int("key", key, -(2**63), INT64_MAX)
    check_int("scatter_index", scatter_index, 0, INT64_MAX)
    check_int("agent", agent, 0, size * size - 1)
    num_cells, width = size * size, size + 2
    pad_of_cell = _pad_of_cell(size)
    grid = torch.empty(width * width, dtype=torch.uint8)
    pads = torch.empty(max(num_obstacles, 1), dtype=torch.int32)
    blocked = torch.empty(num_cells, dtype=torch.uint8)
    library.fq_scatter(
        size, num_obstacles, key, scatter_index, agent,
        pad_of_cell.data_ptr(), grid.data_ptr(), pads.data_ptr(), blocked.data_ptr(),
    )  # fmt: skip
    return blocked.bool()
