"""Bodies and sensor layouts as data (issue 11): every sensor against the obstacle map, turns,
collisions against ``env.dependency``, distractors, noise, and the agent reading the dependency.

The expected sensor readings are computed here from the sensor *names* and ``obstacle_map()``
alone (``front-left`` = one step ahead plus one step left of the heading), independently of
``factorq_envs.body``'s offsets and rotations.
"""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from factorq_envs import FactoredGridEnv
from factorq_envs.grid_world import WorldConfig, sense, step_worlds
from factorq_torch import functional
from factorq_torch.base import keys
from factorq_torch.tables import LocalRewardTable, TaskQTable


def fast_available() -> bool:
    from factorq_trainers.compiled import fast

    return fast.is_available()


#: Row and column steps of the four directions, in the paper's order (north, west, south, east).
STEPS = {0: (-1, 0), 1: (0, -1), 2: (1, 0), 3: (0, 1)}
#: A direction name -> quarter turns to the left of the heading (translate: of north).
TURNS = {"north": 0, "west": 1, "south": 2, "east": 3, "front": 0, "left": 1, "back": 2, "right": 3}

CONFIGS = [
    {},
    {"sensors": "ring"},
    {"sensors": "ring", "num_distractors": 4, "sensor_permutation": 7},
    {"body": "heading"},
    {"body": "heading", "sensors": "ring", "num_distractors": 2, "sensor_permutation": 3},
    {"body": "heading", "sensor_permutation": (3, 1, 0, 2)},
]


def expected_reading(name: str, cell: int, heading: int, blocked, size: int) -> bool:
    """Sensor ``name`` of an agent on ``cell`` facing ``heading``: wall or obstacle there."""
    row, col = divmod(cell, size)
    for part in name.split("-"):
        d_row, d_col = STEPS[(TURNS[part] + heading) % 4]
        row, col = row + d_row, col + d_col
    return not (0 <= row < size and 0 <= col < size) or bool(blocked[row, col])


def random_walk(env: FactoredGridEnv, steps: int, seed: int = 0):
    """Yield ``(before, td)`` per step: the observation acted on and the stepped TensorDict (with
    the world's obstacle map after the step); finished worlds are reset in between."""
    generator = torch.Generator().manual_seed(seed)
    td = env.reset()
    for _ in range(steps):
        before = td.clone()
        td["action"] = torch.randint(
            0, env.config.num_actuators, env.batch_size, generator=generator
        )
        td = env.step(td)
        yield before, td, env.obstacle_map()
        td = env.step_mdp(td)
        done = td["done"].squeeze(-1)
        if done.any():
            td["_reset"] = done.unsqueeze(-1)
            td = env.reset(td)


def make_env(options: dict, period: int = 1, batch: int = 6, **more) -> FactoredGridEnv:
    return FactoredGridEnv(
        size=5, num_obstacles=6, obstacle_period=period, max_steps=30, batch_size=(batch,),
        seed=3, **options, **more,
    )  # fmt: skip


# -- the world -----------------------------------------------------------------------------


@pytest.mark.parametrize("options", CONFIGS, ids=str)
@pytest.mark.parametrize("period", [0, 3, 1])
def test_every_sensor_matches_the_obstacle_map_after_every_step_including_scatters(options, period):
    env = make_env(options, period)
    names = env.config.sensor_names
    size = env.config.size
    checked = 0
    for _, td, blocked in random_walk(env, 120):
        nxt = td["next"]
        heading = nxt.get(keys.HEADING, torch.zeros(env.batch_size, dtype=torch.int64))
        for world in range(env.batch_size[0]):
            if nxt["done"][world]:
                continue  # the next observation is the reset's, checked at the next step
            cell, facing = int(nxt["cell"][world]), int(heading[world])
            for index, name in enumerate(names):
                if name.startswith("distractor"):
                    continue
                want = expected_reading(name, cell, facing, blocked[world], size)
                assert bool(nxt["sensors"][world, index]) == want, (name, cell, facing)
                checked += 1
    assert checked > 1000


def test_the_paper_body_receives_exactly_its_proximity_bits_and_declares_the_identity():
    env = make_env({})
    assert env.config.is_paper_body
    assert torch.equal(env.dependency, torch.eye(4, dtype=torch.bool))
    assert env.config.sensor_names == ("north", "west", "south", "east")
    for _, td, _ in random_walk(env, 30):
        assert torch.equal(td["next", "sensors"], td["next", "proximity"])


@pytest.mark.parametrize("options", CONFIGS, ids=str)
def test_specs_of_every_body_match_what_the_env_writes(options):
    check_env_specs(make_env({**options, "sensor_noise": 0.1, "actuator_noise": 0.1}))


def test_turns_never_move_never_collide_and_turn_by_a_quarter():
    env = make_env({"body": "heading"}, period=3)
    turned = 0
    for before, td, _ in random_walk(env, 200):
        action, nxt = td["action"], td["next"]
        turning = (action > 0) & ~nxt["done"].squeeze(-1)
        assert torch.equal(nxt["cell"][turning], before["cell"][turning])
        assert not nxt["bump"][action > 0].any()
        quarter = torch.where(action == 1, 1, 3)  # left: +1, right: -1 (mod 4)
        want = (before["heading"] + quarter) % 4
        assert torch.equal(nxt["heading"][turning], want[turning])
        turned += int(turning.sum())
    assert turned > 300


def test_only_forward_collides_in_the_heading_body_exactly_when_its_front_is_blocked():
    env = make_env({"body": "heading"}, period=0, batch=8)
    collisions = 0
    front = env.config.sensor_names.index("front")
    for before, td, _ in random_walk(env, 300):
        bumped = td["next", "bump"]
        assert not bumped[:, 1:].any()  # turn-left, turn-right
        forward = td["action"] == 0
        assert torch.equal(bumped[:, 0], forward & before["sensors"][:, front])
        collisions += int(bumped.sum())
    assert collisions > 50


@pytest.mark.parametrize("options", CONFIGS, ids=str)
def test_env_dependency_agrees_with_observed_collisions(options):
    env = make_env(options, period=1, batch=8)
    dependency = env.dependency  # [A, K]
    assert dependency.shape == (env.config.num_actuators, env.config.num_sensors)
    for actuator, name in enumerate(env.config.actuator_names):
        parents = [env.config.sensor_names[k] for k in dependency[actuator].nonzero().flatten()]
        moves = name not in ("turn-left", "turn-right")
        assert parents == ([{"forward": "front"}.get(name, name)] if moves else []), name
    seen = torch.zeros_like(dependency, dtype=torch.int64)
    for before, td, _ in random_walk(env, 150):
        action = td["action"]
        parents = dependency[action]  # [S, K]
        want = (before["sensors"] & parents).any(dim=-1)  # a parent sensed something
        got = td["next", "collision"].gather(1, action.unsqueeze(1)).squeeze(1) == -1.0
        assert torch.equal(got, want)
        seen[action] += before["sensors"].to(torch.int64)
    assert (seen[dependency] > 0).all()  # every parent was seen set at least once


def test_distractors_carry_no_information_about_collisions():
    env = make_env({"num_distractors": 3}, period=1, batch=32)
    names = env.config.sensor_names
    distractors = [i for i, name in enumerate(names) if name.startswith("distractor")]
    counts = torch.zeros(len(distractors), 2, 2)  # [distractor, its value, collided]
    values = []
    for before, td, _ in random_walk(env, 400, seed=1):
        collided = td["next", "bump"].any(dim=-1).long()
        for row, index in enumerate(distractors):
            value = before["sensors"][:, index].long()
            counts[row].index_put_((value, collided), torch.ones(len(value)), accumulate=True)
        values.append(before["sensors"][:, distractors].float())
    values = torch.cat(values)
    n = values.shape[0]
    assert ((values.mean(0) - 0.5).abs() < 4 * math.sqrt(0.25 / n)).all()  # fair coins
    for row in range(len(distractors)):
        on, off = counts[row, 1], counts[row, 0]
        rate_on, rate_off = on[1] / on.sum(), off[1] / off.sum()
        pooled = (on[1] + off[1]) / (on.sum() + off.sum())
        error = math.sqrt(pooled * (1 - pooled) * (1 / on.sum() + 1 / off.sum()))
        assert abs(rate_on - rate_off) < 4 * error, (row, rate_on, rate_off)


def test_sensor_noise_flips_each_bit_at_its_rate():
    noise = 0.2
    env = make_env({"sensors": "ring", "sensor_noise": noise}, period=1, batch=32)
    flips = total = 0
    for _, td, _ in random_walk(env, 150):
        state = env.world_state  # after the step (and before any reset): the next observation
        clean = sense(state.cell, state.heading, state.obstacles, env.config)
        running = ~td["next", "done"].squeeze(-1)
        flips += int((td["next", "sensors"] ^ clean)[running].sum())
        total += int(running.sum()) * env.config.num_sensors
    rate, error = flips / total, math.sqrt(noise * (1 - noise) / total)
    assert abs(rate - noise) < 4 * error, rate


@pytest.mark.parametrize("body", ["translate", "heading"])
def test_actuator_noise_fires_another_actuator_uniformly_at_its_rate(body):
    noise = 0.3
    config = WorldConfig(size=5, num_obstacles=4, body=body, actuator_noise=noise)
    env = FactoredGridEnv(size=5, num_obstacles=4, body=body, actuator_noise=noise, batch_size=(1,))
    count = 20_000
    state = env.world_state._replace(
        ticks=torch.arange(count), **{
            name: tensor.expand(count, *tensor.shape[1:])
            for name, tensor in env.world_state._asdict().items() if name != "ticks"
        },
    )  # fmt: skip
    action = torch.zeros(count, dtype=torch.int64)
    _, outcome = step_worlds(
        state, action, env.world_keys.expand(count), torch.zeros(count), config
    )
    slipped = outcome.fired != action
    rate, error = slipped.float().mean().item(), math.sqrt(noise * (1 - noise) / count)
    assert abs(rate - noise) < 4 * error, rate
    others = outcome.fired[slipped].bincount(minlength=config.num_actuators)[1:].float()
    share = 1 / (config.num_actuators - 1)
    n = int(slipped.sum())
    assert ((others / n - share).abs() < 4 * math.sqrt(share * (1 - share) / n)).all()


def test_heading_world_config_names_and_dependency_follow_the_permutation():
    config = WorldConfig(
        body="heading", sensors="ring", sensor_permutation=(7, 0, 1, 2, 3, 4, 5, 6)
    )
    assert config.sensor_names[:2] == ("front-right", "front")
    assert config.actuator_names == ("forward", "turn-left", "turn-right")
    assert config.dependency.nonzero().tolist() == [[0, 1]]  # forward <- front, now sensor 1
    drawn = WorldConfig(sensors="ring", num_distractors=4, sensor_permutation=5)
    assert sorted(drawn.sensor_permutation) == list(range(12))
    assert drawn == WorldConfig(sensors="ring", num_distractors=4, sensor_permutation=5)


# -- the agent reads the dependency --------------------------------------------------------


def test_project_local_reads_each_actuator_at_the_pattern_of_its_parents():
    dependency = torch.tensor([[True, False, True], [False, True, False], [False, False, False]])
    rho = torch.arange(12.0).view(3, 4)  # rho_a[p] = 4 a + p
    readings = torch.tensor([[True, True, False], [False, False, True]])
    # actuator 0: parents 0, 2 -> patterns 1 + 0 = 1 and 0 + 2 = 2; actuator 1: parent 1 -> 1, 0;
    # actuator 2: no parents -> always entry 0
    got = functional.project_local(rho, readings, dependency)
    assert got.tolist() == [[1.0, 5.0, 8.0], [2.0, 4.0, 8.0]]
    paper = functional.project_local(
        torch.tensor([[[0.0, -1.0]] * 4]),
        torch.tensor([[True, False, False, True]]),
        torch.eye(4).bool(),
    )
    assert paper.tolist() == [[-1.0, 0.0, 0.0, -1.0]]  # the paper: rho_i[o_i]


def test_local_table_learns_per_parent_pattern_and_has_2_to_the_parents_entries():
    dependency = torch.tensor([[True, True, False], [False, False, False]])
    local = LocalRewardTable(1, dependency=dependency)
    assert local.rho.shape == (1, 2, 4)
    readings = torch.tensor([[False, True, True]])  # pattern of actuator 0: 2
    local.update_running_mean(readings, torch.tensor([0]), torch.tensor([[-1.0, 0.0]]))
    local.update_running_mean(readings, torch.tensor([0]), torch.tensor([[0.0, 0.0]]))
    assert local.rho[0, 0].tolist() == [0.0, 0.0, -0.5, 0.0]
    assert local.kappa[0, 0].tolist() == [0, 0, 2, 0]
    value = local(TensorDict(sensors=readings, batch_size=[1]))["local_value"]
    assert value.tolist() == [[-0.5, 0.0]]


def test_task_table_indexes_cell_heading_and_the_pattern_of_all_sensors():
    table = TaskQTable(1, 3, with_sensors=True, num_sensors=5, num_headings=4, num_actions=3)
    assert table.table.shape == (1, 3 * 4 * 32, 3)
    assert table.in_keys == ["cell", "heading", "sensors"]
    td = TensorDict(
        cell=torch.tensor([2]), heading=torch.tensor([3]),
        sensors=torch.tensor([[True, False, False, False, True]]), batch_size=[1],
    )  # fmt: skip
    assert table.state_index(td).tolist() == [(2 * 4 + 3) * 32 + 17]
    factorq = TaskQTable(1, 3, num_headings=4, num_actions=3)
    assert factorq.state_index(td).tolist() == [2 * 4 + 3]


# -- the whole experiment on other bodies --------------------------------------------------


@pytest.mark.parametrize(
    "options",
    [
        {"body": "heading", "sensors": "ring", "sensor_noise": 0.05, "actuator_noise": 0.05},
        {"sensors": "ring", "distractors": 2, "sensor_permutation": 1},
    ],
    ids=str,
)
def test_the_paper_experiment_runs_other_bodies_on_the_modular_path(options):
    from factorq_trainers.commands.paper import command as paper
    from factorq_trainers.commands.paper.config import PaperConfig

    # Episodes cut at 60 steps: the heading body wanders for up to 200 at first, and its equality
    # with the kernel on random bodies is test_fast_bodies.py's; this one runs the whole command.
    small = {"seeds": 2, "runs": 2, "episodes": 2, "size": 4, "obstacles": 2, "max_steps": 60}
    config = PaperConfig(**small, backend="modular", **options)
    results = paper.run(config)
    assert results["timing"]["backend"] == "modular"
    assert len(results["cells"]) == 6
    again = paper.run(config)
    assert again["cells"] == results["cells"]  # deterministic


def test_factored_grid_implements_the_world_protocol_with_the_world_functions():
    from factorq_envs.grid_world import FactoredGrid, reset_worlds, static_layout
    from factorq_envs.protocol import World
    from factorq_torch.base.rng import STREAM_WORLD, derive_keys

    config = WorldConfig(size=5, num_obstacles=4, body="heading", sensors="ring", sensor_noise=0.1)
    grid = FactoredGrid(config)
    assert isinstance(grid, World)
    key, period = derive_keys(0, STREAM_WORLD, 3), torch.tensor([0, 10, 1])
    mask = torch.ones(3, dtype=torch.bool)
    state = grid.reset(grid.initial_state(3), mask, key, period)
    direct = reset_worlds(grid.initial_state(3), mask, key, period, static_layout(config), config)
    assert all(torch.equal(a, b) for a, b in zip(state, direct, strict=True))
    action = torch.tensor([0, 1, 2])
    new, outcome = grid.step(state, action, key, period)
    want, want_outcome = step_worlds(state, action, key, period, config)
    assert all(torch.equal(a, b) for a, b in zip(new, want, strict=True))
    assert grid.observe(new, key).shape == (3, 8)
    assert "A" in grid.render(new, 1)


@pytest.mark.skipif(not fast_available(), reason="fast backend unavailable")
def test_factorq_with_the_oracle_dependency_ignores_diagonals_distractors_and_order():
    # The tables only read each actuator's parent sensor: on ring + distractors, permuted, Factor-Q
    # makes exactly the paper body's decisions (same world and policy streams), bit for bit.
    from factorq_trainers.commands.paper import command as paper
    from factorq_trainers.commands.paper.config import PaperConfig
    from factorq_trainers.runner.results import dumps as dumps_results

    small = {
        "seeds": 2,
        "runs": 2,
        "episodes": 5,
        "size": 5,
        "obstacles": 4,
        "methods": ("factor-q",),
    }
    plain = paper.run(PaperConfig(**small))
    other = paper.run(
        PaperConfig(**small, sensors="ring", distractors=3, sensor_permutation=9, backend="modular")
    )
    assert dumps_results(plain["cells"]) == dumps_results(other["cells"])


def test_gymnasium_env_gives_the_torchrl_envs_sensors_and_heading_for_the_same_actions():
    import gymnasium

    import factorq_envs  # noqa: F401  (registers the id)

    options = {"body": "heading", "sensors": "ring", "num_distractors": 2, "sensor_noise": 0.2}
    world = {"size": 5, "num_obstacles": 4, "obstacle_period": 1}
    gym_env = gymnasium.make("FactoredGrid-v0", **world, **options).unwrapped
    torch_env = FactoredGridEnv(**world, **options, batch_size=(1,), seed=5)
    observation, _ = gym_env.reset(seed=5)
    td = torch_env.reset()
    generator = torch.Generator().manual_seed(0)
    for _ in range(40):
        assert observation["sensors"].tolist() == td["sensors"][0].long().tolist()
        assert int(observation["heading"]) == int(td["heading"][0])
        action = int(torch.randint(0, 3, (), generator=generator))
        observation, _, terminated, truncated, _ = gym_env.step(action)
        td["action"] = torch.tensor([action])
        td = torch_env.step(td)["next"]
        if terminated or truncated:
            break


def test_local_network_sees_only_each_actuators_parents():
    from factorq_torch.neural import LocalRewardNetwork

    dependency = torch.tensor([[True, False, True], [False, False, False], [False, True, False]])
    local = LocalRewardNetwork(2, dependency=dependency, zero_output=False, hidden=(5,))
    assert local.parent_index.tolist() == [[0, 2], [3, 3], [1, 3]]  # 3: the zero column
    readings = torch.tensor([[True, False, True], [True, True, False]])
    value = local(TensorDict(sensors=readings, batch_size=[2]))["local_value"].detach()
    assert value[:, 1].tolist() == [0.0, 0.0]  # no parents: a bias-free network predicts 0
    flipped = readings.clone()
    flipped[:, 1] = ~flipped[:, 1]  # sensor 1 is a parent of actuator 2 only
    again = local(TensorDict(sensors=flipped, batch_size=[2]))["local_value"].detach()
    assert torch.equal(again[:, 0], value[:, 0]) and not torch.equal(again[:, 2], value[:, 2])


def test_factorq_paper_command_runs_another_body_and_records_it(tmp_path, capsys):
    import json

    from factorq_trainers import cli

    out = tmp_path / "heading"
    args = ["paper", "--seeds", "1", "--runs", "1", "--episodes", "2", "--size", "4"]
    args += ["--obstacles", "1", "--body", "heading", "--sensors", "ring", "--distractors", "1"]
    args += ["--sensor-permutation", "3", "--sensor-noise", "0.05", "--actuator-noise", "0.05"]
    assert cli.main([*args, "--out", str(out)]) == 0
    config = json.loads((out / "results.json").read_text())["config"]
    assert (config["body"], config["sensors"], config["distractors"]) == ("heading", "ring", 1)
    assert (config["sensor_permutation"], config["sensor_noise"]) == (3, 0.05)


def test_factorq_compare_runs_every_method_on_another_body(tmp_path):
    from factorq_trainers.commands.compare import command as compare
    from factorq_trainers.commands.compare.config import CompareConfig
    from factorq_trainers.methods.dqn import METHODS

    config = CompareConfig(
        seeds=1, steps=300, size=4, obstacles=1, out=str(tmp_path / "compare"),
        body="heading", sensors="ring", distractors=1, sensor_permutation=2,
    )  # fmt: skip
    results = compare.run(config)
    assert set(results["config"]["methods"]) == set(METHODS)
    assert results["config"]["body"] == "heading"


def test_the_agent_default_body_is_the_paper_body_declared_in_envs():
    from factorq_envs.body import CROSS, TRANSLATE, base_dependency
    from factorq_torch.base.config import PAPER_NUM_ACTIONS

    assert PAPER_NUM_ACTIONS == len(TRANSLATE.actuators) == CROSS.num_sensors
    paper = base_dependency(TRANSLATE, CROSS, 0)
    assert torch.equal(paper, torch.eye(PAPER_NUM_ACTIONS, dtype=torch.bool))
    assert torch.equal(LocalRewardTable(1).dependency, paper)
