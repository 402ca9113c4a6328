"""Epsilon-greedy policies as TensorDict modules, with random tie-breaking (SPEC section 3).

The policies read values written by any value provider (a table or a network) and write
``action`` ``[S]`` int64 and ``exploratory`` ``[S]`` bool; ``FactorQPolicy`` also writes
``combined_value`` ``[S, A]``, eq. 2's ``C(s)`` with eq. 3's ``G``. torchrl's ``QValueModule``
always takes index 0 on an all-equal row and ``EGreedyModule`` does not report which actions
explored, so neither fits (DESIGN section 6).

Randomness: experiment ``i`` owns a counter-based stream (``factorq_torch.base.rng``) with key
``stream_keys[i]`` (by default ``derive_keys(seed, STREAM_POLICY, S)[i]``) and a decision counter
``counter[i]``. Its ``t``-th decision draws counters ``3t`` (explore?), ``3t + 1`` (the random
action) and ``3t + 2`` (the tie-break). The module advances ``counter`` itself on every call, so
there is no exploration schedule to step by hand; where the optional mask entry
``("collector", "mask")`` ``[S]`` is False the experiment is finished: it draws nothing and its
counter stays put (its ``action`` is computed but meaningless). Keys and counters are buffers, so
``state_dict()`` captures the streams exactly.

**Evaluation.** The policies follow torchrl's exploration switch: under
``set_exploration_type(ExplorationType.DETERMINISTIC)`` (or ``MODE``, ``MEAN``, ``MEDIAN``) they
act greedily, ties still broken at random by the same tie draw, and write ``exploratory`` all
False; under ``RANDOM`` or with no type set (the default, as in torchrl's collectors) they are
epsilon-greedy. A greedy decision consumes its counters like an exploring one.

**Any batch.** A tensordict of any batch shape ``[*B]`` is taken, each entry acting for the
experiment ``keys.EXPERIMENT`` names (absent: ``arange(S)`` over ``[S]``, 0 when ``S = 1``;
``tables.experiment_index``). Entries of one experiment in one call take its consecutive
decisions in flattened order.
"""

from __future__ import annotations

import numbers

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.nn.probabilistic import InteractionType, interaction_type

from factorq_torch.base.config import AgentConfig, check_exploration
from factorq_torch.base.indices import row_starts
from factorq_torch.base.rng import POLICY_DRAWS_PER_STEP, STREAM_POLICY, derive_keys, random_bits
from factorq_torch.base.validation import check_device, check_finite, check_seed
from factorq_torch.functional import (
    arbitrated_normaliser,
    combined_values,
    epsilon_greedy_from_bits,
    normaliser,
    risk_mask,
    significant_local,
)
from factorq_torch.tables import check_mask, experiment_index, is_online

#: The mask entry the collector writes: True where the experiment is still running.
MASK_KEY = ("collector", "mask")
#: torchrl exploration types (``set_exploration_type``) under which the policies act greedily.
GREEDY_TYPES = (
    InteractionType.DETERMINISTIC,
    InteractionType.MODE,
    InteractionType.MEAN,
    InteractionType.MEDIAN,
)


def explores() -> bool:
    """Whether the policies explore now: under torchrl's ``RANDOM`` exploration type or none set
    (the default), not under ``DETERMINISTIC``, ``MODE``, ``MEAN`` or ``MEDIAN``."""
    return interaction_type() not in GREEDY_TYPES


class EpsilonGreedyPolicy(TensorDictModuleBase):
    """Epsilon-greedy on ``action_value`` with uniform random tie-breaking (Q-learning, DQN).

    Args:
        num_experiments: ``S``, the experiments of the batch.
        seed: seed of the policy streams (``derive_keys(seed, STREAM_POLICY, S, offset)``).
        epsilon: probability of a uniformly random, exploratory action.
        offset: index of this batch's first experiment among all experiments.
        keys: explicit stream keys ``[S]`` int64 instead of ``seed`` / ``offset``.
        device: where the keys and counters live.
        exploration: ``"uniform"`` only: it reads no local values, so nothing can say which
            actuators are risky (``"risk-aware"`` is refused; ``FactorQPolicy`` takes it).

    Keys: reads ``action_value`` ``[S, A]`` (and ``("collector", "mask")`` ``[S]`` if present),
    writes ``action`` ``[S]`` int64 and ``exploratory`` ``[S]`` bool.

    Example:
        >>> from tensordict import TensorDict
        >>> policy = EpsilonGreedyPolicy(2, seed=0, epsilon=0.0)
        >>> td = TensorDict(action_value=torch.tensor([[0.0, 3.0, 1.0, 2.0]] * 2), batch_size=[2])
        >>> policy(td)["action"], policy.counter
        (tensor([1, 1]), tensor([1, 1]))
    """

    value_key = "action_value"

    def __init__(
        self,
        num_experiments: int,
        *,
        seed: int = 0,
        epsilon: float = 0.01,
        offset: int = 0,
        keys: torch.Tensor | None = None,
        device: torch.device | str | None = None,
        exploration: str = "uniform",
    ) -> None:
        super().__init__()
        check_exploration(exploration)
        if exploration != "uniform" and not isinstance(self, FactorQPolicy):
            raise ValueError(
                f"exploration={exploration!r} needs a local model to say which actuators are "
                f"risky, and {type(self).__name__} reads none (only {self.value_key!r}): use "
                f"FactorQPolicy with a local value provider, or exploration='uniform'"
            )
        self.exploration = exploration
        if isinstance(num_experiments, bool) or not isinstance(num_experiments, int):
            raise TypeError(f"num_experiments must be an int, got {num_experiments!r}")
        if num_experiments < 1:
            raise ValueError(f"num_experiments={num_experiments} is out of range: must be >= 1")
        AgentConfig(epsilon=epsilon)  # validates epsilon with a message naming it
        device = check_device("device", device)
        self.num_experiments = num_experiments
        self.epsilon = float(epsilon)
        self.in_keys = [self.value_key]
        self.out_keys = ["action", "exploratory"]
        self.register_buffer(
            "stream_keys", torch.zeros(num_experiments, dtype=torch.int64, device=device)
        )
        self.register_buffer(
            "counter", torch.zeros(num_experiments, dtype=torch.int64, device=device)
        )
        if keys is None:
            self.set_seed(seed, offset)
        else:
            self.set_stream_keys(keys)

    def set_seed(self, seed: int, offset: int = 0) -> None:
        """Derive the keys from ``seed`` (experiments ``offset ..``) and rewind the streams."""
        for name, value in (("seed", seed), ("offset", offset)):
            if isinstance(value, bool) or not isinstance(value, numbers.Integral):
                raise TypeError(f"{name} must be an int, got {value!r} ({type(value).__name__})")
            if value < 0:
                raise ValueError(f"{name}={value} is out of range: must be >= 0")
        check_seed("seed", int(seed))  # at most INT64_MAX: the keys are 64-bit
        self.set_stream_keys(derive_keys(seed, STREAM_POLICY, self.num_experiments, offset))

    @torch.no_grad()
    def set_stream_keys(self, keys: torch.Tensor) -> None:
        """Use the given stream keys ``[S]`` int64 and rewind the streams to their start."""
        if not isinstance(keys, torch.Tensor) or keys.dtype != torch.int64:
            raise TypeError("keys must be an int64 tensor (see factorq_torch.base.rng.derive_keys)")
        if tuple(keys.shape) != (self.num_experiments,):
            raise ValueError(
                f"keys has shape {list(keys.shape)}, expected [{self.num_experiments}] "
                f"(one stream key per experiment)"
            )
        self.stream_keys.copy_(keys)
        self.counter.zero_()

    def _values(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The values the greedy choice maximises, ``[*B, A]``, and where exploration may go
        (``[*B, A]`` bool; None: everywhere)."""
        return self._read_values(tensordict, self.value_key), None

    def _read_values(self, tensordict: TensorDictBase, key: str) -> torch.Tensor:
        value = tensordict.get(key, None)
        if value is None:
            raise KeyError(
                f"{type(self).__name__} needs {key!r} (written by a value provider such as "
                f"TaskQTable); the tensordict has {list(tensordict.keys())}"
            )
        batch = tuple(tensordict.batch_size)
        if value.dim() != len(batch) + 1 or tuple(value.shape[:-1]) != batch:
            raise ValueError(
                f"{type(self).__name__}: {key!r} has shape {list(value.shape)}, expected "
                f"[{', '.join(map(str, (*batch, 'num_actions')))}] (the tensordict's batch_size "
                f"{list(batch)} and one value per action)"
            )
        if not value.is_floating_point():
            raise ValueError(f"{type(self).__name__}: {key!r} must be floating point")
        return check_finite(type(self).__name__, repr(key), value)  # a NaN would choose silently

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        owner = type(self).__name__
        batch = tuple(tensordict.batch_size)
        values, allowed = self._values(tensordict)  # [*B, A], [*B, A] bool or None
        epsilon = self.epsilon if explores() else 0.0
        # [[0], [1], ...]: draw k of a decision (a cached constant)
        draws = row_starts(POLICY_DRAWS_PER_STEP, 1, self.counter.device, column=True)
        if is_online(
            tensordict, self.num_experiments
        ):  # one decision per experiment, in experiment order (the online step)
            mask = check_mask(tensordict.get(MASK_KEY, None), self.num_experiments, "policy")
            keys, position = self.stream_keys, self.counter  # [S]
            advance = 1 if mask is None else mask.to(torch.int64)
        else:  # experiment e's entries take its next decisions, in flattened order
            experiment = experiment_index(tensordict, self.num_experiments, owner)  # [*B]
            mask = tensordict.get(MASK_KEY, None)
            flat = experiment.reshape(-1)  # [M]
            taken = torch.nn.functional.one_hot(flat, self.num_experiments)  # [M, S]
            if mask is not None:
                taken = taken * mask.reshape(-1, 1).to(torch.int64)
            rank = (taken.cumsum(0) - taken).gather(1, flat.unsqueeze(1)).squeeze(1)  # [M]
            keys, position = self.stream_keys[flat], self.counter[flat] + rank
            advance = taken.sum(0)  # [S]
        bits = random_bits(keys, position * POLICY_DRAWS_PER_STEP + draws)  # [3, M]
        width = values.shape[-1]
        action, exploratory = epsilon_greedy_from_bits(
            values.detach().reshape(-1, width),
            epsilon,
            bits[0],
            bits[1],
            bits[2],
            None if allowed is None else allowed.reshape(-1, width),
        )
        # The stream advances with each decision (only where the experiment is still running).
        self.counter.add_(advance)  # (in place: no Module.__setattr__ per step)
        tensordict.set("action", action.reshape(batch))
        tensordict.set("exploratory", exploratory.reshape(batch))
        return tensordict


class FactorQPolicy(EpsilonGreedyPolicy):
    """Factor-Q's action choice: epsilon-greedy on ``C(s) = Q(s) + G rho`` (eqs. 2-3).

    Args: as ``EpsilonGreedyPolicy``, plus ``eta`` and ``g_min`` of eq. 3's normaliser, and
    ``AgentConfig``'s ``risk_threshold``, ``risk_gate`` (eqs. 2-3 on
    ``functional.significant_local(rho, risk_threshold)``) and ``exploration`` (``"risk-aware"``:
    exploratory actions uniform among ``functional.risk_mask(rho, risk_threshold)``, the
    actuators the local model does not call risky; docs/decisions.md, "Exploration that respects
    known risk"), and ``arbitration`` with ``gamma`` and ``local_span`` (``G = 1`` where the task
    takes priority, ``functional.arbitrated_normaliser``; docs/decisions.md, "Arbitration: when
    the task takes priority"). Their defaults are the paper's.

    Keys: reads ``action_value`` ``[S, A]`` and ``local_value`` ``[S, A]``, writes
    ``combined_value`` ``[S, A]``, ``action`` ``[S]`` and ``exploratory`` ``[S]``.

    Example:
        >>> from tensordict import TensorDict
        >>> policy = FactorQPolicy(1, epsilon=0.0)
        >>> td = TensorDict(
        ...     action_value=torch.zeros(1, 4),  # unvisited state: G = g_min = 0.01
        ...     local_value=torch.tensor([[-1.0, 0.0, 0.0, -1.0]]),  # north, east bump
        ...     batch_size=[1],
        ... )
        >>> td = policy(td)
        >>> td["combined_value"], td["action"] in (1, 2)
        (tensor([[-0.0100,  0.0000,  0.0000, -0.0100]]), True)
    """

    def __init__(
        self,
        num_experiments: int,
        *,
        seed: int = 0,
        epsilon: float = 0.01,
        eta: float = 0.1,
        g_min: float = 0.01,
        offset: int = 0,
        keys: torch.Tensor | None = None,
        device: torch.device | str | None = None,
        risk_threshold: float = 0.5,
        risk_gate: bool = False,
        exploration: str = "uniform",
        arbitration: bool = False,
        gamma: float = 0.9,
        local_span: float = 1.0,
    ) -> None:
        super().__init__(
            num_experiments,
            seed=seed,
            epsilon=epsilon,
            offset=offset,
            keys=keys,
            device=device,
            exploration=exploration,
        )
        AgentConfig(
            eta=eta,
            g_min=g_min,
            risk_threshold=risk_threshold,
            risk_gate=risk_gate,
            exploration=exploration,
            arbitration=arbitration,
            gamma=gamma,
            local_span=local_span,
        )
        self.eta, self.g_min = float(eta), float(g_min)
        self.risk_threshold, self.risk_gate = float(risk_threshold), risk_gate
        self.arbitration, self.gamma, self.local_span = arbitration, float(gamma), float(local_span)
        self.in_keys = ["action_value", "local_value"]
        self.out_keys = ["combined_value", "action", "exploratory"]

    def _values(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor | None]:
        q = self._read_values(tensordict, "action_value")  # [S, A]
        rho = self._read_values(tensordict, "local_value")  # [S, A]
        if rho.shape != q.shape:
            raise ValueError(
                f"FactorQPolicy: local_value has shape {list(rho.shape)} but action_value has "
                f"{list(q.shape)}: one local value per action is needed"
            )
        allowed = None
        if self.exploration == "risk-aware":
            allowed = risk_mask(rho.detach(), self.risk_threshold)  # [S, A], never all False
        if self.risk_gate:
            rho = significant_local(rho, self.risk_threshold)  # [S, A]
        g = normaliser(q, rho, eta=self.eta, g_min=self.g_min)  # [S], eq. 3
        if self.arbitration:  # G = 1 where the task takes priority
            g = arbitrated_normaliser(q, rho, g, self.gamma, self.local_span)
        combined = combined_values(q, rho, g)  # [S, A], eq. 2
        tensordict.set("combined_value", combined)
        return combined, allowed
