"""``S`` declared Gymnasium envs (``factorq_envs.gymnasium_adapter.FactorQEnv``) as one torchrl
env of ``batch_size=(S,)``, built from torchrl's own pieces: ``GymWrapper`` over a Gymnasium
vector env, or torchrl's ``ParallelEnv``. The specs are torchrl's reading of the Gymnasium
spaces (``categorical_action_encoding=True``: ``cell``, ``heading`` and ``action`` categorical;
the adapter's ``FlagSpace`` sensors and bumps bool, ``factorq_envs.gym_spaces``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from functools import partial
from typing import Any

import gymnasium
import torch
from tensordict import TensorDictBase
from torchrl.envs import ExcludeTransform, GymWrapper, ParallelEnv, TransformedEnv

from factorq_envs.gym_spaces import register_torchrl_conversions
from factorq_envs.gymnasium_adapter import FactorQEnv
from factorq_torch.base.validation import check_int

register_torchrl_conversions()  # torchrl reads the adapter's FlagSpace / IndexSpace entries

BACKENDS = ("sync", "async", "parallel")


class DeclaredEnv(TransformedEnv):
    """The torchrl env of ``declared_torchrl_env``: ``config`` (``EnvSizes``: the sizes every
    env of the project states), ``declaration``, ``dependency`` (the declared oracle or
    ``None``) and ``envs`` (the adapters, for the in-process ``"sync"`` backend; else ``None``).
    """

    def __init__(
        self, base: Any, local: FactorQEnv, envs: list[FactorQEnv] | None, exclude: Sequence[str]
    ) -> None:
        super().__init__(base, ExcludeTransform(*exclude) if exclude else None)
        self.config = local.config
        self.declaration = local.declaration
        self.dependency = local.dependency
        self.envs = envs

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        partial = tensordict.get("_step", None)
        if partial is not None and not bool(partial.all()):
            # a Gymnasium vector env steps all its envs: a partial step would silently step the
            # envs the caller meant to freeze
            raise NotImplementedError(
                "DeclaredEnv steps every env at once: a '_step' mask (the online collector's "
                "finished experiments) is not supported; stop at a step budget instead"
            )
        return super()._step(tensordict)

    @property
    def num_cells(self) -> int:
        return self.config.num_cells

    @property
    def num_sensors(self) -> int:
        return self.config.num_sensors

    @property
    def num_actions(self) -> int:
        return self.config.num_actuators


def declared_torchrl_env(
    make_env: Callable[[int], FactorQEnv],
    seeds: Sequence[int],
    *,
    backend: str = "sync",
    exclude: Sequence[str] = (),
    device: torch.device | str | None = None,
) -> DeclaredEnv:
    """``S = len(seeds)`` adapters as one torchrl env of ``batch_size=(S,)``.

    Args:
        make_env: ``seed -> FactorQEnv`` (built with ``FactorQEnv(..., seed=seed)``; picklable
            for ``"async"``: a module-level function or a ``functools.partial`` of one).
        seeds: one seed per env: its first reset uses it; later episodes continue the env's own
            generator, so a seed replays the same episodes under the same actions.
        backend: ``"sync"`` (Gymnasium's ``SyncVectorEnv``, in this process), ``"async"``
            (``AsyncVectorEnv``, one process per env: slow envs use every core) or
            ``"parallel"`` (torchrl's ``ParallelEnv`` of ``GymWrapper``s, forked workers).
        exclude: entries of the env's own observation left out (e.g. a mission string, or an
            image nobody reads).
        device: where the tensors are returned.
    """
    seeds = [check_int("seeds", seed, 0) for seed in seeds]
    if not seeds:
        raise ValueError("seeds is empty: give one seed per env")
    if backend not in BACKENDS:
        raise ValueError(f"backend={backend!r} is unknown: choose one of {', '.join(BACKENDS)}")
    makers = [partial(make_env, seed) for seed in seeds]
    envs = None
    if backend == "parallel":
        base = ParallelEnv(
            len(seeds),
            [partial(_gym_wrapped, maker) for maker in makers],
            mp_start_method="fork",  # the workers inherit the registered ids and the makers
            device=device,
        )
        local = _adapter(make_env(seeds[0]))  # the sizes, read here (the workers hold the envs)
    else:
        autoreset = gymnasium.vector.AutoresetMode.DISABLED  # torchrl resets by mask
        vector: gymnasium.vector.VectorEnv
        if backend == "sync":
            vector = gymnasium.vector.SyncVectorEnv(makers, autoreset_mode=autoreset)
            envs = [_adapter(env) for env in vector.envs]
            local = envs[0]
        else:
            vector = gymnasium.vector.AsyncVectorEnv(makers, autoreset_mode=autoreset)
            local = _adapter(make_env(seeds[0]))
        base = GymWrapper(vector, categorical_action_encoding=True, device=device)
    return DeclaredEnv(base, local, envs, exclude)


def _adapter(env: gymnasium.Env) -> FactorQEnv:
    """``env`` if it is a ``FactorQEnv`` (what the sizes and the declaration are read from)."""
    if not isinstance(env, FactorQEnv):
        raise TypeError(
            f"make_env must return a FactorQEnv (the adapter around the world), got "
            f"{type(env).__name__}"
        )
    return env


def _gym_wrapped(maker: Callable[[], FactorQEnv]) -> Any:
    return GymWrapper(maker(), categorical_action_encoding=True)
