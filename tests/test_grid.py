"""FactoredGridEnv (envs/torchrl_env.py): the batched torchrl env, against SPEC sections 1-2, the
slow reference and torchrl's own checks."""

import pytest
import reference  # tests/reference.py: pytest puts tests/ on sys.path (no __init__.py)
import torch
import torch.nn.functional as F
from torchrl.envs.utils import check_env_specs, step_mdp

from factorq_envs import FactoredGridEnv
from factorq_envs.grid_world import COL_DELTA, ROW_DELTA
from factorq_torch.base.rng import MASK64, STREAM_WORLD, derive_keys


def expected_proximity(obstacle_map: torch.Tensor, cell: torch.Tensor) -> torch.Tensor:
    """Proximity ``[*B, 4]`` computed from the picture ``[*B, size, size]``, walls padded in."""
    size = obstacle_map.shape[-1]
    flat_map = obstacle_map.reshape(-1, size, size)
    padded = F.pad(flat_map.to(torch.uint8), (1, 1, 1, 1), value=1).bool()  # wall all around
    flat = cell.reshape(-1)
    world = torch.arange(flat.numel())
    row, col = flat // size + 1, flat % size + 1
    sensors = torch.stack(
        [
            padded[world, row - 1, col],  # north
            padded[world, row, col - 1],  # west
            padded[world, row + 1, col],  # south
            padded[world, row, col + 1],  # east
        ],
        dim=-1,
    )
    return sensors.reshape(*cell.shape, 4)


def random_actions(env, steps, seed=0):
    generator = torch.Generator().manual_seed(seed)
    return torch.randint(0, 4, (steps, *env.batch_size), generator=generator)


def play(env, actions):
    """Step through ``actions`` ``[T, *B]``, resetting finished worlds; the post-step data."""
    td = env.reset()
    record = []
    for action in actions:
        td["action"] = action
        td = env.step(td)
        record.append(td.clone())
        td = step_mdp(td)
        if td["done"].any():
            td["_reset"] = td["done"].clone()
            td = env.reset(td)
    return torch.stack(record)


# -- sensors, rewards and resets ---------------------------------------------------------------


def test_sensors_match_obstacle_map_after_every_step_including_scatter_steps():
    env = FactoredGridEnv(
        size=6,
        num_obstacles=8,
        obstacle_period=[0, 10, 1, 0, 10, 1],
        max_steps=30,
        batch_size=(6,),
        seed=4,
    )
    td = env.reset()
    assert torch.equal(td["proximity"], expected_proximity(env.obstacle_map(), td["cell"]))
    resets = scatter_steps = 0
    for action in random_actions(env, 150):
        scatters_before = env.world_state.scatters.clone()
        td["action"] = action
        td = env.step(td)
        nxt = td["next"]
        scatter_steps += int((env.world_state.scatters != scatters_before).sum())
        assert torch.equal(nxt["proximity"], expected_proximity(env.obstacle_map(), nxt["cell"]))
        assert torch.equal(nxt["bump"], nxt["collision"] != 0)
        goal = nxt["terminated"].float()
        expected_reward = -1.0 + goal + nxt["collision"].sum(-1, keepdim=True)
        assert torch.equal(nxt["reward"], expected_reward)
        assert torch.equal(nxt["done"], nxt["terminated"] | nxt["truncated"])
        td = step_mdp(td)
        if td["done"].any():
            resets += int(td["done"].sum())
            td["_reset"] = td["done"].clone()
            td = env.reset(td)
            assert torch.equal(td["proximity"], expected_proximity(env.obstacle_map(), td["cell"]))
            assert not td["done"].any()
    assert resets >= 6 and scatter_steps >= 150  # the test did see resets and many scatters


def test_reset_output_starts_every_world_on_the_start_cell_with_nothing_done():
    env = FactoredGridEnv(batch_size=(5,), obstacle_period=1)
    td = env.reset()
    assert td["cell"].eq(0).all()
    assert not td["bump"].any() and not td["done"].any() and not td["truncated"].any()
    assert td["collision"].eq(0).all() and "reward" not in td.keys()
    assert td["collision"].shape == (5, 4) and td["done"].shape == (5, 1)


def test_partial_reset_restarts_only_the_flagged_worlds():
    env = FactoredGridEnv(size=6, num_obstacles=5, obstacle_period=1, batch_size=(4,), seed=2)
    td = env.reset()
    for action in random_actions(env, 7):
        td["action"] = action
        td = step_mdp(env.step(td))
    before = env.world_state
    assert before.episode_step.eq(7).all()
    td["_reset"] = torch.tensor([[True], [False], [True], [False]])
    td = env.reset(td)
    after = env.world_state
    assert after.episode_step.tolist() == [0, 7, 0, 7]
    assert after.cell[0] == 0 and after.cell[2] == 0
    for kept in (1, 3):
        assert after.cell[kept] == before.cell[kept]
        assert torch.equal(after.obstacles[kept], before.obstacles[kept])
        assert torch.equal(after.bump[kept], before.bump[kept])
    assert (after.scatters - before.scatters).tolist() == [1, 0, 1, 0]
    assert td["cell"].tolist() == after.cell.tolist()


def test_episode_ends_terminated_at_the_goal_and_truncated_at_max_steps():
    env = FactoredGridEnv(size=2, num_obstacles=0, max_steps=3, batch_size=(2,))
    td = env.reset()
    # World 0 walks east then south to the goal; world 1 bumps north three times.
    for step, action in enumerate([[3, 0], [2, 0], [0, 0]]):
        td["action"] = torch.tensor(action)
        td = env.step(td)
        nxt = td["next"]
        if step == 1:
            assert nxt["terminated"].flatten().tolist() == [True, False]
            assert nxt["reward"].flatten().tolist() == [0.0, -2.0]
        if step == 2:
            assert nxt["truncated"].flatten().tolist()[1] is True
            assert nxt["terminated"].flatten().tolist()[1] is False
        td = step_mdp(td)


# -- determinism -------------------------------------------------------------------------------


def moving_env(**kwargs):
    settings = dict(size=6, num_obstacles=8, obstacle_period=1, max_steps=20, batch_size=(3,))
    return FactoredGridEnv(**{**settings, **kwargs})


def test_same_seed_gives_identical_trajectories_and_different_seeds_differ():
    actions = random_actions(moving_env(), 60)
    first = play(moving_env(seed=11), actions)
    again = play(moving_env(seed=11), actions)
    other = play(moving_env(seed=12), actions)
    assert (first == again).all()
    assert not torch.equal(first["next", "proximity"], other["next", "proximity"])


def test_set_seed_and_reset_replay_the_same_episode():
    env = moving_env(seed=5)
    actions = random_actions(env, 30)
    first = play(env, actions)
    env.set_seed(5)
    assert (play(env, actions) == first).all()


def test_seed_none_means_seed_zero():
    assert torch.equal(moving_env(seed=None).world_keys, moving_env(seed=0).world_keys)
    env = moving_env(seed=9)
    env.set_seed(None)
    assert torch.equal(env.world_keys, derive_keys(0, STREAM_WORLD, 3))


def test_world_i_of_a_batch_of_eight_replays_alone_in_a_batch_of_one_at_offset_i():
    batch = moving_env(batch_size=(8,), obstacle_period=10, seed=3)
    actions = random_actions(batch, 45)
    together = play(batch, actions)
    for i in (0, 5, 7):
        alone = moving_env(batch_size=(1,), obstacle_period=10, seed=3, experiment_offset=i)
        assert torch.equal(alone.world_keys, batch.world_keys[i : i + 1])
        trajectory = play(alone, actions[:, i : i + 1])
        assert (trajectory == together[:, i : i + 1]).all()


def test_env_draws_nothing_from_the_global_rng():
    torch.manual_seed(0)
    state = torch.get_rng_state()
    env = moving_env(seed=1)
    play(env, torch.zeros(20, 3, dtype=torch.int64))
    assert torch.equal(torch.get_rng_state(), state)


# -- differential check against the slow reference ---------------------------------------------


def reference_trajectory(period, key, static, actions, size, num_obstacles, max_steps):
    """The SPEC's world in plain Python, with tests/reference.py's scatter and sensors."""
    goal = size * size - 1
    cell = step = scatters = 0
    blocked = list(static)
    rows = []

    def reset():
        nonlocal cell, step, scatters, blocked
        cell = step = 0
        if period == 0:
            blocked = list(static)
        else:
            blocked = reference.scatter(key, scatters, 0, size, num_obstacles)
            scatters += 1

    reset()
    for action in actions:
        collided = reference.blocked_faces(cell, blocked, size)[action]
        if not collided:
            cell += ROW_DELTA[action] * size + COL_DELTA[action]
        step += 1
        terminated = cell == goal
        truncated = not terminated and step >= max_steps
        reward = -1.0 + float(terminated) - float(collided)
        if period > 0 and not terminated and step % period == 0:
            blocked = reference.scatter(key, scatters, cell, size, num_obstacles)
            scatters += 1
        rows.append(
            (cell, reference.blocked_faces(cell, blocked, size), reward, terminated, truncated)
        )
        if terminated or truncated:
            reset()
    return rows


@pytest.mark.parametrize("period", [0, 10, 1, 3])
def test_env_matches_the_reference_world_step_by_step(period):
    size, num_obstacles, max_steps = 4, 3, 16
    env = FactoredGridEnv(
        size=size, num_obstacles=num_obstacles, obstacle_period=period, max_steps=max_steps, seed=8
    )
    actions = random_actions(env, 400, seed=period)
    data = play(env, actions)
    expected = reference_trajectory(
        period,
        env.world_keys.item() & MASK64,
        env.static_obstacles.tolist(),
        actions.tolist(),
        size,
        num_obstacles,
        max_steps,
    )
    nxt = data["next"]
    got = list(
        zip(
            nxt["cell"].tolist(),
            nxt["proximity"].tolist(),
            nxt["reward"].flatten().tolist(),
            nxt["terminated"].flatten().tolist(),
            nxt["truncated"].flatten().tolist(),
            strict=True,
        )
    )
    assert got == expected
    assert any(row[3] for row in expected) and any(row[4] for row in expected)


# -- mixed periods -----------------------------------------------------------------------------


def test_mixed_periods_run_static_semi_dynamic_and_dynamic_worlds_side_by_side():
    env = FactoredGridEnv(obstacle_period=[0, 10, 1], batch_size=(3,), seed=1)
    assert env.periods.tolist() == [0, 10, 1]
    td = env.reset()
    static = env.obstacle_map()[0].clone()
    assert torch.equal(static.flatten(), env.static_obstacles)
    changes = torch.zeros(3, dtype=torch.int64)
    for action in random_actions(env, 25):
        before = env.obstacle_map()
        td["action"] = action
        td = step_mdp(env.step(td))
        assert not td["done"].any()
        changes += (env.obstacle_map() != before).flatten(1).any(1).long()
    assert changes[0] == 0 and torch.equal(env.obstacle_map()[0], static)
    assert changes[1] == 2  # after actions 10 and 20
    assert env.world_state.scatters.tolist() == [0, 3, 26]  # reset + every scatter
    assert changes[2] >= 24  # a fresh draw can repeat the old one only by a tiny chance


def test_period_tensor_is_accepted_and_a_moving_only_batch_allows_crowded_grids():
    env = FactoredGridEnv(num_obstacles=90, obstacle_period=torch.tensor([1, 10]), batch_size=2)
    td = env.reset()
    assert env.obstacle_map().flatten(1).sum(1).tolist() == [90, 90]
    assert td["cell"].shape == (2,)


# -- torchrl integration -----------------------------------------------------------------------


@pytest.mark.parametrize("batch_size", [(), (1,), (64,), (2, 3)])
def test_check_env_specs_passes(batch_size):
    check_env_specs(FactoredGridEnv(batch_size=batch_size, obstacle_period=1))


def test_check_env_specs_passes_for_a_mixed_batch_in_both_rollout_modes():
    env = FactoredGridEnv(size=3, num_obstacles=2, obstacle_period=[0, 10, 1], batch_size=(3,))
    check_env_specs(env, break_when_any_done="both")


def test_torchrl_rollout_resets_finished_worlds_and_continues():
    env = FactoredGridEnv(size=2, num_obstacles=0, max_steps=4, batch_size=(4,), seed=0)
    torch.manual_seed(0)  # env.rollout draws its random actions from the global RNG
    data = env.rollout(40, break_when_any_done=False)
    assert data.shape == (4, 40)
    done = data["next", "done"].squeeze(-1)  # [4, 40]
    assert done.any()
    following = data["cell"][:, 1:][done[:, :-1]]
    assert following.eq(0).all()  # after every finished episode the next one starts fresh


def test_rollout_until_all_done_keeps_finished_worlds_in_place():
    env = FactoredGridEnv(size=2, num_obstacles=0, max_steps=50, batch_size=(3,))
    policy_actions = iter([[3, 0, 0], [2, 0, 0], [0, 3, 0], [0, 2, 0], [0, 0, 3], [0, 0, 2]])

    def policy(td):
        td["action"] = torch.tensor(next(policy_actions))
        return td

    data = env.rollout(6, policy, break_when_any_done=False, break_when_all_done=True)
    # World 0 finishes after 2 actions, world 1 after 4 (after bumping twice), world 2 after 6.
    assert data["next", "terminated"].squeeze(-1).any(-1).all()
    assert env.world_state.episode_step.tolist() == [2, 4, 6]
    assert env.world_state.cell.tolist() == [3, 3, 3]


# -- inspection and bad input ------------------------------------------------------------------


def test_obstacle_map_is_a_copy_shaped_like_the_grid():
    env = FactoredGridEnv(batch_size=(2,), obstacle_period=1)
    env.reset()
    picture = env.obstacle_map()
    assert picture.shape == (2, 10, 10) and picture.dtype == torch.bool
    assert picture.flatten(1).sum(1).tolist() == [10, 10]
    picture[:] = True
    assert env.obstacle_map().flatten(1).sum(1).tolist() == [10, 10]
    assert FactoredGridEnv().obstacle_map().shape == (10, 10)


def test_render_shows_walls_obstacles_agent_and_goal():
    env = FactoredGridEnv(size=5, num_obstacles=3, batch_size=(2,))
    env.reset()
    lines = env.render(1).splitlines()
    assert lines[0] == "#######" and lines[-1] == "#######"
    assert lines[1][1] == "A" and lines[5][5] == "G"
    assert sum(line.count("o") for line in lines) == 3
    with pytest.raises(ValueError, match=r"index=2 .*\[0, 2\)"):
        env.render(2)


BAD_ARGUMENTS = [
    (dict(size=1), ValueError, r"size=1 .*>= 2"),
    (dict(size=2.5), TypeError, r"size must be an int"),
    (dict(num_obstacles=98), ValueError, r"num_obstacles=98 .*\[0, 97\]"),
    (dict(num_obstacles=-1), ValueError, r"num_obstacles=-1 .*\[0, 97\]"),
    (dict(num_obstacles=82), ValueError, r"num_obstacles=82 .*static.*\[0, 81\]"),
    (dict(obstacle_period=-1), ValueError, r"obstacle_period=-1 .*>= 0"),
    (dict(obstacle_period=1.5), TypeError, r"obstacle_period must be an int"),
    (dict(obstacle_period=[0, 1], batch_size=(3,)), ValueError, r"obstacle_period has 2 .*3"),
    (dict(obstacle_period=[0, -1, 1], batch_size=(3,)), ValueError, r"obstacle_period\[1\]=-1"),
    (dict(obstacle_period=torch.ones(3), batch_size=(3,)), TypeError, r"obstacle_period.*dtype"),
    (dict(max_steps=-5), ValueError, r"max_steps=-5 .*>= 1"),
    (dict(max_steps=0), ValueError, r"max_steps=0 .*>= 1"),
    (dict(layout_seed=-1), ValueError, r"layout_seed=-1 .*>= 0"),
    (dict(batch_size=(0,)), ValueError, r"batch_size=\(0,\) .*>= 1"),
    (dict(batch_size=(-3,)), ValueError, r"batch_size=\(-3,\)"),
    (dict(batch_size="64"), TypeError, r"batch_size must be"),
    (dict(batch_size=(2.0,)), TypeError, r"batch_size must be"),
    (dict(seed="x"), TypeError, r"seed must be an int"),
    (dict(device="nowhere"), ValueError, r"device='nowhere'"),
    (dict(experiment_offset=-1), ValueError, r"experiment_offset=-1 .*>= 0"),
    (dict(experiment_offset=0.5), TypeError, r"experiment_offset must be an int"),
]


@pytest.mark.parametrize("kwargs, error, message", BAD_ARGUMENTS)
def test_bad_constructor_argument_raises_one_error_naming_it(kwargs, error, message):
    with pytest.raises(error, match=message):
        FactoredGridEnv(**kwargs)


BAD_ACTIONS = [
    (torch.tensor([0, 4]), ValueError, r"action=4 .*\[0, 3\]"),
    (torch.tensor([-1, 0]), ValueError, r"action=-1 .*\[0, 3\]"),
    (torch.tensor([[0], [1]]), ValueError, r"action has shape \(2, 1\).*\(2,\)"),
    (torch.eye(4, dtype=torch.int64)[:2], ValueError, r"action has shape \(2, 4\)"),  # one-hot
    (torch.tensor([0.0, 1.0]), TypeError, r"action must be an integer.*float32"),
    (torch.tensor([True, False]), TypeError, r"action must be an integer.*bool"),
]


@pytest.mark.parametrize("action, error, message", BAD_ACTIONS)
def test_bad_action_raises_one_error_naming_it_and_leaves_the_worlds_alone(action, error, message):
    env = FactoredGridEnv(batch_size=(2,))
    td = env.reset()
    before = env.world_state
    td["action"] = action
    with pytest.raises(error, match=message):
        env.step(td)
    assert env.world_state is before


def test_to_moves_the_state_with_the_specs():
    env = FactoredGridEnv(batch_size=(2,), obstacle_period=1).to("cpu")
    assert env.device == torch.device("cpu")
    assert all(t.device == env.device for t in (*env.world_state, env.world_keys, env.periods))
    check_env_specs(env)


def test_missing_action_raises_naming_it():
    env = FactoredGridEnv()
    with pytest.raises(ValueError, match="action is missing"):
        env.step(env.reset())


def test_world_keys_given_outright_replay_that_world_of_a_larger_batch():
    large = FactoredGridEnv(size=5, num_obstacles=4, obstacle_period=1, batch_size=(3,), seed=5)
    alone = FactoredGridEnv(
        size=5, num_obstacles=4, obstacle_period=1, batch_size=(1,), world_keys=large.world_keys[2:]
    )
    first, second = large.reset(), alone.reset()
    assert torch.equal(large.obstacle_map()[2:], alone.obstacle_map())
    assert torch.equal(first["sensors"][2:], second["sensors"])
    with pytest.raises(ValueError, match=r"world_keys must be an int64 tensor of shape \[2\]"):
        FactoredGridEnv(batch_size=(2,), world_keys=torch.zeros(3, dtype=torch.int64))


def test_reset_mask_restarts_only_those_worlds_and_refuses_a_bad_mask():
    env = FactoredGridEnv(size=4, num_obstacles=0, batch_size=(3,))
    env.reset()
    td = env.reset()
    td["action"] = torch.tensor([2, 2, 3])  # south, south, east: all move
    moved = env.step(td)["next", "cell"]
    assert moved.tolist() == [4, 4, 1]
    out = env.reset(reset_mask=torch.tensor([True, False, False]))
    assert out["cell"].tolist() == [0, 4, 1]
    for bad in (torch.tensor([1, 0, 0]), torch.tensor([True, False])):
        with pytest.raises(ValueError, match="reset_mask"):
            env.reset(reset_mask=bad)


@pytest.mark.parametrize("period", [0, 2])
def test_a_world_config_passed_whole_is_the_same_env_as_its_keywords(period):
    """``FactoredGridEnv(world=WorldConfig(...))`` and ``FactoredGridGym(world=...)``: the grid's
    config passed whole, the same worlds as the keywords it holds; a keyword beside it is
    refused, naming it."""
    import gymnasium

    from factorq_envs.grid_world import WorldConfig
    from factorq_envs.gymnasium_env import FactoredGridGym

    options = dict(size=5, num_obstacles=4, max_steps=30, body="heading", sensors="ring")
    options.update(num_distractors=2, sensor_noise=0.1, actuator_noise=0.05, layout_seed=3)
    config = WorldConfig(**options)
    whole = FactoredGridEnv(world=config, obstacle_period=period, batch_size=(3,), seed=7)
    unpacked = FactoredGridEnv(**options, obstacle_period=period, batch_size=(3,), seed=7)
    rollouts = []
    for env in (whole, unpacked):
        with torch.random.fork_rng():  # the random actions of rollout, the global state kept
            torch.manual_seed(0)
            rollouts.append(env.rollout(40, break_when_any_done=False))
    assert (rollouts[0] == rollouts[1]).all()
    assert rollouts[0]["next", "collision"].any()  # the worlds did something to compare
    assert whole.config == unpacked.config
    with pytest.raises(ValueError, match="size=6"):
        FactoredGridEnv(world=config, size=6)
    gym_whole = FactoredGridGym(world=config, obstacle_period=period)
    gym_unpacked = FactoredGridGym(**options, obstacle_period=period)
    for env in (gym_whole, gym_unpacked):
        env.action_space.seed(1)
    a, _ = gym_whole.reset(seed=2)
    b, _ = gym_unpacked.reset(seed=2)
    for _ in range(30):
        action = gym_whole.action_space.sample()
        a, *rest_a = gym_whole.step(action)
        b, *rest_b = gym_unpacked.step(action)
        assert all((a[k] == b[k]).all() for k in a) and rest_a[:3] == rest_b[:3]
    assert isinstance(gym_whole, gymnasium.Env)
