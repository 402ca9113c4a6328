"""Positive local rewards (issue 40, item 2): the world that pays (``factorq_envs.paying_grid``),
one-signed local tables, the local network and the structure learner on rewards of either sign.

The world is checked against pictures worked by hand and its declared dependency against random
walks; the tables against running means worked by hand; the learners by what they learn from
streams whose answer is known.
"""

from __future__ import annotations

import gymnasium
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import check_env_specs

import factorq_envs  # noqa: F401 - registers PayingGrid-v0
from factorq_envs.paying_grid import PayingConfig, PayingGrid, paying_state
from factorq_envs.torchrl_env import FactoredGridEnv
from factorq_envs.transforms import SplitLocalReward
from factorq_torch.base.rng import STREAM_WORLD, derive_keys
from factorq_torch.neural import LocalRewardNetwork
from factorq_torch.signed_structure import SignedStructureLearner, split_signs
from factorq_torch.structure import StructureLearner
from factorq_torch.tables import LocalRewardTable

ZERO = torch.zeros(1, dtype=torch.int64)
NORTH, WEST, SOUTH, EAST = range(4)

# --------------------------------------------------------------------------------------------
# The world


@pytest.mark.parametrize(
    ("picture", "cell", "action", "to", "local", "items_left"),
    [
        (". $ .\n. . .\n. . .", 0, EAST, 1, [0, 0, 0, 1.0], 0),  # onto the item: it pays
        (". $ .\n. . .\n. . .", 0, SOUTH, 3, [0, 0, 0, 0], 1),  # past it: nothing
        (". o .\n. . .\n. . .", 0, EAST, 0, [0, 0, 0, -1.0], 0),  # into an obstacle
        (". . .\n. . .\n. . .", 0, NORTH, 0, [-1.0, 0, 0, 0], 0),  # into the wall
        (". . .\n. $ $\n. . .", 4, EAST, 5, [0, 0, 0, 1.0], 1),  # one of two items
    ],
)
def test_the_actuator_that_moves_onto_an_item_is_paid_and_a_collision_still_costs(
    picture, cell, action, to, local, items_left
):
    world = PayingGrid(PayingConfig(size=3, num_obstacles=1, num_items=2, item_reward=1.0))
    state, outcome = world.step(paying_state(picture, cell), torch.tensor([action]), ZERO, ZERO)
    assert int(state.cell[0]) == to
    assert outcome.collision[0].tolist() == local
    assert state.bump[0].tolist() == [value < 0 for value in local]  # bump: collisions only
    assert bool(outcome.collected[0]) == (max(local) > 0)
    assert int(state.items.sum()) == items_left
    assert float(outcome.task_reward[0]) == -1.0  # the task's reward knows nothing of items
    assert float(outcome.reward[0]) == -1.0 + sum(local)


def test_the_item_reward_is_the_configs_and_a_bad_one_is_refused():
    world = PayingGrid(PayingConfig(size=3, num_obstacles=0, num_items=1, item_reward=2.5))
    state = paying_state(". $ .\n. . .\n. . .", 0)
    _, outcome = world.step(state, torch.tensor([EAST]), ZERO, ZERO)
    assert outcome.collision[0].tolist() == [0.0, 0.0, 0.0, 2.5]
    with pytest.raises(ValueError, match="item_reward=0.0 is out of range"):
        PayingConfig(item_reward=0.0)
    with pytest.raises(ValueError, match="num_items=7 is out of range"):
        PayingConfig(size=3, num_obstacles=0, num_items=7)  # 9 cells less start, goal, agent


def test_item_sensors_read_the_four_neighbours_and_an_obstacle_hides_an_item():
    world = PayingGrid(PayingConfig(size=3, num_obstacles=1, num_items=2))
    state = paying_state(". $ .\n$ . $\n. . .", 4)  # the agent in the middle
    # proximity N W S E, then items N W S E
    assert world.observe(state, ZERO).int().tolist() == [[0, 0, 0, 0, 1, 1, 0, 1]]
    covered = state._replace(obstacles=state.items & (torch.arange(9) == 1))  # an obstacle on 1
    assert world.observe(covered, ZERO).int().tolist() == [[1, 0, 0, 0, 0, 1, 0, 1]]
    _, outcome = world.step(covered, torch.tensor([NORTH]), ZERO, ZERO)
    assert outcome.collision[0].tolist() == [-1.0, 0.0, 0.0, 0.0]  # a collision, not a pay
    assert "$" in world.render(state) and world.render(state).count("$") == 3


def test_items_are_drawn_at_every_reset_off_start_goal_and_agent_and_replay_by_seed():
    config = PayingConfig(size=5, num_obstacles=3, num_items=6)
    world = PayingGrid(config)
    count = 32
    keys = derive_keys(7, STREAM_WORLD, count)
    periods = torch.zeros(count, dtype=torch.int64)
    start = world.reset(world.initial_state(count), torch.ones(count, dtype=bool), keys, periods)
    assert int(start.items.sum(dim=1).min()) == int(start.items.sum(dim=1).max()) == 6
    assert not start.items[:, 0].any() and not start.items[:, -1].any()
    again = world.reset(world.initial_state(count), torch.ones(count, dtype=bool), keys, periods)
    assert torch.equal(start.items, again.items)  # the same keys, the same items
    second = world.reset(start, torch.ones(count, dtype=bool), keys, periods)
    assert not torch.equal(second.items, start.items)  # the next episode draws anew
    assert torch.equal(world.rewind(second).item_layouts, torch.zeros(count, dtype=torch.int64))


def test_the_dependency_is_each_actuators_proximity_and_item_sensor_and_agrees_with_the_rewards():
    world = PayingGrid(PayingConfig(size=6, num_obstacles=6, num_items=8))
    dependency = world.dependency
    assert dependency.int().tolist()[2] == [0, 0, 1, 0, 0, 0, 1, 0]
    count = 48
    keys = derive_keys(3, STREAM_WORLD, count)
    periods = torch.arange(count) % 3  # static, and obstacles that move
    state = world.reset(world.initial_state(count), torch.ones(count, dtype=bool), keys, periods)
    generator = torch.Generator().manual_seed(0)
    rows, paid, cost = torch.arange(count), 0, 0
    for _ in range(60):
        before = world.observe(state, keys)  # [S, 8]
        action = torch.randint(0, 4, (count,), generator=generator)
        state, outcome = world.step(state, action, keys, periods)
        reward = outcome.collision[rows, action]
        # the fired actuator's local reward is -1 where its proximity sensor read an obstacle,
        # +1 where its item sensor read an item, else 0; the others' are 0
        expected = torch.where(
            before[rows, action], -1.0, torch.where(before[rows, 4 + action], 1.0, 0.0)
        )
        assert torch.equal(reward, expected)
        assert outcome.collision.abs().sum() == reward.abs().sum()
        paid, cost = paid + int((reward > 0).sum()), cost + int((reward < 0).sum())
        state = world.reset(state, outcome.terminated | outcome.truncated, keys, periods)
    assert paid > 20 and cost > 20  # random walks meet both


def test_torchrl_and_gymnasium_envs_of_the_paying_grid_pass_their_checkers():
    world = PayingGrid(PayingConfig(size=5, num_obstacles=3, num_items=5))
    env = FactoredGridEnv(world=world, batch_size=(3,), obstacle_period=[0, 10, 1], seed=1)
    spec = env.observation_spec["collision"]
    assert spec.space.low.max() == -1.0 and spec.space.high.min() == 1.0
    assert env.observation_spec["sensors"].shape == (3, 8)
    check_env_specs(env, seed=0)
    split = TransformedEnv(env, SplitLocalReward())
    check_env_specs(split, seed=0)
    rollout = split.rollout(150, break_when_any_done=False)
    local = rollout["next", "local_reward"]
    assert (local > 0).any() and (local < 0).any()  # random actions are paid and collide
    assert torch.equal(local, rollout["next", "collision"])
    gym_env = gymnasium.make("PayingGrid-v0", size=5, num_obstacles=3, num_items=5)
    check_env(gym_env.unwrapped)
    assert gym_env.observation_space["collision"] == gymnasium.spaces.Box(-1.0, 1.0, (4,))
    assert gym_env.observation_space["sensors"] == gymnasium.spaces.MultiBinary(8)


# --------------------------------------------------------------------------------------------
# The local tables: either sign, or declared one-signed


def test_a_local_table_takes_both_signs_as_running_means_worked_by_hand():
    dependency = PayingConfig().dependency  # actuator a: sensors a and 4 + a
    table = LocalRewardTable(1, dependency=dependency)
    item_east = torch.zeros(1, 8, dtype=torch.bool)
    item_east[0, 7] = True  # pattern of east's parents (3, 7): 0 + 2 * 1 = 2
    east = torch.tensor([EAST])
    for reward in (1.0, 1.0, 0.0):  # paid twice, then an item that was not there any more
        table.update_running_mean(item_east, east, torch.tensor([[0.0, 0.0, 0.0, reward]]))
    wall_east = torch.zeros(1, 8, dtype=torch.bool)
    wall_east[0, 3] = True  # pattern 1
    table.update_running_mean(wall_east, east, torch.tensor([[0.0, 0.0, 0.0, -1.0]]))
    assert table.rho[0, EAST].tolist() == [0.0, -1.0, pytest.approx(2 / 3), 0.0]
    assert table.kappa[0, EAST].tolist() == [0, 1, 3, 0]


def test_a_table_declared_one_signed_refuses_the_other_sign_naming_both():
    positive = LocalRewardTable(1, sign="positive")
    sensors, action = torch.zeros(1, 4, dtype=torch.bool), torch.tensor([0])
    positive.update_running_mean(sensors, action, torch.tensor([[1.0, 0, 0, 0]]))  # taken
    with pytest.raises(
        ValueError,
        match=r"update_running_mean: the table was declared sign='positive' \(local rewards "
        r">= 0, pays only\), but local_reward holds a negative local reward \(-1\)",
    ):
        positive.update_running_mean(sensors, action, torch.tensor([[-1.0, 0, 0, 0]]))
    assert positive.rho[0, 0].tolist() == [1.0, 0.0]  # nothing was written
    negative = LocalRewardTable(1, sign="negative")
    with pytest.raises(ValueError, match=r"sign='negative' \(local rewards <= 0, costs only\)"):
        negative.update_running_mean(sensors, action, torch.tensor([[0.5, 0, 0, 0]]))
    with pytest.raises(ValueError, match="sign='both' is unknown: choose one of either"):
        LocalRewardTable(1, sign="both")


def test_loading_a_mixed_table_into_a_one_signed_one_names_both_signs():
    either = LocalRewardTable(1)
    either.rho[0, 0] = torch.tensor([1.0, -1.0])
    negative = LocalRewardTable(1, sign="negative")
    with pytest.raises(
        ValueError,
        match=r"load_state_dict: the table was declared sign='negative' .* but the loaded 'rho' "
        r"holds a positive local reward \(\+1\) and a negative local reward \(-1\): declare "
        r"sign='either'",
    ):
        negative.load_state_dict(either.state_dict())
    assert negative.rho.abs().sum() == 0  # nothing was loaded
    LocalRewardTable(1).load_state_dict(either.state_dict())  # "either" takes it


# --------------------------------------------------------------------------------------------
# The local network and the structure learner


def test_the_local_network_learns_a_cost_and_a_pay_from_two_parents():
    dependency = PayingConfig().dependency
    network = LocalRewardNetwork(1, dependency=dependency, hidden=(8,), zero_output=False)
    optimizer = torch.optim.Adam(network.parameters(), lr=0.05)
    # east's parents: (wall, item) = (1, 0) costs -1, (0, 1) pays +1, (0, 0) nothing
    readings = torch.zeros(3, 1, 8, dtype=torch.bool)
    readings[0, 0, 3], readings[1, 0, 7] = True, True
    target = torch.tensor([-1.0, 1.0, 0.0])
    for _ in range(300):
        from tensordict import TensorDict

        values = network(TensorDict(sensors=readings, batch_size=[3, 1]))["local_value"]
        loss = 0.5 * (values[:, 0, EAST] - target).pow(2).sum()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    assert values[:, 0, EAST].detach().tolist() == pytest.approx([-1.0, 1.0, 0.0], abs=0.05)


def signed_stream(steps: int) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """One actuator, three sensors: sensor 0 a wall (-1), sensor 1 an item (+1), sensor 2 a coin
    that decides nothing; every third firing meets a wall, every fifth an item."""
    generator = torch.Generator().manual_seed(4)
    stream = []
    for step in range(steps):
        wall, item = step % 3 == 1, step % 5 == 2 and step % 3 != 1
        coin = bool(torch.randint(0, 2, (1,), generator=generator))
        reward = -1.0 if wall else 1.0 if item else 0.0
        stream.append((torch.tensor([[wall, item, coin]]), torch.tensor([[reward]])))
    return stream


def test_the_signed_learner_finds_the_sensors_of_both_signs_where_one_channel_finds_the_cost():
    signed = SignedStructureLearner(1, num_actions=1, num_sensors=3)
    plain = StructureLearner(1, num_actions=1, num_sensors=3)
    action = torch.tensor([0])
    for reading, reward in signed_stream(120):
        signed.update_running_mean(reading, action, reward)
        plain.update_running_mean(reading, action, reward)
    assert signed.structure().int().tolist() == [[[1, 1, 0]]]
    assert signed.costs.structure().int().tolist() == [[[1, 0, 0]]]
    assert signed.pays.structure().int().tolist() == [[[0, 1, 0]]]
    assert bool(signed.is_committed().all())
    values = [
        signed.local_values(torch.tensor([r])).item() for r in ([1, 0, 1], [0, 1, 0], [0, 0, 1])
    ]
    assert values == [-1.0, 1.0, 0.0]
    # the plain learner counts a gain as nothing happened: it can find the wall, never the item
    assert plain.structure().int().tolist() == [[[1, 0, 0]]]
    signed.reset()
    assert not bool(signed.is_committed().any())


def test_split_signs_gives_each_channel_its_part_as_a_cost():
    costs, gains = split_signs(torch.tensor([[-1.0, 0.0, 2.0, -0.5]]))
    assert costs.tolist() == [[-1.0, 0.0, 0.0, -0.5]]
    assert gains.tolist() == [[0.0, 0.0, -2.0, 0.0]]
    assert not torch.signbit(costs[0, 1]) and not torch.signbit(gains[0, 1])  # no -0.0


# --------------------------------------------------------------------------------------------
# Learning in the world that pays (examples/positive_rewards.py's agents)


def load_example():
    """``examples/positive_rewards.py`` as a module (examples are scripts, not a package)."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "examples" / "positive_rewards.py"
    spec = importlib.util.spec_from_file_location("positive_rewards", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_factorq_takes_the_items_it_senses_and_q_learning_mostly_does_not(one_thread):
    example = load_example()
    world = PayingGrid(PayingConfig(size=5, num_obstacles=3, num_items=5))
    seeds, episodes = list(range(5)), 4
    taken, collisions = {}, {}
    for method in example.METHODS:
        result = example.run(method, world, seeds, episodes, 0)
        taken[method] = float(result["items"].sum() / result["offered"].sum())
        collisions[method] = int(result["collisions"].sum())
        if method == "factor-q-learned":  # most actuators already learned both sensors
            right = (result["structure"] == world.dependency).all(dim=-1)
            assert int(right.sum()) >= 12, right
    # pooled over 5 seeds x 4 episodes (measured: 0.77, 0.61 and 0.36; 22, 72 and 292)
    assert taken["factor-q"] > 0.65 and taken["factor-q-learned"] > 0.5, taken
    assert taken["q-learning"] < 0.45, taken
    assert collisions["factor-q"] * 8 < collisions["q-learning"], collisions
    assert collisions["factor-q-learned"] * 2.5 < collisions["q-learning"], collisions
