"""``factorq gym``'s methods, each training and evaluating one unit (one method, one seed):
torchrl's DQN, neural Factor-Q (oracle or learned dependencies) and SB3's DQN, with the
settings they share (``HIGHWAY_DQN``) and the unit's seeds and envs (``RUNNERS``: method -> its
function)."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any

from factorq_trainers.commands.gym.config import METHODS, GymConfig
from factorq_trainers.methods.units import Tally, greedy_rollouts, record, sb3_dqn, sb3_greedy, tick

if TYPE_CHECKING:
    import torch

    from factorq_envs.declared_env import DeclaredEnv


#: highway-env's documented SB3 DQN (its README and scripts/sb3_highway_dqn.py): MlpPolicy
#: [256, 256], learning rate 5e-4, buffer 15,000, learning starts 200, batch 32, gamma 0.8,
#: a gradient step every env step, target update every 50, exploration over 70% of the budget.
#: ``DQNConfig``'s names (``methods.dqn``).
HIGHWAY_DQN: dict[str, Any] = dict(
    hidden=(256, 256),
    lr=5e-4,
    buffer_size=15_000,
    learning_starts=200,
    batch_size=32,
    gamma=0.8,
    train_every=1,
    target_update_interval=50,
    exploration_fraction=0.7,
)
FACTOR_Q_EPSILON = 0.05  # Factor-DQN's (docs/decisions.md): constant, no annealing
FACTOR_Q_LR = 1e-3


# --------------------------------------------------------------------------------------------
# Seeds and envs


def _env_seed(config: GymConfig, index: int, evaluation: bool = False) -> int:
    """The env seed of experiment ``index`` (the same for every method)."""
    from factorq_torch.base.rng import STREAM_WORLD, derive_keys

    offset = index + (config.seeds if evaluation else 0)
    return int(derive_keys(config.seed, STREAM_WORLD, 1, offset)[0]) & 0x7FFFFFFF


def _keys(config: GymConfig, unit: dict[str, Any], stream: int) -> torch.Tensor:
    from factorq_torch.base.rng import derive_keys

    slot = METHODS.index(unit["method"]) * config.seeds + unit["seed_index"]
    return derive_keys(config.seed, stream, 1, slot)


def _torchrl_env(config: GymConfig, seed: int) -> DeclaredEnv:
    from factorq_envs.declared_env import declared_torchrl_env

    return declared_torchrl_env(config.spec.make, [seed], exclude=list(config.spec.exclude))


# --------------------------------------------------------------------------------------------
# The training record and the methods


def _tally(config: GymConfig) -> Tally:
    """A unit's training record: steps to threshold and curves on the mean return."""
    every = max(1, config.steps // config.curve_points)
    return Tally(
        config.window,
        config.return_threshold,
        by_return=True,
        curve_every=every,
        steps=config.steps,
    )


def _measures(
    config: GymConfig, tally: Tally, greedy: list[tuple[float, bool]], wall: float
) -> dict[str, Any]:
    """A unit's result: its training record, the greedy measures (``greedy``: return and
    crashed of each episode) and the env steps per second."""
    return {
        "crashes": tally.collisions,
        "crashes_per_1000": 1000.0 * tally.collisions / max(1, tally.step),
        "episodes": len(tally.episodes),
        "steps_to_threshold": tally.reached,
        **tally.curves,
        "greedy_crash_rate": sum(crashed for _, crashed in greedy) / config.eval_episodes,
        "greedy_return": float(sum(total for total, _ in greedy) / len(greedy)),
        "wall_s": wall,
        "steps_per_s": config.steps / wall,
    }


def _env_and_task_network(
    config: GymConfig, unit: dict[str, Any], *, zero_output: bool
) -> tuple[DeclaredEnv, Any]:
    """The unit's env (its own env seed) and a task Q-network on the world's observation, with
    highway-env's documented hidden layers: what every torchrl method of a unit starts from."""
    from factorq_torch.base.rng import STREAM_TASK_NETWORK
    from factorq_trainers.methods.dqn import observation_network

    env = _torchrl_env(config, _env_seed(config, unit["seed_index"]))
    key = config.spec.observation
    network = observation_network(
        1,
        key,
        tuple(env.observation_spec[key].shape[1:]),
        env.num_actions,
        HIGHWAY_DQN["hidden"],
        _keys(config, unit, STREAM_TASK_NETWORK),
        zero_output=zero_output,
    )
    return env, network


def _run_dqn(
    config: GymConfig, unit: dict[str, Any], progress: Callable[[int], None]
) -> dict[str, Any]:
    from factorq_torch.base.rng import STREAM_POLICY
    from factorq_trainers.methods.dqn import DQNConfig, train_stepwise

    settings = DQNConfig(**HIGHWAY_DQN)
    env, q_network = _env_and_task_network(config, unit, zero_output=False)
    tally = _tally(config)

    def on_step(td: Any, step: int) -> None:
        record([tally], td)
        tick(progress, step, config.steps)

    seed = int(_keys(config, unit, STREAM_POLICY)[0]) & 0x7FFFFFFF
    observed = [config.spec.observation]
    agent, wall = train_stepwise(env, q_network, settings, config.steps, observed, on_step, seed)
    env.close()
    return _measures(config, tally, _evaluate(config, unit, agent.value_network), wall)


def _run_factor_q(
    config: GymConfig, unit: dict[str, Any], progress: Callable[[int], None]
) -> dict[str, Any]:
    import torch

    from factorq_torch.base.config import AgentConfig
    from factorq_torch.base.rng import STREAM_POLICY
    from factorq_torch.collectors import OnlineCollector
    from factorq_torch.structure import StructureLearner
    from factorq_torch.tables import LocalRewardTable
    from factorq_trainers.methods.experiment import online_agent

    base, task = _env_and_task_network(config, unit, zero_output=True)
    oracle = base.dependency
    if unit["method"] == "factor-dqn":
        if oracle is None:
            raise ValueError(f"factor-dqn needs a world that declares its oracle: {config.world}")
        local = LocalRewardTable(1, dependency=oracle)
    else:  # an open actuator predicts no local reward (docs/decisions.md, MiniGrid)
        local = StructureLearner(
            1, num_actions=base.num_actions, num_sensors=base.num_sensors, prediction="committed"
        )
    # "risky": a collision more likely than not, half the declared penalty (highway: 2/3)
    threshold = 0.5 * float(base.declaration.penalty)
    agent = AgentConfig(
        gamma=HIGHWAY_DQN["gamma"], exploration=config.exploration, risk_threshold=threshold
    )
    env, policy, loss = online_agent(
        base, task, local, agent, _keys(config, unit, STREAM_POLICY), epsilon=FACTOR_Q_EPSILON
    )
    optimizer = torch.optim.Adam(task.parameters(), lr=FACTOR_Q_LR)
    collector = OnlineCollector(
        env, policy, loss, runs=1, episodes=config.steps, optimizer=optimizer
    )
    tally = _tally(config)
    started = time.perf_counter()
    for step, td in enumerate(collector, start=1):
        record([tally], td)
        tick(progress, step, config.steps)
        if step >= config.steps:
            break
    wall = time.perf_counter() - started
    collector.shutdown()
    result = _measures(config, tally, _evaluate(config, unit, policy), wall)
    if oracle is not None:  # the declared names and oracle, for a summary without torch
        result["oracle"] = oracle.to(torch.int64).tolist()
        result["actuator_names"] = list(base.config.actuator_names)
        result["sensor_names"] = list(base.declaration.sensor_names) or [
            f"s{k}" for k in range(base.num_sensors)
        ]
    if isinstance(local, StructureLearner):
        learned = local.structure()[0]  # [A, K]
        result["structure"] = learned.to(torch.int64).tolist()
        if oracle is not None:  # a world without one: the structure alone
            result["agrees_with_oracle"] = (learned == oracle).all(dim=-1).tolist()
    return result


def _eval_seeds(config: GymConfig, unit: dict[str, Any]) -> list[int]:
    """The env seeds of the unit's greedy episodes (fresh ones, the same for every method)."""
    first = unit["seed_index"] * config.eval_episodes
    return [_env_seed(config, first + episode, True) for episode in range(config.eval_episodes)]


def _evaluate(config: GymConfig, unit: dict[str, Any], policy: Any) -> list[tuple[float, bool]]:
    """The greedy policy's episodes (exploration off) on fresh env seeds: return, crashed."""

    def envs() -> Iterator[DeclaredEnv]:
        for seed in _eval_seeds(config, unit):
            env = _torchrl_env(config, seed)
            yield env
            env.close()

    episodes = []
    for rollout in greedy_rollouts(policy, envs()):
        rewards = rollout.get(("next", "reward")).reshape(-1).tolist()
        episodes.append((sum(rewards, 0.0), bool(rollout.get(("next", "bump")).any())))
    return episodes


def _run_sb3(
    config: GymConfig, unit: dict[str, Any], progress: Callable[[int], None]
) -> dict[str, Any]:
    """SB3's DQN with the documented hyperparameters on the world's own observation; crashes
    and returns read from the adapter's ``info`` by a recording wrapper."""
    import gymnasium
    import torch

    tally = _tally(config)

    class Record(gymnasium.Wrapper):
        def step(self, action: Any) -> Any:
            out = self.env.step(action)
            observation, reward, terminated, truncated, info = out
            tally.update(float(reward), bool(info["collided"]), terminated or truncated)
            tick(progress, tally.step, config.steps)
            return out

    def make(seed: int) -> gymnasium.Env:
        env = config.spec.make(seed)
        observation = gymnasium.wrappers.FilterObservation(env, [config.spec.observation])
        return gymnasium.wrappers.FlattenObservation(observation)

    seed = _env_seed(config, unit["seed_index"])
    torch.manual_seed(seed)
    model = sb3_dqn(HIGHWAY_DQN, Record(make(seed)), "MlpPolicy", seed=seed, device="cpu")
    started = time.perf_counter()
    model.learn(total_timesteps=config.steps)
    wall = time.perf_counter() - started
    envs = (make(seed) for seed in _eval_seeds(config, unit))
    greedy = sb3_greedy(model, envs, lambda info: bool(info["collided"]))
    return _measures(config, tally, [(total, hits > 0) for total, hits, _ in greedy], wall)


#: Each method's function: ``(config, unit, progress) -> the unit's result``.
RUNNERS: dict[str, Callable[[GymConfig, dict[str, Any], Callable[[int], None]], dict[str, Any]]] = {
    "dqn": _run_dqn,
    "factor-dqn": _run_factor_q,
    "factor-dqn-learned": _run_factor_q,
    "sb3-dqn": _run_sb3,
}
