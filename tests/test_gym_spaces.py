"""A new user's first torchrl moves on the project's Gymnasium envs (issue 38): torchrl's own
``GymEnv`` of a registered id, with no extra transform, gives a categorical ``cell`` and bool
sensors (``factorq_envs.gym_spaces``), so ``SplitLocalReward``, the tables, ``check_env_specs``
and the DQN recipe with the local-risk layer work on it as on ``FactoredGridEnv``."""

from __future__ import annotations

import logging

import gymnasium
import numpy as np
import pytest
import torch

import factorq_envs  # noqa: F401  (registers FactoredGrid-v0)
from factorq_envs.gym_spaces import FlagSpace, IndexSpace
from factorq_envs.gymnasium_adapter import Declaration, FactorQEnv

LAKE = ("SFFF", "FHFH", "FFFH", "HFFG")
STEPS = ((0, -1), (1, 0), (0, 1), (-1, 0))  # FrozenLake's left, down, right, up
LAKE_ID = "FactorQTestLake-v0"


def _holes_around(step) -> np.ndarray:
    row, col = divmod(int(step.observation), 4)
    return np.array(
        [
            0 <= row + dr < 4 and 0 <= col + dc < 4 and LAKE[row + dr][col + dc] == "H"
            for dr, dc in STEPS
        ]
    )


def _fell(step) -> bool:
    return step.terminated and step.reward == 0


def _lake_reward(step) -> float:
    return step.reward


def _cell(step) -> int:
    return step.observation


def make_declared_lake(**kwargs) -> FactorQEnv:
    """The entry point of a declared id: FrozenLake as the adapter declares it."""
    declaration = Declaration(
        num_sensors=4,
        sensors=_holes_around,
        collision=_fell,
        task_reward=_lake_reward,
        task_state=_cell,
        num_cells=16,
        dependency=tuple(tuple(a == k for k in range(4)) for a in range(4)),
    )
    return FactorQEnv(gymnasium.make("FrozenLake-v1", is_slippery=False), declaration, **kwargs)


@pytest.fixture
def declared_id():
    gymnasium.register(id=LAKE_ID, entry_point=make_declared_lake)
    try:
        yield LAKE_ID
    finally:
        del gymnasium.registry[LAKE_ID]


def _check_the_keys(env) -> None:
    spec = env.observation_spec
    assert spec["cell"].dtype == torch.int64 and spec["cell"].shape == ()
    assert type(spec["cell"]).__name__ == "Categorical"
    assert spec["sensors"].dtype == torch.bool and spec["bump"].dtype == torch.bool


def test_gymnasium_and_sb3_still_see_discrete_and_multibinary():
    env = gymnasium.make("FactoredGrid-v0", size=3, num_obstacles=0)
    space = env.observation_space
    assert (
        isinstance(space["cell"], gymnasium.spaces.Discrete) and type(space["cell"]) is IndexSpace
    )
    assert isinstance(space["sensors"], gymnasium.spaces.MultiBinary)
    assert type(space["sensors"]) is FlagSpace
    observation, _ = env.reset(seed=0)
    assert observation["sensors"].dtype == np.int8  # Gymnasium's MultiBinary values
    vector = gymnasium.vector.SyncVectorEnv([lambda: make_declared_lake()] * 2)
    assert type(vector.observation_space["sensors"]) is FlagSpace  # batched, still flags
    assert vector.observation_space["sensors"].shape == (2, 4)


def test_gym_env_of_factored_grid_feeds_split_local_reward_and_the_tables():
    """``GymEnv("FactoredGrid-v0")``, torchrl's defaults (a one-hot action): the cell is an
    index, the sensors bool; ``check_env_specs`` passes with ``SplitLocalReward`` on top; the
    tables read a rollout; a step north into the wall is the hand-worked collision."""
    from torchrl.envs import GymEnv, TransformedEnv
    from torchrl.envs.utils import check_env_specs

    from factorq_envs import SplitLocalReward
    from factorq_envs.gymnasium_env import torchrl_info_reader
    from factorq_torch.tables import LocalRewardTable, TaskQTable

    base = GymEnv("FactoredGrid-v0", size=3, num_obstacles=0)
    _check_the_keys(base)
    assert base.reward_key == "reward"
    env = TransformedEnv(base.set_info_dict_reader(torchrl_info_reader()), SplitLocalReward())
    check_env_specs(env)
    td = env.reset()
    assert td["cell"].item() == 0 and td["sensors"].tolist() == [True, True, False, False]
    td["action"] = torch.tensor([1, 0, 0, 0])  # one-hot north: into the wall
    nxt = env.step(td)["next"]
    assert nxt["local_reward"].tolist() == [-1.0, 0.0, 0.0, 0.0]
    assert nxt["reward"].item() == -1.0 == nxt["task_reward"].item()  # the task reward: a step
    task = TaskQTable(1, 9, num_actions=4)
    rollout = env.rollout(5)
    assert task(rollout.reshape(5, 1).clone())["action_value"].shape == (5, 1, 4)
    local = LocalRewardTable(1, dependency=torch.eye(4, dtype=torch.bool))
    local.update_running_mean(nxt["sensors"][None], torch.tensor([0]), nxt["local_reward"][None])
    assert int(local.kappa.sum()) == 1 and local.rho.min().item() == -1.0  # north's reading


def test_gym_env_of_a_declared_id_feeds_split_local_reward(declared_id):
    from torchrl.envs import GymEnv, TransformedEnv
    from torchrl.envs.utils import check_env_specs

    from factorq_envs import SplitLocalReward
    from factorq_envs.gymnasium_env import torchrl_info_reader

    base = GymEnv(declared_id)
    _check_the_keys(base)
    env = TransformedEnv(base.set_info_dict_reader(torchrl_info_reader()), SplitLocalReward())
    check_env_specs(env)
    td = env.reset()
    td["action"] = torch.tensor([0, 0, 1, 0])  # right, to cell 1
    td = env.step_mdp(env.step(td))
    td["action"] = torch.tensor([0, 1, 0, 0])  # down, into the hole at 5
    nxt = env.step(td)["next"]
    assert nxt["cell"].item() == 5 and nxt["terminated"].item()
    assert nxt["local_reward"].tolist() == [0.0, -1.0, 0.0, 0.0]
    assert nxt["reward"].item() == 0.0 == nxt["task_reward"].item()  # FrozenLake's own


def test_the_dqn_recipe_with_the_layer_runs_on_gym_env():
    """torchrl's DQN recipe (its one-hot action, ``QValueActor``, ``EGreedyModule`` with the
    layer's mask, a ``Collector``) with ``with_local_risk`` and ``LocalRiskLoss`` on
    ``GymEnv("FactoredGrid-v0")``: every step counted once in the local table."""
    from tensordict.nn import TensorDictModule, TensorDictSequential
    from torchrl.collectors import Collector
    from torchrl.envs import GymEnv, TransformedEnv
    from torchrl.modules import MLP, EGreedyModule, QValueActor
    from torchrl.objectives import DQNLoss

    from factorq_envs import SplitLocalReward
    from factorq_torch import LocalRewardTable, LocalRiskLoss, with_local_risk

    logger = logging.getLogger("torchrl")
    level = logger.level
    logger.setLevel(logging.WARNING)
    try:
        torch.manual_seed(0)
        env = TransformedEnv(
            GymEnv("FactoredGrid-v0", size=4, num_obstacles=2, obstacle_period=1),
            SplitLocalReward(keep_reward=True),
        )
        spec = env.action_spec_unbatched

        def features(cell, sensors):
            return torch.cat([torch.nn.functional.one_hot(cell, 16).float(), sensors.float()], -1)

        net = TensorDictSequential(
            TensorDictModule(features, ["cell", "sensors"], ["features"]),
            TensorDictModule(
                MLP(in_features=20, out_features=4, num_cells=[16]), ["features"], ["action_value"]
            ),
        )
        actor = QValueActor(net, in_keys=["cell"], spec=spec)
        local = LocalRewardTable(1, dependency=torch.eye(4, dtype=torch.bool))
        acting = with_local_risk(actor, local, env=env)
        local_loss = LocalRiskLoss(local)
        explore = EGreedyModule(spec, annealing_num_steps=50, action_mask_key="risk_mask")
        loss = DQNLoss(actor, action_space=spec)
        collector = Collector(
            env,
            TensorDictSequential(acting, explore),
            frames_per_batch=10,
            total_frames=40,
            auto_register_policy_transforms=False,
        )
        for data in collector:
            local_loss(data)
            assert torch.isfinite(loss(data)["loss"])
        collector.shutdown()
    finally:
        logger.setLevel(level)
    assert int(local.kappa.sum()) == 40
