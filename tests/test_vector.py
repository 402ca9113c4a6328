"""Simultaneous actuators (issue 40, item 4): the two-drive world (``factorq_envs.vector_grid``,
``factorq_envs.vector_torchrl``), the adapter on action vectors, the per-actuator equations
(``factorq_torch.functional``) and the tabular agent (``factorq_torch.vector``), against cases
worked out by hand."""

from __future__ import annotations

import runpy
from pathlib import Path

import gymnasium
import numpy as np
import pytest
import torch
from gymnasium import spaces

from factorq_envs.gymnasium_adapter import Declaration, FactorQEnv
from factorq_envs.vector_grid import (
    VectorGridConfig,
    VectorGridGym,
    VectorState,
    drive_collisions,
    drive_dependency,
    step_vector_worlds,
)
from factorq_torch.functional import (
    actuator_mean_values,
    combined_values,
    joint_action_index,
    joint_action_vector,
    normaliser,
    vector_combined_values,
    vector_normalisers,
)
from factorq_torch.vector import VectorFactorQ

ROOT = Path(__file__).resolve().parent.parent

# -- the per-actuator equations --------------------------------------------------------------


def test_joint_action_index_is_mixed_radix_with_actuator_zero_most_significant():
    action = torch.tensor([[0, 0], [0, 2], [1, 0], [2, 2]])
    assert joint_action_index(action, (3, 3)).tolist() == [0, 2, 3, 8]  # 3 a_0 + a_1
    assert joint_action_index(torch.tensor([1, 0, 1]), (2, 3, 2)).item() == 7  # (1*3 + 0)*2 + 1
    every = torch.arange(18)
    assert joint_action_index(joint_action_vector(every, (2, 3, 3)), (2, 3, 3)).equal(every)


def test_an_action_vector_of_the_wrong_length_names_both_lengths():
    with pytest.raises(ValueError, match=r"length 3 but nvec=\[3, 3\] names 2 actuators"):
        joint_action_index(torch.tensor([[0, 1, 2]]), (3, 3))


def test_actuator_mean_values_average_over_the_other_actuators():
    q = torch.tensor([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])  # a_0 in {0, 1} x a_1 in {0, 1, 2}
    first, second = actuator_mean_values(q, (2, 3))
    assert first.tolist() == [2.0, 5.0]  # (1 + 2 + 3) / 3, (4 + 5 + 6) / 3
    assert second.tolist() == [2.5, 3.5, 4.5]  # (1 + 4) / 2, (2 + 5) / 2, (3 + 6) / 2


def test_vector_normalisers_by_hand():
    # 2 x 2 joint actions 00, 01, 10, 11: a_hat = 11 (Q 4), so a_hat_0 = 1 and a_hat_1 = 1.
    q = torch.tensor([0.0, 2.0, 1.0, 4.0])
    # actuator 0: the joint actions with a_0 != 1 are 00, 01: Q_bar_0 = 1, x_0 = 3;
    #   rho_0 = (-2, 0): a_check 0, P_bar_0 = 0, y_0 = 2 -> G_0 = 3 / 2 * 1.1 = 1.65
    # actuator 1: a_1 != 1 are 00, 10: Q_bar_1 = 0.5, x_1 = 3.5;
    #   rho_1 = (0, -1): y_1 = 1 -> G_1 = 3.5 * 1.1 = 3.85
    rho = torch.tensor([-2.0, 0.0, 0.0, -1.0])
    g = vector_normalisers(q, rho, (2, 2), eta=0.1, g_min=0.01)
    assert torch.allclose(g, torch.tensor([1.65, 3.85]))
    # C = Q + G_0 rho_0(a_0) + G_1 rho_1(a_1): 00: 0 - 3.3 + 0 = -3.3; 01: 2 - 3.3 - 3.85;
    #   10: 1 + 0 + 0 = 1; 11: 4 + 0 - 3.85 = 0.15 -> the greedy joint action becomes 10
    c = vector_combined_values(q, rho, g, (2, 2))
    assert torch.allclose(c, torch.tensor([-3.3, -5.15, 1.0, 0.15]))
    assert int(c.argmax()) == 2


def test_vector_normalisers_floor_at_g_min_where_an_actuator_cannot_collide():
    q = torch.tensor([1.0, 0.0, 0.0, 0.0])
    rho = torch.tensor([-1.0, 0.0, 0.0, 0.0])  # actuator 1's local values are all equal
    assert vector_normalisers(q, rho, (2, 2))[1].item() == pytest.approx(0.01)


def test_one_actuator_is_the_papers_eqs_2_and_3():
    generator = torch.Generator().manual_seed(0)
    q = torch.randn(64, 4, generator=generator)
    rho = -torch.rand(64, 4, generator=generator)
    g = vector_normalisers(q, rho, (4,))
    assert torch.allclose(g[:, 0], normaliser(q, rho))
    c = vector_combined_values(q, rho, g, (4,))
    assert torch.allclose(c, combined_values(q, rho, g[:, 0]))


# -- the world --------------------------------------------------------------------------------


def test_drive_collisions_charge_each_drive_for_its_own_face():
    # north and east blocked (the top-right corner): sensors N, W, S, E
    sensors = torch.tensor([True, False, False, True]).expand(9, 4)
    joint = torch.cartesian_prod(torch.arange(3), torch.arange(3))  # (horizontal, vertical)
    bumped = drive_collisions(sensors, joint).tolist()
    # horizontal bumps only pushing east (value 2), vertical only pushing north (value 0)
    expected = [[h == 2, v == 0] for h, v in joint.tolist()]
    assert bumped == expected


def _one_world(cell: int, obstacles: list[int], size: int = 3) -> VectorState:
    blocked = torch.zeros(1, size * size, dtype=torch.bool)
    blocked[0, obstacles] = True
    zeros = torch.zeros(1, dtype=torch.int64)
    return VectorState(
        torch.tensor([cell]), blocked, torch.zeros(1, 2, dtype=torch.bool), zeros, zeros
    )


def test_a_blocked_drive_bumps_and_the_other_still_moves():
    config = VectorGridConfig(size=3, num_obstacles=1)
    state = _one_world(4, [3])  # centre, an obstacle to the west
    key = torch.zeros(1, dtype=torch.int64)
    new, outcome = step_vector_worlds(state, torch.tensor([[0, 2]]), key, config)  # west + south
    assert new.cell.item() == 7  # one row down, same column
    assert outcome.collision.tolist() == [[-1.0, 0.0]]
    assert outcome.reward.item() == -2.0 and outcome.task_reward.item() == -1.0


def test_a_diagonal_onto_an_obstacle_slides_horizontally_without_a_bump():
    config = VectorGridConfig(size=3, num_obstacles=1)
    state = _one_world(4, [6])  # centre, an obstacle south-west
    key = torch.zeros(1, dtype=torch.int64)
    new, outcome = step_vector_worlds(state, torch.tensor([[0, 2]]), key, config)  # south-west
    assert new.cell.item() == 3 and outcome.collision.tolist() == [[0.0, 0.0]]
    new, outcome = step_vector_worlds(state, torch.tensor([[2, 2]]), key, config)  # the goal
    assert new.cell.item() == 8 and bool(outcome.terminated) and outcome.reward.item() == 0.0


def test_the_gymnasium_env_passes_check_env_and_refuses_a_wrong_length():
    from gymnasium.utils.env_checker import check_env

    env = VectorGridGym(size=4, num_obstacles=2)
    check_env(env, skip_render_check=True)
    assert isinstance(env.action_space, spaces.MultiDiscrete)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="has length 3 but the body has 2 actuators"):
        env.step([0, 1, 2])


def test_the_torchrl_env_passes_check_env_specs():
    from torchrl.data import MultiCategorical
    from torchrl.envs.utils import check_env_specs

    from factorq_envs.vector_torchrl import VectorGridEnv

    env = VectorGridEnv(num_worlds=3, size=4, num_obstacles=2, obstacle_period=1)
    check_env_specs(env)
    assert isinstance(env.action_spec, MultiCategorical)
    td = env.reset()
    td["action"] = torch.zeros(3, 3, dtype=torch.int64)
    with pytest.raises(ValueError, match=r"\(length 2: one value per actuator"):
        env.step(td)


# -- the adapter ------------------------------------------------------------------------------


class TwoWheels(gymnasium.Env):
    """A third-party-like env: a cart on a line of 5 cells with two wheels of 3 values each
    (-1, 0, +1); each wheel that pushes past an end stalls (``info["stalled"]``, one bool per
    wheel); the reward is -1 a step."""

    def __init__(self, binary: bool = False) -> None:
        self.action_space = spaces.MultiBinary(2) if binary else spaces.MultiDiscrete([3, 3])
        self.observation_space = spaces.Box(0.0, 4.0, (1,), np.float32)
        self.binary = binary

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.position = 0
        return np.array([self.position], np.float32), {}

    def step(self, action):
        pushes = np.asarray(action) * (2 if self.binary else 1) - 1  # [2] in {-1, 0, +1}
        stalled = np.zeros(2, dtype=bool)
        for wheel, push in enumerate(pushes.tolist()):
            if not 0 <= self.position + push <= 4:
                stalled[wheel] = True
            else:
                self.position += push
        info = {"stalled": stalled}
        return np.array([self.position], np.float32), -1.0, self.position == 4, False, info


def _declaration(**changes):
    fields = dict(
        num_sensors=2,
        sensors=lambda step: np.array([step.observation[0] == 0, step.observation[0] == 4]),
        collision="stalled",
        task_reward=lambda step: step.reward,
        actuator_names=("left", "right"),
    )
    fields.update(changes)
    return Declaration(**fields)


def test_the_adapter_keeps_one_local_reward_per_actuator():
    env = FactorQEnv(TwoWheels(), _declaration())
    assert env.nvec == (3, 3) and isinstance(env.action_space, spaces.MultiDiscrete)
    env.reset(seed=0)
    observation, reward, *_, info = env.step(np.array([0, 2]))  # left wheel back: stalls
    assert observation["collision"].tolist() == [-1.0, 0.0]
    assert observation["bump"].tolist() == [1, 0]
    assert reward == -2.0 and info["task_reward"] == -1.0 and info["collided"]
    env.reset(seed=0)
    observation, reward, *_ = env.step(np.array([0, 0]))  # both back at the start: both stall
    assert observation["collision"].tolist() == [-1.0, -1.0] and reward == -3.0


def test_the_adapter_takes_multibinary_as_two_valued_actuators():
    env = FactorQEnv(TwoWheels(binary=True), _declaration())
    assert env.nvec == (2, 2)
    env.reset(seed=0)
    observation, *_ = env.step(np.array([0, 1]))  # back (stalls) and forward
    assert observation["collision"].tolist() == [-1.0, 0.0]


def test_the_adapter_refuses_an_action_vector_of_the_wrong_length():
    env = FactorQEnv(TwoWheels(), _declaration())
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"has length 3 but the env's action space .* length 2"):
        env.step(np.array([0, 1, 1]))
    with pytest.raises(ValueError, match="actuator_names has 3 names but the action vector has"):
        FactorQEnv(TwoWheels(), _declaration(actuator_names=("a", "b", "c")))
    with pytest.raises(ValueError, match="dependency has 1 rows but the action vector has len"):
        FactorQEnv(TwoWheels(), _declaration(dependency=((True, False),)))
    with pytest.raises(ValueError, match=r"must return \[2\] bool"):
        FactorQEnv(TwoWheels(), _declaration(collision=lambda step: bool(step.info["stalled"][0])))


# -- the agent --------------------------------------------------------------------------------


def test_each_local_table_learns_only_its_own_actuators_reward():
    agent = VectorFactorQ(1, num_cells=9, nvec=(3, 3), dependency=drive_dependency())
    sensors = torch.tensor([[True, True, False, False]])  # north and west walls
    cell, next_cell = torch.tensor([0]), torch.tensor([3])
    # west + south: the horizontal drive bumped (-1), the vertical one moved (0)
    agent.update(
        cell, sensors, torch.tensor([[0, 2]]), torch.tensor([-1.0]), torch.tensor([[-1.0, 0.0]]),
        next_cell, torch.tensor([[False, True, False, False]]), torch.tensor([False]),
    )  # fmt: skip
    # rows: horizontal west, still, east, vertical north, still, south; column: the pattern
    # of the row's parent sensor (west wall read 1 for "west"; the south sensor read 0)
    assert agent.rho[0, 0].tolist() == [0.0, -1.0]  # horizontal west, under a west wall
    assert agent.rho[0, 5].tolist() == [0.0, 0.0]  # vertical south: its own 0 reward
    assert agent.kappa[0].tolist() == [[0, 1], [0, 0], [0, 0], [0, 0], [0, 0], [1, 0]]
    # eq. 4: every table was 0 before, so C(s') = 0 and Q(0, joint 2) = 0.2 * (-1 + 0.9 * 0)
    assert agent.q[0, 0, 2].item() == pytest.approx(-0.2)
    assert agent.q[0].count_nonzero().item() == 1
    # a second step's local reward averages in (eq. 5's running mean): -1 then 0 -> -0.5
    agent.update(
        cell, sensors, torch.tensor([[0, 1]]), torch.tensor([-1.0]), torch.tensor([[0.0, 0.0]]),
        cell, sensors, torch.tensor([False]),
    )  # fmt: skip
    assert agent.rho[0, 0, 1].item() == -0.5


def test_the_agent_avoids_the_drive_that_would_bump():
    agent = VectorFactorQ(1, num_cells=9, nvec=(3, 3), dependency=drive_dependency(), epsilon=0)
    sensors = torch.tensor([[True, True, False, False]])
    agent.rho[0, 0, 1] = -1.0  # pushing west into a wall bumps
    agent.rho[0, 3, 1] = -1.0  # pushing north into a wall bumps
    agent.q[0, 0] = torch.tensor([5.0, 1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0])  # a_hat = (0, 0)
    # each drive: mean values (2, 1/3, 0), Q_bar_j = 1/6, x_j = 29/6, y_j = 1: G_j = 29/6 * 1.1;
    # C: 00 = 5 - 2 G, 01 = 10 = 1 - G, 02 = 20 = -G, and 0 for 11, 12, 21, 22 (no bump)
    q, rho, g, c = agent.values(torch.tensor([0]), sensors)
    assert torch.allclose(g, torch.tensor([[29 / 6 * 1.1] * 2]))
    big = 29 / 6 * 1.1
    expected = [5 - 2 * big, 1 - big, -big, 1 - big, 0.0, 0.0, -big, 0.0, 0.0]
    assert torch.allclose(c[0], torch.tensor(expected))
    actions = {tuple(agent.act(torch.tensor([0]), sensors)[0][0].tolist()) for _ in range(16)}
    assert actions <= {(1, 1), (1, 2), (2, 1), (2, 2)} and len(actions) > 1  # random ties


def test_loading_tables_of_another_action_vector_names_both_lengths():
    saved = VectorFactorQ(2, 9, (3, 3, 2), torch.zeros(8, 4, dtype=torch.bool)).state_dict()
    agent = VectorFactorQ(2, 9, (3, 3), drive_dependency())
    with pytest.raises(ValueError, match=r"length 3 \(nvec=\[3, 3, 2\]\) but this agent's has len"):
        agent.load_state_dict(saved)
    agent.load_state_dict(VectorFactorQ(2, 9, (3, 3), drive_dependency()).state_dict())


def test_vector_factorq_collides_less_than_flat_q_learning(one_thread):
    """A learned outcome over 6 seeds on a small static grid (the example's loop): measured
    27-34 collisions per seed against 205-230 (about 7x); every seed must show 3x."""
    run = runpy.run_path(str(ROOT / "examples" / "action_vectors.py"))["run"]
    config = VectorGridConfig(size=5, num_obstacles=4, max_steps=200)
    vector = run("vector-factor-q", seeds=6, episodes=15, config=config)
    flat = run("flat-q-learning", seeds=6, episodes=15, config=config)
    assert (vector["collisions"].sum(1) * 3 < flat["collisions"].sum(1)).all()


def test_neural_vector_factorq_moves_only_its_own_experiments_value_toward_the_target():
    from factorq_torch.vector import NeuralVectorFactorQ

    neural = NeuralVectorFactorQ(2, num_cells=9, nvec=(3, 3), dependency=drive_dependency())
    table = VectorFactorQ(2, num_cells=9, nvec=(3, 3), dependency=drive_dependency())
    cells = torch.tensor([0, 4])
    assert neural.task_values(cells).abs().max().item() == 0.0  # the output layer starts at 0
    sensors = torch.tensor([[True, True, False, False], [False] * 4])
    step = (
        cells, sensors, torch.tensor([[0, 2], [2, 2]]), torch.tensor([-1.0, -1.0]),
        torch.tensor([[-1.0, 0.0], [0.0, 0.0]]), torch.tensor([3, 8]), sensors,
        torch.tensor([False, True]),
    )  # fmt: skip
    for agent in (neural, table):
        agent.update(*step)
    assert neural.rho.equal(table.rho) and neural.kappa.equal(table.kappa)  # eq. 5 unchanged
    after = neural.task_values(cells).detach()
    # both targets are -1 (C(s') = 0, or terminated): each Q(s, a) moved down from 0
    assert after[0, 2].item() < 0 and after[1, 8].item() < 0
    # the output layer started at 0, so the first step moves only the chosen action's output
    # column (the hidden layers' gradients pass through zero output weights)
    assert after[0].nonzero().flatten().tolist() == [2]
    assert after[1].nonzero().flatten().tolist() == [8]


def test_the_declared_torchrl_env_steps_an_action_vector():
    from torchrl.envs.utils import check_env_specs

    from factorq_envs.declared_env import declared_torchrl_env

    env = declared_torchrl_env(
        lambda seed: FactorQEnv(TwoWheels(), _declaration(), seed=seed), [0, 1]
    )
    check_env_specs(env)
    assert tuple(env.action_spec.shape) == (2, 2)  # one vector of 2 actuators per env
    td = env.reset()
    td["action"] = torch.tensor([[0, 2], [0, 0]])  # env 0: left stalls; env 1: both stall
    out = env.step(td)["next"]
    assert out["collision"].tolist() == [[-1.0, 0.0], [-1.0, -1.0]]
    assert out["reward"].flatten().tolist() == [-2.0, -3.0]


def test_separate_local_rewards_collide_less_than_a_summed_one(one_thread):
    """The paper's section 9 in a small dynamic grid, 6 seeds: flat Factor-Q over the 9 joint
    actions, fed the summed local reward, against per-actuator rewards (measured 21-31
    collisions per seed against 95-117); every seed must show 2x."""
    run = runpy.run_path(str(ROOT / "examples" / "action_vectors.py"))["run"]
    config = VectorGridConfig(size=5, num_obstacles=4, max_steps=200, obstacle_period=1)
    vector = run("vector-factor-q", seeds=6, episodes=20, config=config)
    flat = run("flat-factor-q", seeds=6, episodes=20, config=config)
    assert (vector["collisions"].sum(1) * 2 < flat["collisions"].sum(1)).all()
