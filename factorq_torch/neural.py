"""Neural value providers: the task Q-network and the local reward network (Factor-DQN).

They write the same keys as the tables of ``factorq_torch.tables``, so the policies
(``FactorQPolicy``, ``EpsilonGreedyPolicy``), the losses (``FactorQLoss``, ``TabularQLoss``) and
the collector run unchanged with either (DESIGN section 1):

- ``TaskQNetwork`` writes ``action_value`` ``[..., S, A]`` from the cell (one-hot) or, with
  ``with_proximity=True`` (the DQN baseline's observation), from the cell one-hot concatenated with
  the 4 proximity bits;
- ``LocalRewardNetwork`` writes ``local_value`` ``[..., S, A]``: for every actuator ``a`` a small
  network of the readings of its parent sensors (``dependency``; the paper: its own proximity
  bit) predicts the local reward of firing ``a``.
  ``FactorQLoss`` trains it on ``loss_local = 0.5 * (rho[a] - r_L[a])**2`` of the fired actuator
  ``a`` (it has no ``update_running_mean``, the tables' eq. 5).

**One network per experiment.** A batch of ``S`` experiments holds ``S`` independent networks,
stored as stacked weights ``[S, ..., in, out]`` and applied with one batched matmul. A loss summed
over experiments gives each network the gradient of its own experiment only, and Adam keeps
per-parameter moments, so nothing is shared across the batch. Experiment ``i``'s initial weights
are drawn from a generator seeded with its own key (``derive_keys(seed, STREAM_TASK_NETWORK, S,
offset)[i]``, ``STREAM_LOCAL_NETWORK`` for the local network): the same whatever the batch size.

**Initial values.** ``zero_output=True`` (the default) zeroes the output layer, so every value
starts at exactly 0, as the tables do (SPEC section 3); on this world's negative rewards that is
the optimism that makes tabular Factor-Q explore. The DQN baseline uses PyTorch's default
initialisation instead (as torchrl's and CleanRL's DQN examples).

**The local network's architecture follows from eq. 3**: no bias and tanh (so "nothing sensed"
predicts exactly no local reward), one network shared across actuators (equal ``rho`` for every
sensed obstacle). Why, with the measurements behind it: ``docs/decisions.md``, "Neural
Factor-Q's local network".

``GatedLocalRewardNetwork`` is told no dependency: every actuator reads all ``K``
sensors through learnable sigmoid gates with an L1 penalty, and its parents are read from the
gates (``structure``).

These are architectural priors, stated here; ``bias``, ``activation`` and ``shared`` are
arguments so that the difference can be measured
(``factorq_trainers.commands.compare.command.FactorDQNConfig``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from tensordict import NestedKey, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn

from factorq_torch.base import keys as names
from factorq_torch.base.config import PAPER_NUM_ACTIONS
from factorq_torch.base.rng import MASK64, STREAM_LOCAL_NETWORK, STREAM_TASK_NETWORK, derive_keys
from factorq_torch.base.validation import check_hidden, check_int, check_seed
from factorq_torch.functional import check_dependency

NUM_ACTIONS = PAPER_NUM_ACTIONS  # the default body (base.config)
ACTIVATIONS = ("relu", "tanh")


class BatchedMLP(nn.Module):
    """``S`` independent multilayer perceptrons (``activation`` between layers), applied at once.

    Weights ``[*lead, in, out]`` and biases ``[*lead, out]`` with ``lead = (S, *extra)``; the input
    ``[..., *lead, in]`` gives ``[..., *lead, out]``: every leading index has its own network, and
    any dimensions before ``lead`` (e.g. a replay minibatch) share it.

    Args:
        lead: the leading shape of independent networks, ``(S,)`` or ``(S, A)``.
        in_features, out_features: input and output widths.
        hidden: widths of the hidden layers (``()``: one linear layer).
        keys: ``[S]`` int64, the key of each experiment's initialisation stream.
        bias: whether the layers have biases.
        zero_output: start the output layer at 0 (every output exactly 0).

    Initialisation: as ``nn.Linear``, ``U(-1/sqrt(in), 1/sqrt(in))`` for weights and biases, drawn
    for experiment ``i`` (all its ``extra`` networks, layer by layer) from a ``torch.Generator``
    seeded with ``keys[i]``.
    """

    def __init__(
        self,
        lead: Sequence[int],
        in_features: int,
        out_features: int,
        *,
        hidden: Sequence[int] = (),
        keys: torch.Tensor,
        bias: bool = True,
        activation: str = "relu",
        zero_output: bool = False,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__()
        if activation not in ACTIVATIONS:
            raise ValueError(f"activation={activation!r} is unknown: choose one of {ACTIVATIONS}")
        self.activation = getattr(torch, activation)
        self.lead = tuple(lead)
        widths = (in_features, *hidden, out_features)
        self.weights = nn.ParameterList()
        self.biases = nn.ParameterList() if bias else None
        for fan_in, fan_out in zip(widths[:-1], widths[1:], strict=True):
            self.weights.append(nn.Parameter(torch.empty(*self.lead, fan_in, fan_out)))
            if self.biases is not None:
                self.biases.append(nn.Parameter(torch.empty(*self.lead, fan_out)))
        self._initialise(keys, zero_output)
        self.to(device)

    @torch.no_grad()
    def _initialise(self, keys: torch.Tensor, zero_output: bool) -> None:
        if tuple(keys.shape) != (self.lead[0],):
            raise ValueError(f"keys has shape {list(keys.shape)}, expected [{self.lead[0]}]")
        last = len(self.weights) - 1
        for experiment, key in enumerate(keys.tolist()):
            generator = torch.Generator().manual_seed(key & MASK64)
            for layer, weight in enumerate(self.weights):
                bound = 1.0 / math.sqrt(weight.shape[-2])
                tensors = [weight[experiment]]
                if self.biases is not None:
                    tensors.append(self.biases[layer][experiment])
                for tensor in tensors:
                    tensor.uniform_(-bound, bound, generator=generator)
                    if zero_output and layer == last:
                        tensor.zero_()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        lead = self.lead
        if tuple(x.shape[-1 - len(lead) : -1]) != lead:
            raise ValueError(
                f"BatchedMLP of networks {list(lead)} got an input of shape {list(x.shape)}: "
                f"expected [..., {', '.join(map(str, lead))}, in_features]"
            )
        before = x.shape[: -1 - len(lead)]
        networks = math.prod(lead)
        # One bmm per layer: [L, P, in] @ [L, in, out], L networks, P inputs each. A broadcast
        # matmul would copy the weights once per input instead.
        x = x.reshape(-1, networks, x.shape[-1]).transpose(0, 1)  # [L, P, in]
        last = len(self.weights) - 1
        for layer, weight in enumerate(self.weights):
            x = torch.bmm(x, weight.reshape(networks, *weight.shape[-2:]))  # [L, P, out]
            if self.biases is not None:
                x = x + self.biases[layer].reshape(networks, 1, -1)
            if layer < last:
                x = self.activation(x)
        return x.transpose(0, 1).reshape(*before, *lead, x.shape[-1])  # [..., *lead, out]


def _keys(
    keys: torch.Tensor | None, seed: int, stream: int, count: int, offset: int
) -> torch.Tensor:
    """The given initialisation keys ``[S]`` int64, or those derived from ``seed``."""
    if keys is None:
        check_seed("seed", seed)  # [0, INT64_MAX]: the keys are 64-bit
        return derive_keys(seed, stream, count, offset)
    if not isinstance(keys, torch.Tensor) or keys.dtype != torch.int64:
        raise TypeError("keys must be an int64 tensor (see factorq_torch.base.rng.derive_keys)")
    if tuple(keys.shape) != (count,):
        raise ValueError(
            f"keys has shape {list(keys.shape)}, expected [{count}] (one per experiment)"
        )
    return keys


def _sensors(
    tensordict: TensorDictBase, owner: str, num_experiments: int, num_sensors: int
) -> torch.Tensor:
    """The ``sensors`` entry, checked to be ``[..., S, K]`` with ``K = num_sensors``."""
    sensors = tensordict.get(names.SENSORS, None)
    if sensors is None:
        raise KeyError(f"{owner} needs 'sensors' in the tensordict")
    _experiment_dim(sensors, 1, num_experiments, owner, "sensors")
    if sensors.shape[-1] != num_sensors:
        raise ValueError(
            f"{owner}: 'sensors' has {sensors.shape[-1]} sensors, expected K={num_sensors}"
        )
    return sensors


def _experiment_dim(
    value: torch.Tensor, trailing: int, num_experiments: int, owner: str, key: NestedKey
) -> None:
    """Check that ``value`` is ``[..., S, *trailing]`` with ``S = num_experiments``."""
    dim = value.dim() - 1 - trailing
    if dim < 0 or value.shape[dim] != num_experiments:
        raise ValueError(
            f"{owner} holds S={num_experiments} experiments but {key!r} has shape "
            f"{list(value.shape)}: expected [..., {num_experiments}"
            f"{', K' if trailing else ''}] (build the env with batch_size=({num_experiments},))"
        )


class TaskQNetwork(TensorDictModuleBase):
    """Task values ``Q(s, .)`` of ``S`` experiments from a network per experiment.

    The input features (documented observation of the neural agents):

    - ``with_proximity=False`` (Factor-DQN, like ``TaskQTable``'s Factor-Q state): the cell as a
      one-hot vector ``[N]`` (float32);
    - ``with_proximity=True`` (the DQN baseline, like Q-learning's state): the cell one-hot ``[N]``
      concatenated with the ``K`` sensor bits (``sensors``) as 0/1 floats, ``[N + K]``.

    Args:
        num_experiments: ``S``, one network each.
        num_cells: ``N``, cells of the grid (``size**2``).
        with_proximity: add the sensor bits to the input.
        num_sensors: ``K`` (4 in the paper's body).
        num_headings: ``H``; above 1 the one-hot is over (cell, heading) pairs, ``[N H]``.
        hidden: hidden layer widths of each network.
        activation: hidden activation, ``"relu"`` (default) or ``"tanh"``.
        num_actions: ``A``, the outputs.
        seed, offset: initialisation keys ``derive_keys(seed, STREAM_TASK_NETWORK, S, offset)``.
        keys: explicit initialisation keys ``[S]`` int64 instead of ``seed`` / ``offset``.
        zero_output: start every value at exactly 0 (as the tables).
        device: where the weights live.

    Keys: reads ``cell`` ``[..., S]`` (and ``sensors`` ``[..., S, K]``), writes ``action_value``
    ``[..., S, A]``: any leading dimensions (a replay minibatch ``[B, S]``) are allowed.

    Example:
        >>> from tensordict import TensorDict
        >>> network = TaskQNetwork(2, num_cells=9)
        >>> td = network(TensorDict(cell=torch.tensor([0, 8]), batch_size=[2]))
        >>> td["action_value"].detach()  # zero_output: every value starts at 0, as the tables
        tensor([[0., 0., 0., 0.],
                [0., 0., 0., 0.]])
    """

    def __init__(
        self,
        num_experiments: int,
        num_cells: int,
        *,
        with_proximity: bool = False,
        num_sensors: int = NUM_ACTIONS,
        num_headings: int = 1,
        hidden: Sequence[int] = (64,),
        activation: str = "relu",
        num_actions: int = NUM_ACTIONS,
        seed: int = 0,
        offset: int = 0,
        keys: torch.Tensor | None = None,
        zero_output: bool = True,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__()
        self.num_experiments = check_int("num_experiments", num_experiments, 1)
        self.num_cells = check_int("num_cells", num_cells, 1)
        self.num_actions = check_int("num_actions", num_actions, 1)
        self.with_proximity = bool(with_proximity)
        self.num_sensors = check_int("num_sensors", num_sensors, 0)
        self.num_headings = check_int("num_headings", num_headings, 1)
        self.in_keys = [names.CELL] + ([names.HEADING] if num_headings > 1 else [])
        self.in_keys += [names.SENSORS] if with_proximity else []
        self.out_keys = [names.ACTION_VALUE]
        in_features = num_cells * num_headings + (num_sensors if with_proximity else 0)
        self.network = BatchedMLP(
            (num_experiments,),
            in_features,
            num_actions,
            hidden=check_hidden("hidden layer", hidden),
            keys=_keys(keys, seed, STREAM_TASK_NETWORK, num_experiments, offset),
            activation=activation,
            zero_output=zero_output,
            device=device,
        )

    def features(self, tensordict: TensorDictBase) -> torch.Tensor:
        """The network input ``[..., S, N]`` or ``[..., S, N + 4]`` float32."""
        owner = type(self).__name__
        cell = tensordict.get("cell", None)
        if cell is None:
            raise KeyError(
                f"{owner} needs 'cell' in the tensordict; it has {list(tensordict.keys())}"
            )
        _experiment_dim(cell, 0, self.num_experiments, owner, "cell")
        position = cell.to(torch.int64)
        if self.num_headings > 1:  # the state is (cell, heading): one-hot over both
            heading = tensordict.get(names.HEADING, None)
            if heading is None:
                raise KeyError(f"{owner} with num_headings > 1 needs 'heading' in the tensordict")
            position = position * self.num_headings + heading.to(torch.int64)
        positions = self.num_cells * self.num_headings
        one_hot = nn.functional.one_hot(position, positions).to(torch.float32)
        if not self.with_proximity:
            return one_hot
        sensors = tensordict.get(names.SENSORS, None)
        if sensors is None:
            raise KeyError(f"{owner} with_proximity=True needs 'sensors' in the tensordict")
        return torch.cat([one_hot, sensors.to(torch.float32)], dim=-1)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        tensordict.set("action_value", self.network(self.features(tensordict)))  # [..., S, A]
        return tensordict


class LocalRewardNetwork(TensorDictModuleBase):
    """Factor-Q's projected local reward ``rho(o)`` from small networks of each actuator's parents.

    ``local_value[..., s, a] = f_s(x_a)`` (``shared=True``) or ``f_{s,a}(x_a)`` (one network per
    actuator), where ``x_a`` ``[P]`` holds the readings (0 or 1, as floats) of actuator ``a``'s
    parent sensors ``D(a)`` (row ``a`` of ``dependency``) in sensor order, zero-padded to
    ``P = max(1, max_a |D(a)|)``: the dependency-masked input, the network counterpart of the
    table ``rho_a[o_D(a)]`` (the paper's body: ``x_a = proximity[a]``, ``P = 1``). An actuator
    without parents always sees zeros, so a bias-free network predicts exactly 0 for it.
    Trained by ``FactorQLoss``'s ``loss_local`` (regression on the chosen actuator's local
    reward). The defaults (no bias, tanh, shared) are explained in the module docstring.

    Args:
        num_experiments: ``S``.
        dependency: bool ``[A, K]``, the parents of each actuator (default ``eye(num_actions)``).
        hidden: hidden layer widths of each actuator's network.
        num_actions: ``A`` when ``dependency`` is not given.
        bias: layers with biases; ``False`` (default) maps the reading 0 to exactly 0.
        activation: hidden activation, ``"tanh"`` (default) or ``"relu"``.
        shared: one network per experiment for all actuators (default), else one per actuator.
        seed, offset: initialisation keys ``derive_keys(seed, STREAM_LOCAL_NETWORK, S, offset)``.
        keys: explicit initialisation keys ``[S]`` int64 instead of ``seed`` / ``offset``.
        zero_output: start every value at exactly 0 (as the tables).
        device: where the weights live.

    Keys: reads ``sensors`` ``[..., S, K]`` bool, writes ``local_value`` ``[..., S, A]``.

    Example:
        >>> from tensordict import TensorDict
        >>> local = LocalRewardNetwork(1, zero_output=False)
        >>> td = local(TensorDict(sensors=torch.tensor([[False] * 4]), batch_size=[1]))
        >>> td["local_value"].detach()  # no bias: nothing sensed predicts exactly 0
        tensor([[0., 0., 0., 0.]])
    """

    def __init__(
        self,
        num_experiments: int,
        *,
        dependency: torch.Tensor | None = None,
        hidden: Sequence[int] = (8,),
        num_actions: int = NUM_ACTIONS,
        bias: bool = False,
        activation: str = "tanh",
        shared: bool = True,
        seed: int = 0,
        offset: int = 0,
        keys: torch.Tensor | None = None,
        zero_output: bool = True,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__()
        self.num_experiments = check_int("num_experiments", num_experiments, 1)
        if dependency is None:
            dependency = torch.eye(check_int("num_actions", num_actions, 1), dtype=torch.bool)
        dependency = check_dependency(dependency)
        self.num_actions, self.num_sensors = dependency.shape
        self.shared = bool(shared)
        self.in_keys = [names.SENSORS]
        self.out_keys = [names.LOCAL_VALUE]
        parents = max(1, int(dependency.sum(dim=1).max()))
        # parent_index[a, r]: the r-th parent of a, or K (a zero column) past its last parent.
        parent_index = torch.full((self.num_actions, parents), self.num_sensors)
        for actuator in range(self.num_actions):
            found = dependency[actuator].nonzero().squeeze(1)
            parent_index[actuator, : found.numel()] = found
        self.register_buffer("parent_index", parent_index.to(device))
        self.network = BatchedMLP(
            (num_experiments,) if shared else (num_experiments, self.num_actions),
            parents,
            1,
            hidden=check_hidden("hidden layer", hidden),
            keys=_keys(keys, seed, STREAM_LOCAL_NETWORK, num_experiments, offset),
            bias=bias,
            activation=activation,
            zero_output=zero_output,
            device=device,
        )

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        sensors = _sensors(tensordict, type(self).__name__, self.num_experiments, self.num_sensors)
        padded = torch.cat(  # [..., S, K + 1]: a zero column for missing parents
            [
                sensors.to(torch.float32),
                sensors.new_zeros(*sensors.shape[:-1], 1, dtype=torch.float32),
            ],
            dim=-1,
        )
        reading = padded[..., self.parent_index]  # [..., S, A, P]
        if self.shared:  # one network per experiment, applied to each of its A actuators
            value = self.network(reading.movedim(-2, -3)).movedim(-3, -2)  # [..., S, A, 1]
        else:
            value = self.network(reading)
        tensordict.set(names.LOCAL_VALUE, value.squeeze(-1))  # [..., S, A]
        return tensordict


#: ``GatedLocalRewardNetwork.structure`` probes all ``2**K`` sensor patterns up to this many
#: sensors, and ``PROBES`` random patterns beyond.
MAX_PROBE_SENSORS = 10
PROBES = 1024


class GatedLocalRewardNetwork(TensorDictModuleBase):
    """A local reward network that learns each actuator's parent sensors: sparse input gates.

    ``local_value[..., s, a] = f_{s,a}(sigmoid(z_{s,a}) * sensors[..., s, :])``: every actuator
    ``a`` of experiment ``s`` has its own network ``f_{s,a}`` (bias-free, tanh, output starting at
    0, as ``LocalRewardNetwork``'s defaults: nothing sensed predicts exactly 0) over all ``K``
    sensors, each multiplied by a gate ``g = sigmoid(z)`` with a learnable logit ``z``
    ``[S, A, K]`` (initially ``gate_init``). ``regularisation()`` is the L1 penalty
    ``l1 * sum g`` (gates are positive, so the L1 norm is their sum), which ``FactorQLoss`` adds
    to its losses as ``loss_regularisation``: trained through the same loss as every provider,
    the gates of sensors that do not help predict the local reward shrink towards 0, and
    ``structure()`` reads the parents from what the network predicts: sensor ``k`` is a parent of
    actuator ``a`` when flipping it changes ``a``'s predicted local reward by more than
    ``threshold`` for some reading. (Not "gate above a value": under L1 every gate shrinks, since
    the weights behind a gate make up its scale, so a gate's size alone is not identifiable;
    measured in ``docs/decisions.md``.)

    Args:
        num_experiments: ``S``.
        num_actions: ``A``.
        num_sensors: ``K``.
        hidden: hidden layer widths of each actuator's network.
        l1: weight of the L1 penalty on the gates (>= 0).
        gate_init: initial gate value, in (0, 1).
        threshold: the change of predicted local reward (reward units: a quarter of a
            collision by default) above which a sensor counts as a parent (> 0).
        seed, offset, keys, device: as ``LocalRewardNetwork``.

    Keys: reads ``sensors`` ``[..., S, K]`` bool, writes ``local_value`` ``[..., S, A]``.

    Example:
        >>> from tensordict import TensorDict
        >>> local = GatedLocalRewardNetwork(1, num_actions=2, num_sensors=3)
        >>> td = local(TensorDict(sensors=torch.tensor([[True, False, True]]), batch_size=[1]))
        >>> td["local_value"].detach()  # the output layer starts at 0
        tensor([[0., 0.]])
        >>> local.gates().shape, round(local.regularisation().item(), 6)  # 1e-3 * 6 * 0.5
        (torch.Size([1, 2, 3]), 0.003)
    """

    def __init__(
        self,
        num_experiments: int,
        *,
        num_actions: int,
        num_sensors: int,
        hidden: Sequence[int] = (8,),
        l1: float = 1e-3,
        gate_init: float = 0.5,
        threshold: float = 0.25,
        seed: int = 0,
        offset: int = 0,
        keys: torch.Tensor | None = None,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__()
        self.num_experiments = check_int("num_experiments", num_experiments, 1)
        self.num_actions = check_int("num_actions", num_actions, 1)
        self.num_sensors = check_int("num_sensors", num_sensors, 1)
        for name, value, low in (("l1", l1, 0.0), ("gate_init", gate_init, None)):
            bad = not isinstance(value, (int, float)) or not math.isfinite(value)
            if not bad and low is not None:
                bad = value < low
            if not bad and low is None:
                bad = not 0.0 < value < 1.0
            if bad:
                allowed = ">= 0" if low is not None else "in (0, 1)"
                raise ValueError(f"{name}={value!r} must be a finite number {allowed}")
        if (
            isinstance(threshold, bool)
            or not isinstance(threshold, (int, float))
            or not math.isfinite(threshold)
            or threshold <= 0.0
        ):
            raise ValueError(f"threshold={threshold!r} must be a finite number > 0")
        self.l1, self.threshold = float(l1), float(threshold)
        self.in_keys = [names.SENSORS]
        self.out_keys = [names.LOCAL_VALUE]
        logit = math.log(gate_init / (1.0 - gate_init))
        self.gate_logits = nn.Parameter(
            torch.full((num_experiments, num_actions, num_sensors), logit, device=device)
        )
        self.network = BatchedMLP(
            (num_experiments, num_actions),
            num_sensors,
            1,
            hidden=check_hidden("hidden layer", hidden),
            keys=_keys(keys, seed, STREAM_LOCAL_NETWORK, num_experiments, offset),
            bias=False,
            activation="tanh",
            zero_output=True,
            device=device,
        )

    def gates(self) -> torch.Tensor:
        """``[S, A, K]``: ``sigmoid`` of the gate logits."""
        return torch.sigmoid(self.gate_logits)

    @torch.no_grad()
    def sensor_effects(self, readings: torch.Tensor | None = None) -> torch.Tensor:
        """``[S, A, K]``: the largest change of each actuator's predicted local reward when one
        sensor flips, over the probe ``readings`` (bool ``[N, K]``; default: all ``2**K`` patterns
        for ``K <= MAX_PROBE_SENSORS``, else ``PROBES`` patterns drawn from a fixed seed)."""
        K = self.num_sensors
        device = self.gate_logits.device
        if readings is None:
            if K <= MAX_PROBE_SENSORS:
                codes = torch.arange(2**K, device=device)
                bits = 2 ** torch.arange(K, device=device)
                readings = (codes[:, None] & bits) != 0
            else:
                generator = torch.Generator().manual_seed(0)
                readings = (torch.rand(PROBES, K, generator=generator) < 0.5).to(device)
        if readings.dim() != 2 or readings.shape[-1] != K:
            raise ValueError(f"readings must be [N, {K}] (K sensors), got {list(readings.shape)}")
        probes = readings.to(torch.float32)[:, None, None, :]  # [N, 1, 1, K]
        gates = self.gates()
        effects = []
        for k in range(K):
            on, off = probes.clone(), probes.clone()
            on[..., k], off[..., k] = 1.0, 0.0
            change = self.network(on * gates) - self.network(off * gates)  # [N, S, A, 1]
            effects.append(change.squeeze(-1).abs().amax(dim=0))  # [S, A]
        return torch.stack(effects, dim=-1)

    def structure(self, readings: torch.Tensor | None = None) -> torch.Tensor:
        """``[S, A, K]`` bool: sensor ``k`` is a parent of actuator ``a`` when flipping it changes
        ``a``'s predicted local reward by more than ``threshold`` (``sensor_effects``)."""
        return self.sensor_effects(readings) > self.threshold

    def regularisation(self) -> torch.Tensor:
        """The L1 penalty on the gates, ``l1 * sum g`` (a scalar with a gradient)."""
        return self.l1 * self.gates().sum()

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        sensors = _sensors(tensordict, type(self).__name__, self.num_experiments, self.num_sensors)
        # [..., S, 1, K] * [S, A, K] -> [..., S, A, K]: each actuator's gated view of the readings
        gated = sensors.to(torch.float32).unsqueeze(-2) * self.gates()
        tensordict.set(names.LOCAL_VALUE, self.network(gated).squeeze(-1))  # [..., S, A]
        return tensordict
