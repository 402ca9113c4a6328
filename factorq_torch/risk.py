"""Factor-Q's local model as a safety layer for any value-based agent.

Factor-Q's combined value ``C(s) = Q(s) + G rho(o)`` (eqs. 2-3) needs two things: a task value
``Q(s, .)`` per action, and a model ``rho(o)`` of which actuator is dangerous given which
sensors. ``LocalRisk`` takes the first from *any* value network (torchrl's ``QValueActor``, a
dueling head, the expected values of a distributional head, the project's ``TaskQTable`` /
``TaskQNetwork``: whatever writes ``action_value``) and the second from a local value provider
(``LocalRewardTable``, ``LocalRewardNetwork``, ``GatedLocalRewardNetwork``,
``StructureLearner``), and writes ``C(s)`` back under ``action_value``: torchrl's
``QValueModule``, ``EGreedyModule`` and collectors then act on it unchanged. The raw task values
are kept under ``task_value``, and the actuators it does not call risky under ``risk_mask``
(``EGreedyModule(spec, action_mask_key="risk_mask")`` then explores among those only: most of
an epsilon-greedy agent's early collisions are its random actions). ``LocalRiskLoss`` trains the
provider from ``local_reward``; its ``loss_local`` adds to torchrl's ``DQNLoss`` (or any loss) as
one more loss term.

torchrl's DQN recipe becomes "DQN + local risk" with two lines::

    actor = QValueActor(net, in_keys=[...], spec=env.action_spec_unbatched)  # as before
    egreedy = EGreedyModule(spec, action_mask_key="risk_mask")  # explore among safe actions
    policy = TensorDictSequential(with_local_risk(actor, provider, env=env), egreedy)  # 1
    local_loss = LocalRiskLoss(provider)                                             # 2
    ...
    loss = dqn_loss(sample)["loss"] + local_loss(sample)["loss_local"]

``DQNLoss`` keeps training the plain ``actor`` (its values, not the combined ones): the layer
changes which action is taken, not what the task value learns.

**Which reward each part reads.** The env is wrapped in ``SplitLocalReward(keep_reward=True)``:
``("next", "reward")`` stays the conventional reward (step + goal + collisions), what a recipe
and ``DQNLoss`` expect, and ``("next", "local_reward")`` ``[A]`` (the collision vector) is added
as an observation entry, so ``env.reward_key`` is still ``"reward"``. ``LocalRiskLoss`` reads
``local_reward``, the value network reads whatever its recipe reads. (The default
``SplitLocalReward()`` is Factor-Q's: ``reward`` becomes the task reward alone, and a DQN fed that
never sees a collision: its greedy policy keeps colliding. ``FactorQLoss`` wants that; a DQN
recipe does not.)

**Batch.** A provider holds ``S`` independent experiments. With one agent acting in a batch of
worlds (one Q-network for all of them, torchrl's usual recipe), the provider has ``S = 1`` and is
shared by every world; with one agent per world (the project's batched ``TaskQNetwork``), ``S``
is the env's batch. Anything else is refused at construction, naming both sides.

**Explanations.** ``explain(td)`` returns, for every state of the batch, which actuators the layer
penalises (``G rho_a`` below ``-threshold``), by how much and because of which sensors (the
dependency, the structure a ``StructureLearner`` committed to, or the parents read off a
``GatedLocalRewardNetwork``), and ``explain_text`` one line per state (``"forward: -0.93, front
blocked"``). ``RiskSummary`` keeps the per-episode counts for the logs.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, overload

import torch
from tensordict import NestedKey, TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torchrl.envs.utils import set_exploration_type
from torchrl.modules.tensordict_module.rnn import set_recurrent_mode
from torchrl.objectives import LossModule
from torchrl.objectives import common as _torchrl_loss_common

from factorq_torch.base import keys as names
from factorq_torch.base.config import AgentConfig
from factorq_torch.base.risk_text import summary_line
from factorq_torch.base.validation import check_finite
from factorq_torch.functional import (
    check_dependency,
    combined_values,
    local_risk_rows,
    normaliser,
    risk_mask,
)
from factorq_torch.structure import StructureLearner
from factorq_torch.tables import LocalRewardTable

#: The batch size of a loss's output (a scalar loss).
_NO_BATCH = torch.Size([])
#: Where the layer keeps the task values it read (``action_value`` then holds ``C(s)``).
TASK_VALUE = "task_value"
#: Where it writes eq. 3's ``G`` ``[*B]`` (explanations and monitoring).
NORMALISER = "risk_normaliser"
#: Where it writes the actions it does not call risky ``[*B, A]`` bool: torchrl's
#: ``EGreedyModule(spec, action_mask_key=RISK_MASK)`` then explores among them only.
RISK_MASK = "risk_mask"


def _provider_size(provider: TensorDictModuleBase) -> tuple[int, int, int | None]:
    """``(S, A, K)`` a provider declares (``K`` None when it does not say)."""
    for attribute in ("num_experiments", "num_actions"):
        if not isinstance(getattr(provider, attribute, None), int):
            raise TypeError(
                f"the local value provider {type(provider).__name__} declares no {attribute}: "
                f"use LocalRewardTable, LocalRewardNetwork, GatedLocalRewardNetwork or "
                f"StructureLearner (or give yours num_experiments, num_actions, num_sensors)"
            )
    return provider.num_experiments, provider.num_actions, getattr(provider, "num_sensors", None)


def _spec_actions(spec: Any) -> tuple[int | None, tuple[int, ...]]:
    """``(number of actions, shape)`` of an action spec (a ``Composite`` holding ``action``)."""
    if spec is None:
        return None, ()
    if hasattr(spec, "keys") and "action" in spec.keys():
        spec = spec["action"]
    count = getattr(getattr(spec, "space", None), "n", None)
    shape = tuple(spec.shape)
    if count is not None and shape and shape[-1] == count and "OneHot" in type(spec).__name__:
        shape = shape[:-1]  # one-hot: the last dimension is the actions
    return (int(count) if count is not None else None), shape


def _value_module_spec(value_network: TensorDictModuleBase) -> Any:
    """The action spec of the ``QValueModule`` inside ``value_network`` (None if there is none)."""
    from torchrl.modules import QValueModule

    for module in value_network.modules():
        if isinstance(module, QValueModule):
            return module.spec
    return None


class LocalRisk(TensorDictModuleBase):
    """Eqs. 2-3 on any task value and any local value provider, as a TensorDict module.

    Runs ``provider`` on the tensordict (it writes ``local_value`` ``[*B, A]``), reads the task
    values ``action_value`` ``[*B, A]`` written by the value network before it, and writes
    ``C(s) = Q(s) + G rho(o)`` (``functional.normaliser``, ``functional.combined_values``) under
    ``out_key`` (default ``action_value``, what ``QValueModule`` reads), the task values under
    ``task_value`` and ``G`` under ``risk_normaliser``.

    Args:
        provider: the local value provider (a table, a network, a ``StructureLearner``).
        num_actions: the value network's action count (checked against the provider's).
        batch_size: the env's batch (checked: the provider's ``S`` is 1 or the batch).
        dependency: bool ``[A, K]``, which sensors decide which actuator's local reward, for
            the explanations (default: the provider's own, or what it learned).
        sensor_names, actuator_names: names for the explanations (default ``sensor k`` /
            ``actuator a``).
        active: the word for a sensor reading 1 (``"blocked"`` for the grid worlds).
        eta, g_min: eq. 3's margin and floor of ``G``.
        mask_threshold: an actuator whose local value ``rho_a`` is below ``-mask_threshold``
            (local reward units: a collision more likely than not, by default) is left out of
            ``risk_mask`` (every actuator is kept where all would be left out).
        action_value_key, out_key: where the task values are read and ``C(s)`` is written.

    Example:
        >>> from factorq_torch.tables import LocalRewardTable
        >>> local = LocalRewardTable(1)
        >>> local.rho[0, 0, 1] = -1.0  # north into a sensed obstacle: a collision
        >>> risk = LocalRisk(local, num_actions=4)
        >>> td = TensorDict(action_value=torch.tensor([[1.0, 0.0, 0.0, 0.0]]),
        ...                 sensors=torch.tensor([[True, False, False, False]]), batch_size=[1])
        >>> risk(td)["action_value"].argmax(-1)  # north was best, is now the worst
        tensor([1])
        >>> risk.explain_text(td)
        ['actuator 0: -1.10, sensor 0 on']
    """

    def __init__(
        self,
        provider: TensorDictModuleBase,
        *,
        num_actions: int | None = None,
        batch_size: Sequence[int] | None = None,
        dependency: torch.Tensor | None = None,
        sensor_names: Sequence[str] | None = None,
        actuator_names: Sequence[str] | None = None,
        eta: float = 0.1,
        g_min: float = 0.01,
        active: str = "on",
        mask_threshold: float = 0.5,
        action_value_key: NestedKey = names.ACTION_VALUE,
        out_key: NestedKey = names.ACTION_VALUE,
    ) -> None:
        super().__init__()
        if not isinstance(provider, TensorDictModuleBase):
            raise TypeError(
                f"provider must be a TensorDict module writing local_value (LocalRewardTable, "
                f"LocalRewardNetwork, GatedLocalRewardNetwork, StructureLearner), got "
                f"{type(provider).__name__}"
            )
        AgentConfig(eta=eta, g_min=g_min)  # validates both with messages naming them
        self.eta, self.g_min = float(eta), float(g_min)
        self.provider = provider
        experiments, actions, sensors = _provider_size(provider)
        self.num_experiments, self.num_actions, self.num_sensors = experiments, actions, sensors
        if num_actions is not None and num_actions != actions:
            raise ValueError(
                f"the value network has {num_actions} actions but the local value provider "
                f"{type(provider).__name__} has {actions} actuators: both must score the same "
                f"actions"
            )
        if batch_size is not None:
            batch = tuple(batch_size)
            worlds = math.prod(batch)
            if experiments != 1 and batch != (experiments,):
                raise ValueError(
                    f"the env has batch_size {list(batch)} ({worlds} worlds) but the local value "
                    f"provider {type(provider).__name__} holds S={experiments} experiments: use "
                    f"S=1 (one provider shared by every world, one agent) or S={worlds} with "
                    f"batch_size [{worlds}] (one provider per world)"
                )
        if dependency is not None:
            dependency = check_dependency(dependency)
            if sensors is not None and tuple(dependency.shape) != (actions, sensors):
                raise ValueError(
                    f"dependency has shape {list(dependency.shape)} but the local value "
                    f"provider {type(provider).__name__} has {actions} actuators and {sensors} "
                    f"sensors: it must be [{actions}, {sensors}]"
                )
            if tuple(dependency.shape[:1]) != (actions,):
                raise ValueError(
                    f"dependency has shape {list(dependency.shape)} but the local value "
                    f"provider has {actions} actuators: one row per actuator"
                )
            self.register_buffer("dependency", dependency.clone())
        else:
            self.dependency = None
        self.sensor_names = self._names("sensor_names", sensor_names, sensors, "sensor")
        self.actuator_names = self._names("actuator_names", actuator_names, actions, "actuator")
        self.active = str(active)
        if not isinstance(mask_threshold, (int, float)) or not math.isfinite(mask_threshold):
            raise ValueError(f"mask_threshold={mask_threshold!r} must be a finite number")
        self.mask_threshold = float(mask_threshold)
        self.action_value_key, self.out_key = action_value_key, out_key
        self._str_keys = isinstance(out_key, str)  # (every other key the layer writes is)
        # The online step of a LocalRewardTable or StructureLearner (their own forward, not a
        # subclass's) reads the sensors and calls local_values: the same values, without the
        # module call and a tensordict write and read (a third of the layer's time on a [1] step)
        self._reads_sensors = type(provider).forward in (
            LocalRewardTable.forward,
            StructureLearner.forward,
        )
        self._sensors_key = getattr(provider, "sensors_key", None)
        self._readings_shape = torch.Size((experiments, sensors or 0))
        provider_keys = [key for key in provider.in_keys if key != action_value_key]
        self.in_keys = [action_value_key, *provider_keys]
        self.out_keys = list(
            dict.fromkeys([out_key, TASK_VALUE, names.LOCAL_VALUE, NORMALISER, RISK_MASK])
        )

    @overload
    @staticmethod
    def _names(
        label: str, given: Sequence[str] | None, count: int, default: str
    ) -> tuple[str, ...]: ...
    @overload
    @staticmethod
    def _names(
        label: str, given: Sequence[str] | None, count: int | None, default: str
    ) -> tuple[str, ...] | None: ...
    @staticmethod
    def _names(
        label: str, given: Sequence[str] | None, count: int | None, default: str
    ) -> tuple[str, ...] | None:
        if given is None:
            return None if count is None else tuple(f"{default} {i}" for i in range(count))
        given = tuple(str(name) for name in given)
        if count is not None and len(given) != count:
            raise ValueError(f"{label} has {len(given)} names, the provider has {count}")
        return given

    # -- the provider's values for any batch ---------------------------------------------------

    def local_values(self, tensordict: TensorDictBase) -> torch.Tensor:
        """The provider's ``local_value`` ``[*B, A]`` for a tensordict of any batch ``[*B]``.

        With ``S = 1`` the provider sees the batch with a trailing experiment dimension
        ``[*B, 1]`` (every world is its experiment 0); a ``StructureLearner`` (which reads one
        ``[S]`` step) is read row by row.
        """
        batch = tuple(tensordict.batch_size)
        # (the submodule by its dict: nn.Module's attribute lookup is a microsecond a step)
        provider, count = self._modules["provider"], self.num_experiments
        leading = count != 1 and len(batch) > 1 and batch[0] == count and batch[-1] != count
        if count != 1 and not leading and (not batch or batch[-1] != count):
            raise ValueError(
                f"LocalRisk: the local value provider holds S={count} experiments but the "
                f"tensordict has batch_size {list(batch)}: expected [..., {count}] or "
                f"[{count}, ...]"
            )
        if batch == (count,):  # the online step (every provider reads it as is)
            if self._reads_sensors:  # a table or learner: its values, without a tensordict
                key = self._sensors_key
                if type(tensordict) is TensorDict and type(key) is str:
                    # (a plain TensorDict holds its entries in a dict, as get() returns them)
                    entries = tensordict._tensordict
                    readings = entries.get(key)
                    numbered = names.EXPERIMENT in entries
                else:
                    readings = tensordict.get(key, None)
                    numbered = tensordict.get(names.EXPERIMENT, None) is not None
                if (
                    readings is not None
                    and readings.shape == self._readings_shape
                    and readings.dtype == torch.bool
                    and not numbered
                    and not (provider._forward_hooks or provider._forward_pre_hooks)
                ):
                    return provider.local_values(readings)
                # anything else: the provider's own forward (and its errors)
            return provider(tensordict).get(names.LOCAL_VALUE)
        view = tensordict.select(*provider.in_keys, strict=False)
        if leading:  # a [S, T] rollout: experiments last, as the networks read them
            view = view.permute(*range(1, len(batch)), 0)
        if count != 1:  # each transition's experiment, for the tables (networks ignore it)
            experiment = torch.arange(count, device=tensordict.device)
            view = view.set(names.EXPERIMENT, experiment.expand(view.batch_size))
        if count == 1 and (not batch or batch[-1] != 1):
            view = view.unsqueeze(-1)  # every world is the shared provider's experiment 0
        if isinstance(provider, StructureLearner):  # it reads one [S] step at a time
            sensors = view.get(provider.sensors_key)
            rows = sensors.reshape(-1, count, sensors.shape[-1])
            value = torch.stack([provider.local_values(row) for row in rows])  # [N, S, A]
            value = value.reshape(*view.batch_size, self.num_actions)
        else:
            value = provider(view).get(names.LOCAL_VALUE)
        if count == 1 and (not batch or batch[-1] != 1):
            value = value.squeeze(-2)
        if leading:
            value = value.movedim(-2, 0)
        return value.reshape(*batch, self.num_actions)

    # -- eqs. 2-3 -------------------------------------------------------------------------------

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        q = tensordict.get(self.action_value_key, None)
        if q is None:
            raise KeyError(
                f"LocalRisk needs {self.action_value_key!r}, written by the value network before "
                f"it (put LocalRisk after it: with_local_risk(actor, provider)); the tensordict "
                f"has {list(tensordict.keys())}"
            )
        if q.shape[-1] != self.num_actions:
            raise ValueError(
                f"LocalRisk: {self.action_value_key!r} has {q.shape[-1]} actions, the provider "
                f"{self.num_actions}"
            )
        if torch.is_grad_enabled():  # the layer chooses actions; nothing learns through it
            with torch.no_grad():
                return self._combine(tensordict, q)
        return self._combine(tensordict, q)  # (a collector's policy runs without gradients)

    def _combine(self, tensordict: TensorDictBase, q: torch.Tensor) -> TensorDictBase:
        rho = self.local_values(tensordict)  # [*B, A]
        if rho.dtype != q.dtype:
            rho = rho.to(q.dtype)
        # eqs. 2-3 and the mask: fused for a small batch (one agent's step), whose values it
        # checks are finite; else the functions that define them
        fused = local_risk_rows(q, rho, self.eta, self.g_min, self.mask_threshold)
        if fused is None:
            q = check_finite("LocalRisk", repr(self.action_value_key), q)
            g = normaliser(q, rho, eta=self.eta, g_min=self.g_min)  # [*B], eq. 3
            combined = combined_values(q, rho, g)  # [*B, A], eq. 2
            allowed = risk_mask(rho, self.mask_threshold)  # never an empty choice
        else:
            combined, g, allowed = fused
        # one update (local_value: the provider wrote it already on the online step; written
        # again, it is the same tensor unless another dtype or batch was read)
        values = {
            names.LOCAL_VALUE: rho,
            RISK_MASK: allowed,
            TASK_VALUE: q,
            NORMALISER: g,
            self.out_key: combined,
        }
        if fused is not None and type(tensordict) is TensorDict and self._str_keys:
            # the fused step's CPU tensors, shaped [*B, A] / [*B] from the tensordict's own
            # entry: what set() would validate holds, so they are stored as they are (a plain
            # TensorDict on no device or the CPU; a locked one still raises)
            device = tensordict.device
            if device is None or device.type == "cpu":
                for key, value in values.items():
                    tensordict._set_str(key, value, inplace=False, validated=True)
                return tensordict
        tensordict.update(values)
        return tensordict

    # -- explanations ---------------------------------------------------------------------------

    def parents(self) -> torch.Tensor | None:
        """bool ``[A, K]``: the sensors each actuator's risk is read from (the given
        dependency, else the provider's own, what a ``StructureLearner`` committed to or the
        parents read off a ``GatedLocalRewardNetwork``; experiment 0's for ``S > 1``)."""
        if self.dependency is not None:
            return self.dependency
        provider = self.provider
        own = getattr(provider, "dependency", None)
        if isinstance(own, torch.Tensor):
            return own
        structure = getattr(provider, "structure", None)
        if callable(structure):
            return structure()[0]
        return None

    def _sensor_name(self, k: int) -> str:
        """Sensor ``k``'s name (``sensor k`` where neither the caller nor the provider says K)."""
        return f"sensor {k}" if self.sensor_names is None else self.sensor_names[k]

    @torch.no_grad()
    def explain(self, tensordict: TensorDictBase, threshold: float = 0.05) -> list[list[dict]]:
        """For every state of the (flattened) batch: the actuators the layer penalises.

        One list per state of dicts ``{"actuator", "penalty", "sensors"}``, most penalised first:
        ``penalty`` is ``G rho_a`` (below ``-threshold``: the change eq. 2 makes to actuator
        ``a``'s value), ``sensors`` the names of ``a``'s parent sensors that read 1 (``"blocked"``
        by any reading of the world's sensors) in this state. Runs the value network's output
        through the layer first if it has not been (needs ``action_value``).
        """
        if NORMALISER not in tensordict.keys():
            tensordict = self(tensordict.clone(False))
        g = tensordict.get(NORMALISER).reshape(-1)  # [M]
        rho = tensordict.get(names.LOCAL_VALUE).reshape(-1, self.num_actions)  # [M, A]
        penalty = g.unsqueeze(-1) * rho  # [M, A]
        parents = self.parents()
        sensors = tensordict.get(names.SENSORS, None)
        readings = None if sensors is None else sensors.reshape(-1, sensors.shape[-1])
        explanations = []
        for row in range(penalty.shape[0]):
            found = []
            for actuator in torch.argsort(penalty[row]).tolist():
                amount = float(penalty[row, actuator])
                if amount >= -threshold:
                    break
                because = []
                if parents is not None and readings is not None:
                    on = parents[actuator] & readings[row]
                    because = [self._sensor_name(k) for k in on.nonzero().flatten().tolist()]
                found.append(
                    {
                        "actuator": self.actuator_names[actuator],
                        "index": actuator,
                        "penalty": amount,
                        "sensors": because,
                    }
                )
            explanations.append(found)
        return explanations

    def explain_text(self, tensordict: TensorDictBase, threshold: float = 0.05) -> list[str]:
        """One line per state: ``"forward: -0.93, front blocked"`` (``""`` when nothing is
        penalised), actuators separated by ``"; "``."""
        explained = self.explain(tensordict, threshold)
        return [format_explanation(row, self.active) for row in explained]


def format_explanation(penalised: list[dict], active: str = "on") -> str:
    """``explain``'s entries of one state as one line of text."""
    parts = []
    for entry in penalised:
        text = f"{entry['actuator']}: {entry['penalty']:.2f}"
        if entry["sensors"]:
            text += ", " + " and ".join(f"{name} {active}" for name in entry["sensors"])
        parts.append(text)
    return "; ".join(parts)


def find_local_risk(module: torch.nn.Module) -> LocalRisk:
    """The ``LocalRisk`` layer inside a composed policy (``with_local_risk``'s output, an actor
    wrapped further, a ``TensorDictSequential`` with an exploration module), found by type.

    Args:
        module: the policy (or any module holding exactly one ``LocalRisk``).

    Example:
        >>> from factorq_torch.tables import LocalRewardTable, TaskQTable
        >>> policy = with_local_risk(TaskQTable(1, num_cells=4), LocalRewardTable(1))
        >>> find_local_risk(policy).num_actions
        4
    """
    if not isinstance(module, torch.nn.Module):
        raise TypeError(f"find_local_risk takes a module, got {type(module).__name__}")
    found = [inner for inner in module.modules() if isinstance(inner, LocalRisk)]
    if not found:
        raise ValueError(
            f"{type(module).__name__} holds no LocalRisk layer: build the policy with "
            f"with_local_risk(value_network, provider)"
        )
    if len({id(layer) for layer in found}) > 1:
        raise ValueError(
            f"{type(module).__name__} holds {len(found)} LocalRisk layers: pass the part that "
            f"holds the one you mean"
        )
    return found[0]


def with_local_risk(
    value_network: TensorDictModuleBase,
    provider: TensorDictModuleBase,
    *,
    env: Any = None,
    spec: Any = None,
    **options: Any,
) -> TensorDictSequential:
    """``value_network`` with a ``LocalRisk`` layer placed before its action choice.

    A ``QValueActor`` (or any sequence ending in torchrl's ``QValueModule``) gets the layer
    spliced in before the ``QValueModule``; any other value network gets it appended, then a
    ``QValueModule(spec=spec)`` when ``spec`` is given. ``env`` (optional) is checked against
    the parts: its batch against the provider's ``S``, its ``dependency`` (if it has one) against
    the provider's shape, and its names are used by the explanations. ``options`` go to
    ``LocalRisk``.

    Args:
        value_network: a ``QValueActor``, a sequence ending in a ``QValueModule``, or any
            module writing ``action_value``.
        provider: the local value provider (a table, a network, a ``StructureLearner``).
        env: the env, checked against the parts and read for names (optional).
        spec: the action spec of the ``QValueModule`` to append (a value network without one).
        options: ``LocalRisk``'s keyword arguments (``eta``, ``g_min``, ``mask_threshold``, ...).
    """
    from torchrl.modules import QValueModule

    value_spec = _value_module_spec(value_network)
    count, shape = _spec_actions(value_spec if value_spec is not None else spec)
    if env is not None:
        batch = tuple(env.batch_size)
        if shape and batch and shape[: len(batch)] == batch:
            raise ValueError(
                f"the QValueModule's action spec has shape {list(shape)}: the env's batched "
                f"action_spec (batch_size {list(batch)}) was given; build QValueActor / "
                f"QValueModule with spec=env.action_spec_unbatched (one action per sample)"
            )
        options.setdefault("batch_size", batch)
        dependency = getattr(env, "dependency", None)
        experiments, actions, sensors = _provider_size(provider)
        if isinstance(dependency, torch.Tensor) and sensors is not None:
            if tuple(dependency.shape) != (actions, sensors):
                raise ValueError(
                    f"the env's dependency has shape {list(dependency.shape)} (actuators, "
                    f"sensors) but the local value provider {type(provider).__name__} has "
                    f"{actions} actuators and {sensors} sensors"
                )
        config = getattr(env, "config", None)
        if config is not None:
            options.setdefault("active", "blocked")  # the grid worlds' sensors: wall or obstacle
        for option_name in ("sensor_names", "actuator_names"):
            given = getattr(config, option_name, None)
            if given is not None:
                options.setdefault(option_name, given)
    elif shape and shape != ():
        raise ValueError(
            f"the QValueModule's action spec has shape {list(shape)}, a batched spec: build "
            f"QValueActor / QValueModule with spec=env.action_spec_unbatched"
        )
    if count is not None:
        options.setdefault("num_actions", count)
    risk = LocalRisk(provider, **options)
    modules = (
        list(value_network.module) if isinstance(value_network, TensorDictSequential) else None
    )
    if modules and isinstance(modules[-1], QValueModule):
        return TensorDictSequential(*modules[:-1], risk, modules[-1])
    parts = [value_network, risk]
    if spec is not None:
        parts.append(QValueModule(spec=spec))
    return TensorDictSequential(*parts)


class LocalRiskLoss(LossModule):
    """Trains a local value provider from ``("next", "local_reward")``; adds to any loss.

    - a provider with ``update_running_mean`` (``LocalRewardTable``, ``StructureLearner``):
      eq. 5's running mean of the fired actuator's local reward under the sensors before acting,
      applied in ``forward`` in training mode (as ``FactorQLoss`` does; ``loss.eval()`` turns it
      off). Give it each transition once (the collected batch), so the running means and a
      ``StructureLearner``'s evidence count every firing once; ``loss_local`` is 0.
    - a network (``LocalRewardNetwork``, ``GatedLocalRewardNetwork``): ``loss_local =
      0.5 * mean((rho(o)[a] - r_L[a])**2)`` over the transitions, a gradient term to add to
      the agent's loss (``dqn_loss(sample)["loss"] + local_loss(sample)["loss_local"]``), plus
      the gated network's ``loss_regularisation`` folded in.

    Keys (``set_keys``): ``sensors``, ``action``, ``local_reward`` (under ``"next"``).

    Args:
        provider: the local value provider to train (the one the ``LocalRisk`` layer reads).
    """

    @dataclass
    class _AcceptedKeys:
        sensors: NestedKey = names.SENSORS
        action: NestedKey = names.ACTION
        local_reward: NestedKey = names.LOCAL_REWARD

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    out_keys = ["loss_local"]

    def __init__(self, provider: TensorDictModuleBase) -> None:
        super().__init__()
        # torchrl's pre-hook warns of target networks without an updater: this loss has none,
        # and without hooks the module call takes torch's fast path (a few us of every step)
        check = getattr(_torchrl_loss_common, "_updater_check_forward_prehook", None)
        for handle, hook in list(self._forward_pre_hooks.items()):
            if hook is check:
                del self._forward_pre_hooks[handle]
        self.risk = LocalRisk(provider)  # the provider's values for any batch (and its checks)
        self.provider = provider
        # the online step of a table or learner goes straight to its update_running_mean (its own
        # no_grad, or none needed: the learner's read path writes numbers through numpy)
        self._online: int | None = self.risk.num_experiments
        if getattr(type(provider), "update_running_mean", None) not in (
            LocalRewardTable.update_running_mean,
            StructureLearner.update_running_mean,
        ):
            self._online = None  # another provider's: under no_grad (_running_mean)

    def _forward_value_estimator_keys(self, **kwargs: Any) -> None:
        pass

    @property
    def in_keys(self) -> list[NestedKey]:
        keys = self.tensor_keys
        return [keys.sensors, keys.action, ("next", keys.local_reward)]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        # (submodules by their dict: LossModule's attribute lookup is a microsecond each)
        modules = self._modules
        keys, actions = self.tensor_keys, modules["risk"].num_actions
        batch = tuple(tensordict.batch_size)
        action = local_reward = sensors = None
        if (
            type(tensordict) is TensorDict
            and type(keys.action) is str
            and type(keys.sensors) is str
            and type(keys.local_reward) is str
        ):  # a plain TensorDict holds its entries in a dict, as get() returns them
            entries = tensordict._tensordict
            action, sensors = entries.get(keys.action), entries.get(keys.sensors)
            following = entries.get("next")
            if type(following) is TensorDict:
                local_reward = following._tensordict.get(keys.local_reward)
        if action is None or local_reward is None:  # (anything else: get(), its errors)
            action = tensordict.get(keys.action, None)
            local_reward = tensordict.get(("next", keys.local_reward), None)
        if action is None or local_reward is None:
            raise KeyError(
                f"LocalRiskLoss needs {keys.action!r} and ('next', {keys.local_reward!r}) (wrap "
                f"the env in SplitLocalReward(keep_reward=True)); the tensordict has "
                f"{list(tensordict.keys(True))}"
            )
        if action.shape == (*batch, actions):  # one-hot actions
            action = action.argmax(-1)
        if action.shape != batch:
            action = action.reshape(*batch)
        if action.dtype != torch.int64:
            action = action.to(torch.int64)
        if tuple(local_reward.shape) != (*batch, actions):
            raise ValueError(
                f"LocalRiskLoss: ('next', {keys.local_reward!r}) has shape "
                f"{list(local_reward.shape)}, expected {[*batch, actions]} (one local reward per "
                f"actuator of the provider)"
            )
        update = getattr(modules["provider"], "update_running_mean", None)
        if update is not None:
            if self.training:
                if sensors is None:
                    sensors = tensordict.get(keys.sensors)
                if batch == (self._online,):  # the online step of a table or learner
                    update(sensors, action, local_reward)
                else:  # (any provider's update, under torchrl's loss contexts)
                    with set_exploration_type(self.deterministic_sampling_mode):
                        with set_recurrent_mode(True):
                            self._running_mean(update, sensors, action, local_reward)
            zero = torch.zeros((), device=local_reward.device)
            # (one 0-d entry of this device in a []-batch: nothing for the constructor to check)
            return TensorDict._new_unsafe({"loss_local": zero}, batch_size=_NO_BATCH)
        # a network's values: under torchrl's loss contexts, as its other losses run theirs
        with set_exploration_type(self.deterministic_sampling_mode), set_recurrent_mode(True):
            rho = self.risk.local_values(tensordict)  # [*B, A], with a gradient
        out = TensorDict(batch_size=[])
        fired = action.unsqueeze(-1)
        error = rho.gather(-1, fired).squeeze(-1) - local_reward.gather(-1, fired).squeeze(-1)
        loss = 0.5 * error.pow(2).mean()
        regularisation = getattr(self.provider, "regularisation", None)
        if regularisation is not None:
            loss = loss + regularisation()
        out.set("loss_local", loss)
        return out

    @torch.no_grad()
    def _running_mean(
        self,
        update: Callable[..., object],  # the provider's update_running_mean
        sensors: torch.Tensor,
        action: torch.Tensor,
        local_reward: torch.Tensor,
    ) -> None:
        count, width = self.risk.num_experiments, sensors.shape[-1]
        batch = tuple(action.shape)
        if batch == (count,):  # one transition per experiment (the online step): as it is
            update(sensors, action, local_reward)
            return
        if count != 1 and len(batch) > 1 and batch[0] == count and batch[-1] != count:
            # a [S, T] rollout: experiments last
            sensors, action = sensors.movedim(0, -2), action.movedim(0, -1)
            local_reward = local_reward.movedim(0, -2)
        elif count != 1 and (not batch or batch[-1] != count):
            raise ValueError(
                f"LocalRiskLoss: the provider holds S={count} experiments but the transitions "
                f"have batch_size {list(batch)}: expected [..., {count}] or [{count}, ...]"
            )
        rows = sensors.reshape(-1, count, width)
        actions = action.reshape(-1, count)
        rewards = local_reward.reshape(-1, count, local_reward.shape[-1])
        if isinstance(self.provider, StructureLearner):  # one [S] step at a time
            for row in range(rows.shape[0]):
                update(rows[row], actions[row], rewards[row])
            return
        if count == 1:  # one shared provider: the table's own [N] form (experiment 0)
            update(rows.reshape(-1, width), actions.reshape(-1), rewards.flatten(0, 1))
            return
        experiment = torch.arange(count, device=action.device).expand(rows.shape[0], count)
        update(rows, actions, rewards, experiment=experiment)


# torchrl's loss metaclass wraps every loss's forward in two context managers (the exploration
# type and the recurrent mode, ~20 us a call, the dearest part of a table's online step); a
# table's or learner's update runs no module, so LocalRiskLoss enters them itself, around the
# network it reads (a subclass is wrapped again by the metaclass, as any loss is)
LocalRiskLoss.forward = LocalRiskLoss.forward.__wrapped__  # type: ignore[attr-defined,method-assign]


@dataclass
class RiskSummary:
    """Per-episode counts of what the layer did, for the logs: states where it penalised
    something, how often each actuator was penalised and its mean penalty, and how often the
    greedy action on ``C(s)`` differs from the greedy action on the task values (the layer's
    overrides).

    Call ``update(td)`` with each step's tensordict (after the policy), ``episode()`` at the end
    of an episode: it returns the summary and starts the next.

    Args:
        actuator_names: one name per actuator (``LocalRisk.actuator_names``).
        threshold: a penalty ``G rho_a`` below ``-threshold`` counts as penalising ``a``.
        combined_key: where the layer wrote ``C(s)`` (the policy's ``action_value``).
        steps, risky_steps, overrides, penalised, penalty_sum: the episode's running counts
            (start empty; ``episode()`` returns and clears them).
    """

    actuator_names: Sequence[str]
    threshold: float = 0.05
    combined_key: NestedKey = names.ACTION_VALUE
    steps: int = 0
    risky_steps: int = 0
    overrides: int = 0
    penalised: list = field(default_factory=list)
    penalty_sum: list = field(default_factory=list)

    def __post_init__(self) -> None:
        self.actuator_names = tuple(self.actuator_names)
        self._clear()

    @classmethod
    def for_env(cls, env: Any, **options: Any) -> RiskSummary:
        """A summary named by ``env``'s actuators (``env.config.actuator_names``, or the env's
        own ``actuator_names``), so nothing is typed by hand.

        Args:
            env: the env the policy acts in.
            options: the other fields (``threshold``, ``combined_key``).
        """
        config = getattr(env, "config", None)
        given = getattr(config, "actuator_names", None)
        given = getattr(env, "actuator_names", None) if given is None else given
        if given is None:
            raise ValueError(
                f"{type(env).__name__} names no actuators (no config.actuator_names): pass "
                f"RiskSummary(actuator_names=...) or find_local_risk(policy).actuator_names"
            )
        return cls(actuator_names=tuple(str(name) for name in given), **options)

    def _clear(self) -> None:
        self.steps = self.risky_steps = self.overrides = 0
        self.penalised = [0] * len(self.actuator_names)
        self.penalty_sum = [0.0] * len(self.actuator_names)

    def update(self, tensordict: TensorDictBase) -> None:
        g = tensordict.get(NORMALISER).reshape(-1, 1)
        rho = tensordict.get(names.LOCAL_VALUE)
        penalty = g * rho.reshape(g.shape[0], -1)  # [M, A]
        flagged = penalty < -self.threshold
        self.steps += penalty.shape[0]
        self.risky_steps += int(flagged.any(-1).sum())
        # per actuator at once (two reads, not two per actuator: it runs at every step)
        counts = flagged.sum(0).tolist()
        sums = torch.where(flagged, penalty, 0.0).sum(0).tolist()
        for actuator, (count, total) in enumerate(zip(counts, sums, strict=True)):
            self.penalised[actuator] += count
            self.penalty_sum[actuator] += total
        task = tensordict.get(TASK_VALUE, None)
        combined = tensordict.get(self.combined_key, None)
        if task is not None and combined is not None:  # greedy on C(s) differs from greedy on Q
            greedy = task.reshape(penalty.shape).argmax(-1)
            self.overrides += int((greedy != combined.reshape(penalty.shape).argmax(-1)).sum())

    def episode(self) -> dict:
        summary = {
            "steps": self.steps,
            "risky_steps": self.risky_steps,
            "overrides": self.overrides,
            "penalised": dict(zip(self.actuator_names, self.penalised, strict=True)),
            "mean_penalty": {
                name: (total / count if count else 0.0)
                for name, total, count in zip(
                    self.actuator_names, self.penalty_sum, self.penalised, strict=True
                )
            },
        }
        self._clear()
        return summary

    @staticmethod
    def line(summary: dict) -> str:
        """One log line of an ``episode()`` summary (``base.risk_text.summary_line``)."""
        return summary_line(summary)
