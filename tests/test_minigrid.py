"""The MiniGrid adapter (issue 16): its sensors, local reward and seeding against MiniGrid's own
state, torchrl citizenship, the missing-extra message and ``factorq minigrid`` end to end.

The checks read MiniGrid's grid directly (``env.unwrapped.grid``, ``agent_pos``, ``dir_vec``),
an implementation independent of the adapter (which reads the egocentric ``image``). Tests that
need MiniGrid skip cleanly without the extra ``factorq-torch[minigrid]``.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from factorq_envs import minigrid_adapter as adapter
from factorq_torch.base import keys

#: outcomes that depend on float rounding: `make test` reruns these under other CPU kernels
pytestmark = pytest.mark.float_sensitive


def _need_minigrid():
    return pytest.importorskip("minigrid")


def _world_cell(base, offset):
    """The grid cell of a layout offset ``(d_row, d_col)`` (heading-0 frame: ahead is -1 row)."""
    d_row, d_col = offset
    position = np.array(base.agent_pos)
    return position + (-d_row) * np.array(base.dir_vec) + d_col * np.array(base.right_vec)


def _blocked(base, cell) -> bool:
    x, y = int(cell[0]), int(cell[1])
    if not (0 <= x < base.width and 0 <= y < base.height):
        return True  # outside the grid MiniGrid's view shows walls
    thing = base.grid.get(x, y)
    return thing is not None and thing.type in ("wall", "ball")


def _expected(base, layout):
    return [int(_blocked(base, _world_cell(base, o))) for o in layout.offsets]


def test_layouts_and_dependency_are_data():
    layout = adapter.VIEW_LAYOUTS["front3"]
    assert adapter.view_cells(layout) == ((3, 5), (2, 6), (4, 6))  # the front/left/right
    assert adapter.sensor_names("front3") == ("front", "left", "right")
    assert adapter.dependency("front3").tolist() == [
        [True, False, False],
        [False, False, False],
        [False, False, False],
    ]
    assert adapter.view_cells(adapter.VIEW_LAYOUTS["ahead6"])[3:] == ((2, 5), (4, 5), (3, 4))
    assert adapter.ACTION_TO_MINIGRID == (2, 0, 1)  # forward, left, right in MiniGrid's numbers
    with pytest.raises(ValueError, match="size=7 is not a Dynamic-Obstacles size"):
        adapter.env_id(7)
    with pytest.raises(ValueError, match="semantics='lava'"):
        adapter.check_semantics("lava")


def test_missing_extra_names_it(monkeypatch, tmp_path, capsys):
    import sys

    monkeypatch.setitem(sys.modules, "minigrid", None)  # import minigrid now fails, as uninstalled
    with pytest.raises(ModuleNotFoundError, match=r"factorq-torch\[minigrid\]"):
        adapter.require_minigrid()
    from factorq_trainers.cli import main

    code = main(["minigrid", "--seeds", "1", "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and "factorq-torch[minigrid]" in err[0]


@pytest.mark.parametrize("semantics", adapter.SEMANTICS)
@pytest.mark.parametrize("size", [5, 8])
def test_sensors_and_local_reward_equal_minigrid(size, semantics):
    """After every step the sensors equal the grid's contents around the agent, the cell and
    heading equal MiniGrid's, and the collision equals MiniGrid's outcome: forward into a cell
    that held a wall or ball before the step."""
    _need_minigrid()
    env = adapter.make_minigrid(size, semantics, layout="ahead6")
    base = env.unwrapped
    layout = adapter.VIEW_LAYOUTS["ahead6"]
    rng = np.random.default_rng(size)
    obs, _ = env.reset(seed=size)
    collisions = forward_moves = 0
    for _ in range(400):
        assert obs[keys.SENSORS].tolist() == _expected(base, layout)
        x, y = base.agent_pos
        assert obs[keys.CELL] == y * base.width + x
        assert obs[keys.HEADING] == {0: 3, 1: 2, 2: 1, 3: 0}[base.agent_dir]  # E S W N
        action = int(rng.choice(3, p=[0.6, 0.2, 0.2]))
        front = _blocked(base, np.array(base.front_pos))
        obs, reward, terminated, truncated, info = env.step(action)
        collided = action == adapter.FORWARD and front
        forward_moves += action == adapter.FORWARD
        collisions += collided
        expected = [-1.0 if collided else 0.0, 0.0, 0.0]
        assert obs[keys.COLLISION].tolist() == expected
        assert obs[keys.BUMP].tolist() == [int(collided), 0, 0]
        assert info["collided"] == collided
        if collided:
            assert reward == -1.0
            assert terminated == (semantics == "minigrid")
        if terminated or truncated:
            obs, _ = env.reset()
    assert collisions > 5 and forward_moves > 100  # the check met collisions


def test_hand_computed_collision_and_split():
    """5x5: the agent starts at (1, 1) facing east; turning left faces the wall to the north;
    forward then collides: local reward -1 at forward, task reward 0."""
    _need_minigrid()
    from torchrl.envs import TransformedEnv

    from factorq_envs.minigrid_torchrl import MiniGridEnv
    from factorq_envs.transforms import SplitLocalReward

    for semantics, ends in (("minigrid", True), ("nodeath", False)):
        env = TransformedEnv(MiniGridEnv(5, semantics, seeds=[3]), SplitLocalReward())
        td = env.reset()
        assert td[keys.HEADING].tolist() == [3]  # east
        assert td[keys.CELL].tolist() == [1 * 5 + 1]
        td["action"] = torch.tensor([1])  # turn left: north
        td = env.step(td)
        assert td["next", keys.HEADING].tolist() == [0]
        assert td["next", keys.SENSORS][0, :2].tolist() == [True, True]  # walls: front, left
        td = env.step_mdp(td)
        td["action"] = torch.tensor([0])  # forward into the wall
        td = env.step(td)
        assert td["next", "local_reward"].tolist() == [[-1.0, 0.0, 0.0]]
        assert td["next", "reward"].tolist() == [[0.0]]
        assert td["next", "terminated"].tolist() == [[ends]]
        assert td["next", keys.CELL].tolist() == [6]


def _rollout(seeds, steps=120):
    from factorq_envs.minigrid_torchrl import MiniGridEnv

    env = MiniGridEnv(6, "nodeath", seeds=seeds)
    generator = torch.Generator().manual_seed(0)
    td = env.reset()
    cells, sensors = [], []
    for _ in range(steps):
        td["action"] = torch.randint(0, 3, (len(seeds),), generator=generator)
        td, td = env.step_and_maybe_reset(td)
        cells.append(td[keys.CELL].clone())
        sensors.append(td[keys.SENSORS].clone())
    balls = [tuple(b.cur_pos) for b in env.envs[0].unwrapped.obstacles]
    return torch.stack(cells), torch.stack(sensors), balls


def test_seeding_reproduces_episodes():
    _need_minigrid()
    first, second, other = _rollout([4, 5]), _rollout([4, 5]), _rollout([9, 5])
    assert torch.equal(first[0], second[0]) and torch.equal(first[1], second[1])
    assert first[2] == second[2]
    assert not (torch.equal(first[1][:, 0], other[1][:, 0]) and first[2] == other[2])
    assert torch.equal(first[1][:, 1], other[1][:, 1])  # world 1 kept its seed


def test_torchrl_citizenship():
    _need_minigrid()
    import gymnasium as gym
    from torchrl.envs import GymWrapper, ParallelEnv, SerialEnv
    from torchrl.envs.utils import check_env_specs

    from factorq_envs.minigrid_torchrl import MiniGridEnv

    for semantics in adapter.SEMANTICS:
        check_env_specs(MiniGridEnv(5, semantics, seeds=[0, 1], with_image=True))
    check_env_specs(GymWrapper(adapter.make_minigrid(5, "nodeath", layout="ahead6")))
    # torchrl 0.14 cannot stack a vector env's mission strings: leave the text out there
    vector = gym.vector.SyncVectorEnv(
        [lambda: gym.wrappers.FilterObservation(adapter.make_minigrid(6), _NO_TEXT)] * 2,
        autoreset_mode=gym.vector.AutoresetMode.DISABLED,
    )
    wrapped = GymWrapper(vector)
    check_env_specs(wrapped)
    assert wrapped.rollout(40, break_when_any_done=False).batch_size == (2, 40)
    serial = SerialEnv(2, lambda: GymWrapper(adapter.make_minigrid(5)))
    check_env_specs(serial)
    parallel = ParallelEnv(2, _gym_wrapped, mp_start_method="fork")  # fork: no re-import
    try:
        check_env_specs(parallel)
        assert parallel.rollout(20, break_when_any_done=False).batch_size == (2, 20)
    finally:
        parallel.close()


_NO_TEXT = ["image", "direction", "cell", "heading", "sensors", "bump", "collision"]


def _gym_wrapped():
    from torchrl.envs import GymWrapper

    return GymWrapper(adapter.make_minigrid(5, "nodeath"))


def test_committed_learner_predicts_nothing_until_it_commits():
    from factorq_torch.structure import StructureLearner

    plain = StructureLearner(1, num_actions=2, num_sensors=3, prediction="posterior")
    committed = StructureLearner(1, num_actions=2, num_sensors=3, prediction="committed")
    generator = torch.Generator().manual_seed(1)
    for step in range(80):
        sensors = torch.rand(1, 3, generator=generator) < 0.5
        reward = torch.zeros(1, 2)
        reward[0, 0] = -float(sensors[0, 2])  # actuator 0 collides where sensor 2 is set
        for learner in (plain, committed):
            learner.update_running_mean(sensors, torch.tensor([0]), reward)
        if step == 0:  # open after one sample: the plain learner already predicts
            probe = torch.tensor([[False, False, True]])
            assert committed.local_values(probe).tolist() == [[0.0, 0.0]]
            assert plain.local_values(probe)[0, 0] < 0
    assert committed.structure()[0, 0].tolist() == [False, False, True]
    probe = torch.tensor([[True, False, True]])
    assert torch.equal(committed.local_values(probe), plain.local_values(probe))
    assert committed.local_values(probe)[0, 0] == -1.0


def test_cli_runs_a_tiny_budget(tmp_path, capsys):
    _need_minigrid()
    from factorq_trainers.cli import main

    out = tmp_path / "mg"
    code = main(["minigrid", "--seeds", "2", "--sizes", "5", "--steps", "60", "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    results = json.loads((out / "minigrid.json").read_text())
    assert set(results["results"]["5"]) == set(default_methods())
    for entry in results["results"]["5"].values():
        assert len(entry["seeds"]["collisions"]) == 2
        assert entry["summary"]["env_steps_per_seed"] == 60
    assert (out / "minigrid.png").stat().st_size > 0
    assert "| Factor-Q |" in (out / "minigrid.md").read_text()
    assert main(["minigrid", "--seeds", "0", "--out", str(out)]) == 2
    assert "--seeds=0" in capsys.readouterr().err


def default_methods():
    from factorq_trainers.commands.minigrid.config import DEFAULT_METHODS

    return DEFAULT_METHODS


def test_gymnasium_and_minigrid_tools_accept_the_adapter():
    """Gymnasium's check_env (the env re-created from its spec: RecordConstructorArgs) and
    MiniGrid's own observation wrappers, which find the image and the mission passed through."""
    _need_minigrid()
    from gymnasium.utils.env_checker import check_env
    from minigrid.wrappers import FlatObsWrapper, ImgObsWrapper

    check_env(adapter.make_minigrid(5), skip_render_check=True)
    image, _ = ImgObsWrapper(adapter.make_minigrid(8)).reset(seed=0)
    assert image.shape == (7, 7, 3)
    flat, _ = FlatObsWrapper(adapter.make_minigrid(8)).reset(seed=0)
    assert flat.shape == (7 * 7 * 3 + 96 * 28,)  # the image and the mission (28 characters)
    env = adapter.make_minigrid(5, seed=4)
    observation, _ = env.reset()
    assert observation["mission"] == "get to the green goal square"
    assert env.config.num_cells == 25 and env.config.actuator_names == adapter.HEADING.actuators


def test_the_minigrid_command_takes_risk_aware_exploration_for_tabular_factor_q():
    # issue 39: Factor-Q's exploration is the option's, Q-learning's stays uniform (not refused)
    pytest.importorskip("minigrid")
    from factorq_trainers.commands.minigrid import command

    config = command.MiniGridConfig(
        seeds=1,
        sizes=("5",),
        steps=60,
        methods=("factor-q", "q-learning"),
        exploration="risk-aware",
        out="unused",
    )
    results = command.run(config)["results"]["5"]
    assert set(results) == {"factor-q", "q-learning"}
    with pytest.raises(ValueError, match="exploration='careful' is unknown"):
        command.MiniGridConfig(exploration="careful", out="unused")
