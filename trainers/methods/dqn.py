"""DQN baseline on the FactoredGrid worlds, built from torchrl's own pieces:

    config -> keys -> env (conventional reward) -> Q-network -> QValueModule -> EGreedyModule
           -> DQNLoss + HardUpdate + Adam -> torchrl Collector -> ReplayBuffer -> per-episode traces

``TaskQNetwork(with_proximity=True)`` reads the cell one-hot ``[N]`` and the 4 proximity bits
(what Q-learning's table holds); the replay buffer stores the raw entries. ``S`` seeds x ``W``
worlds are ``E = W S`` experiments in one batched env, each with its own network, Adam moments
and target network, sharing the minibatch's time indices and torch's global random stream (so a
DQN experiment's numbers depend on its batch). The defaults, their sources and the exploratory
flag under ``EGreedyModule``: ``docs/decisions.md`` ("Neural Factor-Q (Factor-DQN) and the
baselines of ``factorq compare``"). Per episode of every experiment: ``EpisodeRecorder``'s
records.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torchrl.data import Categorical, LazyTensorStorage, ReplayBuffer
from torchrl.envs.utils import ExplorationType, exploration_type
from torchrl.modules import EGreedyModule, QValueModule
from torchrl.objectives import DQNLoss, HardUpdate

from factorq_envs.grid_world import NUM_ACTIONS
from factorq_envs.torchrl_env import FactoredGridEnv
from factorq_torch.base.rng import STREAM_TASK_NETWORK, STREAM_WORLD
from factorq_torch.base.validation import INT32_MAX, check_float, check_hidden, check_int
from factorq_torch.neural import BatchedMLP, TaskQNetwork
from factorq_trainers.analysis.vocabulary import among
from factorq_trainers.methods import experiment
from factorq_trainers.methods.experiment import EpisodeRecorder, ExperimentConfig
from factorq_trainers.runner.options import option

with warnings.catch_warnings():
    # torchrl 0.14.1 warns about its own deprecated weight updaters when the package is imported.
    warnings.filterwarnings("ignore", "Creating .*WeightUpdater", DeprecationWarning)
    from torchrl.collectors import Collector

#: Methods of ``factorq_trainers.commands.compare.command``; a method's index is part of its
#: experiments' keys.
METHODS = among("factor-q", "q-learning", "dqn", "factor-dqn")


def batch_keys(
    experiments: ExperimentConfig, stream: int, method: str | None = None
) -> torch.Tensor:
    """Keys ``[E]`` of ``stream`` for the experiments of ``factorq compare``'s batch: number
    ``3 i + w`` (as ``factorq paper``'s worlds), or with a ``method`` number
    ``4 (3 i + w) + m`` (``m`` its index in ``METHODS``); see
    ``factorq_trainers.methods.experiment.experiment_keys``."""
    return experiment.experiment_keys(experiments.seed, stream, experiments.labels, METHODS, method)


# --------------------------------------------------------------------------------------------
# DQN


def batch_env(
    experiments: ExperimentConfig, device: torch.device | str | None = None
) -> FactoredGridEnv:
    """The batch's worlds: ``E`` experiments, one obstacle period and world key each."""
    world_keys = batch_keys(experiments, STREAM_WORLD)
    return experiment.make_env(
        experiments.world, experiments.periods, world_keys, device=device, seed=experiments.seed
    )


@dataclass(frozen=True)
class DQNConfig:
    """DQN's hyperparameters (their sources: the module docstring)."""

    gamma: float = option(
        0.9, "Discount of future reward, in [0, 1) (the SPEC's, shared by every method)."
    )
    hidden: tuple[int, ...] = option(
        (64, 64), "Hidden layer widths of each experiment's Q-network."
    )
    lr: float = option(1e-3, "Adam learning rate.")
    buffer_size: int = option(
        10_000, "Replay buffer capacity, in env steps (each holds one transition per experiment)."
    )
    batch_size: int = option(128, "Transitions per experiment in a minibatch.")
    learning_starts: int = option(500, "Env steps before the first gradient step.")
    train_every: int = option(4, "Env steps per gradient step.")
    target_update_interval: int = option(
        50, "Gradient steps between hard copies of the network into the target network."
    )
    eps_start: float = option(1.0, "Initial exploration probability of EGreedyModule.")
    eps_end: float = option(0.05, "Final exploration probability.")
    exploration_fraction: float = option(
        0.5, "Fraction of the step budget over which epsilon anneals linearly to eps_end."
    )

    def __post_init__(self) -> None:
        check_float("gamma", self.gamma, 0.0, 1.0, high_open=True)
        object.__setattr__(self, "hidden", check_hidden("hidden", self.hidden))
        check_float("lr", self.lr, 0.0, 1.0, low_open=True)
        for name in ("buffer_size", "batch_size", "train_every", "target_update_interval"):
            check_int(name, getattr(self, name), 1, INT32_MAX)
        check_int("learning_starts", self.learning_starts, 0, INT32_MAX)
        check_float("eps_start", self.eps_start, 0.0, 1.0)
        check_float("eps_end", self.eps_end, 0.0, 1.0)
        if self.eps_end > self.eps_start:
            raise ValueError(
                f"eps_end={self.eps_end} is out of range: must be <= eps_start={self.eps_start} "
                f"(epsilon only decreases)"
            )
        check_float("exploration_fraction", self.exploration_fraction, 0.0, 1.0, low_open=True)


class ExploratoryEGreedy(TensorDictModuleBase):
    """torchrl's ``EGreedyModule`` that also writes which actions it drew (``exploratory``).

    ``EGreedyModule`` replaces ``action`` by a random one with probability ``eps`` and keeps no
    record of it. Here it is handed ``action + A`` (out of the action range): an entry that comes
    back in ``[0, A)`` was drawn by the epsilon branch -- even when it equals the greedy action,
    the project's definition of exploratory (docs/decisions.md) -- and every other entry gets its
    greedy action back. After each call that explored (exploration type ``RANDOM``), epsilon
    anneals by one step: one call is one env step of every experiment.

    Keys: reads ``action`` ``[E]`` int64 (the greedy one, from ``QValueModule``), writes
    ``action`` and ``exploratory`` ``[E]`` bool.

    Example:
        >>> from tensordict import TensorDict
        >>> explore = ExploratoryEGreedy(eps_init=1.0, eps_end=0.0, annealing_num_steps=2)
        >>> td = explore(TensorDict(action=torch.tensor([3, 3]), batch_size=[2]))
        >>> td["exploratory"], float(explore.eps)
        (tensor([True, True]), 0.5)
    """

    def __init__(
        self,
        eps_init: float = 1.0,
        eps_end: float = 0.05,
        annealing_num_steps: int = 1000,
        num_actions: int = NUM_ACTIONS,
    ) -> None:
        super().__init__()
        self.num_actions = num_actions
        self.in_keys, self.out_keys = ["action"], ["action", "exploratory"]
        self.egreedy = EGreedyModule(
            Categorical(num_actions, dtype=torch.int64),
            eps_init=float(eps_init),
            eps_end=float(eps_end),
            annealing_num_steps=annealing_num_steps,
        )

    @property
    def eps(self) -> torch.Tensor:
        """The current exploration probability (a scalar tensor)."""
        return self.egreedy.eps

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        greedy = tensordict.get("action")  # [E]
        tensordict.set("action", greedy + self.num_actions)
        self.egreedy(tensordict)
        chosen = tensordict.get("action")
        exploratory = chosen < self.num_actions  # [E]: drawn by the epsilon branch
        tensordict.set("action", torch.where(exploratory, chosen, greedy))
        tensordict.set("exploratory", exploratory)
        if exploration_type() in (ExplorationType.RANDOM, None):
            self.egreedy.step()
        return tensordict


#: Entries a DQN minibatch needs (the rest of a collected transition is not stored).
_STATE = ("cell", "proximity", "sensors", "heading")
_STORED = (*_STATE, "action", *(("next", key) for key in (*_STATE, "reward", "done", "terminated")))


@dataclass
class DQNAgent:
    """The torchrl modules of a DQN batch (``dqn_agent``)."""

    q_network: TensorDictModuleBase
    value_network: TensorDictSequential
    exploration: ExploratoryEGreedy
    policy: TensorDictSequential
    loss: DQNLoss
    target_updater: HardUpdate
    optimizer: torch.optim.Optimizer
    buffer: ReplayBuffer


def dqn_agent(
    q_network: TensorDictModuleBase,
    actions: int,
    config: DQNConfig,
    steps: int,
    device: torch.device | str | None = None,
) -> DQNAgent:
    """The DQN agent around ``q_network`` (``actions`` actions, ``steps`` env steps of budget for
    the exploration schedule): greedy value module, exploration, DQNLoss with a target network,
    Adam and a replay buffer on ``device``."""
    device = torch.device("cpu" if device is None else device)
    # QValueModule's spec is per sample (one action), not per batch.
    value_network = TensorDictSequential(q_network, QValueModule(spec=Categorical(actions)))
    annealing = max(1, round(config.exploration_fraction * steps))
    exploration = ExploratoryEGreedy(config.eps_start, config.eps_end, annealing, actions)
    policy = TensorDictSequential(value_network, exploration)
    # Summed over the [B, E] minibatch and divided by B below: each experiment's network gets the
    # gradient of its own mean squared TD error, as in a single-seed DQN.
    loss = DQNLoss(
        value_network,
        loss_function="l2",
        delay_value=True,
        action_space="categorical",
        reduction="sum",
    )
    loss.make_value_estimator(gamma=config.gamma)  # TD(0), bootstraps on "terminated" only
    target_updater = HardUpdate(loss, value_network_update_interval=config.target_update_interval)
    optimizer = torch.optim.Adam(loss.parameters(), lr=config.lr)
    buffer = ReplayBuffer(
        storage=LazyTensorStorage(config.buffer_size, device=device),
        batch_size=config.batch_size,
    )
    return DQNAgent(
        q_network, value_network, exploration, policy, loss, target_updater, optimizer, buffer
    )


def run(
    config: DQNConfig,
    experiments: ExperimentConfig,
    *,
    progress: Callable[[int], None] | None = None,
    device: torch.device | str | None = None,
) -> dict[str, Any]:
    """Train DQN on every experiment of ``experiments`` for its step budget.

    Returns ``{"traces", "wall_s"}``: ``traces`` holds one ``EpisodeRecorder`` trace per
    experiment (world-major, seed-minor). ``progress(n)`` is called after every collector batch
    with the env steps per experiment done since its last call.
    """
    started = time.perf_counter()
    device = torch.device("cpu" if device is None else device)
    torch.manual_seed(experiments.seed)  # EGreedyModule and the sampler draw from it
    env = batch_env(experiments, device)
    count, steps = experiments.num_experiments, experiments.steps  # an env step: E frames
    world = experiments.world
    q_network = TaskQNetwork(
        count,
        experiments.size**2,
        with_proximity=True,
        num_sensors=world.num_sensors,
        num_headings=world.num_headings,
        num_actions=world.num_actuators,
        hidden=config.hidden,
        keys=batch_keys(experiments, STREAM_TASK_NETWORK, "dqn"),
        zero_output=False,  # PyTorch's default initialisation, as the DQN examples
        device=device,
    )
    agent = dqn_agent(q_network, world.num_actuators, config, steps, device)
    collector = Collector(
        env,
        agent.policy,
        frames_per_batch=count * config.train_every,
        total_frames=count * steps,
        device=device,
        auto_register_policy_transforms=False,  # the policy keeps no recurrent state
    )
    recorder = EpisodeRecorder(experiments.labels)
    loss_per_experiment = torch.full((count,), math.nan)
    done_steps, gradient_steps = 0, 0
    for data in collector:  # [E, T]
        before = done_steps
        data = data.select(
            *_STORED, "exploratory", ("next", "bump"), ("next", "collision"), strict=False
        )
        for t in range(data.shape[1]):
            if done_steps >= steps:
                break
            done_steps += 1
            recorder.update(data[:, t], agent.exploration.eps, loss_per_experiment)
        # One row [E] per env step: a minibatch [B, E] holds B transitions of every experiment.
        agent.buffer.extend(data.select(*_STORED, strict=False).transpose(0, 1).contiguous())
        due = done_steps // config.train_every - gradient_steps
        if done_steps >= config.learning_starts and len(agent.buffer) > 0:
            for _ in range(due):
                loss_per_experiment = _gradient_step(agent, config.batch_size)
                gradient_steps += 1
        else:
            gradient_steps += due
        if progress is not None:
            progress(done_steps - before)
        if done_steps >= steps:
            break
    collector.shutdown()
    return {"traces": recorder.traces(), "wall_s": time.perf_counter() - started}


def train_stepwise(
    env: Any,
    q_network: TensorDictModuleBase,
    config: DQNConfig,
    steps: int,
    observed: Sequence[str],
    record: Callable[[TensorDictBase, int], None],
    seed: int,
) -> tuple[DQNAgent, float]:
    """``steps`` env steps of the DQN agent around ``q_network`` (``dqn_agent``, made once
    torch's global stream is seeded with ``seed``) in ``env`` stepped by hand (a declared env,
    one transition ``[S]`` a step, rather than torchrl's ``Collector``): each transition goes to
    ``record(td, step)``, its ``observed`` entries (now and next), action, reward and flags to
    the replay buffer, and from ``learning_starts`` on every ``train_every`` steps one gradient
    step follows. Returns the agent and the seconds its training took."""
    torch.manual_seed(seed)
    agent = dqn_agent(q_network, env.num_actions, config, steps)
    nexts = (*observed, "reward", "done", "terminated")
    stored = [*observed, "action", *(("next", key) for key in nexts)]
    started = time.perf_counter()
    td = env.reset()
    for step in range(1, steps + 1):
        with torch.no_grad():
            td = env.step(agent.policy(td))
        record(td, step)
        agent.buffer.extend(td.select(*stored).unsqueeze(0))
        if step >= config.learning_starts and step % config.train_every == 0:
            _gradient_step(agent, config.batch_size)
        td = env.step_mdp(td)
        done = td.get("done")
        if bool(done.any()):
            td.set("_reset", done)
            td = env.reset(td)
    return agent, time.perf_counter() - started


def observation_network(
    count: int,
    key: str,
    shape: Sequence[int],
    actions: int,
    hidden: Sequence[int],
    keys: torch.Tensor,
    zero_output: bool = False,
) -> TensorDictModuleBase:
    """``S`` MLPs on an observation entry: ``key`` ``[..., S, *shape]`` -> ``action_value``
    ``[..., S, A]`` (the entry flattened, as float32; MiniGrid's ``image`` divided by 10: its
    object, colour and state indices are below 11).

    Args:
        count: ``S``, the MLPs (one per experiment).
        key: the observation entry they read.
        shape: the entry's shape per experiment.
        actions: ``A``, the outputs.
        hidden: the hidden layers' widths.
        keys: ``[S]`` seeds of their initial weights (``BatchedMLP``).
        zero_output: start with a zero output layer (every value 0).
    """
    size = math.prod(shape)
    divisor = 10.0 if key == "image" else 1.0

    class ObservationQNetwork(TensorDictModuleBase):
        def __init__(self) -> None:
            super().__init__()
            self.in_keys, self.out_keys = [key], ["action_value"]
            self.mlp = BatchedMLP(
                (count,), size, actions, hidden=hidden, keys=keys, zero_output=zero_output
            )

        def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
            value = tensordict.get(key)
            x = value.reshape(*value.shape[: value.dim() - len(shape)], size)
            tensordict.set("action_value", self.mlp(x.to(torch.float32) / divisor))
            return tensordict

    return ObservationQNetwork()


def _gradient_step(agent: DQNAgent, batch_size: int) -> torch.Tensor:
    """One Adam step on a minibatch ``[B, E]``; returns each experiment's ``0.5 * mean td^2``."""
    sample = agent.buffer.sample()  # [B, E]
    loss = agent.loss(sample)["loss"] / batch_size
    agent.optimizer.zero_grad(set_to_none=True)
    loss.backward()
    agent.optimizer.step()
    agent.target_updater.step()
    squared = sample.get("td_error").detach()  # [B, E, 1]: DQNLoss writes (Q - target)^2
    return 0.5 * squared.reshape(squared.shape[0], -1).mean(dim=0)  # [E]
