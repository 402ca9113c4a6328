"""``factorq risk``'s methods, each training and evaluating one unit (one world, method and
seed): torchrl's DQN recipe alone or with ``factorq_torch.risk``'s layer (``run_torchrl``: the
env, its features, the local reward provider, the greedy evaluation) and Stable-Baselines3's DQN
alone or with ``factorq_torch.integrations.sb3`` (``run_sb3``); ``quiet_torchrl`` silences
torchrl's INFO lines while a unit runs. The command is ``factorq_trainers.commands.risk.command``.
"""

from __future__ import annotations

import contextlib
import logging
import math
import statistics
import time
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any

from factorq_envs.worlds import resolve_world
from factorq_trainers.commands.risk.config import OWN_WORLDS, Progress, RiskConfig
from factorq_trainers.methods import units

if TYPE_CHECKING:
    import torch

    from factorq_torch.structure import StructureLearner
    from factorq_torch.tables import LocalRewardTable


# --------------------------------------------------------------------------------------------
# One unit: the torchrl recipe


def make_env(config: RiskConfig, world: str, seed: int) -> Any:  # a TransformedEnv (untyped)
    """The world as a torchrl env of batch ``[1]`` with ``local_reward`` beside the reward.

    Args:
        world: ``"grid"``, ``"minigrid"`` or a declared world's name
            (``factorq_envs.worlds``: ``highway``, an installed one, ``package.module:NAME``),
            through the Gymnasium adapter.
        seed: the world's seed.
    """
    from torchrl.envs import TransformedEnv

    from factorq_envs import FactoredGridEnv, SplitLocalReward

    base: Any
    if world == "grid":
        base = FactoredGridEnv(
            size=config.grid_size,
            num_obstacles=config.grid_obstacles,
            obstacle_period=1,
            batch_size=(1,),
            seed=seed,
        )
    elif world == "minigrid":
        from factorq_envs.minigrid_torchrl import MiniGridEnv

        base = MiniGridEnv(config.minigrid_size, seeds=[seed])
    else:
        from factorq_envs.declared_env import declared_torchrl_env

        declared = resolve_world(world)
        base = declared_torchrl_env(declared.make, [seed], exclude=list(declared.exclude))
    return TransformedEnv(base, SplitLocalReward(keep_reward=True))


def _survival(world: str) -> bool:
    """Whether ``world``'s success is running to the time limit without a collision (highway)
    rather than ending without one (``DeclaredWorld.survival``)."""
    return world not in OWN_WORLDS and resolve_world(world).survival


def _penalty(env: Any) -> float:
    """The world's collision penalty: the declared one (highway: 2/3), else 1."""
    declaration = getattr(env.base_env, "declaration", None)
    return 1.0 if declaration is None else float(declaration.penalty)


def features(env: Any) -> tuple[Any, int]:
    """``features`` ``[*B, N H + K]``: the (cell, heading) one-hot and the sensor bits, the
    information Q-learning's state holds, as a TensorDict module, and its width. A declared world
    without a task state (no ``cell``: highway) has its own observation (``observation``, left as
    it is; highway's ``Kinematics`` ``[*B, 5, 5]``) flattened instead of the one-hot, so DQN alone
    sees what the layer sees. ``features`` never collides with an env's own entry (a non-Dict
    env's observation is ``observation``).

    Args:
        env: a ``make_env`` env.
    """
    import torch
    from tensordict.nn import TensorDictModule

    spec = env.observation_spec
    encode: Callable[..., torch.Tensor]
    if "cell" not in spec.keys():
        own = spec["observation"].shape[len(env.batch_size) :]
        first, rest, width = "observation", [], own.numel()

        def encode(observation: torch.Tensor) -> torch.Tensor:
            return observation.flatten(observation.dim() - len(own))

    else:
        cells = int(spec["cell"].space.n)
        headings = int(spec["heading"].space.n) if "heading" in spec.keys() else 1
        first, rest, width = "cell", ["heading"] if headings > 1 else [], cells * headings

        def encode(cell: torch.Tensor, heading: torch.Tensor | None = None) -> torch.Tensor:
            position = cell if heading is None else cell * headings + heading
            return torch.nn.functional.one_hot(position, cells * headings)

    class Features(torch.nn.Module):
        def forward(self, own: torch.Tensor, sensors: torch.Tensor, *rest: torch.Tensor) -> Any:
            return torch.cat([encode(own, *rest).to(torch.float32), sensors.float()], dim=-1)

    in_keys = [first, "sensors", *rest]
    width += spec["sensors"].shape[-1]
    return TensorDictModule(Features(), in_keys=in_keys, out_keys=["features"]), width


def provider(method: str, env: Any) -> LocalRewardTable | StructureLearner | None:
    """The local value provider of a ``dqn+risk-*`` method (None for plain DQN).

    Args:
        env: a ``make_env`` env (its base env's dependency).
    """
    from factorq_torch.structure import StructureLearner
    from factorq_torch.tables import LocalRewardTable

    dependency = env.base_env.dependency
    if method.endswith("+risk"):
        return LocalRewardTable(1, dependency=dependency)
    if method.endswith("risk-learned"):
        actions, sensors = dependency.shape
        return StructureLearner(1, num_actions=actions, num_sensors=sensors)
    return None


def _step_flags(td: Any, survive: bool) -> Iterator[tuple[float, bool, bool, bool]]:
    """Per world of one collected step: reward, collided, done, success (the goal reached;
    ``survive``, as on highway: the episode ran to its time limit without a crash)."""
    reward = td["next", "reward"].reshape(-1).tolist()
    collided = (td["next", "collision"] < 0).any(-1).reshape(-1)
    done = td["next", "done"].reshape(-1)
    ended = td["next", "truncated" if survive else "terminated"].reshape(-1)
    success = ended & ~collided
    return zip(reward, collided.tolist(), done.tolist(), success.tolist(), strict=True)


def run_torchrl(
    config: RiskConfig, unit: dict[str, Any], progress: Progress | None = None
) -> dict[str, Any]:
    """torchrl's DQN recipe, plus the two lines of the local-risk layer for ``dqn+risk-*``.

    Args:
        progress: called with the env steps of each collected batch.
    """
    import torch
    from tensordict.nn import TensorDictModule, TensorDictSequential
    from torchrl.data import LazyTensorStorage, ReplayBuffer
    from torchrl.modules import MLP, EGreedyModule, QValueActor
    from torchrl.objectives import DQNLoss, SoftUpdate

    from factorq_torch.risk import RISK_MASK, LocalRisk, LocalRiskLoss, RiskSummary, with_local_risk
    from factorq_torch.structure import StructureLearner
    from factorq_trainers.methods.dqn import Collector  # imported without torchrl's warnings

    torch.manual_seed(unit["seed"])
    env = make_env(config, unit["world"], unit["seed"])
    spec = env.action_spec_unbatched
    encoder, width = features(env)
    network = MLP(in_features=width, out_features=int(spec.space.n), num_cells=[config.hidden] * 2)
    actor = QValueActor(
        TensorDictSequential(encoder, TensorDictModule(network, ["features"], ["action_value"])),
        in_keys=list(encoder.in_keys),
        spec=spec,
    )
    local = provider(unit["method"], env)
    survive = _survival(unit["world"])
    # "risky" in local-reward units: a collision more likely than not, whatever its penalty
    options: dict[str, Any] = {"mask_threshold": 0.5 * _penalty(env)}
    if unit["world"] not in OWN_WORLDS:  # a declared world: sensor names from its declaration
        names = env.base_env.declaration.sensor_names
        options.update(active="on", **({"sensor_names": names} if names else {}))
    acting = actor if local is None else with_local_risk(actor, local, env=env, **options)  # 1
    local_loss = None if local is None else LocalRiskLoss(local)  # line 2
    summary: RiskSummary | None = None  # what the layer did, per training episode (the logs)
    if local is not None:
        layer = next(module for module in acting.modules() if isinstance(module, LocalRisk))
        summary = RiskSummary(layer.actuator_names)
    risk_log: list[dict[str, Any]] = []
    annealing = max(1, round(config.exploration_fraction * config.steps))
    mask = None if local is None else RISK_MASK  # explore among the actions not called risky
    egreedy = EGreedyModule(
        spec,
        eps_init=config.eps_start,
        eps_end=config.eps_end,
        annealing_num_steps=annealing,
        action_mask_key=mask,
    )
    policy = TensorDictSequential(acting, egreedy)
    loss = DQNLoss(actor, action_space=spec, delay_value=True, loss_function="l2")
    loss.make_value_estimator(gamma=config.gamma)
    target = SoftUpdate(loss, tau=config.tau)
    optimizer = torch.optim.Adam(loss.parameters(), lr=config.lr)
    buffer = ReplayBuffer(
        storage=LazyTensorStorage(config.buffer_size), batch_size=config.batch_size
    )
    collector = Collector(
        env,
        policy,
        frames_per_batch=config.train_every,
        total_frames=config.steps,
        auto_register_policy_transforms=False,  # no recurrent state
    )
    tally = units.Tally(10, config.success_threshold)
    started = time.perf_counter()
    for data in collector:  # [1, T]
        data = data.reshape(-1)
        for t in range(data.shape[0]):
            step = data[t : t + 1]
            if summary is not None:
                summary.update(step)
            for flags in _step_flags(step, survive):
                tally.update(*flags)
                if summary is not None and flags[2]:  # the episode is done
                    risk_log.append(summary.episode())
        egreedy.step(data.shape[0])
        if local_loss is not None:
            local_loss(data)  # eq. 5 on every transition once (the running means)
        buffer.extend(data)
        if tally.step >= config.learning_starts:
            value = loss(buffer.sample())["loss"]
            optimizer.zero_grad()
            value.backward()
            optimizer.step()
            target.step()
        if progress is not None:
            progress(data.shape[0])
    collector.shutdown()
    wall = time.perf_counter() - started
    result = _result(tally, evaluate(config, unit, acting), wall)
    if summary is not None:
        result["risk_log"] = risk_log
    if isinstance(local, StructureLearner):  # what it found, beside the env's declared oracle
        result["structure"] = _structure(local, layer, env)
    return result


def _structure(learner: StructureLearner, layer: Any, env: Any) -> dict[str, Any]:
    """The learner's committed parents per actuator (sensor names; ``None`` while open) and the
    env's dependency in the same form (``None`` where it declares none)."""
    sensors, actuators = layer.sensor_names, layer.actuator_names

    def parents(rows: Any) -> list[list[str]]:
        return [[sensors[k] for k, on in enumerate(row) if on] for row in rows.tolist()]

    committed = learner.is_committed()[0].tolist()
    found = parents(learner.structure()[0])
    dependency = getattr(env, "dependency", None)
    return {
        "actuators": list(actuators),
        "parents": [names if done else None for names, done in zip(found, committed, strict=True)],
        "oracle": None if dependency is None else parents(dependency),
    }


def evaluate(config: RiskConfig, unit: dict[str, Any], acting: Any) -> dict[str, int]:
    """Greedy episodes after training (torchrl's ``DETERMINISTIC`` exploration) on fresh worlds
    of the same kind: collisions and successes.

    Args:
        acting: the greedy policy (a tensordict module).
    """
    env = make_env(config, unit["world"], 10_000 + unit["seed"])
    collisions = successes = 0
    survive = _survival(unit["world"])
    if unit["world"] not in OWN_WORLDS:
        limit = resolve_world(unit["world"]).max_steps  # the env's own time limit ends sooner
    else:
        limit = 4 * (config.grid_size if unit["world"] == "grid" else config.minigrid_size) ** 2
    for rollout in units.greedy_rollouts(acting, [env] * config.eval_episodes, limit):
        collided = (rollout["next", "collision"] < 0).any(-1)
        collisions += int(collided.sum())
        if survive:  # survived: ran to the time limit, no crash
            successes += int(not bool(collided.any()))
        else:
            successes += int((rollout["next", "terminated"].squeeze(-1) & ~collided).any())
    return {"collisions": collisions, "successes": successes, "episodes": config.eval_episodes}


def _result(tally: units.Tally, greedy: dict[str, int], wall: float) -> dict[str, Any]:
    """A unit's result; ``final_return``: the mean return of the last 20% of training episodes,
    ``steps_to_threshold``: the env step at which the success rate of the last 10 first reached
    ``success_threshold``."""
    returns = [episode[1] for episode in tally.episodes]
    tail = returns[-max(1, len(returns) // 5) :] if returns else [math.nan]
    return {
        "train_collisions": tally.collisions,
        "episodes": len(returns),
        "final_return": statistics.fmean(tail),
        "steps_to_threshold": tally.reached,
        "greedy_collisions": greedy["collisions"],
        "greedy_success": greedy["successes"] / max(1, greedy["episodes"]),
        "wall_s": wall,
    }


# --------------------------------------------------------------------------------------------
# One unit: Stable-Baselines3


def run_sb3(
    config: RiskConfig, unit: dict[str, Any], progress: Progress | None = None
) -> dict[str, Any]:
    """SB3's DQN on the gymnasium grid (``FactoredGrid-v0``), alone or as ``LocalRiskDQN`` with
    the oracle table (the ``sb3`` extra); the same budget and hyperparameters as the torchrl
    units.

    Args:
        unit: one of ``units(config)`` (its world must be ``"grid"``).
        progress: called with the env steps of each callback.
    """
    import gymnasium
    from stable_baselines3.common.callbacks import BaseCallback

    import factorq_envs  # noqa: F401  (registers FactoredGrid-v0)
    from factorq_envs.gymnasium_env import FactoredGridGym
    from factorq_torch.integrations.sb3 import LocalRiskDQN
    from factorq_torch.tables import LocalRewardTable

    if unit["world"] != "grid":
        raise ValueError("the sb3 methods run on the grid world only (sb3_worlds)")
    tally = units.Tally(10, config.success_threshold)

    def collided(info: dict) -> bool:
        return bool((info["local_reward"] < 0).any())

    class Record(BaseCallback):
        def _on_step(self) -> bool:
            for reward, done, info in zip(
                self.locals["rewards"], self.locals["dones"], self.locals["infos"], strict=True
            ):
                success = bool(done) and not info.get("TimeLimit.truncated", False)
                hit = collided(info)
                tally.update(float(reward), hit, bool(done), success and not hit)
            if progress is not None:
                progress(len(self.locals["infos"]))
            return True

    def grid_env(seed: int) -> gymnasium.Env:
        size, obstacles = config.grid_size, config.grid_obstacles
        env = gymnasium.make(
            "FactoredGrid-v0", size=size, num_obstacles=obstacles, obstacle_period=1
        )
        env.reset(seed=seed)
        return env

    env = grid_env(unit["seed"])
    # the torchrl recipe's settings; target update every gradient step (with tau: SoftUpdate's)
    settings = {
        name: getattr(config, name)
        for name in units.SB3_DQN_NAMES
        if name != "target_update_interval"
    }
    settings.update(hidden=(config.hidden,) * 2, target_update_interval=1)
    extra: dict[str, Any] = {"seed": unit["seed"]}
    if unit["method"] == "sb3-dqn+risk":
        grid = env.unwrapped
        assert isinstance(grid, FactoredGridGym)  # what FactoredGrid-v0 makes; for mypy
        extra.update(
            model=LocalRiskDQN, provider=LocalRewardTable(1, dependency=grid.config.dependency)
        )
    model = units.sb3_dqn(settings, env, "MultiInputPolicy", **extra)
    started = time.perf_counter()
    model.learn(config.steps, callback=Record())
    wall = time.perf_counter() - started
    evaluation = [grid_env(10_000 + unit["seed"])] * config.eval_episodes
    greedy = units.sb3_greedy(model, evaluation, collided, 4 * config.grid_size**2)
    collisions, successes = sum(e[1] for e in greedy), sum(e[2] for e in greedy)
    result = {"collisions": collisions, "successes": successes, "episodes": config.eval_episodes}
    return _result(tally, result, wall)


@contextlib.contextmanager
def quiet_torchrl() -> Iterator[None]:
    """torchrl's logger at WARNING while the block runs (it prints an INFO line per replay buffer
    it allocates, to stdout by default), its own level restored after."""
    import torchrl  # noqa: F401  (its import sets the logger's level: before ours, not after)

    logger = logging.getLogger("torchrl")
    level = logger.level
    if logger.getEffectiveLevel() < logging.WARNING:
        logger.setLevel(logging.WARNING)
    try:
        yield
    finally:
        logger.setLevel(level)
