"""``MiniGridEnv``: ``S`` MiniGrid Dynamic-Obstacles worlds as one torchrl env, the adapter's
``declared_torchrl_env`` over ``make_minigrid`` (see ``factorq_envs.minigrid_adapter`` for the
observation, the rewards and the collision semantics)."""

from __future__ import annotations

from collections.abc import Sequence
from functools import partial

import torch

from factorq_envs.declared_env import DeclaredEnv, declared_torchrl_env
from factorq_envs.gymnasium_adapter import FactorQEnv
from factorq_envs.minigrid_adapter import make_minigrid


def MiniGridEnv(  # noqa: N802  (a constructor: the torchrl env it returns is a DeclaredEnv)
    size: int,
    semantics: str = "minigrid",
    *,
    layout: str = "front3",
    with_image: bool = False,
    seeds: Sequence[int] = (0,),
    backend: str = "sync",
    device: torch.device | str | None = None,
) -> DeclaredEnv:
    """``S`` MiniGrid worlds as one torchrl env of ``batch_size=(S,)``.

    Args:
        size, semantics, layout: as ``make_minigrid``.
        with_image: keep MiniGrid's ``image`` ``[S, 7, 7, 3]`` uint8 (and ``direction``) in the
            tensordicts (the image-based DQN reads it); the mission string is always left out.
        seeds: one seed per world: its first reset is ``reset(seed=seeds[i])`` and every later
            episode continues MiniGrid's own generator, so a seed replays the same episodes under
            the same actions.
        backend: ``"sync"`` (in-process), ``"async"`` or ``"parallel"`` (one process per world).
        device: where the tensors are returned.

    Keys: ``cell`` ``[S]``, ``heading`` ``[S]``, ``sensors`` ``[S, K]`` bool, ``bump`` ``[S, 3]``
    bool, ``collision`` ``[S, 3]`` float32, [``image``], ``reward`` ``[S, 1]`` (MiniGrid's),
    ``done`` / ``terminated`` / ``truncated`` ``[S, 1]``. A ``_reset`` ``[S, 1]`` restarts only the
    marked worlds.

    Example (not a doctest: MiniGrid is an optional extra)::

        env = MiniGridEnv(5, seeds=[0, 1])
        td = env.reset()  # td["sensors"] [2, 3] bool; td["heading"] [3, 3] (facing east)
    """
    exclude = ["mission"] if with_image else ["mission", "image", "direction"]
    return declared_torchrl_env(
        partial(_make, size, semantics, layout),
        list(seeds),
        backend=backend,
        exclude=exclude,
        device=device,
    )


def _make(size: int, semantics: str, layout: str, seed: int) -> FactorQEnv:
    return make_minigrid(size, semantics, layout=layout, seed=seed)
