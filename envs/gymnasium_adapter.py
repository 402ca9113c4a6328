"""Factor-Q on any Gymnasium env with a ``Discrete`` action space (or an action vector): the
adapter, declared as data.

A user's env is stepped as it is; a ``Declaration`` says what Factor-Q reads from it:

- ``sensors(step) -> [K]`` bool (or float32 features with ``features=True``);
- ``collision(step) -> bool`` (or the name of a bool ``info`` key), charged to the chosen
  actuator unless ``charge(step) -> actuator`` says otherwise;
- optionally the task state for tables (``task_state(step) -> cell`` or ``(cell, heading)``,
  with ``num_cells`` and ``num_headings``), the task reward (``task_reward(step) -> float``;
  default: the env's reward without the collision's part, for an env whose reward holds the
  penalty), the actuators (``actions``: the env action of each, ``actuator_names``) and the
  oracle ``dependency`` ``[A][K]``.

Every declared function reads one ``Transition``, the whole step of the env: ``observation``,
``reward``, ``terminated``, ``truncated`` and ``info`` as the env returned them, ``env`` (the env
inside the adapter, for what an env keeps outside its observation: a second observation type,
the agent's position) and ``action`` (the chosen actuator; ``None`` at a reset, where ``reward``
is 0.0 and ``terminated``/``truncated`` are False). So a hazard that ends the episode with
reward 0 (FrozenLake's holes, MiniGrid's lava) is one line,
``collision=lambda step: step.terminated and step.reward == 0``, no wrapper.

**The default task reward never pays for a collision.** It is the env's reward plus the
penalty on a collision step, right for an env whose reward holds the penalty (MiniGrid's -1,
CliffWalking's -100); on an env whose reward holds none (a hole worth 0, the goal worth 1) it
would turn the fall into the goal's +1. So on a collision with the default, the env's reward
must be at most ``-penalty`` (the task reward then at most 0): otherwise the adapter stops at
that step (the probing step or the first collision) and says what to declare
(``task_reward=lambda step: step.reward``: the env's reward is the task's, the collision is the
penalty beside it).

Two ways in, the same numbers:

- ``FactorQEnv(env, declaration)``: a ``gymnasium.Wrapper`` (and ``RecordConstructorArgs``, so
  Gymnasium's ``check_env`` and ``env.spec`` accept it) whose observation is the env's own
  (its ``Dict`` entries, or ``"observation"``) plus the project's keys: ``cell`` and ``heading``
  (with a task state, ``IndexSpace``: a ``Discrete``), ``sensors`` and ``bump``
  (``FlagSpace``: ``MultiBinary(K)``, ``MultiBinary(A)``),
  ``collision`` ``Box(-penalty, 0, (A,))``. Its reward is the conventional one, ``task reward +
  sum(collision)``; ``info`` adds ``collided`` (a bool) and ``task_reward`` (a numpy float32,
  which torchrl's ``GymEnv`` reads with ``factorq_envs.gymnasium_env.torchrl_info_reader()``).
  The env's own wrappers (a ``Dict`` env's observation wrappers) still find their entries.
- ``factorq_envs.declared_env.declared_torchrl_env(make_env, seeds)`` (its own file, so this one
  needs no torchrl): ``S`` of them through torchrl's ``GymWrapper`` over a
  Gymnasium vector env (``backend="sync"`` in-process, ``"async"`` one process per env) or
  torchrl's ``ParallelEnv`` (``"parallel"``), categorical ``cell``/``heading``/``action`` and
  bool ``sensors``/``bump``, batch ``(S,)``: the keys the tables, ``SplitLocalReward`` and the
  online collector read. torchrl's ``GymWrapper`` reads the specs from the Gymnasium spaces;
  nothing here writes a spec by hand.

torchrl's own ``GymEnv`` of an id whose entry point returns a ``FactorQEnv`` reads the same
keys, with no transform: ``IndexSpace`` and ``FlagSpace`` (``factorq_envs.gym_spaces``) tell
torchrl's Gym reader to give an index ``cell`` and bool flags whatever its
``categorical_action_encoding``.

Every env of the project states its sizes the same way: ``env.config`` holds the
``factorq_envs.protocol.CONFIG_FIELDS`` (``FactoredGridEnv``'s ``WorldConfig``, the adapter's
``EnvSizes``), so an agent is built from ``env.config`` whatever the env.

**Action vectors** (simultaneous actuators, issue 40): an env whose action space is
``MultiDiscrete(nvec)`` or ``MultiBinary(n)`` (one dimension) has one actuator per entry of the
action vector, all firing together (``nvec``: the values of each; ``MultiBinary(n)`` is ``n``
actuators of two values). Its ``collision(step)`` returns one bool per actuator (a numpy bool
array ``[J]``, or an ``info`` key holding one): each actuator's local reward is kept separate,
``-penalty`` at every actuator that collided (``charge`` and ``actions`` do not apply). The
adapter's action space is the env's own; ``step`` takes a vector of ``J`` integers and refuses
one of another length in one error naming both lengths, as construction refuses
``actuator_names`` or ``dependency`` rows of another count. The default task reward adds back
``penalty`` for each actuator that collided. ``declared_torchrl_env`` gives ``S`` of them an
int64 ``action`` ``[S, J]`` (torchrl's reading of the space). ``factorq_envs.vector_grid`` is
such a body and ``factorq_torch.vector`` the agent that acts on it.

Bad input is refused where it enters, in one message naming the env and the field: a
non-``Discrete`` action space (other than an action vector), a declared function that returns the
wrong shape, dtype or type (a collision that is not a bool, a cell or charged actuator that is not
an int, NaN or inf features, rewards or task rewards) or reads a missing ``info`` key (one probing
reset and step at construction, ``probe=True``, then every step), an env whose ``reset``/``step``
returns something else than Gymnasium's tuples, an env id that is not registered, an extra that is
not installed (``require_extra``).

Example (a third-party env would be declared the same way; ``docs/tutorials/own-env.md``
declares one):

    >>> import gymnasium, numpy as np
    >>> declaration = Declaration(
    ...     num_sensors=1,
    ...     sensors=lambda step: np.array([step.observation[2] > 0.1]),  # pole leaning right
    ...     collision=lambda step: step.terminated,  # the pole fell (or the cart left)
    ...     task_reward=lambda step: step.reward,  # CartPole's +1 holds no penalty
    ...     actuator_names=("left", "right"),
    ... )
    >>> env = FactorQEnv(gymnasium.make("CartPole-v1"), declaration)
    >>> obs, info = env.reset(seed=0)
    >>> sorted(obs), env.config.num_actuators
    (['bump', 'collision', 'observation', 'sensors'], 2)
"""

from __future__ import annotations

import importlib
import inspect
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from numbers import Real
from types import ModuleType
from typing import TYPE_CHECKING, Any

import gymnasium
import numpy as np
from gymnasium import spaces
from gymnasium.utils import RecordConstructorArgs

from factorq_envs.gym_spaces import FlagSpace, IndexSpace, register_if_torchrl_loaded
from factorq_envs.protocol import EnvSizes
from factorq_torch.base import keys
from factorq_torch.base.validation import check_int, is_int

if TYPE_CHECKING:
    import torch

#: The entries the adapter adds to the observation (a Dict env may not already use them).
ADDED_KEYS = (keys.CELL, keys.HEADING, keys.SENSORS, keys.BUMP, keys.COLLISION)
#: The key of a non-Dict env's own observation.
OBSERVATION = "observation"


def require_extra(module: str, extra: str) -> ModuleType:
    """Import ``module`` (registering its envs), or raise one ModuleNotFoundError naming the
    optional ``extra`` that installs it (e.g. ``factorq-torch[highway]``)."""
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as error:
        if error.name is not None and error.name.split(".")[0] != module.split(".")[0]:
            raise
        raise ModuleNotFoundError(
            f"{module} is not installed: install the optional extra with pip install '{extra}'",
            name=module,
        ) from None


def make_registered(env_id: str, **kwargs: Any) -> gymnasium.Env:
    """``gymnasium.make(env_id, **kwargs)``, or one ValueError naming an id that is not
    registered (import the package that registers it first)."""
    if env_id not in gymnasium.registry:
        raise ValueError(
            f"env id {env_id!r} is not registered with gymnasium: import the package that "
            f"registers it (or install its extra) first"
        )
    return gymnasium.make(env_id, **kwargs)


def _callable_or_none(name: str, value: object) -> None:
    if value is not None and not callable(value):
        raise TypeError(f"Declaration.{name} must be callable or None, got {value!r}")


def _takes_the_step(name: str, function: object) -> None:
    """Refuse a declared function that cannot be called with one argument, the step (a function
    of the old ``(observation, info, env)`` form), here rather than at the env's first step; an
    info key or ``None`` passes."""
    if not callable(function):
        return
    try:
        signature = inspect.signature(function)
    except (TypeError, ValueError):  # a builtin without a signature: its call will tell
        return
    try:
        signature.bind(None)
    except TypeError:
        raise TypeError(
            f"Declaration.{name} must take one argument, the step (step.observation, "
            f"step.reward, step.info, ...), but its signature is {signature}"
        ) from None


@dataclass(frozen=True, slots=True)
class Transition:
    """One step of the env, as every declared function reads it (``step`` in the examples).

    Attributes:
        observation: the env's own observation after the step (or the reset).
        reward: the env's own reward of the step, a finite float (0.0 at a reset).
        terminated, truncated: the env's own flags (False at a reset).
        info: the env's own ``info`` of the step (or the reset; ``{}`` when it gives none).
        env: the env inside the adapter (what it keeps outside its observation: MiniGrid's
            ``agent_pos``, highway's second observation type).
        action: the chosen actuator (``None`` at a reset).
    """

    observation: Any
    reward: float
    terminated: bool
    truncated: bool
    info: Mapping[str, Any]
    env: gymnasium.Env
    action: int | None = None


@dataclass(frozen=True)
class Declaration:
    """What Factor-Q reads from a Gymnasium env (module docstring); the env itself is not part
    of it, so one declaration serves every env of a family (MiniGrid's sizes, highway's ids).
    Every function reads the step as one ``Transition`` (``step.observation``, ``step.reward``,
    ``step.terminated``, ``step.truncated``, ``step.info``, ``step.env``, ``step.action``).

    Args:
        num_sensors: ``K``, the length of what ``sensors`` returns.
        sensors: ``step -> [K]`` bool numpy array (finite float32 features with
            ``features=True``); at a reset ``step.info`` is the reset's info.
        collision: ``step -> bool`` (a Python or numpy bool, nothing else), or the name of a
            bool ``info`` key. A hazard that ends the episode with reward 0:
            ``lambda step: step.terminated and step.reward == 0``.
        charge: ``step -> actuator`` (an int) that pays for a collision; ``None``: the chosen
            one, ``step.action``.
        actions: the env action of each actuator (default: actuator ``a`` is action ``a``).
        actuator_names: one name per actuator (default: the action numbers).
        task_state: ``step -> cell`` or ``(cell, heading)`` (ints) for tables; ``None``: no
            ``cell`` in the observation (networks only).
        num_cells, num_headings: the task state's ranges (``num_headings > 1``: ``task_state``
            returns ``(cell, heading)``).
        task_reward: ``step -> float``; ``None``: the env's reward plus ``penalty`` on a
            collision (the env's reward without the collision's part, so the conventional reward
            is the env's own), only for an env whose reward holds the penalty: a collision whose
            env reward is above ``-penalty`` is refused, naming what to declare (module
            docstring).
        dependency: the oracle, ``A`` rows of ``K`` bools (which sensors decide each actuator's
            collision), or ``None`` when nobody states it.
        sensor_names: one name per sensor (default ``s0 ... s{K-1}``).
        features: the sensors are float32 features (``Box``) rather than bool.
        spaces: replacements for entries of a Dict env's own observation space (a space torchrl
            cannot read, such as MiniGrid's ``MissionSpace``); ``None`` leaves an entry out.
        penalty: the collision's size: the collision vector holds ``-penalty`` at the charged
            actuator.
    """

    num_sensors: int
    sensors: Callable[[Transition], Any]
    collision: Callable[[Transition], bool] | str
    charge: Callable[[Transition], int] | None = None
    actions: tuple[int, ...] = ()
    actuator_names: tuple[str, ...] = ()
    task_state: Callable[[Transition], Any] | None = None
    num_cells: int = 1
    num_headings: int = 1
    task_reward: Callable[[Transition], float] | None = None
    dependency: tuple[tuple[bool, ...], ...] | None = None
    sensor_names: tuple[str, ...] = ()
    features: bool = False
    spaces: Mapping[str, spaces.Space | None] = field(default_factory=dict)
    penalty: float = 1.0

    def __post_init__(self) -> None:
        check_int("Declaration.num_sensors", self.num_sensors, 1)
        check_int("Declaration.num_cells", self.num_cells, 1)
        check_int("Declaration.num_headings", self.num_headings, 1)
        if not callable(self.sensors):
            raise TypeError(f"Declaration.sensors must be callable, got {self.sensors!r}")
        if not (callable(self.collision) or isinstance(self.collision, str)):
            raise TypeError(
                f"Declaration.collision must be callable (step) -> bool or an info key, "
                f"got {self.collision!r}"
            )
        for name in ("charge", "task_state", "task_reward"):
            _callable_or_none(name, getattr(self, name))
        for name in ("sensors", "collision", "charge", "task_state", "task_reward"):
            _takes_the_step(name, getattr(self, name))
        object.__setattr__(
            self,
            "actions",
            tuple(check_int(f"Declaration.actions[{i}]", a, 0) for i, a in enumerate(self.actions)),
        )
        object.__setattr__(self, "actuator_names", tuple(self.actuator_names))
        if self.actions and self.actuator_names and len(self.actions) != len(self.actuator_names):
            raise ValueError(
                f"Declaration: {len(self.actions)} actions but {len(self.actuator_names)} "
                f"actuator_names"
            )
        if self.sensor_names and len(self.sensor_names) != self.num_sensors:
            raise ValueError(
                f"Declaration.sensor_names has {len(self.sensor_names)} names for "
                f"num_sensors={self.num_sensors}"
            )
        if self.dependency is not None:
            rows = tuple(tuple(bool(b) for b in row) for row in self.dependency)
            if any(len(row) != self.num_sensors for row in rows):
                raise ValueError(
                    f"Declaration.dependency must be [actuators][{self.num_sensors}] bools, got "
                    f"rows of lengths {[len(row) for row in rows]}"
                )
            object.__setattr__(self, "dependency", rows)
        if not isinstance(self.features, bool):
            raise TypeError(f"Declaration.features must be a bool, got {self.features!r}")
        penalty = self.penalty
        if isinstance(penalty, bool) or not isinstance(penalty, Real):
            raise TypeError(
                f"Declaration.penalty must be a number, got {penalty!r} ({type(penalty).__name__})"
            )
        if not (math.isfinite(penalty) and penalty > 0):
            raise ValueError(f"Declaration.penalty={penalty!r} must be finite and > 0")
        object.__setattr__(self, "penalty", float(penalty))


def _is_bool(value: object) -> bool:
    return isinstance(value, bool | np.bool_)


def _finite(where: str, what: str, value: object) -> float:
    """``value`` as a float if it is a finite real number (not a bool), else one ValueError
    naming ``where`` (the env) and ``what`` (the field)."""
    if (
        _is_bool(value)
        or not isinstance(value, Real | np.number)
        or isinstance(value, np.complexfloating)
    ):
        raise TypeError(f"{where}: {what} must be a finite number, got {value!r}")
    number = float(value)
    if not math.isfinite(number):
        raise ValueError(f"{where}: {what} is {number}: must be finite")
    return number


class FactorQEnv(gymnasium.Wrapper, RecordConstructorArgs):
    """A Gymnasium env with the project's observation entries, read as ``declaration`` says
    (module docstring).

    Args:
        env: any Gymnasium env with a ``Discrete`` action space, or a one-dimensional
            ``MultiDiscrete`` / ``MultiBinary`` one (an action vector, module docstring).
        declaration: a ``Declaration``.
        seed: the seed of the first reset that is given none (so a batch of adapters built with
            one seed each replays, as ``MiniGridEnv`` did); ``None``: the env's own behaviour.
        probe: run one reset and one step at construction to check the declaration against
            the env (then the env is reset again by whoever uses it).
    """

    def __init__(
        self,
        env: gymnasium.Env,
        declaration: Declaration,
        *,
        seed: int | None = None,
        probe: bool = True,
    ) -> None:
        RecordConstructorArgs.__init__(self, declaration=declaration, seed=seed, probe=probe)
        gymnasium.Wrapper.__init__(self, env)
        if not isinstance(declaration, Declaration):
            raise TypeError(f"declaration must be a Declaration, got {type(declaration).__name__}")
        #: the values of each actuator of an action vector (``None``: a Discrete env)
        self.nvec = _action_vector(env.action_space, _name(env))
        if self.nvec is None and not isinstance(env.action_space, spaces.Discrete):
            raise TypeError(
                f"FactorQEnv needs a Discrete action space (one actuator per action), or a "
                f"one-dimensional MultiDiscrete / MultiBinary one (an action vector), "
                f"{_name(env)} has {env.action_space}"
            )
        self.declaration = declaration
        self._probe_on_init = probe
        self._label = _name(env)
        self._pending_seed = None if seed is None else check_int("seed", seed, 0)
        if self.nvec is not None:
            self._init_vector(env)
            return
        assert isinstance(env.action_space, spaces.Discrete)  # (an action vector returned above)
        count = int(env.action_space.n)
        actions = declaration.actions or tuple(range(count))
        bad = [a for a in actions if not 0 <= a < count]
        if bad:
            raise ValueError(
                f"{self._label}: Declaration.actions {bad} are not actions of {env.action_space}"
            )
        self._actions = actions
        names = declaration.actuator_names or tuple(str(a) for a in actions)
        if len(names) != len(actions):
            raise ValueError(
                f"Declaration.actuator_names has {len(names)} names for {len(actions)} actions"
            )
        num_actuators = len(actions)
        if declaration.dependency is not None and len(declaration.dependency) != num_actuators:
            raise ValueError(
                f"Declaration.dependency has {len(declaration.dependency)} rows for "
                f"{num_actuators} actuators"
            )
        self.config = EnvSizes(
            num_cells=declaration.num_cells,
            num_sensors=declaration.num_sensors,
            num_actuators=num_actuators,
            num_headings=declaration.num_headings,
            max_steps=getattr(env.spec, "max_episode_steps", None) if env.spec else None,
            actuator_names=names,
        )
        self.observation_space = spaces.Dict(self._spaces(env.observation_space))
        self.action_space = spaces.Discrete(num_actuators)
        if probe:
            self._probe()

    def _init_vector(self, env: gymnasium.Env) -> None:
        """The rest of ``__init__`` for an action vector (module docstring)."""
        declaration, nvec, label = self.declaration, self.nvec, self._label
        assert nvec is not None
        length = len(nvec)
        for name in ("actions", "charge"):
            if getattr(declaration, name):
                raise ValueError(
                    f"{label}: Declaration.{name} does not apply to an action vector "
                    f"({env.action_space}): its actuators are the vector's {length} entries and "
                    f"collision(step) says which of them collided"
                )
        names = declaration.actuator_names or tuple(str(j) for j in range(length))
        if len(names) != length:
            raise ValueError(
                f"{label}: Declaration.actuator_names has {len(names)} names but the action "
                f"vector has length {length} ({env.action_space})"
            )
        if declaration.dependency is not None and len(declaration.dependency) != length:
            raise ValueError(
                f"{label}: Declaration.dependency has {len(declaration.dependency)} rows but the "
                f"action vector has length {length} ({env.action_space}): one row per actuator"
            )
        self._actions = ()
        self.config = EnvSizes(
            num_cells=declaration.num_cells,
            num_sensors=declaration.num_sensors,
            num_actuators=length,
            num_headings=declaration.num_headings,
            max_steps=getattr(env.spec, "max_episode_steps", None) if env.spec else None,
            actuator_names=names,
        )
        self.observation_space = spaces.Dict(self._spaces(env.observation_space))
        self.action_space = env.action_space
        if self._probe_on_init:
            self._probe()

    def _action_vector(self, action: Any) -> np.ndarray:
        """``action`` as an int64 vector of the env's length with each entry in range, else one
        error naming both lengths (or the entry out of range)."""
        nvec = self.nvec
        assert nvec is not None
        array = np.asarray(action)
        if array.dtype.kind not in "iub" or array.ndim != 1:
            raise TypeError(
                f"{self._label}: the action must be a vector of {len(nvec)} integers (one per "
                f"actuator), got {action!r}"
            )
        if array.shape[0] != len(nvec):
            raise ValueError(
                f"{self._label}: the action vector has length {array.shape[0]} but the env's "
                f"action space {self.env.action_space} has length {len(nvec)}"
            )
        values = array.astype(np.int64)
        bad = [
            j for j, (a, n) in enumerate(zip(values.tolist(), nvec, strict=True)) if not 0 <= a < n
        ]
        if bad:
            raise ValueError(
                f"{self._label}: action {values.tolist()} is out of range at actuators {bad}: "
                f"entry j must be in [0, nvec[j]) with nvec={list(nvec)}"
            )
        return values

    def _collided_vector(self, step: Transition) -> np.ndarray:
        """The declared collision of an action vector: bool ``[J]``, one per actuator."""
        collision, length = self.declaration.collision, len(self.nvec or ())
        if isinstance(collision, str):
            if collision not in step.info:
                raise KeyError(
                    f"{self._label}: Declaration.collision read the key {collision!r}, which the "
                    f"env does not provide (its info has {sorted(step.info)})"
                )
            value, what = step.info[collision], f"collision (info[{collision!r}])"
        else:
            value, what = self._call("collision", collision, step), "collision"
        array = np.asarray(value)
        if array.dtype != np.bool_ or array.shape != (length,):
            raise ValueError(
                f"{self._label}: Declaration.{what} must return [{length}] bool (one per "
                f"actuator of the action vector), got {value!r}"
            )
        return array

    def _step_vector(self, action: Any) -> tuple[dict[str, Any], float, bool, bool, dict[str, Any]]:
        """``step`` for an action vector: every actuator fires; each one's collision is kept."""
        declaration = self.declaration
        vector = self._action_vector(action)
        step = self._checked_step(vector, tuple(vector.tolist()))
        collided = self._collided_vector(step)
        penalty = declaration.penalty * int(collided.sum())
        task, conventional = self._task_reward(step, bool(collided.any()), penalty)
        info = dict(step.info, collided=bool(collided.any()), task_reward=np.float32(task))
        out = self._observe(step, None)
        out[keys.BUMP] = collided.astype(np.int8)
        out[keys.COLLISION] = np.where(collided, -declaration.penalty, 0.0).astype(np.float32)
        return out, conventional, step.terminated, step.truncated, info

    # ---------------------------------------------------------------------------------------
    # Spaces

    def _own_entries(self, space: spaces.Space) -> dict[str, spaces.Space]:
        if not isinstance(space, spaces.Dict):
            return {OBSERVATION: space}
        own: dict[str, spaces.Space] = {}
        for name, entry in space.spaces.items():
            if name in ADDED_KEYS:
                raise ValueError(
                    f"{_name(self.env)}'s observation already has an entry {name!r}, a key the "
                    f"adapter writes: rename it with an observation wrapper first"
                )
            declared = self.declaration.spaces.get(name, entry)
            if declared is not None:
                own[name] = declared
        return own

    def _spaces(self, space: spaces.Space) -> dict[str, spaces.Space]:
        declaration, config = self.declaration, self.config
        entries = self._own_entries(space)
        register_if_torchrl_loaded()  # IndexSpace, FlagSpace: what torchrl reads them as
        if declaration.task_state is not None:
            entries[keys.CELL] = IndexSpace(config.num_cells)
            if config.num_headings > 1:
                entries[keys.HEADING] = IndexSpace(config.num_headings)
        if declaration.features:
            entries[keys.SENSORS] = spaces.Box(-np.inf, np.inf, (config.num_sensors,), np.float32)
        else:
            entries[keys.SENSORS] = FlagSpace(config.num_sensors)
        entries[keys.BUMP] = FlagSpace(config.num_actuators)
        entries[keys.COLLISION] = spaces.Box(
            -declaration.penalty, 0.0, (config.num_actuators,), np.float32
        )
        self._own_keys = [k for k in entries if k not in ADDED_KEYS]
        return entries

    @property
    def num_actions(self) -> int:
        return self.config.num_actuators

    @property
    def dependency(self) -> torch.Tensor | None:
        """The declared oracle as a bool tensor ``[A, K]``, or ``None``."""
        if self.declaration.dependency is None:
            return None
        import torch

        return torch.tensor(self.declaration.dependency, dtype=torch.bool)

    # ---------------------------------------------------------------------------------------
    # Reading the env

    def _call(self, declaration_field: str, function: Callable[..., Any], step: Transition) -> Any:
        """Call a declared function on ``step``; a KeyError (a missing info or observation key)
        becomes one message naming the env, the field and the keys the env's info has."""
        try:
            return function(step)
        except KeyError as error:
            raise KeyError(
                f"{self._label}: Declaration.{declaration_field} read the key "
                f"{error.args[0]!r}, which the env does not provide (its info has "
                f"{sorted(step.info)})"
            ) from None

    def _sensors(self, step: Transition) -> np.ndarray:
        declaration = self.declaration
        array = np.asarray(self._call("sensors", declaration.sensors, step))
        want = np.float32 if declaration.features else np.bool_
        if array.shape != (declaration.num_sensors,) or array.dtype != want:
            raise ValueError(
                f"{self._label}: Declaration.sensors must return [{declaration.num_sensors}] "
                f"{np.dtype(want).name}, got shape {array.shape} dtype {array.dtype}"
            )
        if declaration.features:
            if not np.isfinite(array).all():
                raise ValueError(
                    f"{self._label}: Declaration.sensors returned features {array.tolist()}: "
                    f"every feature must be finite"
                )
            return array
        return array.astype(np.int8)

    def _index(self, what: str, value: object, size: int) -> int:
        """``value`` if it is an int in ``[0, size)`` (a numpy integer is one; a float, a bool
        or NaN is not), else one error naming the env and the field."""
        if isinstance(value, np.ndarray) and value.shape == () and value.dtype.kind in "iu":
            value = value.item()
        if isinstance(value, np.integer):
            value = int(value)
        if not is_int(value):
            raise TypeError(
                f"{self._label}: Declaration.{what} returned {value!r} "
                f"({type(value).__name__}): must be an int in [0, {size})"
            )
        if not 0 <= value < size:
            raise ValueError(
                f"{self._label}: Declaration.{what} returned {value}: must be in [0, {size})"
            )
        return value

    def _task_state(self, task_state: Callable[..., Any], step: Transition) -> tuple[int, int]:
        declaration = self.declaration
        state = self._call("task_state", task_state, step)
        if declaration.num_headings > 1:
            if not (isinstance(state, tuple | list) and len(state) == 2):
                raise TypeError(
                    f"{self._label}: Declaration.task_state returned {state!r}: with "
                    f"num_headings={declaration.num_headings} it must return (cell, heading)"
                )
            cell, heading = state
        else:
            cell, heading = state, 0
        cell = self._index("task_state (the cell)", cell, declaration.num_cells)
        heading = self._index("task_state (the heading)", heading, declaration.num_headings)
        return cell, heading

    def _collided(self, step: Transition) -> bool:
        collision = self.declaration.collision
        if isinstance(collision, str):
            if collision not in step.info:
                raise KeyError(
                    f"{self._label}: Declaration.collision read the key {collision!r}, which the "
                    f"env does not provide (its info has {sorted(step.info)})"
                )
            value, what = step.info[collision], f"collision (info[{collision!r}])"
        else:
            value, what = self._call("collision", collision, step), "collision"
        if not _is_bool(value):
            raise TypeError(
                f"{self._label}: Declaration.{what} returned {value!r} "
                f"({type(value).__name__}): must be a bool"
            )
        return bool(value)

    def _observe(self, step: Transition, charged: int | None) -> dict[str, Any]:
        config, observation = self.config, step.observation
        if isinstance(observation, dict):
            missing = [name for name in self._own_keys if name not in observation]
            if missing:
                raise ValueError(
                    f"{self._label}: the env's observation lacks the entries {missing} of its "
                    f"observation space"
                )
            out = {name: observation[name] for name in self._own_keys}
        else:
            out = {OBSERVATION: observation}
        task_state = self.declaration.task_state
        if task_state is not None:
            cell, heading = self._task_state(task_state, step)
            out[keys.CELL] = cell
            if config.num_headings > 1:
                out[keys.HEADING] = heading
        out[keys.SENSORS] = self._sensors(step)
        bump = np.zeros(config.num_actuators, dtype=np.int8)
        collision = np.zeros(config.num_actuators, dtype=np.float32)
        if charged is not None:
            bump[charged] = 1
            collision[charged] = -self.declaration.penalty
        out[keys.BUMP] = bump
        out[keys.COLLISION] = collision
        return out

    # ---------------------------------------------------------------------------------------
    # The Gymnasium API

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, Any], dict[str, Any]]:
        if seed is None and self._pending_seed is not None:
            seed = self._pending_seed
        self._pending_seed = None
        returned = self.env.reset(seed=seed, options=options)
        if not (isinstance(returned, tuple) and len(returned) == 2):
            raise TypeError(
                f"{self._label}: reset() returned {_shape_of(returned)}: a Gymnasium env's "
                f"reset returns (observation, info)"
            )
        observation, info = returned
        info = self._info("reset", info)
        step = Transition(observation, 0.0, False, False, info, self.env, None)
        # task_reward a numpy scalar: torchrl's info reader (torchrl_info_reader) reads numpy
        info = dict(info, collided=False, task_reward=np.float32(0.0))
        return self._observe(step, None), info

    def step(self, action: Any) -> tuple[dict[str, Any], float, bool, bool, dict[str, Any]]:
        if self.nvec is not None:
            return self._step_vector(action)
        if isinstance(action, np.ndarray) and action.shape == ():
            action = action.item()
        count = self.config.num_actuators
        if isinstance(action, bool | np.bool_) or not isinstance(action, int | np.integer):
            raise TypeError(
                f"{self._label}: action must be an int in [0, {count - 1}], got {action!r}"
            )
        actuator = int(action)
        if not 0 <= actuator < count:
            names = ", ".join(f"{i} {n}" for i, n in enumerate(self.config.actuator_names))
            raise ValueError(
                f"{self._label}: action={actuator} is out of range: must be in [0, {count}) "
                f"({names})"
            )
        declaration = self.declaration
        step = self._checked_step(self._actions[actuator], actuator)
        collided = self._collided(step)
        charged = None
        if collided:
            charged = actuator
            if declaration.charge is not None:
                charged = self._index(
                    "charge", self._call("charge", declaration.charge, step), count
                )
        penalty = declaration.penalty if collided else 0.0
        task, conventional = self._task_reward(step, collided, penalty)
        info = dict(step.info, collided=collided, task_reward=np.float32(task))
        out = self._observe(step, charged)
        return out, conventional, step.terminated, step.truncated, info

    def _checked_step(self, env_action: Any, action: Any) -> Transition:
        """The env's ``step(env_action)`` as a ``Transition`` of ``action`` (the chosen actuator
        or the action vector), its 5-tuple, finite reward, bool flags and info checked."""
        returned = self.env.step(env_action)
        if not (isinstance(returned, tuple) and len(returned) == 5):
            raise TypeError(
                f"{self._label}: step() returned {_shape_of(returned)}: a Gymnasium env's step "
                f"returns (observation, reward, terminated, truncated, info)"
            )
        observation, reward, terminated, truncated, info = returned
        reward = _finite(self._label, "the env's reward", reward)
        for name, flag in (("terminated", terminated), ("truncated", truncated)):
            if not _is_bool(flag):
                raise TypeError(
                    f"{self._label}: step() returned {name}={flag!r} "
                    f"({type(flag).__name__}): must be a bool"
                )
        info = self._info("step", info)
        return Transition(
            observation, reward, bool(terminated), bool(truncated), info, self.env, action
        )

    def _task_reward(self, step: Transition, collided: bool, penalty: float) -> tuple[float, float]:
        """``(task reward, conventional reward)`` of ``step``: the declared task reward, or the
        env's reward plus the ``penalty`` of its collisions, refused where that would pay for a
        collision (the env's reward holds no penalty; module docstring)."""
        declaration = self.declaration
        reward = step.reward
        if declaration.task_reward is None:
            task = reward + penalty
            if collided and task > 1e-9 * max(1.0, penalty):  # rounding is no reward
                raise ValueError(
                    f"{self._label}: a collision with the env's reward {reward!r}: the default "
                    f"task reward (the env's reward + penalty {penalty!r} = {task!r}) would pay "
                    f"for it, as the env's reward holds no penalty of {penalty!r}. Declare "
                    f"task_reward=lambda step: step.reward (the env's reward is the task's, the "
                    f"collision is the penalty beside it), or the penalty the env's reward holds"
                )
            return task, reward  # the conventional reward: the env's own, exactly
        task = _finite(
            self._label,
            "Declaration.task_reward's result",
            self._call("task_reward", declaration.task_reward, step),
        )
        return task, task - penalty

    def _info(self, where: str, info: object) -> dict[str, Any]:
        if not isinstance(info, Mapping):
            raise TypeError(
                f"{self._label}: {where}() returned info={info!r} ({type(info).__name__}): "
                f"must be a dict"
            )
        return dict(info)

    def _probe(self) -> None:
        """One reset and one step (actuator 0), checking every declared function; the seed of
        the first real reset is kept."""
        pending = self._pending_seed
        observation, info = self.reset()
        if observation not in self.observation_space:
            raise ValueError(
                f"{self._label}: the adapter's observation is not in its space: {observation}"
            )
        self.step(0 if self.nvec is None else np.zeros(len(self.nvec), dtype=np.int64))
        self._pending_seed = pending


def _shape_of(value: object) -> str:
    if isinstance(value, tuple):
        return f"a tuple of {len(value)}"
    return f"{type(value).__name__} {value!r}"[:80]


def _name(env: gymnasium.Env) -> str:
    spec = getattr(env, "spec", None)
    return spec.id if spec is not None else type(env.unwrapped).__name__


def _action_vector(space: spaces.Space, label: str) -> tuple[int, ...] | None:
    """The values of each actuator of a one-dimensional ``MultiDiscrete`` / ``MultiBinary``
    action space (``MultiBinary(n)``: ``n`` actuators of two values), ``None`` for any other
    space; a multi-dimensional one is refused, naming it."""
    if isinstance(space, spaces.MultiBinary):
        shape = tuple(np.atleast_1d(space.n).tolist())
        if len(shape) != 1:
            raise TypeError(
                f"FactorQEnv needs a one-dimensional action vector, {label} has {space}"
            )
        return (2,) * shape[0]
    if isinstance(space, spaces.MultiDiscrete):
        if space.nvec.ndim != 1 or (space.start != 0).any():
            raise TypeError(
                f"FactorQEnv needs a one-dimensional action vector starting at 0, {label} has "
                f"{space}"
            )
        return tuple(int(n) for n in space.nvec)
    return None
