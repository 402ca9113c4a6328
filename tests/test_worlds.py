"""A new world is one new file (issue 11): the env wrappers, SplitLocalReward, the agents and the
trainers' modular path run any ``factorq_envs.protocol.World``; ``factorq_envs.corridor`` proves it.

The corridor is checked against hand-computed cases and an independent per-world Python loop;
the wrappers against their default-world outputs; the trainers by learning in it.
"""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import check_env_specs

from factorq_envs.corridor import MOVES, Corridor, CorridorConfig, CorridorState
from factorq_envs.grid_world import FactoredGrid, WorldConfig
from factorq_envs.gymnasium_env import FactoredGridGym
from factorq_envs.protocol import World, check_world
from factorq_envs.torchrl_env import FactoredGridEnv
from factorq_envs.transforms import SplitLocalReward
from factorq_torch.base.config import AgentConfig
from factorq_torch.base.rng import STREAM_WORLD, derive_keys, probability_threshold, random_bits


def corridor_state(hurdles: str, cell: int) -> CorridorState:
    """One corridor from a picture of its cells (``o`` a hurdle)."""
    blocked = torch.tensor([[c == "o" for c in hurdles]])
    zero = torch.zeros(1, dtype=torch.int64)
    return CorridorState(
        torch.tensor([cell]), blocked, torch.zeros(1, 3, dtype=torch.bool), zero, zero
    )


# --------------------------------------------------------------------------------------------
# The corridor's rules


@pytest.mark.parametrize(
    ("hurdles", "cell", "action", "to", "collision"),
    [
        (".o.o..", 0, 1, 0, [0, -1, 0]),  # forward into a hurdle
        (".o.o..", 0, 2, 2, [0, 0, 0]),  # jump over it
        (".o.o..", 0, 0, 0, [-1, 0, 0]),  # back into the end
        (".o.o..", 2, 0, 2, [-1, 0, 0]),  # back into the hurdle behind
        (".o.o..", 2, 2, 4, [0, 0, 0]),
        ("......", 4, 2, 4, [0, 0, -1]),  # a jump past the end
        ("......", 3, 2, 5, [0, 0, 0]),  # onto the goal
    ],
)
def test_corridor_moves_jumps_and_collisions_by_hand(hurdles, cell, action, to, collision):
    world = Corridor(CorridorConfig(length=len(hurdles)))
    key, period = torch.zeros(1, dtype=torch.int64), torch.zeros(1, dtype=torch.int64)
    state, outcome = world.step(corridor_state(hurdles, cell), torch.tensor([action]), key, period)
    assert int(state.cell[0]) == to
    assert outcome.collision[0].tolist() == collision
    assert state.bump[0].tolist() == [c < 0 for c in collision]
    goal = to == len(hurdles) - 1
    assert bool(outcome.terminated[0]) == goal
    assert float(outcome.task_reward[0]) == (0.0 if goal else -1.0)
    assert float(outcome.reward[0]) == float(outcome.task_reward[0]) + sum(collision)


def test_corridor_sensors_read_behind_ahead_and_two_and_three_ahead():
    world = Corridor(CorridorConfig(length=6))
    key = torch.zeros(1, dtype=torch.int64)
    assert world.observe(corridor_state(".o.o..", 0), key).tolist() == [[True, True, False, True]]
    assert world.observe(corridor_state(".o.o..", 2), key).tolist() == [[True, True, False, False]]
    assert world.observe(corridor_state(".o.o..", 4), key).tolist() == [[True, False, True, True]]


def test_the_dependency_is_three_actuators_over_four_sensors_and_agrees_with_collisions():
    world = Corridor(CorridorConfig(length=10, density=0.5))
    dependency = world.dependency
    assert dependency.int().tolist() == [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]
    # After every step of random walks: each actuator collides exactly when its parent sensor
    # (read before acting) is set, whatever the others read.
    count = 64
    keys = derive_keys(3, STREAM_WORLD, count)
    periods = torch.arange(count) % 3
    state = world.reset(world.initial_state(count), torch.ones(count, dtype=bool), keys, periods)
    generator = torch.Generator().manual_seed(0)
    for _ in range(40):
        before = world.observe(state, keys)
        action = torch.randint(0, 3, (count,), generator=generator)
        state, outcome = world.step(state, action, keys, periods)
        parent = before[torch.arange(count), dependency.int().argmax(dim=1)[action]]
        assert torch.equal(outcome.collision[torch.arange(count), action] < 0, parent)
        done = outcome.terminated | outcome.truncated
        state = world.reset(state, done, keys, periods)


def test_layouts_never_put_hurdles_side_by_side_on_start_goal_or_agent():
    config = CorridorConfig(length=9, density=0.9)
    world = Corridor(config)
    count = 200
    keys = derive_keys(1, STREAM_WORLD, count)
    periods = torch.ones(count, dtype=torch.int64)  # a new layout after every action
    state = world.reset(world.initial_state(count), torch.ones(count, dtype=bool), keys, periods)
    generator = torch.Generator().manual_seed(1)
    for _ in range(30):
        hurdles = state.hurdles
        assert not hurdles[:, 0].any() and not hurdles[:, -1].any()
        assert not (hurdles[:, 1:] & hurdles[:, :-1]).any()
        assert not hurdles[torch.arange(count), state.cell].any()
        action = torch.randint(0, 3, (count,), generator=generator)
        state, outcome = world.step(state, action, keys, periods)
        state = world.reset(state, outcome.terminated | outcome.truncated, keys, periods)


def reference_layout(key: int, layout: int, agent: int, config: CorridorConfig) -> list[bool]:
    """The module docstring's layout rule, one world and one cell at a time."""
    threshold = probability_threshold(config.density)
    hurdles = [False] * config.length
    for cell in range(1, config.length - 1):
        draw = int(random_bits(torch.tensor(key), layout * config.length + cell))
        hurdles[cell] = draw < threshold and not hurdles[cell - 1] and cell != agent
    return hurdles


def test_the_batched_corridor_equals_a_one_world_python_loop():
    config = CorridorConfig(length=8, density=0.5, max_steps=7)
    world = Corridor(config)
    count = 6
    keys = derive_keys(5, STREAM_WORLD, count)
    periods = torch.tensor([0, 1, 2, 0, 3, 1])
    static = reference_layout(int(derive_keys(0, 3, 1)[0]), 0, 0, config)  # STREAM_LAYOUT = 3
    generator = torch.Generator().manual_seed(2)
    actions = torch.randint(0, 3, (40, count), generator=generator)
    for i in range(count):  # the reference, world i alone
        key, period = int(keys[i]), int(periods[i])
        layouts = 0
        if period:
            hurdles, layouts = reference_layout(key, 0, 0, config), 1
        else:
            hurdles = list(static)
        cell, steps, trace = 0, 0, []
        for action in actions[:, i].tolist():
            target = cell + MOVES[action]
            collided = not 0 <= target < config.length or hurdles[target]
            cell = cell if collided else target
            steps += 1
            done = cell == config.length - 1 or steps >= config.max_steps
            if period and cell != config.length - 1 and steps % period == 0:
                hurdles, layouts = reference_layout(key, layouts, cell, config), layouts + 1
            trace.append((cell, collided, list(hurdles)))
            if done:
                cell, steps = 0, 0
                if period:
                    hurdles, layouts = reference_layout(key, layouts, 0, config), layouts + 1
                else:
                    hurdles = list(static)
        batched = world.reset(
            world.initial_state(count), torch.ones(count, dtype=bool), keys, periods
        )
        for t, action in enumerate(actions.unbind(0)):
            batched, outcome = world.step(batched, action, keys, periods)
            expected_cell, expected_collided, expected_hurdles = trace[t]
            assert int(batched.cell[i]) == expected_cell, (i, t)
            assert bool(batched.bump[i].any()) == expected_collided, (i, t)
            assert batched.hurdles[i].tolist() == expected_hurdles, (i, t)
            batched = world.reset(batched, outcome.terminated | outcome.truncated, keys, periods)


def test_bad_corridor_options_are_refused_naming_them():
    with pytest.raises(ValueError, match="length=2 is out of range"):
        CorridorConfig(length=2)
    with pytest.raises(ValueError, match="density=1.5 is out of range"):
        CorridorConfig(density=1.5)
    with pytest.raises(TypeError, match="config must be a CorridorConfig"):
        Corridor(WorldConfig())


# --------------------------------------------------------------------------------------------
# The wrappers read the world


def test_the_corridor_and_the_grid_implement_the_protocol():
    assert isinstance(Corridor(), World)
    assert check_world(FactoredGrid(WorldConfig(size=3, num_obstacles=0))) is not None
    with pytest.raises(
        TypeError, match=r"world must implement factorq_envs.protocol.World, got int"
    ):
        check_world(3)
    with pytest.raises(TypeError, match=r"without .*rewind"):
        FactoredGridEnv(world=object())


def test_torchrl_env_of_a_corridor_reads_its_specs_from_the_config_and_passes_check_env_specs():
    world = Corridor(CorridorConfig(length=11))
    env = FactoredGridEnv(world=world, batch_size=(3,), obstacle_period=[0, 10, 1], seed=4)
    spec = env.observation_spec
    assert spec["cell"].space.n == 11 and spec["sensors"].shape == (3, 4)
    assert spec["bump"].shape == (3, 3) and spec["collision"].shape == (3, 3)
    assert "heading" not in spec.keys() and "proximity" not in spec.keys()
    assert env.action_spec.space.n == 3
    assert torch.equal(env.dependency, world.dependency)
    check_env_specs(env, seed=0)
    rollout = env.rollout(30, break_when_any_done=False)
    assert rollout["next", "sensors"].shape == (3, 30, 4)
    picture = env.render(0)
    # the goal shows unless the agent stands on it (random actions may have walked it there)
    assert len(picture) == 13 and picture.count("A") == 1 and picture[-2] in "GA"
    assert picture.endswith("#") and picture.count("G") == (picture[-2] == "G")
    assert env.obstacle_map().shape == (3, 11)


def test_a_seeded_corridor_env_replays_and_a_batch_of_one_replays_its_world():
    world = Corridor(CorridorConfig(length=9))
    actions = torch.randint(0, 3, (25, 3), generator=torch.Generator().manual_seed(5))

    def cells(env, columns):
        td = env.reset()
        out = []
        for action in actions[:, columns].unbind(0):
            td["action"] = action.reshape(env.batch_size)
            td = env.step(td)["next"]
            out.append(td["cell"].reshape(-1).clone())
            if td["done"].any():
                td = env.reset(td.clone().set("_reset", td["done"]))
        return torch.stack(out)

    batch = FactoredGridEnv(world=world, batch_size=(3,), obstacle_period=1, seed=2)
    single = FactoredGridEnv(
        world=world, batch_size=(1,), obstacle_period=1, seed=2, experiment_offset=2
    )
    whole = cells(batch, [0, 1, 2])
    assert torch.equal(whole[:, 2:], cells(single, [2]))
    batch.set_seed(2)
    assert torch.equal(whole, cells(batch, [0, 1, 2]))


def test_the_default_world_given_as_world_gives_the_same_env():
    options = {"size": 5, "num_obstacles": 3, "body": "heading", "sensors": "ring"}
    default = FactoredGridEnv(**options, batch_size=(2,), obstacle_period=[0, 1], seed=3)
    config = WorldConfig(**options)
    given = FactoredGridEnv(
        world=FactoredGrid(config), batch_size=(2,), obstacle_period=[0, 1], seed=3
    )
    assert given.observation_spec == default.observation_spec
    assert given.action_spec == default.action_spec
    torch.manual_seed(0)
    a = default.rollout(40, break_when_any_done=False)
    torch.manual_seed(0)
    b = given.rollout(40, break_when_any_done=False)
    assert (a == b).all()
    assert "heading" in a.keys() and "proximity" in a.keys()


def test_grid_arguments_beside_a_world_are_refused_naming_them():
    with pytest.raises(ValueError, match=r"size=5, body='heading' describe the default"):
        FactoredGridEnv(world=Corridor(), size=5, body="heading")
    with pytest.raises(ValueError, match=r"num_obstacles=3 describe the default"):
        FactoredGridGym(world=Corridor(), num_obstacles=3)


def test_split_local_reward_splits_the_corridors_collisions():
    env = TransformedEnv(
        FactoredGridEnv(world=Corridor(CorridorConfig(length=7)), batch_size=(4,), seed=1),
        SplitLocalReward(),
    )
    check_env_specs(env, seed=0)
    rollout = env.rollout(30, break_when_any_done=False)
    nxt = rollout["next"]
    assert nxt["local_reward"].shape == (4, 30, 3)
    assert torch.equal(nxt["local_reward"], nxt["collision"])
    collided = nxt["bump"].any(-1)
    assert collided.any()  # random actions do collide
    goal = nxt["terminated"].squeeze(-1)
    expected = torch.where(goal, 0.0, -1.0)  # the task reward: no collision in it
    assert torch.equal(nxt["reward"].squeeze(-1), expected)


def test_gymnasium_env_of_a_corridor_passes_check_env_and_reads_its_spaces():
    env = FactoredGridGym(
        world=Corridor(CorridorConfig(length=8)), obstacle_period=1, render_mode="ansi"
    )
    check_env(env)
    assert env.observation_space["cell"] == gymnasium.spaces.Discrete(8)
    assert env.observation_space["sensors"] == gymnasium.spaces.MultiBinary(4)
    assert env.action_space == gymnasium.spaces.Discrete(3)
    assert "proximity" not in env.observation_space.spaces
    observation, info = env.reset(seed=0)
    assert info["local_reward"].tolist() == [0.0, 0.0, 0.0]
    assert env.render().startswith("#A")
    with pytest.raises(TypeError, match="Corridor has no render_rgb"):
        env.render_rgb()


def test_gymnasium_and_torchrl_envs_of_a_corridor_walk_alike():
    world = Corridor(CorridorConfig(length=9))
    gym_env = FactoredGridGym(world=world, obstacle_period=2)
    torch_env = FactoredGridEnv(world=world, obstacle_period=2, seed=6)
    observation, _ = gym_env.reset(seed=6)
    td = torch_env.reset()
    for action in [1, 2, 2, 0, 1, 2, 1, 1, 2, 2]:
        observation, reward, terminated, truncated, _ = gym_env.step(action)
        td["action"] = torch.tensor(action)
        td = torch_env.step(td)["next"]
        assert int(observation["cell"]) == int(td["cell"])
        assert observation["sensors"].tolist() == td["sensors"].int().tolist()
        assert reward == float(td["reward"])
        if terminated or truncated:
            break
    assert np.array_equal(gym_env.obstacle_map(), torch_env.obstacle_map().numpy())


# --------------------------------------------------------------------------------------------
# The trainers: the modular path learns in it, the fast path refuses it


def test_the_fast_path_refuses_a_foreign_world_and_takes_the_grid():
    from factorq_trainers.compiled import fast

    assert "Corridor" in fast.unsupported_reason(Corridor())
    assert fast.unsupported_reason(FactoredGrid(WorldConfig())) is None
    assert fast.unsupported_reason(WorldConfig()) is None


def test_tabular_factorq_learns_the_corridor_through_the_online_collector(one_thread):
    from factorq_torch.collectors import OnlineCollector
    from factorq_trainers.methods import experiment

    world = Corridor(CorridorConfig(length=12))
    count = 6
    periods = [0, 10, 1] * 2
    results = {}
    for algorithm in ("q-learning", "factor-q"):
        env = experiment.make_env(world, periods, derive_keys(0, STREAM_WORLD, count))
        task, local = experiment.tabular_values(algorithm, count, world)
        env, policy, loss = experiment.online_agent(
            env, task, local, AgentConfig(), derive_keys(0, 2, count)
        )
        results[algorithm] = OnlineCollector(env, policy, loss, runs=1, episodes=30).run()
    for metrics in results.values():  # both learn the way: later episodes are shorter
        steps = metrics["steps"][:, 0].float()
        assert steps[:, -10:].mean() < steps[:, :5].mean()
    collisions = {name: m["collisions"][:, 0].sum().item() for name, m in results.items()}
    # Factor-Q's local tables know each actuator's parent sensor: far fewer collisions
    assert collisions["factor-q"] * 5 < collisions["q-learning"], collisions
    factorq = results["factor-q"]["collisions"][:, 0]
    assert factorq[:, -10:].sum() <= 2  # the last episodes hardly collide (epsilon 0.01)


def test_paper_run_falls_back_to_the_modular_path_for_a_foreign_world(tmp_path, capsys):
    from factorq_trainers.commands.paper import command as paper
    from factorq_trainers.compiled import fast

    config = paper.PaperConfig(seeds=2, runs=1, episodes=4, out=str(tmp_path))
    world = Corridor(CorridorConfig(length=8))
    assert paper.resolve_backend(config, world) == "modular"
    results = paper.run(config, world=world)
    notice = capsys.readouterr().err.strip().splitlines()
    assert len(notice) == 1 and "the world is Corridor" in notice[0]
    assert "modular torchrl path" in notice[0]
    assert results["timing"]["backend"] == "modular"
    assert results["world"] == {
        "name": "Corridor",
        "config": {"length": 8, "density": 0.4, "max_steps": 1000, "layout_seed": 0},
    }
    assert set(results["cells"]) == {
        f"{w}/{a}" for w in ("static", "semi-dynamic", "dynamic") for a in config.methods
    }
    if fast.is_available():
        with pytest.raises(ValueError, match="backend='fast' cannot run this config: the world"):
            paper.resolve_backend(paper.PaperConfig(backend="fast"), world)
    with pytest.raises(ValueError, match="the compiled path runs the grid only"):
        paper.run(paper.PaperConfig(backend="fast", out=str(tmp_path)), world=world)
    with pytest.raises(ValueError, match="the paper's grid is the config's own world"):
        paper.run(config, world=FactoredGrid(WorldConfig()))
