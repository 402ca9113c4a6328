"""Arbitration (issue 40, item 3): the strike world's rules by hand, its envs through torchrl's and
Gymnasium's checkers, the mechanism (``functional.arbitrated_normaliser``) on hand-computed rows,
wired into the policy and eq. 4, and shown to change nothing where the paper's rewards hold."""

from __future__ import annotations

import pytest
import torch
from gymnasium.utils.env_checker import check_env
from tensordict import TensorDict
from tensordict.nn import TensorDictSequential
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import check_env_specs

from factorq_envs.gymnasium_env import FactoredGridGym
from factorq_envs.protocol import World
from factorq_envs.strike import StrikeConfig, StrikeWorld
from factorq_envs.torchrl_env import FactoredGridEnv
from factorq_envs.transforms import SplitLocalReward
from factorq_torch.base.config import AgentConfig
from factorq_torch.base.rng import STREAM_POLICY, derive_keys
from factorq_torch.collectors import OnlineCollector
from factorq_torch.functional import arbitrated_normaliser, combined_values, normaliser
from factorq_torch.objectives import FactorQLoss, tabular_optimizer
from factorq_torch.policy import FactorQPolicy
from factorq_torch.tables import LocalRewardTable, TaskQTable

ZERO = torch.zeros(1, dtype=torch.int64)
NORTH, WEST, SOUTH, EAST = range(4)


def started(world: StrikeWorld, cell: int) -> tuple:
    """One world just reset, the agent moved to ``cell``."""
    state = world.reset(world.initial_state(1), torch.ones(1, dtype=torch.bool), ZERO, ZERO)
    return state._replace(cell=torch.tensor([cell]))


# --------------------------------------------------------------------------------------------
# The world


def test_the_layout_walls_the_goal_room_and_the_door_is_above_the_goal():
    config = StrikeConfig(size=5, room=2)
    layout = config.layout.reshape(5, 5).int().tolist()
    assert layout == [
        [0, 0, 0, 0, 0],
        [0, 0, 0, 0, 0],
        [0, 0, 1, 1, 1],
        [0, 0, 1, 0, 0],
        [0, 0, 1, 0, 0],
    ]
    assert config.door_cell == 14 and config.goal_cell == 24
    assert isinstance(StrikeWorld(config), World)
    assert StrikeConfig(size=6).door_cell == 3 * 6 + 5


def test_striking_the_closed_door_collides_and_opens_it_until_the_next_reset():
    world = StrikeWorld(StrikeConfig(size=5, room=2))
    state = started(world, 9)  # (1, 4): the door south, the wall east
    assert world.observe(state, ZERO).tolist() == [[False, False, True, True]]
    state, outcome = world.step(state, torch.tensor([SOUTH]), ZERO, ZERO)
    assert int(state.cell[0]) == 9 and outcome.collision.tolist() == [[0.0, 0.0, -1.0, 0.0]]
    assert bool(state.door_open[0]) and not bool(state.obstacles[0, 14])
    assert world.observe(state, ZERO).tolist() == [[False, False, False, True]]
    state, outcome = world.step(state, torch.tensor([SOUTH]), ZERO, ZERO)  # through
    assert int(state.cell[0]) == 14 and outcome.collision.abs().sum() == 0
    state = world.reset(state, torch.ones(1, dtype=torch.bool), ZERO, ZERO)
    assert int(state.cell[0]) == 0 and not bool(state.door_open[0])
    assert bool(state.obstacles[0, 14])


@pytest.mark.parametrize(
    ("cell", "action"),
    [(9, EAST), (4, NORTH), (8, SOUTH), (13, WEST)],  # the outer wall, the L, the L from inside
)
def test_other_collisions_leave_the_door_shut(cell, action):
    world = StrikeWorld(StrikeConfig(size=5, room=2))
    state, outcome = world.step(started(world, cell), torch.tensor([action]), ZERO, ZERO)
    assert outcome.collision[0, action] == -1.0 and int(state.cell[0]) == cell
    assert not bool(state.door_open[0]) and bool(state.obstacles[0, 14])


def test_the_goal_pays_goal_reward_and_ends_the_episode():
    world = StrikeWorld(StrikeConfig(size=5, room=2, goal_reward=7.0))
    state, outcome = world.step(started(world, 19), torch.tensor([SOUTH]), ZERO, ZERO)
    assert bool(outcome.terminated[0]) and float(outcome.task_reward[0]) == 6.0
    assert float(outcome.reward[0]) == 6.0


def test_a_heading_body_strikes_with_forward_when_facing_the_door():
    world = StrikeWorld(StrikeConfig(size=5, room=2, body="heading"))
    state = started(world, 9)._replace(heading=torch.tensor([2]))  # facing south
    state, outcome = world.step(state, torch.tensor([0]), ZERO, ZERO)  # forward
    assert outcome.collision.tolist() == [[-1.0, 0.0, 0.0]] and bool(state.door_open[0])


def test_bad_strike_options_are_refused_naming_them():
    with pytest.raises(ValueError, match="room"):
        StrikeConfig(size=5, room=4)
    with pytest.raises(ValueError, match="body"):
        StrikeConfig(body="wheels")
    with pytest.raises(TypeError, match="StrikeConfig"):
        StrikeWorld(object())


def test_the_strike_world_passes_torchrl_and_gymnasium_checks():
    world = StrikeWorld(StrikeConfig(size=5))
    env = FactoredGridEnv(world=world, batch_size=(3,), seed=1)
    assert env.observation_spec["door_open"].shape == (3, 1)
    check_env_specs(env, seed=0)
    check_env_specs(TransformedEnv(env, SplitLocalReward()), seed=0)
    check_env(FactoredGridGym(world=world))
    rollout = env.rollout(40, break_when_any_done=False)
    opened = rollout["next", "door_open"][..., 0] & ~rollout["door_open"][..., 0]
    # a door opens only on a step that collided
    assert not (opened & ~rollout["next", "bump"].any(-1)).any()


# --------------------------------------------------------------------------------------------
# The mechanism


@pytest.mark.parametrize(
    ("q", "rho", "gamma", "span", "priority"),
    [
        # Q + rho = [19, 5, 5, 5]: gap 14 > 0.9 / 0.1 = 9
        ([20.0, 5.0, 5.0, 5.0], [-1.0, 0.0, 0.0, 0.0], 0.9, 1.0, True),
        # gap exactly 9: not strictly more
        ([15.0, 5.0, 5.0, 5.0], [-1.0, 0.0, 0.0, 0.0], 0.9, 1.0, False),
        # the paper's range: a task advantage of 10 is never enough against a collision
        ([0.0, -10.0, -10.0, -10.0], [-1.0, 0.0, 0.0, 0.0], 0.9, 1.0, False),
        # the runner-up counts its own local value: [19, 5, 5, 15 - 1 = 14], gap 5
        ([20.0, 5.0, 5.0, 15.0], [-1.0, 0.0, 0.0, -1.0], 0.9, 1.0, False),
        # gamma 0.5: margin 0.5 * 1 / 0.5 = 1 < the gap of [1, -1, -1, -1], 2
        ([2.0, -1.0, -1.0, -1.0], [-1.0, 0.0, 0.0, 0.0], 0.5, 1.0, True),
        # a local span of 2 doubles the margin: 18 > 14
        ([20.0, 5.0, 5.0, 5.0], [-1.0, 0.0, 0.0, 0.0], 0.9, 2.0, False),
        # span 0 (no local future): any strict gap; eq. 3's G = 16.5 refuses action 0
        ([0.0, -0.5, -2.0, -2.0], [-0.1, 0.0, 0.0, 0.0], 0.9, 0.0, True),
        # the same gap where eq. 2 already chooses the dominant action: G stands
        ([0.0, -0.5, -2.0, -2.0], [0.0, 0.0, 0.0, 0.0], 0.9, 0.0, False),
        # every actuator collides (G = g_min): eq. 2 chooses action 0 already
        ([0.0, -10.0, -10.0, -10.0], [-1.0, -1.0, -1.0, -1.0], 0.9, 0.0, False),
    ],
)
def test_arbitration_by_hand(q, rho, gamma, span, priority):
    q_t, rho_t = torch.tensor([q]), torch.tensor([rho])
    g = normaliser(q_t, rho_t)
    out = arbitrated_normaliser(q_t, rho_t, g, gamma, span)
    assert out.tolist() == ([1.0] if priority else g.tolist())


def test_under_priority_the_strike_is_chosen_and_otherwise_eq_2_decides():
    q = torch.tensor([[20.0, 5.0, 5.0, 5.0], [20.0, 5.0, 5.0, 15.0]])
    rho = torch.tensor([[-1.0, 0.0, 0.0, 0.0], [-1.0, 0.0, 0.0, -1.0]])
    g = normaliser(q, rho)  # [16.5, 1.1 * 11.25 / 0.5 = 24.75]
    plain = combined_values(q, rho, g)
    arbitrated = combined_values(q, rho, arbitrated_normaliser(q, rho, g, 0.9))
    assert plain[0].argmax() != 0 and arbitrated[0].tolist() == [19.0, 5.0, 5.0, 5.0]
    assert torch.equal(arbitrated[1], plain[1])  # no priority: eq. 2 unchanged


def test_arbitration_handles_one_action_and_leading_dimensions():
    g = torch.tensor([0.3])
    assert arbitrated_normaliser(torch.ones(1, 1), -torch.ones(1, 1), g, 0.9) is g
    q = torch.tensor([20.0, 5.0, 5.0, 5.0]).expand(2, 3, 4)
    rho = torch.tensor([-1.0, 0.0, 0.0, 0.0]).expand(2, 3, 4)
    out = arbitrated_normaliser(q, rho, normaliser(q, rho), 0.9)
    assert out.shape == (2, 3) and bool((out == 1.0).all())


def test_in_the_papers_value_range_arbitration_never_changes_the_greedy_choice():
    # Task values in [-10, 0] (rewards -1 per step, 0 on the goal step, gamma 0.9) and
    # deterministic local values (0 or -1): the argmax and the max of C(s) are eq. 2's.
    generator = torch.Generator().manual_seed(0)
    q = -10.0 * torch.rand(20_000, 4, generator=generator)
    q[::3, 0] = 0.0  # unvisited actions next to well-known ones: the widest gaps
    q[::3, 1:] = -10.0
    rho = -(torch.rand(20_000, 4, generator=generator) < 0.4).float()
    g = normaliser(q, rho)
    plain = combined_values(q, rho, g)
    arbitrated = combined_values(q, rho, arbitrated_normaliser(q, rho, g, 0.9))
    assert torch.equal(plain, arbitrated)
    # and the same rows with a goal worth 100 (task values up to 100) do arbitrate
    rich = combined_values(
        10 * q + 100.0, rho, arbitrated_normaliser(10 * q + 100.0, rho, normaliser(q, rho), 0.9)
    )
    assert (rich != combined_values(10 * q + 100.0, rho, normaliser(q, rho))).any()


def test_agent_config_validates_the_options():
    assert AgentConfig().arbitration is False and AgentConfig().local_span == 1.0
    with pytest.raises(TypeError, match="arbitration"):
        AgentConfig(arbitration=1)
    with pytest.raises(ValueError, match="local_span"):
        AgentConfig(local_span=-1.0)
    with pytest.raises(TypeError, match="arbitration"):
        FactorQPolicy(1, arbitration="yes")


def test_the_policy_strikes_only_with_arbitration():
    td = TensorDict(
        action_value=torch.tensor([[5.0, 5.0, 20.0, 5.0]]),  # south: the door, worth the most
        local_value=torch.tensor([[0.0, 0.0, -1.0, -1.0]]),  # south: a collision, east a wall
        batch_size=[1],
    )
    plain = FactorQPolicy(1, epsilon=0.0)(td.clone())
    arbitrated = FactorQPolicy(1, epsilon=0.0, arbitration=True)(td.clone())
    assert int(plain["action"][0]) in (NORTH, WEST) and int(arbitrated["action"][0]) == SOUTH
    assert arbitrated["combined_value"].tolist() == [[5.0, 5.0, 19.0, 4.0]]


@pytest.mark.parametrize("path", ["gradient", "tabular_step"])
@pytest.mark.parametrize(("arbitration", "expected"), [(False, 1.1), (True, 3.62)])
def test_eq_4_bootstraps_on_the_arbitrated_value(arbitration, expected, path):
    task, local = TaskQTable(1, num_cells=4), LocalRewardTable(1)
    with torch.no_grad():
        task.table[0, 0, SOUTH] = 0.5
        task.table[0, 1] = torch.tensor([20.0, 5.0, 5.0, 5.0])  # Q(s')
        local.rho[0, NORTH, 1], local.kappa[0, NORTH, 1] = -1.0, 1  # north, sensor on: -1
    following = TensorDict(
        cell=torch.tensor([1]),
        sensors=torch.tensor([[True, False, False, False]]),
        reward=torch.tensor([[-1.0]]),
        local_reward=torch.zeros(1, 4),
        terminated=torch.tensor([[False]]),
        truncated=torch.tensor([[False]]),
        done=torch.tensor([[False]]),
        batch_size=[1],
    )
    td = TensorDict(
        cell=torch.tensor([0]),
        sensors=torch.tensor([[False, False, False, False]]),
        action=torch.tensor([SOUTH]),
        next=following,
        batch_size=[1],
    )
    loss = FactorQLoss(task, local, arbitration=arbitration)
    if path == "tabular_step":  # the online step's direct write (the collector's)
        assert loss.tabular_step(td)
    else:  # the loss, its gradient and one SGD step (networks' path)
        optimizer = tabular_optimizer(loss)
        loss(td)["loss_task"].backward()
        optimizer.step()
    # C(s') by eq. 3: G = 1.1 * 15 / 1 = 16.5, C = [3.5, 5, 5, 5]: target -1 + 0.9 * 5 = 3.5,
    # Q = 0.5 + 0.2 * 3 = 1.1. Arbitrated: Q + rho = [19, 5, 5, 5], gap 14 > 9, G = 1:
    # target -1 + 0.9 * 19 = 16.1, Q = 0.5 + 0.2 * 15.6 = 3.62.
    assert task.table[0, 0, SOUTH].item() == pytest.approx(expected, abs=1e-5)


def test_in_the_papers_grid_arbitration_changes_no_number():
    # The three regimes side by side, two experiments each: every episode's metrics and every
    # table entry are the same with the option on (the paper's rewards never give the margin).
    def run(arbitration: bool) -> tuple:
        env = FactoredGridEnv(
            size=4,
            num_obstacles=2,
            obstacle_period=[0, 0, 10, 10, 1, 1],
            batch_size=(6,),
            seed=3,
            max_steps=100,
        )
        task, local = TaskQTable(6, num_cells=16), LocalRewardTable(6)
        keys = derive_keys(3, STREAM_POLICY, 6)
        policy = FactorQPolicy(6, keys=keys, arbitration=arbitration)
        loss = FactorQLoss(task, local, arbitration=arbitration)
        agent = TensorDictSequential(task, local, policy)
        env = TransformedEnv(env, SplitLocalReward())
        metrics = OnlineCollector(env, agent, loss, runs=1, episodes=3).run()
        return metrics, task.table.clone(), local.rho.clone()

    (m_off, q_off, rho_off), (m_on, q_on, rho_on) = run(False), run(True)
    assert (m_off == m_on).all() and torch.equal(q_off, q_on) and torch.equal(rho_off, rho_on)
    assert int(m_off["collisions"].sum()) > 0  # there were collisions to change


def trained_tables(world: StrikeWorld) -> tuple:
    """Tables as a trained agent holds them: ``Q(s, a) = 100 gamma^d`` with ``d`` the distance
    from where ``a`` leads to the goal through the open door (a blocked move stays), and every
    actuator's local value -1 where its sensor reads blocked."""
    config = world.config
    size, goal, door = config.size, config.goal_cell, config.door_cell
    walls = config.layout.clone()
    walls[door] = False
    distance, frontier = {goal: 0}, [goal]
    while frontier:  # breadth-first from the goal
        cell = frontier.pop(0)
        row, col = divmod(cell, size)
        for r, c in ((row - 1, col), (row, col - 1), (row + 1, col), (row, col + 1)):
            if 0 <= r < size and 0 <= c < size and not walls[r * size + c]:
                if r * size + c not in distance:
                    distance[r * size + c] = distance[cell] + 1
                    frontier.append(r * size + c)
    task, local = TaskQTable(1, num_cells=size * size), LocalRewardTable(1)
    with torch.no_grad():
        for cell, d in distance.items():
            row, col = divmod(cell, size)
            for action, (r, c) in enumerate(
                ((row - 1, col), (row, col - 1), (row + 1, col), (row, col + 1))
            ):
                target = r * size + c if 0 <= r < size and 0 <= c < size else None
                steps = distance.get(target, d + 1)  # a wall or the L: the agent stays
                task.table[0, cell, action] = 100.0 * 0.9**steps
        local.rho[0, :, 1], local.kappa[0, :, 1] = -1.0, 1
    return task, local


@pytest.mark.parametrize(("arbitration", "steps"), [(False, None), (True, 9)])
def test_with_trained_tables_only_arbitration_goes_through_the_door(arbitration, steps):
    world = StrikeWorld(StrikeConfig(size=5))
    task, local = trained_tables(world)
    policy = TensorDictSequential(
        task, local, FactorQPolicy(1, epsilon=0.0, arbitration=arbitration)
    )
    env = FactoredGridEnv(world=world, batch_size=(1,))
    td, reached = env.reset(), None
    for step in range(1, 51):
        td = env.step(policy(td))
        if td["next", "terminated"].all():
            reached = step
            break
        td = env.step_mdp(td)
    # 5 moves to the door, the strike, 3 moves to the goal; without arbitration never
    assert reached == steps
