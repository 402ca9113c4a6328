"""DQN baseline on the FactoredGrid worlds, built from torchrl's own pieces.

    config -> keys -> env (conventional reward) -> Q-network -> QValueModule -> EGreedyModule
           -> DQNLoss + HardUpdate + Adam -> torchrl Collector -> ReplayBuffer -> per-episode traces

**Observation.** ``TaskQNetwork(with_proximity=True)`` reads the env's ``cell`` and ``proximity``
and feeds the network the cell as a one-hot vector ``[N]`` concatenated with the 4 proximity bits
as 0/1 floats, ``[N + 4]`` (the information Q-learning's tabular state holds). The replay buffer
stores the raw ``cell``/``proximity`` entries; the features are recomputed inside the network.

**Independent seeds in one batch.** ``S`` seeds x ``W`` worlds are ``E = W S`` experiments in one
``FactoredGridEnv`` of ``batch_size=(E,)`` with one obstacle period per experiment. Each experiment
has its own network: ``TaskQNetwork`` stacks ``E`` independent MLPs (weights ``[E, in, out]``), the
loss is summed over experiments (so each network's gradient is its own experiment's), Adam keeps
per-parameter moments, and the target network is a copy of all of them. torchrl's ``Collector``
steps the batched env; the replay buffer (``ReplayBuffer`` + ``LazyTensorStorage``) stores one
``[E]`` row per env step, so a minibatch ``[B, E]`` holds ``B`` transitions of every experiment.
What the experiments do share: the minibatch's time indices and the position in torch's global
random stream (``EGreedyModule`` and the sampler draw from it), which is why a DQN experiment's
numbers depend on the batch it ran in (the network initialisation, the world and the env's
obstacles do not; see ``experiment_keys``).

**Exploration.** torchrl's ``EGreedyModule``, epsilon annealed linearly from ``eps_start`` to
``eps_end`` over ``exploration_fraction`` of the step budget. ``EGreedyModule`` does not record
which actions it drew (DESIGN section 6), and greedy collisions need that flag;
``ExploratoryEGreedy`` wraps it: it hands ``EGreedyModule`` the greedy action shifted out of range
(``a + A``), so whatever comes back inside ``[0, A)`` is exactly what the epsilon branch drew, then
restores the greedy action elsewhere and writes ``exploratory``. The wrapper also steps the
annealing itself, once per call that explores (no schedule to step by hand, DESIGN section 5).

**Defaults and their source.** CleanRL's ``dqn.py`` and torchrl's ``sota-implementations/dqn``
(CartPole) agree on Adam, replay buffer 10,000, minibatch 128, epsilon 1.0 -> 0.05 over half the
budget and a hard target update every 50 gradient steps (CleanRL: every 500 env steps at one
update per 10 steps; torchrl: ``hard_update_freq: 50``). Those are kept. Scaled to this tiny
world and a budget of thousands rather than 500,000 steps: learning starts after 500 env steps
(both: 10,000), one gradient step every 4 env steps (the Nature DQN's update frequency; both
examples: every 10), learning rate 1e-3 (both: 2.5e-4, over some 50,000 updates; the default
budget here allows 3,750), hidden layers (64, 64) (torchrl: (120, 84)) and ``gamma = 0.9``, the
SPEC's discount, shared by all methods here. No gradient clipping (CleanRL has none; torchrl's
example clips the global norm, which would couple the experiments of a batch). Measured at a
10,000-step budget (3 seeds x 3 worlds): a gradient step every 2 env steps instead of 4 learned
about as well (final paths 19-21 steps either way) at about twice the cost; annealing epsilon over
20% of the budget instead of 50% reached short paths about twice as early with fewer collisions in
total, but three times the greedy collisions.

Per episode of every experiment (``EpisodeRecorder``): path length, collisions, greedy collisions
(collisions on non-exploratory actions), task return (step + goal rewards, as the tabular
trainers record it), env steps so far, epsilon and loss.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torchrl.data import Categorical, LazyTensorStorage, ReplayBuffer
from torchrl.envs.utils import ExplorationType, exploration_type
from torchrl.modules import EGreedyModule, QValueModule
from torchrl.objectives import DQNLoss, HardUpdate

from envs.grid import FactoredGridEnv
from envs.world import NUM_ACTIONS, WORLD_PERIODS, WORLDS, WorldConfig, static_layout
from factorq_torch.base.rng import STREAM_TASK_NETWORK, STREAM_WORLD, derive_keys
from factorq_torch.base.validation import check_float, check_int, check_names
from factorq_torch.neural import TaskQNetwork

with warnings.catch_warnings():
    # torchrl 0.14.1 warns about its own deprecated weight updaters when the package is imported.
    warnings.filterwarnings("ignore", "Creating .*WeightUpdater", DeprecationWarning)
    from torchrl.collectors import Collector

#: Methods of ``trainers.compare``; a method's index is part of its experiments' keys.
METHODS = ("factor-q", "q-learning", "dqn", "factor-dqn")
#: Per-episode records of ``EpisodeRecorder``.
EPISODE_FIELDS = (
    "steps",
    "collisions",
    "greedy_collisions",
    "task_return",
    "env_steps",
    "epsilon",
    "loss",
)
_MAX_SEED = 2**63 - 1


# --------------------------------------------------------------------------------------------
# Validation


def check_hidden(name: str, value: Any) -> tuple[int, ...]:
    """Hidden layer widths as a tuple of ints >= 1."""
    if isinstance(value, str) or not isinstance(value, Sequence):
        raise TypeError(
            f"{name} must be a sequence of layer widths such as (64, 64), got {value!r}"
        )
    for width in value:
        check_int(f"{name} width", width, 1)
    return tuple(value)


# --------------------------------------------------------------------------------------------
# The experiments: worlds x seeds in one batch


@dataclass(frozen=True)
class ExperimentConfig:
    """Which experiments run, and their budget: ``seeds`` per world, ``steps`` env steps each."""

    seed: int = 0
    """Master seed: worlds, policies and network initialisations derive from it."""
    seeds: int = 3
    """Independent experiments per world (and method)."""
    worlds: tuple[str, ...] = WORLDS
    """Worlds to run: static, semi-dynamic, dynamic (comma-separated)."""
    steps: int = 15_000
    """Budget of env steps per experiment (episodes are as many as fit)."""
    size: int = 10
    """Side of the square grid, in cells."""
    obstacles: int = 10
    """Number of single-cell obstacles."""
    max_steps: int = 10_000
    """Actions after which an episode is truncated."""
    layout_seed: int = 0
    """Seed of the static world's obstacle layout."""
    body: str = "translate"
    """Agent body: translate (the paper) or heading (forward, turn left/right)."""
    sensors: str = "cross"
    """Sensor layout: cross (the paper: 4 neighbours) or ring (8 neighbours)."""
    distractors: int = 0
    """Extra sensor bits that carry no information."""
    sensor_permutation: int | None = None
    """Seed of a random order in which the agent receives its sensors."""
    sensor_noise: float = 0.0
    """Probability that each sensor bit is flipped at each observation, in [0, 1]."""
    actuator_noise: float = 0.0
    """Probability that another actuator fires than the chosen one, in [0, 1]."""

    def __post_init__(self) -> None:
        check_int("seed", self.seed, 0, _MAX_SEED)
        check_int("seeds", self.seeds, 1)
        object.__setattr__(self, "worlds", check_names("worlds", self.worlds, WORLDS))
        check_int("steps", self.steps, 1)
        check_int("size", self.size, 2)
        check_int("max_steps", self.max_steps, 1)
        check_int("layout_seed", self.layout_seed, 0, _MAX_SEED)
        try:
            world = self.world
            if "static" in self.worlds:
                static_layout(world)
        except ValueError as error:
            raise ValueError(str(error).replace("num_obstacles", "obstacles")) from None

    @property
    def world(self) -> WorldConfig:
        """The world of every experiment; the obstacle period is set per experiment."""
        return WorldConfig(
            size=self.size,
            num_obstacles=self.obstacles,
            max_steps=self.max_steps,
            layout_seed=self.layout_seed,
            body=self.body,
            sensors=self.sensors,
            num_distractors=self.distractors,
            sensor_permutation=self.sensor_permutation,
            sensor_noise=self.sensor_noise,
            actuator_noise=self.actuator_noise,
        )

    @property
    def num_experiments(self) -> int:
        return len(self.worlds) * self.seeds

    @property
    def labels(self) -> list[tuple[str, int]]:
        """``(world, seed index)`` of every experiment of the batch, world-major."""
        return [(world, index) for world in self.worlds for index in range(self.seeds)]


def experiment_keys(
    config: ExperimentConfig, stream: int, method: str | None = None
) -> torch.Tensor:
    """Keys ``[E]`` of ``stream`` for the batch's experiments (world-major, seed-minor).

    Experiment (seed index ``i``, world ``w`` = index in ``WORLDS``) takes key number ``3 i + w``
    (as ``trainers.paper``: every method meets the same worlds, common random numbers), or with a
    ``method`` number ``4 (3 i + w) + m`` (``m`` its index in ``METHODS``). Neither depends on what
    else is selected.
    """
    per_method = method is not None
    slots = []
    for world, index in config.labels:
        slot = len(WORLDS) * index + WORLDS.index(world)
        slots.append(len(METHODS) * slot + METHODS.index(method) if per_method else slot)
    count = max(slots) + 1
    return derive_keys(config.seed, stream, count)[torch.tensor(slots)]


def make_env(config: ExperimentConfig, device: torch.device | str | None = None) -> FactoredGridEnv:
    """The batch's worlds: ``E`` experiments, one obstacle period each, keyed per experiment."""
    env = FactoredGridEnv(
        size=config.size,
        num_obstacles=config.obstacles,
        obstacle_period=[WORLD_PERIODS[world] for world, _ in config.labels],
        max_steps=config.max_steps,
        layout_seed=config.layout_seed,
        batch_size=(config.num_experiments,),
        seed=config.seed,
        device=device,
        body=config.body,
        sensors=config.sensors,
        num_distractors=config.distractors,
        sensor_permutation=config.sensor_permutation,
        sensor_noise=config.sensor_noise,
        actuator_noise=config.actuator_noise,
    )
    env.world_keys = experiment_keys(config, STREAM_WORLD).to(env.device)
    return env


# --------------------------------------------------------------------------------------------
# Recording


class EpisodeRecorder:
    """Per-episode records of ``E`` experiments, fed one transition ``[E]`` at a time.

    ``update(td, epsilon, loss)`` reads ``("next", "bump")`` (a collision), ``exploratory``,
    ``("next", "done")`` and the task reward: ``("next", "reward")`` when ``("next",
    "local_reward")`` exists (the reward was split), else the conventional reward minus the sum of
    ``("next", "collision")``. ``epsilon`` and ``loss`` are per-experiment values of this step
    (``loss`` NaN where there was none); an episode records the epsilon at its end and the mean
    finite loss over its steps. ``logger`` (a torchrl ``Logger``) receives every finished
    episode's records under ``"{world}/seed_{i}/{name}"`` at step = that experiment's env steps.

    ``totals`` counts collisions and greedy collisions over every step, including an episode left
    unfinished by the budget, and the *boxed-in* greedy collisions among them: those where all
    four sensors read an obstacle or wall before acting, so that every action collided (in the
    moving worlds a scatter can box the agent in; no policy avoids those).
    """

    def __init__(self, labels: Sequence[tuple[str, int]], logger=None) -> None:
        self.labels = list(labels)
        count = len(self.labels)
        self.logger = logger
        self.env_steps = np.zeros(count, dtype=np.int64)
        self._sums = {name: np.zeros(count) for name in ("steps", "collisions", "greedy", "task")}
        self._loss_sum, self._loss_count = np.zeros(count), np.zeros(count)
        self.episodes: list[dict[str, list[float]]] = [
            {name: [] for name in EPISODE_FIELDS} for _ in range(count)
        ]
        self.totals = {
            "collisions": np.zeros(count, dtype=np.int64),
            "greedy_collisions": np.zeros(count, dtype=np.int64),
            "boxed_in_greedy_collisions": np.zeros(count, dtype=np.int64),
        }

    def update(
        self,
        td: TensorDictBase,
        epsilon: float | torch.Tensor | np.ndarray,
        loss: torch.Tensor | np.ndarray | None = None,
    ) -> None:
        next_td = td.get("next")
        collided = next_td.get("bump").any(dim=-1).cpu().numpy()  # [E]
        greedy = collided & ~td.get("exploratory").cpu().numpy()
        boxed_in = greedy & td.get("proximity").all(dim=-1).cpu().numpy()
        reward = next_td.get("reward").squeeze(-1)
        if next_td.get("local_reward", None) is None:
            reward = reward - next_td.get("collision").sum(dim=-1)
        done = next_td.get("done").squeeze(-1).cpu().numpy()
        sums = self._sums
        sums["steps"] += 1
        sums["collisions"] += collided
        sums["greedy"] += greedy
        sums["task"] += reward.cpu().numpy()
        self.env_steps += 1
        self.totals["collisions"] += collided
        self.totals["greedy_collisions"] += greedy
        self.totals["boxed_in_greedy_collisions"] += boxed_in
        if loss is not None:
            loss = loss.detach().cpu().numpy() if isinstance(loss, torch.Tensor) else loss
            finite = np.isfinite(loss)
            self._loss_sum += np.where(finite, loss, 0.0)
            self._loss_count += finite
        if not done.any():
            return
        epsilon = np.broadcast_to(
            epsilon.detach().cpu().numpy() if isinstance(epsilon, torch.Tensor) else epsilon,
            done.shape,
        )
        for row in np.flatnonzero(done).tolist():
            count = self._loss_count[row]
            record = {
                "steps": int(sums["steps"][row]),
                "collisions": int(sums["collisions"][row]),
                "greedy_collisions": int(sums["greedy"][row]),
                "task_return": float(sums["task"][row]),
                "env_steps": int(self.env_steps[row]),
                "epsilon": float(epsilon[row]),
                "loss": float(self._loss_sum[row] / count) if count else math.nan,
            }
            for name, value in record.items():
                self.episodes[row][name].append(value)
            if self.logger is not None:
                self._log(row, record)
            for values in (*sums.values(), self._loss_sum, self._loss_count):
                values[row] = 0

    def _log(self, row: int, record: dict[str, float]) -> None:
        world, index = self.labels[row]
        step = record["env_steps"]
        names = {"steps": "path_length", "task_return": "return"}
        for name, value in record.items():
            if name != "env_steps" and math.isfinite(value):
                self.logger.log_scalar(f"{world}/seed_{index}/{names.get(name, name)}", value, step)

    def traces(self) -> list[dict[str, Any]]:
        """One dict per experiment: the per-episode arrays, totals and label."""
        out = []
        for row, (world, index) in enumerate(self.labels):
            trace: dict[str, Any] = {"world": world, "seed_index": index}
            for name in EPISODE_FIELDS:
                dtype = np.float64 if name in ("task_return", "epsilon", "loss") else np.int64
                trace[name] = np.asarray(self.episodes[row][name], dtype=dtype)
            trace["total_collisions"] = int(self.totals["collisions"][row])
            trace["total_greedy_collisions"] = int(self.totals["greedy_collisions"][row])
            trace["total_boxed_in_greedy_collisions"] = int(
                self.totals["boxed_in_greedy_collisions"][row]
            )
            trace["total_env_steps"] = int(self.env_steps[row])
            out.append(trace)
        return out


# --------------------------------------------------------------------------------------------
# DQN


@dataclass(frozen=True)
class DQNConfig:
    """DQN's hyperparameters (sources in the module docstring)."""

    gamma: float = 0.9
    """Discount of future reward, in [0, 1) (the SPEC's, shared by every method)."""
    hidden: tuple[int, ...] = (64, 64)
    """Hidden layer widths of each experiment's Q-network."""
    lr: float = 1e-3
    """Adam learning rate."""
    buffer_size: int = 10_000
    """Replay buffer capacity, in env steps (each holds one transition per experiment)."""
    batch_size: int = 128
    """Transitions per experiment in a minibatch."""
    learning_starts: int = 500
    """Env steps before the first gradient step."""
    train_every: int = 4
    """Env steps per gradient step."""
    target_update_interval: int = 50
    """Gradient steps between hard copies of the network into the target network."""
    eps_start: float = 1.0
    """Initial exploration probability of EGreedyModule."""
    eps_end: float = 0.05
    """Final exploration probability."""
    exploration_fraction: float = 0.5
    """Fraction of the step budget over which epsilon anneals linearly to eps_end."""

    def __post_init__(self) -> None:
        check_float("gamma", self.gamma, 0.0, 1.0, high_open=True)
        object.__setattr__(self, "hidden", check_hidden("hidden", self.hidden))
        check_float("lr", self.lr, 0.0, 1.0, low_open=True)
        check_int("buffer_size", self.buffer_size, 1)
        check_int("batch_size", self.batch_size, 1)
        check_int("learning_starts", self.learning_starts, 0)
        check_int("train_every", self.train_every, 1)
        check_int("target_update_interval", self.target_update_interval, 1)
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
        self.in_keys = ["action"]
        self.out_keys = ["action", "exploratory"]
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
_STORED = (
    "cell",
    "proximity",
    "sensors",
    "heading",
    "action",
    ("next", "cell"),
    ("next", "proximity"),
    ("next", "sensors"),
    ("next", "heading"),
    ("next", "reward"),
    ("next", "done"),
    ("next", "terminated"),
)


@dataclass
class DQNAgent:
    """The torchrl modules of a DQN batch (``build_dqn``)."""

    q_network: TaskQNetwork
    value_network: TensorDictSequential
    exploration: ExploratoryEGreedy
    policy: TensorDictSequential
    loss: DQNLoss
    target_updater: HardUpdate
    optimizer: torch.optim.Optimizer
    buffer: ReplayBuffer


def build_dqn(config: DQNConfig, experiments: ExperimentConfig, device=None) -> DQNAgent:
    """Q-network, exploration, DQNLoss with a target network, Adam and a replay buffer."""
    device = torch.device("cpu" if device is None else device)
    count = experiments.num_experiments
    world = experiments.world
    q_network = TaskQNetwork(
        count,
        experiments.size**2,
        with_proximity=True,
        num_sensors=world.num_sensors,
        num_headings=world.num_headings,
        num_actions=world.num_actuators,
        hidden=config.hidden,
        keys=experiment_keys(experiments, STREAM_TASK_NETWORK, "dqn"),
        zero_output=False,  # PyTorch's default initialisation, as the DQN examples
        device=device,
    )
    # QValueModule's spec is per sample (one action), not per batch.
    actions = world.num_actuators
    value_network = TensorDictSequential(q_network, QValueModule(spec=Categorical(actions)))
    annealing = max(1, round(config.exploration_fraction * experiments.steps))
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


ProgressCallback = Callable[[int, int], None]


def run(
    config: DQNConfig,
    experiments: ExperimentConfig,
    *,
    logger=None,
    progress: ProgressCallback | None = None,
    device: torch.device | str | None = None,
) -> dict[str, Any]:
    """Train DQN on every experiment of ``experiments`` for its step budget.

    Returns ``{"config", "experiments", "traces", "wall_s", "env_steps"}``: ``traces`` holds one
    ``EpisodeRecorder`` trace per experiment (world-major, seed-minor). ``progress(done, total)``
    is called with env steps per experiment after every collector batch.
    """
    started = time.perf_counter()
    device = torch.device("cpu" if device is None else device)
    torch.manual_seed(experiments.seed)  # EGreedyModule and the sampler draw from it
    env = make_env(experiments, device)
    agent = build_dqn(config, experiments, device)
    count, steps = experiments.num_experiments, experiments.steps
    frames_per_step = count  # one env step of the batch is E frames
    collector = Collector(
        env,
        agent.policy,
        frames_per_batch=frames_per_step * config.train_every,
        total_frames=frames_per_step * steps,
        device=device,
        auto_register_policy_transforms=False,  # the policy keeps no recurrent state
    )
    recorder = EpisodeRecorder(experiments.labels, logger)
    loss_per_experiment = torch.full((count,), math.nan)
    done_steps, gradient_steps = 0, 0
    for data in collector:  # [E, T]
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
            progress(done_steps, steps)
        if done_steps >= steps:
            break
    collector.shutdown()
    wall = time.perf_counter() - started
    return {
        "config": asdict(config),
        "experiments": asdict(experiments),
        "traces": recorder.traces(),
        "wall_s": wall,
        "env_steps": done_steps * count,
    }


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
