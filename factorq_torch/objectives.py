"""The learning rules as torchrl losses: ``TabularQLoss`` (eq. 1) and ``FactorQLoss`` (eqs. 4-5).

Each loss reads a transition (``[S]`` experiments, one step each), computes the paper's target
with the functions of ``factorq_torch.functional``, and writes a TensorDict of ``loss_*``
entries. Inputs are never mutated.

**How the task update (eqs. 1 and 4) is applied.** ``loss_task = alpha * 0.5 * sum(td_error**2)``
over the experiments, with ``td_error = Q(s, a) - target`` and the target detached. Its gradient
with respect to the visited entry ``Q(s, a)`` is exactly ``alpha * (Q - target)`` (one rounding:
the factors 0.5 and 2 are exact), each experiment owns its own entry (a sum, not a mean), so one
plain SGD step of learning rate 1 (``tabular_optimizer``) gives, bit for bit,
``Q + alpha (target - Q)`` = ``functional.q_update``. The same loss trains a neural value
provider unchanged (any optimizer, ``alpha`` then only scales the step).

Why alpha sits in the loss and not in the optimizer: one SGD step of learning rate ``alpha`` on
``0.5 * td_error**2`` is the same update in exact arithmetic, but not in float32 on CPUs with FMA:
torch's vectorised ``param.add_(grad, alpha=-lr)`` (plain, foreach and fused SGD alike) rounds
``Q - alpha * grad`` once instead of twice, and about 17% of random entries then differ from
``Q + alpha (target - Q)`` in the last bit (measured on AVX2). With learning rate 1 the product
``-1 * grad`` is exact, so the only multiplication by ``alpha`` is the loss's.

**The direct tabular step.** ``loss.tabular_step(td)`` applies the same update without
autograd: it computes the target exactly as ``forward`` does and writes
``functional.q_update(Q(s, a), target, alpha)`` into the table entry (and eq. 5, in training mode),
which is bit for bit what ``forward``, ``backward`` and one step of ``tabular_optimizer`` give
(``Q - fl(alpha td)`` and ``Q + fl(alpha (-td))`` are the same float). ``OnlineCollector`` uses it
when it built the optimizer itself, ``supports_tabular_step()`` holds (a ``TaskQTable`` as the
only parameter, reduction ``"sum"``) and no hook watches the loss's ``forward`` (a trainer that
reads ``td_error`` from it keeps getting it): a step then builds no graph, no sparse gradient and
no optimizer call.

**How the local update (eq. 5) is applied.** Eq. 5 is a running mean (``alpha_L = 1 / kappa``),
not a gradient step. Like a BatchNorm's running statistics, it is applied by
``FactorQLoss.forward`` in training mode (the default; ``loss.eval()`` turns it off): after the
target has been computed with the local tables as they were (so eq. 4's ``C(s')`` sees them before
this step's update, SPEC section 3), the loss calls the local provider's
``update_running_mean(sensors, action, local_reward, mask)`` (``LocalRewardTable``), under
``torch.no_grad()``. Call the loss once per step. A neural local provider without that method
learns from ``loss_local = 0.5 * sum((rho(s)[a] - r_L[a])**2)`` instead (for the tables it is a
constant, reported for monitoring).

Bootstrapping uses ``("next", "terminated")`` only: a truncated transition still bootstraps.
Experiments where the optional ``("collector", "mask")`` ``[S]`` is False contribute nothing and
their tables do not change (the collector masks finished experiments this way).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from tensordict import NestedKey, TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.objectives import LossModule

from factorq_torch.base import keys as names
from factorq_torch.base.config import AgentConfig
from factorq_torch.base.indices import row_starts
from factorq_torch.base.validation import check_finite, check_indices, check_same_device
from factorq_torch.functional import (
    arbitrated_normaliser,
    combined_values,
    factorq_target,
    normaliser,
    q_learning_target,
    q_update,
    significant_local,
)
from factorq_torch.tables import TaskQTable, experiment_index

REDUCTIONS = ("sum", "mean")


def _check_provider(name: str, module: object) -> None:
    """A value provider must be a TensorDict module (a table, a network, a sequence of them)."""
    if not isinstance(module, TensorDictModuleBase):
        raise TypeError(
            f"{name} must be a TensorDict module (e.g. TaskQTable, LocalRewardTable or a "
            f"network), got {type(module).__name__}"
        )


def tabular_optimizer(loss: LossModule) -> torch.optim.SGD:
    """Plain SGD of learning rate 1 over ``loss.parameters()``: one ``step()`` after
    ``loss(td)["loss_task"].backward()`` applies ``Q + alpha (target - Q)`` exactly.

    Args:
        loss: a ``FactorQLoss`` or ``TabularQLoss`` (its tables' parameters are stepped).
    """
    return torch.optim.SGD(loss.parameters(), lr=1.0)


class _TransitionLoss(LossModule):
    """Reading and checking one step of ``S`` experiments, shared by the two losses."""

    def __init__(self, *, gamma: float, alpha: float, reduction: str) -> None:
        super().__init__()
        AgentConfig(gamma=gamma, alpha=alpha)  # validates both, naming the one out of range
        if reduction not in REDUCTIONS:
            raise ValueError(f"reduction={reduction!r} is unknown: choose one of {REDUCTIONS}")
        self.gamma, self.alpha, self.reduction = float(gamma), float(alpha), reduction

    @property
    def _task_provider(self) -> TensorDictModuleBase:
        return self.task_value_network

    def _forward_value_estimator_keys(self, **kwargs: Any) -> None:
        """No value estimator: the target is computed here, from ``functional`` (DESIGN 5)."""

    def _batch(self, tensordict: TensorDictBase) -> tuple[int, ...]:
        """The batch ``[*B]`` of transitions (any shape; see ``_experiment``)."""
        return tuple(tensordict.batch_size)

    def _experiment(self, tensordict: TensorDictBase) -> torch.Tensor | None:
        """Each transition's experiment ``[*B]``, or ``None`` for the online step: a ``[S]``
        batch without ``keys.EXPERIMENT``, one transition per experiment (nothing to merge).

        ``S`` is the task provider's ``num_experiments``; a provider without ``state_index``
        (a network: ``[..., S]`` inputs, the experiment last) gets its batch as it is.
        """
        count = getattr(self._task_provider, "num_experiments", None)
        batch = tuple(tensordict.batch_size)
        if count is None or not hasattr(self._task_provider, "state_index"):
            return None
        if batch == (count,) and names.EXPERIMENT not in tensordict.keys():
            return None
        return experiment_index(tensordict, count, type(self).__name__)

    def _entry_weight(
        self, tensordict: TensorDictBase, experiment: torch.Tensor | None, action: torch.Tensor
    ) -> torch.Tensor | None:
        """``1 / n`` per transition, ``n`` the transitions of the batch on its table entry
        ``(experiment, state, action)``: the minibatch update moves ``Q(s, a)`` by ``alpha`` times
        the *mean* TD error of its transitions. ``None`` (weight 1) for the online step and for
        providers without ``state_index`` (networks: a plain sum)."""
        state_index = getattr(self._task_provider, "state_index", None)
        if experiment is None or state_index is None:
            return None
        provider = self._task_provider
        state = state_index(tensordict).reshape(-1)  # [M]
        row = experiment.reshape(-1) * provider.num_states + state  # [M]
        entry = row * provider.num_actions + action.reshape(-1)  # [M]
        _, inverse, counts = torch.unique(entry, return_inverse=True, return_counts=True)
        weight = 1.0 / counts[inverse].to(torch.float32)  # [M]
        return weight.reshape(action.shape)

    def _read(self, tensordict: TensorDictBase, key: NestedKey, trailing: tuple) -> torch.Tensor:
        """``tensordict[key]`` of shape ``[*B, *trailing]`` (``[*B, 1]`` accepted for ``[*B]``)."""
        value = tensordict.get(key, None)
        name = type(self).__name__
        if value is None:
            raise KeyError(f"{name} needs {key!r} in the tensordict (see loss.in_keys)")
        shape = (*tensordict.batch_size, *trailing)
        if not trailing and tuple(value.shape) == (*shape, 1):
            value = value.squeeze(-1)
        if tuple(value.shape) != shape:
            raise ValueError(
                f"{name}: {key!r} has shape {list(value.shape)}, expected {list(shape)}"
            )
        return value

    def _read_reward(
        self,
        tensordict: TensorDictBase,
        key: NestedKey,
        trailing: tuple,
        device: torch.device,
        dtype: torch.dtype,
    ) -> torch.Tensor:
        """A reward ``[*B, *trailing]`` on the tables' ``device``, of the values' ``dtype`` (a
        float64 reward against float32 tables would be rounded differently by the two update
        paths, or fail in ``index_copy_``), finite (a NaN or an infinity would make the loss, the
        targets and the local tables NaN from then on)."""
        value = self._read(tensordict, key, trailing)
        name = type(self).__name__
        check_same_device(name, repr(key), value, device)
        if value.dtype != dtype:
            raise TypeError(
                f"{name}: {key!r} is {value.dtype} but the values are {dtype}: give {dtype} "
                f"rewards (e.g. torchrl's DoubleToFloat transform on the env)"
            )
        return check_finite(name, repr(key), value, cause="the env or a transform gave it")

    def _check_overflow(self, what: str, value: torch.Tensor) -> None:
        """Refuse a target (eqs. 1 and 4), TD error or updated value that overflowed float32:
        finite rewards and values can still add up past float32's range (a reward of 3e38), and
        the step would write an infinity into the table (nothing is written then)."""
        cause = "rewards or values too large for float32 (|r + gamma * max C(s')| > 3.4e38)"
        check_finite(type(self).__name__, what, value, cause=cause)

    def _read_action(self, tensordict: TensorDictBase, num_actions: int) -> torch.Tensor:
        key = self.tensor_keys.action
        action = self._read(tensordict, key, ())
        if action.dtype not in (torch.int64, torch.int32):
            raise ValueError(
                f"{type(self).__name__}: {key!r} must be integer action "
                f"indices in [0, {num_actions}), got dtype {action.dtype}"
            )
        check_indices(
            type(self).__name__, key if isinstance(key, str) else repr(key), action, num_actions
        )
        return action.to(torch.int64)

    def _read_terminated(self, tensordict: TensorDictBase) -> torch.Tensor:
        terminated = self._read(tensordict, ("next", self.tensor_keys.terminated), ())
        if terminated.dtype != torch.bool:
            raise ValueError(f"{type(self).__name__}: terminated must be bool")
        return terminated

    def _mask(self, tensordict: TensorDictBase, batch: tuple) -> torch.Tensor | None:
        """The optional mask ``[*B]`` bool (``[*B, 1]`` accepted), else None."""
        mask = tensordict.get(self.tensor_keys.mask, None)
        if mask is None:
            return None
        if not isinstance(mask, torch.Tensor) or mask.dtype != torch.bool:
            raise TypeError(f"{type(self).__name__}: mask must be a bool tensor [{list(batch)}]")
        if tuple(mask.shape) == (*batch, 1):
            mask = mask.squeeze(-1)
        if tuple(mask.shape) != batch:
            raise ValueError(
                f"{type(self).__name__}: mask has shape {list(mask.shape)}, expected "
                f"{list(batch)} (one flag per transition)"
            )
        return mask

    def supports_tabular_step(self) -> bool:
        """Whether ``tabular_step`` gives what ``forward`` + ``backward`` + one step of
        ``tabular_optimizer(self)`` give: the task provider is a ``TaskQTable``, its table is the
        loss's only parameter (no network to train by gradient) and the reduction is ``"sum"``."""
        provider = self._task_provider
        return (
            isinstance(provider, TaskQTable)
            and self.reduction == "sum"
            and [id(p) for p in self.parameters()] == [id(provider.table)]
        )

    def _takes_tabular_step(self, tensordict: TensorDictBase) -> bool:
        """Whether ``tabular_step`` applies to ``tensordict``: the online step (batch_size
        ``[S]``, no ``keys.EXPERIMENT`` entry); a loss that does not support it raises."""
        if not self.supports_tabular_step():
            raise ValueError(
                f"{type(self).__name__}.tabular_step needs a TaskQTable as the only parameter "
                f"and reduction='sum'; use forward + backward + an optimizer step instead"
            )
        return self._experiment(tensordict) is None

    @torch.no_grad()
    def _write_task_update(
        self,
        tensordict: TensorDictBase,
        action: torch.Tensor,
        target: torch.Tensor,
        mask: torch.Tensor | None,
    ) -> None:
        """``Q(s, a) <- q_update(Q(s, a), target, alpha)`` of every experiment (the online
        ``[S]`` step: one entry each), unchanged where ``mask`` is False or the table is
        frozen (``requires_grad=False``: the optimizer would not move it either)."""
        provider = self._task_provider
        table = provider.table
        if not table.requires_grad:
            return
        state = provider.state_index(tensordict)  # [S]
        count, states, width = table.shape
        # The flat entry (experiment, state, action) of each experiment, -1 (refused by
        # index_select) where the state or the action is out of range.
        inside = (state >= 0) & (state < states) & (action >= 0) & (action < width)
        rows = row_starts(count, states * width, state.device)  # [S], where each table starts
        entry = torch.where(inside, rows + state * width + action, -1)
        flat = table.detach().view(-1)
        try:
            q_sa = flat.index_select(0, entry)  # [S], Q(s, a)
        except IndexError:
            if bool(((state < 0) | (state >= states)).any()):
                raise ValueError(provider._misfit(state)) from None
            raise ValueError(
                f"{type(self).__name__}: action holds values outside [0, {width})"
            ) from None
        new = q_update(q_sa, target, self.alpha)  # eqs. 1 and 4
        if mask is not None:
            new = torch.where(mask, new, q_sa)
        self._check_overflow("the updated Q(s, a) (eqs. 1, 4)", new)  # an infinite target too
        flat.index_copy_(0, entry, new)

    @staticmethod
    def _provide(
        provider: TensorDictModuleBase,
        tensordict: TensorDictBase,
        key: NestedKey,
        experiment: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Run a value provider on a shallow copy of its inputs (the input is not mutated); its
        values must be finite (a NaN or an infinity would spread through every target)."""
        inputs = tensordict.select(*provider.in_keys)
        if experiment is not None:
            inputs.set(names.EXPERIMENT, experiment)
        value = provider(inputs).get(key)
        return check_finite(f"{type(provider).__name__} (read by the loss)", repr(key), value)

    def _reduce(self, per_experiment: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
        """Sum (or mean) over the transitions that count."""
        if mask is not None:
            per_experiment = torch.where(mask, per_experiment, torch.zeros_like(per_experiment))
        total = per_experiment.sum()
        if self.reduction == "mean":
            count = per_experiment.numel() if mask is None else mask.sum().clamp(min=1)
            total = total / count
        return total

    def _task_loss(
        self,
        q: torch.Tensor,
        action: torch.Tensor,
        target: torch.Tensor,
        mask: torch.Tensor | None,
        weight: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``alpha * 0.5 * sum(weight * td_error**2)`` and ``td_error = Q(s, a) - target``
        ``[*B]`` (``weight``: ``_entry_weight``, None for 1)."""
        q_sa = q.gather(-1, action.unsqueeze(-1)).squeeze(-1)  # [*B]
        td_error = q_sa - target.detach()
        per_transition = self.alpha * (0.5 * td_error.pow(2))
        if weight is not None:
            per_transition = per_transition * weight
        return self._reduce(per_transition, mask), td_error


class TabularQLoss(_TransitionLoss):
    """Q-learning's update (paper eq. 1) as a loss, for any provider of ``action_value``.

    ``Q(s, a) <- Q(s, a) + alpha [r + gamma max_a' Q(s', a') - Q(s, a)]``, ``r`` alone where
    ``("next", "terminated")``; ``r`` is the env's (conventional) reward. Applied by one step of
    ``tabular_optimizer(loss)`` on ``loss_task`` (see the module docstring).

    Args:
        task_value_network: writes ``action_value`` ``[S, A]`` (e.g. ``TaskQTable`` with
            ``with_sensors=True``); run with gradients at ``s``, without at ``s'``.
        gamma: discount, in ``[0, 1)``.
        alpha: learning rate of eq. 1, in ``(0, 1]``.
        reduction: ``"sum"`` (exact tabular update) or ``"mean"`` over experiments.

    Keys (``set_keys``): ``action_value``, ``action``, ``reward`` and ``terminated`` (both read
    under ``"next"``), ``mask`` (``("collector", "mask")``, optional). Output: ``loss_task``
    (scalar) and ``td_error`` ``[S]`` (detached).
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable input keys (``loss.set_keys(reward="conventional_reward")``)."""

        action_value: NestedKey = "action_value"
        action: NestedKey = "action"
        reward: NestedKey = "reward"
        terminated: NestedKey = "terminated"
        mask: NestedKey = ("collector", "mask")

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    out_keys = ["loss_task", "td_error"]

    def __init__(
        self,
        task_value_network: TensorDictModuleBase,
        *,
        gamma: float = 0.9,
        alpha: float = 0.2,
        reduction: str = "sum",
    ) -> None:
        super().__init__(gamma=gamma, alpha=alpha, reduction=reduction)
        _check_provider("task_value_network", task_value_network)
        self.task_value_network = task_value_network

    @property
    def in_keys(self) -> list[NestedKey]:
        keys = self.tensor_keys
        provider = list(self.task_value_network.in_keys)
        return [
            *provider,
            keys.action,
            *(("next", key) if isinstance(key, str) else ("next", *key) for key in provider),
            ("next", keys.reward),
            ("next", keys.terminated),
        ]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        # read
        keys, batch = self.tensor_keys, self._batch(tensordict)
        experiment = self._experiment(tensordict)  # [*B] (None: the online [S] step)
        provider = self.task_value_network
        q = self._provide(provider, tensordict, keys.action_value, experiment)  # [*B, A]
        action = self._read_action(tensordict, q.shape[-1])  # [*B]
        reward = self._read_reward(tensordict, ("next", keys.reward), (), q.device, q.dtype)
        terminated = self._read_terminated(tensordict)  # [*B]
        mask = self._mask(tensordict, batch)
        weight = self._entry_weight(tensordict, experiment, action)
        with torch.no_grad():
            next_td = tensordict.get("next")
            q_next = self._provide(provider, next_td, keys.action_value, experiment)  # [*B, A]
        # compute: eq. 1's target and the loss whose SGD step is eq. 1's update
        target = q_learning_target(reward, q_next, terminated, self.gamma)  # [*B]
        loss_task, td_error = self._task_loss(q, action, target, mask, weight)
        self._check_overflow("the TD error Q(s, a) - target (eq. 1)", td_error)  # and target
        # write
        return TensorDict(loss_task=loss_task, td_error=td_error.detach(), batch_size=[])

    @torch.no_grad()
    def tabular_step(self, tensordict: TensorDictBase) -> bool:
        """Eq. 1's update written straight into the table: what ``forward``, ``backward`` and
        one step of ``tabular_optimizer`` give, bit for bit, without autograd (see the module
        docstring; ``supports_tabular_step()``). Returns False, changing nothing, for anything
        but the online ``[S]`` step (transitions with experiment indices: use ``forward``)."""
        if not self._takes_tabular_step(tensordict):
            return False
        keys, batch = self.tensor_keys, self._batch(tensordict)
        provider = self.task_value_network
        action = self._read_action(tensordict, provider.num_actions)  # [S]
        table = provider.table
        reward = self._read_reward(tensordict, ("next", keys.reward), (), table.device, table.dtype)
        terminated = self._read_terminated(tensordict)  # [S]
        mask = self._mask(tensordict, batch)
        q_next = self._provide(provider, tensordict.get("next"), keys.action_value)  # [S, A]
        target = q_learning_target(reward, q_next, terminated, self.gamma)  # [S], eq. 1
        self._write_task_update(tensordict, action, target, mask)
        return True


class FactorQLoss(_TransitionLoss):
    """Factor-Q's updates (paper eqs. 4 and 5) as a loss.

    - eq. 4 (gradient, ``loss_task``): ``Q(s, a) <- Q(s, a) + alpha [r_task + gamma max_a' C(s')
      - Q(s, a)]`` with ``C(s') = Q(s') + G(s') rho(s')`` (eqs. 2-3 at ``s'``, local values before
      this step's eq. 5); ``r_task`` alone where ``("next", "terminated")``.
    - eq. 5 (running mean, in ``forward`` in training mode): ``kappa_a[o] += 1``,
      ``rho_a[o] += (r_L[a] - rho_a[o]) / kappa_a[o]`` for the chosen actuator ``a`` and the
      pattern ``o = o_D(a)`` of its parent sensors before acting (the local provider knows the
      dependency).

    See the module docstring for why ``loss_task`` carries ``alpha`` and how eq. 5 is applied.

    Args:
        task_value_network: writes ``action_value`` ``[S, A]`` (e.g. ``TaskQTable``).
        local_value_network: writes ``local_value`` ``[S, A]`` (e.g. ``LocalRewardTable``).
        gamma, alpha: discount and task learning rate (eq. 4).
        eta, g_min: eq. 3's margin and floor of ``G`` (the policy's values).
        reduction: ``"sum"`` (exact tabular update) or ``"mean"`` over experiments.
        risk_threshold, risk_gate: eq. 4's ``C(s')`` from ``functional.significant_local(rho,
            risk_threshold)`` where ``risk_gate`` (the policy's values; default: the paper).
        arbitration, local_span: eq. 4's ``C(s')`` with ``G = 1`` where the task takes priority
            (``functional.arbitrated_normaliser``; the policy's values; default: the paper).

    Keys (``set_keys``): ``action_value``, ``local_value``, ``action``, ``sensors`` (all
    sensors before acting, ``[S, K]``), ``reward`` (task reward), ``local_reward`` and
    ``terminated`` (the last three read under ``"next"``), ``mask`` (optional). Output:
    ``loss_task``, ``loss_local`` (scalars) and ``td_error`` ``[S]`` (detached); with a local
    provider that has ``regularisation()`` (``GatedLocalRewardNetwork``), ``loss_regularisation``.
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable input keys (``loss.set_keys(local_reward="collision")``)."""

        action_value: NestedKey = "action_value"
        local_value: NestedKey = "local_value"
        action: NestedKey = "action"
        sensors: NestedKey = "sensors"
        reward: NestedKey = "reward"
        local_reward: NestedKey = "local_reward"
        terminated: NestedKey = "terminated"
        mask: NestedKey = ("collector", "mask")

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    out_keys = ["loss_task", "loss_local", "td_error"]

    def __init__(
        self,
        task_value_network: TensorDictModuleBase,
        local_value_network: TensorDictModuleBase,
        *,
        gamma: float = 0.9,
        alpha: float = 0.2,
        eta: float = 0.1,
        g_min: float = 0.01,
        reduction: str = "sum",
        risk_threshold: float = 0.5,
        risk_gate: bool = False,
        arbitration: bool = False,
        local_span: float = 1.0,
    ) -> None:
        super().__init__(gamma=gamma, alpha=alpha, reduction=reduction)
        AgentConfig(
            eta=eta,
            g_min=g_min,
            risk_threshold=risk_threshold,
            risk_gate=risk_gate,
            arbitration=arbitration,
            local_span=local_span,
        )
        self.eta, self.g_min = float(eta), float(g_min)
        self.risk_threshold, self.risk_gate = float(risk_threshold), risk_gate
        self.arbitration, self.local_span = arbitration, float(local_span)
        _check_provider("task_value_network", task_value_network)
        self.task_value_network = task_value_network
        _check_provider("local_value_network", local_value_network)
        self.local_value_network = local_value_network

    @property
    def in_keys(self) -> list[NestedKey]:
        keys = self.tensor_keys
        providers = [*self.task_value_network.in_keys, *self.local_value_network.in_keys]
        providers = list(dict.fromkeys(providers))
        return [
            *providers,
            keys.action,
            keys.sensors,
            *(("next", key) if isinstance(key, str) else ("next", *key) for key in providers),
            ("next", keys.reward),
            ("next", keys.local_reward),
            ("next", keys.terminated),
        ]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        # read
        keys, batch = self.tensor_keys, self._batch(tensordict)
        experiment = self._experiment(tensordict)  # [*B] (None: the online [S] step)
        task, local = self.task_value_network, self.local_value_network
        q = self._provide(task, tensordict, keys.action_value, experiment)  # [*B, A]
        rho = self._provide(local, tensordict, keys.local_value, experiment)  # [*B, A]
        num_actions = q.shape[-1]
        action = self._read_action(tensordict, num_actions)  # [*B]
        num_sensors = getattr(self.local_value_network, "num_sensors", None)
        if num_sensors is None:  # a provider that does not declare K: take the entry's own
            num_sensors = getattr(tensordict.get(keys.sensors, None), "shape", (0,))[-1]
        sensors = self._read(tensordict, keys.sensors, (num_sensors,))  # [*B, K], before acting
        reward = self._read_reward(
            tensordict, ("next", keys.reward), (), q.device, q.dtype
        )  # [*B], task
        local_reward = self._read_reward(
            tensordict, ("next", keys.local_reward), (num_actions,), q.device, q.dtype
        )
        terminated = self._read_terminated(tensordict)  # [*B]
        mask = self._mask(tensordict, batch)
        weight = self._entry_weight(tensordict, experiment, action)
        with torch.no_grad():
            next_td = tensordict.get("next")
            q_next = self._provide(task, next_td, keys.action_value, experiment)
            rho_next = self._provide(local, next_td, keys.local_value, experiment)
        # compute: eq. 4's target from C(s') (eqs. 2-3 at s'), then the loss whose SGD step is
        # eq. 4's update; the local regression error on the fired actuator
        if self.risk_gate:  # the policy's local values (significant_local)
            rho_next = significant_local(rho_next, self.risk_threshold)  # [*B, A]
        g_next = normaliser(q_next, rho_next, eta=self.eta, g_min=self.g_min)  # [*B], eq. 3
        if self.arbitration:  # the policy's G: 1 where the task takes priority
            g_next = arbitrated_normaliser(q_next, rho_next, g_next, self.gamma, self.local_span)
        c_next = combined_values(q_next, rho_next, g_next)  # [*B, A], eq. 2
        target = factorq_target(reward, c_next, terminated, self.gamma)  # [*B], eq. 4
        loss_task, td_error = self._task_loss(q, action, target, mask, weight)
        self._check_overflow("the TD error Q(s, a) - target (eq. 4)", td_error)  # and target
        fired = action.unsqueeze(-1)
        local_error = rho.gather(-1, fired).squeeze(-1) - local_reward.gather(-1, fired).squeeze(-1)
        loss_local = self._reduce(0.5 * local_error.pow(2), mask)
        # eq. 5, after the target used the local tables as they were
        update = getattr(local, "update_running_mean", None)
        if self.training and update is not None:
            if experiment is None:  # the online step: the provider's own [S] form
                update(sensors, action, local_reward, mask)
            else:
                update(sensors, action, local_reward, mask, experiment=experiment)
        # write
        out = TensorDict(
            loss_task=loss_task,
            loss_local=loss_local,
            td_error=td_error.detach(),
            batch_size=[],
        )
        # a provider's own penalty (GatedLocalRewardNetwork's L1 on its gates), trained with
        # the rest: the collector steps on the sum of every loss_* entry
        regularisation = getattr(local, "regularisation", None)
        if regularisation is not None:
            out.set("loss_regularisation", regularisation())
        return out

    @torch.no_grad()
    def tabular_step(self, tensordict: TensorDictBase) -> bool:
        """Eqs. 4 and 5 written straight into the tables: what ``forward``, ``backward`` and one
        step of ``tabular_optimizer`` give, bit for bit, without autograd (see the module
        docstring; ``supports_tabular_step()``). Returns False, changing nothing, for anything
        but the online ``[S]`` step (transitions with experiment indices: use ``forward``)."""
        if not self._takes_tabular_step(tensordict):
            return False
        keys, batch = self.tensor_keys, self._batch(tensordict)
        task, local = self.task_value_network, self.local_value_network
        num_actions = task.num_actions
        action = self._read_action(tensordict, num_actions)  # [S]
        num_sensors = getattr(local, "num_sensors", None)
        if num_sensors is None:  # a provider that does not declare K: take the entry's own
            num_sensors = getattr(tensordict.get(keys.sensors, None), "shape", (0,))[-1]
        sensors = self._read(tensordict, keys.sensors, (num_sensors,))  # [S, K], before acting
        device, dtype = task.table.device, task.table.dtype
        reward = self._read_reward(tensordict, ("next", keys.reward), (), device, dtype)  # [S]
        local_reward = self._read_reward(
            tensordict, ("next", keys.local_reward), (num_actions,), device, dtype
        )
        terminated = self._read_terminated(tensordict)  # [S]
        mask = self._mask(tensordict, batch)
        next_td = tensordict.get("next")
        q_next = self._provide(task, next_td, keys.action_value)  # [S, A]
        rho_next = self._provide(local, next_td, keys.local_value)  # [S, A]
        if self.risk_gate:  # the policy's local values (significant_local)
            rho_next = significant_local(rho_next, self.risk_threshold)  # [S, A]
        g_next = normaliser(q_next, rho_next, eta=self.eta, g_min=self.g_min)  # [S], eq. 3
        if self.arbitration:  # the policy's G: 1 where the task takes priority
            g_next = arbitrated_normaliser(q_next, rho_next, g_next, self.gamma, self.local_span)
        c_next = combined_values(q_next, rho_next, g_next)  # [S, A], eq. 2
        target = factorq_target(reward, c_next, terminated, self.gamma)  # [S], eq. 4
        self._write_task_update(tensordict, action, target, mask)
        # eq. 5, after the target used the local tables as they were
        update = getattr(local, "update_running_mean", None)
        if self.training and update is not None:
            update(sensors, action, local_reward, mask)
        return True
