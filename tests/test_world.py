"""The world as pure batched functions (envs/grid_functions.py), checked against SPEC sections 1-2
and the slow reference (tests/reference.py)."""

from collections import deque
from itertools import combinations

import pytest
import reference  # tests/reference.py: pytest puts tests/ on sys.path (no __init__.py)
import torch

from factorq_envs.grid_world import (
    NUM_ACTIONS,
    WorldConfig,
    WorldState,
    empty_state,
    is_reachable,
    proximity,
    render_world,
    reset_worlds,
    scatter_obstacles,
    static_layout,
    step_worlds,
)
from factorq_torch.base.rng import MASK64, STREAM_LAYOUT, STREAM_WORLD, derive_keys, random_bits

NORTH, WEST, SOUTH, EAST = range(4)


def one_world(cell: int, blocked_cells=(), size: int = 4, episode_step: int = 0) -> WorldState:
    """A single world ``[1]`` with the agent on ``cell`` and obstacles on ``blocked_cells``."""
    state = empty_state(1, size)
    obstacles = state.obstacles.clone()
    obstacles[0, list(blocked_cells)] = True
    return state._replace(
        cell=torch.tensor([cell]),
        obstacles=obstacles,
        episode_step=torch.tensor([episode_step]),
    )


def step_one(state, action, period=0, config=None):
    config = config or WorldConfig(size=4, num_obstacles=2, max_steps=100)
    key = derive_keys(0, STREAM_WORLD, 1)
    return step_worlds(state, torch.tensor([action]), key, torch.tensor([period]), config)


def bfs_reachable(obstacles: list[bool], size: int) -> bool:
    """An independent reachability check (the world's own is under test)."""
    seen, frontier = {0}, deque([0])
    while frontier:
        row, col = divmod(frontier.popleft(), size)
        for r, c in ((row - 1, col), (row + 1, col), (row, col - 1), (row, col + 1)):
            nxt = r * size + c
            if 0 <= r < size and 0 <= c < size and not obstacles[nxt] and nxt not in seen:
                seen.add(nxt)
                frontier.append(nxt)
    return size * size - 1 in seen


# -- collisions --------------------------------------------------------------------------------

# In a 4x4 grid: a cell whose face ``action`` is the wall.
WALL_CASES = [(NORTH, 1), (WEST, 4), (SOUTH, 13), (EAST, 7)]


@pytest.mark.parametrize("action, cell", WALL_CASES)
def test_collision_with_the_wall_leaves_agent_in_place_and_sets_bump_bit(action, cell):
    state, outcome = step_one(one_world(cell), action)
    assert state.cell.item() == cell
    expected_bump = [face == action for face in range(NUM_ACTIONS)]
    assert state.bump[0].tolist() == expected_bump
    assert outcome.collision[0].tolist() == [-1.0 if b else 0.0 for b in expected_bump]
    assert outcome.reward.item() == -2.0  # step -1 + collision -1


# Agent on cell 5 (row 1, col 1) of a 4x4 grid: the neighbour on each face.
NEIGHBOUR_OF_5 = {NORTH: 1, WEST: 4, SOUTH: 9, EAST: 6}


@pytest.mark.parametrize("action", range(NUM_ACTIONS))
def test_collision_with_an_obstacle_leaves_agent_in_place_and_sets_bump_bit(action):
    state, outcome = step_one(one_world(5, [NEIGHBOUR_OF_5[action]]), action)
    assert state.cell.item() == 5
    assert state.bump[0].tolist() == [face == action for face in range(NUM_ACTIONS)]
    assert outcome.collision[0, action].item() == -1.0
    assert outcome.collision.sum().item() == -1.0


@pytest.mark.parametrize("action", range(NUM_ACTIONS))
def test_free_move_goes_to_the_neighbour_and_clears_the_bump(action):
    start = one_world(5)._replace(bump=torch.tensor([[True, True, False, False]]))
    state, outcome = step_one(start, action)
    assert state.cell.item() == NEIGHBOUR_OF_5[action]
    assert not bool(state.bump.any())
    assert outcome.collision.abs().sum().item() == 0.0
    assert outcome.reward.item() == -1.0


def test_proximity_reads_walls_and_obstacles_in_action_order():
    # Cell 4 (row 1, col 0): west is the wall; obstacle south (8); north (0) and east (5) free.
    sensors = proximity(torch.tensor([4]), one_world(4, [8]).obstacles, 4)
    assert sensors[0].tolist() == [False, True, True, False]
    corner = proximity(torch.tensor([0]), one_world(0).obstacles, 4)
    assert corner[0].tolist() == [True, True, False, False]


def test_step_does_not_modify_its_inputs():
    state = one_world(5, [1, 6])
    before = WorldState(*(t.clone() for t in state))
    action = torch.tensor([EAST])
    step_worlds(state, action, derive_keys(0, 1, 1), torch.tensor([1]), WorldConfig(size=4))
    assert all(torch.equal(a, b) for a, b in zip(state, before, strict=True))
    assert action.item() == EAST


# -- rewards and episode end -------------------------------------------------------------------


def test_goal_step_gives_zero_total_reward_terminates_and_does_not_scatter():
    size = 4
    state = one_world(size * size - 2, [2, 3], size=size)._replace(scatters=torch.tensor([5]))
    config = WorldConfig(size=size, num_obstacles=2, max_steps=100)
    new, outcome = step_one(state, EAST, period=1, config=config)  # dynamic: would scatter
    assert new.cell.item() == size * size - 1
    assert outcome.terminated.item() and not outcome.truncated.item()
    assert outcome.step_reward.item() == -1.0 and outcome.goal_reward.item() == 1.0
    assert outcome.task_reward.item() == 0.0 and outcome.reward.item() == 0.0
    assert torch.equal(new.obstacles, state.obstacles)
    assert new.scatters.item() == 5


def test_rewards_follow_the_spec_for_move_wall_and_goal_in_one_batch():
    size = 4
    state = empty_state(3, size)._replace(cell=torch.tensor([5, 0, 14]))
    config = WorldConfig(size=size, num_obstacles=0, max_steps=100)
    _, outcome = step_worlds(
        state,
        torch.tensor([EAST, NORTH, EAST]),
        derive_keys(0, 1, 3),
        torch.zeros(3, dtype=torch.int64),
        config,
    )
    assert outcome.step_reward.tolist() == [-1.0, -1.0, -1.0]
    assert outcome.goal_reward.tolist() == [0.0, 0.0, 1.0]
    assert outcome.collision.tolist() == [[0.0] * 4, [-1.0, 0.0, 0.0, 0.0], [0.0] * 4]
    assert outcome.task_reward.tolist() == [-1.0, -1.0, 0.0]
    assert outcome.reward.tolist() == [-1.0, -2.0, 0.0]
    assert outcome.reward.dtype == torch.float32 and outcome.collision.dtype == torch.float32


def test_episode_is_truncated_at_max_steps_and_not_before():
    config = WorldConfig(size=4, num_obstacles=0, max_steps=3)
    state = one_world(0)
    flags = []
    for _ in range(3):
        state, outcome = step_one(state, NORTH, config=config)  # into the wall, never the goal
        flags.append((outcome.terminated.item(), outcome.truncated.item()))
    assert flags == [(False, False), (False, False), (False, True)]


def test_reaching_the_goal_on_the_last_allowed_step_is_terminated_not_truncated():
    config = WorldConfig(size=2, num_obstacles=0, max_steps=2)
    state, outcome = step_one(one_world(0, size=2), EAST, config=config)
    assert not outcome.terminated.item() and not outcome.truncated.item()
    state, outcome = step_one(state, SOUTH, config=config)
    assert outcome.terminated.item() and not outcome.truncated.item()


# -- scatter -----------------------------------------------------------------------------------


def test_scatter_places_exactly_k_distinct_obstacles_never_on_start_goal_or_agent():
    size, num_obstacles, batch = 5, 12, 500
    keys = derive_keys(7, STREAM_WORLD, batch)
    agents = torch.arange(batch) % (size * size)  # every cell, start and goal included
    obstacles = scatter_obstacles(keys, torch.arange(batch), agents, size, num_obstacles)
    assert obstacles.shape == (batch, size * size) and obstacles.dtype == torch.bool
    assert obstacles.sum(dim=1).eq(num_obstacles).all()
    assert not obstacles[:, 0].any() and not obstacles[:, -1].any()
    assert not obstacles.gather(1, agents.unsqueeze(1)).any()


@pytest.mark.parametrize(
    "size, num_obstacles", [(2, 1), (3, 4), (3, 6), (4, 5), (10, 10), (10, 97)]
)
def test_scatter_equals_the_reference_bit_for_bit(size, num_obstacles):
    batch = 60
    keys = torch.cat([derive_keys(1, STREAM_WORLD, batch - 2), torch.tensor([-1, 1 << 62])])
    indices = torch.arange(batch) * 3
    agents = torch.arange(batch) % (size * size)
    obstacles = scatter_obstacles(keys, indices, agents, size, num_obstacles)
    for i in range(batch):
        expected = reference.scatter(
            keys[i].item() & MASK64, indices[i].item(), agents[i].item(), size, num_obstacles
        )
        assert obstacles[i].tolist() == expected, i


def test_scatter_draws_every_subset_about_equally_often():
    # 4x4 grid, agent on cell 5: 13 allowed cells, 3 obstacles -> C(13, 3) = 286 subsets.
    size, num_obstacles, draws = 4, 3, 28_600
    agents = torch.full((draws,), 5)
    obstacles = scatter_obstacles(
        derive_keys(11, STREAM_WORLD, 1).expand(draws), torch.arange(draws), agents, size, 3
    )
    allowed = [c for c in range(size * size) if c not in (0, 5, size * size - 1)]
    index = {subset: i for i, subset in enumerate(combinations(allowed, num_obstacles))}
    codes = [index[tuple(row.nonzero().flatten().tolist())] for row in obstacles]
    counts = torch.bincount(torch.tensor(codes), minlength=len(index)).double()
    expected = draws / len(index)
    chi_square = (((counts - expected) ** 2) / expected).sum().item()
    assert chi_square < 285 + 6 * (2 * 285) ** 0.5  # 285 dof: mean 285, sd ~24; loose
    per_cell = obstacles.sum(dim=0).double()[allowed]
    cell_chi = (((per_cell - draws * 3 / 13) ** 2) / (draws * 3 / 13)).sum().item()
    assert cell_chi < 45  # 12 dof


def test_scatter_with_the_same_key_and_index_is_identical_and_other_indices_differ():
    key = derive_keys(2, STREAM_WORLD, 1)
    start = torch.zeros(1, dtype=torch.int64)
    first = scatter_obstacles(key, torch.tensor([4]), start, 10, 10)
    assert torch.equal(first, scatter_obstacles(key, torch.tensor([4]), start, 10, 10))
    assert not torch.equal(first, scatter_obstacles(key, torch.tensor([5]), start, 10, 10))


# -- static layout -----------------------------------------------------------------------------


@pytest.mark.parametrize("layout_seed", range(8))
def test_static_layout_is_reachable_fixed_and_has_k_obstacles(layout_seed):
    config = WorldConfig(size=6, num_obstacles=14, layout_seed=layout_seed)
    layout = static_layout(config)
    assert layout.shape == (36,) and layout.sum().item() == 14
    assert not layout[0] and not layout[-1]
    assert bfs_reachable(layout.tolist(), 6) and is_reachable(layout, 6)
    assert torch.equal(layout, static_layout(config))


@pytest.mark.parametrize("size, num_obstacles", [(3, 4), (5, 12), (10, 10)])
def test_static_layout_is_the_first_reachable_draw_of_the_layout_stream(size, num_obstacles):
    for layout_seed in range(3):
        key = derive_keys(layout_seed, STREAM_LAYOUT, 1).item() & MASK64
        attempt = 0
        blocked = reference.scatter(key, attempt, 0, size, num_obstacles)
        while not bfs_reachable(blocked, size):  # draw number = attempt, agent on the start
            attempt += 1
            blocked = reference.scatter(key, attempt, 0, size, num_obstacles)
        config = WorldConfig(size=size, num_obstacles=num_obstacles, layout_seed=layout_seed)
        assert static_layout(config).tolist() == blocked


def test_static_layout_redraws_until_reachable():
    # 3x3 with 4 obstacles: only the 2 monotone-path layouts (of C(7, 4) = 35) are reachable.
    for layout_seed in range(5):
        layout = static_layout(WorldConfig(size=3, num_obstacles=4, layout_seed=layout_seed))
        assert bfs_reachable(layout.tolist(), 3)
    assert not is_reachable(torch.tensor([0, 1, 1, 1, 1, 0, 0, 0, 0], dtype=torch.bool), 3)


def test_static_layout_refuses_at_once_a_count_that_cannot_leave_a_path():
    with pytest.raises(ValueError, match=r"num_obstacles=82 .* must be in \[0, 81\]"):
        static_layout(WorldConfig(size=10, num_obstacles=82))


def test_static_world_never_changes_its_obstacles():
    config = WorldConfig(size=6, num_obstacles=10, max_steps=50)
    layout = static_layout(config)
    batch = 4
    keys = derive_keys(0, STREAM_WORLD, batch)
    periods = torch.zeros(batch, dtype=torch.int64)
    everyone = torch.ones(batch, dtype=torch.bool)
    state = reset_worlds(empty_state(batch, 6), everyone, keys, periods, layout, config)
    generator = torch.Generator().manual_seed(0)
    for _ in range(120):
        action = torch.randint(0, 4, (batch,), generator=generator)
        state, outcome = step_worlds(state, action, keys, periods, config)
        assert bool((state.obstacles == layout).all())
        assert state.scatters.eq(0).all()
        state = reset_worlds(
            state, outcome.terminated | outcome.truncated, keys, periods, layout, config
        )


# -- moving worlds -----------------------------------------------------------------------------


@pytest.mark.parametrize("period", [1, 10])
def test_moving_world_scatters_exactly_after_every_kth_action_like_the_reference(period):
    size, num_obstacles, batch = 10, 10, 6
    config = WorldConfig(size=size, num_obstacles=num_obstacles, max_steps=10_000)
    keys = derive_keys(3, STREAM_WORLD, batch)
    periods = torch.full((batch,), period)
    everyone = torch.ones(batch, dtype=torch.bool)
    unused_layout = torch.zeros(size * size, dtype=torch.bool)
    state = reset_worlds(empty_state(batch, size), everyone, keys, periods, unused_layout, config)
    for i in range(batch):  # the reset scatter is number 0, drawn with the agent on the start
        assert state.obstacles[i].tolist() == reference.scatter(
            keys[i].item() & MASK64, 0, 0, size, num_obstacles
        )
    assert state.scatters.eq(1).all()
    generator = torch.Generator().manual_seed(1)
    for step in range(1, 36):
        before = state
        action = torch.randint(0, 4, (batch,), generator=generator)
        state, outcome = step_worlds(state, action, keys, periods, config)
        assert not outcome.terminated.any()  # 35 random steps cannot reach the far corner here
        scattered = step % period == 0
        assert state.scatters.eq(before.scatters + int(scattered)).all()
        for i in range(batch):
            if scattered:
                expected = reference.scatter(
                    keys[i].item() & MASK64,
                    before.scatters[i].item(),
                    state.cell[i].item(),
                    size,
                    num_obstacles,
                )
                assert state.obstacles[i].tolist() == expected
            else:
                assert torch.equal(state.obstacles[i], before.obstacles[i])


def test_scatter_after_a_step_avoids_the_agents_new_cell():
    config = WorldConfig(size=3, num_obstacles=6, max_steps=100)  # all free cells but one filled
    batch = 200
    keys = derive_keys(5, STREAM_WORLD, batch)
    state = empty_state(batch, 3)._replace(cell=torch.full((batch,), 4))
    periods = torch.ones(batch, dtype=torch.int64)
    state, _ = step_worlds(state, torch.full((batch,), EAST), keys, periods, config)
    assert state.cell.eq(5).all()  # no obstacles before the move
    assert not state.obstacles[:, 5].any()
    assert state.obstacles.sum(dim=1).eq(6).all()


# -- reset -------------------------------------------------------------------------------------


def test_reset_restarts_only_the_masked_worlds_with_the_layout_of_their_kind():
    size = 5
    config = WorldConfig(size=size, num_obstacles=4, max_steps=100)
    layout = static_layout(config)
    keys = derive_keys(0, STREAM_WORLD, 3)
    periods = torch.tensor([0, 10, 1])
    state = WorldState(
        cell=torch.tensor([7, 8, 9]),
        obstacles=torch.zeros(3, size * size, dtype=torch.bool),
        bump=torch.ones(3, 4, dtype=torch.bool),
        episode_step=torch.tensor([3, 4, 5]),
        scatters=torch.tensor([2, 2, 2]),
        heading=torch.zeros(3, dtype=torch.int64),
        ticks=torch.tensor([5, 6, 7]),
    )
    new = reset_worlds(state, torch.tensor([True, True, False]), keys, periods, layout, config)
    assert new.cell.tolist() == [0, 0, 9]
    assert new.episode_step.tolist() == [0, 0, 5]
    assert new.bump.tolist() == [[False] * 4, [False] * 4, [True] * 4]
    assert torch.equal(new.obstacles[0], layout)
    expected = reference.scatter(keys[1].item() & MASK64, 2, 0, size, 4)
    assert new.obstacles[1].tolist() == expected
    assert not new.obstacles[2].any()
    assert new.scatters.tolist() == [2, 3, 2]
    assert new.ticks.tolist() == [6, 7, 7]


def test_render_world_shows_walls_obstacles_agent_and_goal():
    picture = render_world(
        4, torch.tensor([False, True, False, False, False, False, False, False, False]), 3
    )
    assert picture == "#####\n#.o.#\n#.A.#\n#..G#\n#####"


@pytest.mark.parametrize(
    "options",
    [
        {},
        {"body": "heading", "sensors": "ring", "num_distractors": 2, "sensor_permutation": 3},
        {"sensor_noise": 0.1, "actuator_noise": 0.2, "size": 4, "num_obstacles": 9},
    ],
)
def test_reset_step_and_observe_run_on_the_meta_device_so_never_synchronise_with_the_host(
    options,
):
    # A meta tensor has no data: .item(), bool(), nonzero() and data-dependent shapes raise on it.
    # The world's functions running on meta is the proof that a step never waits for the device
    # (GPU readiness: CUDA graphs, torch.compile without graph breaks).
    from factorq_envs.grid_world import FactoredGrid

    config = WorldConfig(**options)
    count = 6
    static = torch.zeros(config.num_cells, dtype=torch.bool, device="meta")
    world = FactoredGrid(config, static_obstacles=static)
    state = world.initial_state(count, device="meta")
    key = derive_keys(0, STREAM_WORLD, count).to("meta")
    period = torch.tensor([0, 10, 1] * 2, device="meta")
    state = world.reset(state, torch.ones(count, dtype=torch.bool, device="meta"), key, period)
    for _ in range(2):
        action = torch.zeros(count, dtype=torch.int64, device="meta")
        state, outcome = world.step(state, action, key, period)
        state = world.reset(state, outcome.terminated | outcome.truncated, key, period)
    readings = world.observe(state, key)
    assert readings.device.type == "meta" and state.obstacles.shape == (count, config.num_cells)


@pytest.mark.parametrize("size", [2, 3, 5, 10])
def test_scatter_equals_floyds_sequential_loop_in_crowded_and_sparse_worlds(size):
    # The scatter resolves Floyd's steps without a loop over them; the plain loop is the spec.
    cells = size * size
    generator = torch.Generator().manual_seed(size)
    count = 500
    for num_obstacles in range(cells - 2):
        key = torch.randint(-(2**62), 2**62, (count,), generator=generator)
        index = torch.randint(0, 1000, (count,), generator=generator)
        agent = torch.randint(0, cells, (count,), generator=generator)
        fast = scatter_obstacles(key, index, agent, size, num_obstacles)
        for row in range(0, count, 50):
            agent_cell = int(agent[row])
            excluded = {0, cells - 1, agent_cell}
            allowed = [cell for cell in range(cells) if cell not in excluded]
            bits = random_bits(
                key[row : row + 1].unsqueeze(1),
                index[row] * num_obstacles + torch.arange(num_obstacles),
            )[0].tolist()
            taken: list[int] = []
            for k in range(num_obstacles):
                j = len(allowed) - num_obstacles + k
                t = (bits[k] * (j + 1)) >> 32
                taken.append(j if t in taken else t)
            expected = torch.zeros(cells, dtype=torch.bool)
            expected[[allowed[position] for position in taken]] = True
            assert torch.equal(fast[row], expected), (size, num_obstacles, row)


@pytest.mark.parametrize("size", [2, 3, 10])
def test_the_neighbour_lookup_equals_the_row_and_column_arithmetic(size):
    from factorq_envs.grid_world import _neighbour_cells, neighbours

    cell = torch.arange(size * size).repeat(3).reshape(3, -1)  # any leading shape
    target, inside = neighbours(cell, size)
    expected_target, expected_inside = _neighbour_cells(cell, size)
    assert torch.equal(target, expected_target) and torch.equal(inside, expected_inside)
    # by hand: cell 0 has only its south and east neighbours inside
    assert inside[0, 0].tolist() == [False, False, True, True]
    assert target[0, 0].tolist() == [0, 0, size, 1]


@pytest.mark.parametrize("width", [1, 3, 4, 6, 8, 100, 101])
def test_where_rows_equals_torch_where_on_any_width_offset_and_layout(width):
    from factorq_envs.grid_world import where_rows

    generator = torch.Generator().manual_seed(width)
    big = torch.rand(7, width + 1, generator=generator) < 0.5
    new = torch.rand(6, width, generator=generator) < 0.5
    mask = torch.rand(6, generator=generator) < 0.5
    for old in (
        torch.rand(6, width, generator=generator) < 0.5,  # contiguous
        big[1:, 1:],  # an offset, strided slice
        big.reshape(-1)[1 : 1 + 6 * width].reshape(6, width),  # an odd storage offset
    ):
        expected = torch.where(mask.unsqueeze(1), new, old)
        assert torch.equal(where_rows(mask, new, old), expected)
    meta = where_rows(mask.to("meta"), new.to("meta"), old.to("meta"))
    assert meta.shape == (6, width) and meta.dtype == torch.bool


def test_a_terminated_world_restarts_from_the_scatter_its_last_step_drew():
    # The draws kept by a step are a terminated world's next reset draws, exactly: start from
    # random positions next to the goal so that many worlds terminate, then compare the reset
    # with and without the kept draws on those worlds.
    from factorq_envs.grid_world import FactoredGrid

    config = WorldConfig(size=4, num_obstacles=5, max_steps=3)
    count = 600
    grid = FactoredGrid(config, static_obstacles=torch.zeros(16, dtype=torch.bool))
    key = derive_keys(9, STREAM_WORLD, count)
    period = torch.tensor([10, 1, 2] * (count // 3))
    generator = torch.Generator().manual_seed(9)
    state = grid.reset(grid.initial_state(count), torch.ones(count, dtype=torch.bool), key, period)
    for _ in range(4):
        state = state._replace(cell=torch.randint(0, 16, (count,), generator=generator))
        action = torch.randint(0, 4, (count,), generator=generator)
        state, outcome, draws = grid.step_keeping_draws(state, action, key, period)
        ended = outcome.terminated
        assert ended.sum() > 20
        kept = grid.reset(state, ended, key, period, draws=draws)
        drawn = grid.reset(state, ended, key, period)
        for mine, theirs in zip(kept, drawn, strict=True):
            assert torch.equal(mine, theirs)
        state = drawn


def test_an_env_told_that_restarts_terminated_refuses_a_world_that_did_not():
    from factorq_envs import FactoredGridEnv

    env = FactoredGridEnv(size=3, num_obstacles=2, obstacle_period=1, batch_size=(2,))
    td = env.reset()
    td["action"] = torch.tensor([0, 0])  # north from the start: into the wall, no goal
    td = env.step_mdp(env.step(td))
    td["_reset"] = torch.tensor([[True], [False]])
    with pytest.raises(RuntimeError, match="restarts a world that did not terminate"):
        env.reset(td, restarts_terminated=True)
