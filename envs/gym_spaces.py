"""Gymnasium spaces that say how torchrl should read them: a state index and bool flags.

torchrl's ``GymEnv`` / ``GymWrapper`` read a ``Discrete`` observation entry as one-hot unless
the whole env is built with ``categorical_action_encoding=True`` (which also changes the
action), and a ``MultiBinary`` entry as int8; the tables read ``cell`` and ``heading`` as indices
and the sensors as bool. So the project's Gymnasium envs (``FactoredGridGym``, ``FactorQEnv``)
declare those entries with two subclasses, and register with torchrl's own hook
(``torchrl.envs.libs.gym.register_gym_spec_conversion``) how it reads them:

- ``IndexSpace(n)``: a ``Discrete`` that torchrl reads as ``Categorical(n)`` (int64, shape
  ``[]``), whatever the wrapper's ``categorical_action_encoding``;
- ``FlagSpace(n)``: a ``MultiBinary`` (int8 on the Gymnasium side, what Gymnasium's tools and
  SB3 expect) that torchrl reads as ``Binary(n, dtype=torch.bool)``; torchrl's ``encode`` casts
  the int8 values. Gymnasium's ``batch_space`` keeps it a ``FlagSpace`` in a vector env.

For Gymnasium, SB3 and every tool that checks ``isinstance(space, Discrete)`` they are the
spaces they subclass. The conversions are registered when torchrl is loaded: at the
construction of an env that uses these spaces (``GymEnv`` imports torchrl before it builds the
env) and at the import of the project's torchrl modules (``register_torchrl_conversions``); an
env built before torchrl was first imported is read as its base spaces until then.
"""

from __future__ import annotations

import sys
from typing import Any

from gymnasium import spaces
from gymnasium.vector.utils import batch_space


class IndexSpace(spaces.Discrete):
    """A ``Discrete`` observation entry that is a state index (a cell, a heading): torchrl reads
    it as ``Categorical`` (module docstring)."""


class FlagSpace(spaces.MultiBinary):
    """A ``MultiBinary`` observation entry of flags (sensors, bumps): torchrl reads it as bool
    (module docstring)."""


@batch_space.register(FlagSpace)
def _batch_flags(space: FlagSpace, n: int = 1) -> FlagSpace:
    return FlagSpace((n, *space.shape))


_registered = False


def register_torchrl_conversions() -> None:
    """Tell torchrl's Gym reader how to read ``IndexSpace`` and ``FlagSpace`` (idempotent;
    imports torchrl)."""
    global _registered
    if _registered:
        return
    import torch
    from torchrl.data import Binary, Categorical
    from torchrl.envs.libs.gym import register_gym_spec_conversion

    @register_gym_spec_conversion(IndexSpace)
    def _index(spec: IndexSpace, *, device: Any = None, **kwargs: Any) -> Categorical:
        return Categorical(int(spec.n), device=device, dtype=torch.int64)

    @register_gym_spec_conversion(FlagSpace)
    def _flags(spec: FlagSpace, *, device: Any = None, **kwargs: Any) -> Binary:
        return Binary(shape=torch.Size(spec.shape), device=device, dtype=torch.bool)

    _registered = True


def register_if_torchrl_loaded() -> None:
    """``register_torchrl_conversions`` when torchrl is already imported (so a Gymnasium user who
    never imports torchrl does not pay for it)."""
    if not _registered and "torchrl" in sys.modules:
        register_torchrl_conversions()
