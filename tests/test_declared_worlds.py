"""One registry of declared worlds (issue 38): ``--world`` names a built-in world, one an installed
package adds through the ``factorq.worlds`` entry point group, or a user's own
``package.module:NAME``; every bad name is one line naming it, before any work.

The user's world is Gymnasium's CliffWalking declared in a module written into ``tmp_path`` (as a
user's own file next to their script), run through ``factorq gym`` and ``factorq risk`` in-process.
"""

from __future__ import annotations

import json
import textwrap

import pytest

from factorq_envs import worlds
from factorq_envs.worlds import BUILT_IN, DeclaredWorld, WorldError, resolve_world
from factorq_trainers import cli

USER_MODULE = '''
"""A user's own declared world: CliffWalking, the fall as the collision."""

import gymnasium
import numpy as np

from factorq_envs.gymnasium_adapter import Declaration, FactorQEnv
from factorq_envs.worlds import DeclaredWorld

MOVES = ((-1, 0), (0, 1), (1, 0), (0, -1))


def cliff_ahead(step):
    row, col = divmod(int(step.observation), 12)
    return np.array([row + dr == 3 and 0 < col + dc < 11 for dr, dc in MOVES])


DECLARATION = Declaration(
    num_sensors=4,
    sensors=cliff_ahead,
    collision=lambda step: step.reward == -100,
    penalty=100.0,
    actuator_names=("up", "right", "down", "left"),
    task_state=lambda step: int(step.observation),
    num_cells=48,
    dependency=tuple(tuple(a == k for k in range(4)) for a in range(4)),
)


def make(seed):
    env = gymnasium.make("CliffWalking-v1", max_episode_steps=50)
    return FactorQEnv(env, DECLARATION, seed=seed)


CLIFF = DeclaredWorld(make, "CliffWalking-v1", threshold=-60.0, max_steps=50)
NOT_A_WORLD = 42


class Slow(gymnasium.Wrapper):
    """CliffWalking as slow as a simulator: 2 ms a step."""

    def step(self, action):
        import time

        time.sleep(0.002)
        return self.env.step(action)


def make_slow(seed):
    env = Slow(gymnasium.make("CliffWalking-v1", max_episode_steps=50))
    return FactorQEnv(env, DECLARATION, seed=seed)


SLOW = DeclaredWorld(make_slow, "slow CliffWalking", threshold=-60.0, max_steps=50)
'''


@pytest.fixture(autouse=True)
def fresh_registry():
    """``resolve_world`` caches by name: every test starts and ends with an empty cache."""
    resolve_world.cache_clear()
    yield
    resolve_world.cache_clear()


@pytest.fixture
def user_world(tmp_path, monkeypatch):
    """``<module>:CLIFF`` importable, as a user's own module is from where they run the command."""
    folder = tmp_path / "user"
    folder.mkdir()
    (folder / "cliff_user_world.py").write_text(USER_MODULE)
    (folder / "broken_user_world.py").write_text("raise RuntimeError('the module is broken')\n")
    monkeypatch.syspath_prepend(str(folder))
    yield "cliff_user_world"
    import sys

    for name in ("cliff_user_world", "broken_user_world"):
        sys.modules.pop(name, None)


def test_built_in_names_resolve_to_their_declared_worlds():
    assert worlds.names()[:5] == ["highway", *(f"minigrid-{n}x{n}" for n in (5, 6, 8, 16))]
    assert resolve_world("highway") is BUILT_IN["highway"]
    assert resolve_world("highway").survival and not resolve_world("minigrid-8x8").survival
    assert resolve_world("minigrid-8x8").observation == "image"


def test_a_users_own_world_runs_through_factorq_gym(user_world, tmp_path, capsys):
    name = f"{user_world}:CLIFF"
    out = tmp_path / "out"
    args = ["gym", "--world", name, "--seeds", "1", "--steps", "40", "--eval-episodes", "1"]
    args += ["--methods", "dqn,factor-dqn", "--curve-points", "4", "--out", str(out)]
    assert cli.main(args) == 0
    summary = json.loads((out / "gym.json").read_text())
    assert summary["config"]["world"] == name  # kept as given: --resume resolves it again
    assert summary["world"] == "CliffWalking-v1"
    assert summary["actuators"] == ["up", "right", "down", "left"]
    assert set(summary["methods"]) == {"dqn", "factor-dqn"}
    assert "# Factor-Q on CliffWalking-v1" in (out / "gym.md").read_text()


def test_a_users_own_world_resumes_to_the_same_numbers(user_world, tmp_path, monkeypatch, capsys):
    """Interrupted after its first unit, the run resumes from the name kept in its config (the
    world resolved again) and equals an uninterrupted one."""
    from factorq_trainers.commands.gym import command as gym

    args = ["gym", "--world", f"{user_world}:CLIFF", "--seeds", "1", "--steps", "40"]
    args += ["--eval-episodes", "1", "--methods", "dqn,factor-dqn", "--curve-points", "4"]
    whole, cut = tmp_path / "whole", tmp_path / "cut"
    assert cli.main([*args, "--out", str(whole)]) == 0
    run_unit = gym.run_unit

    def interrupted(config, unit, *rest, **keywords):
        if unit["method"] == "factor-dqn":
            raise KeyboardInterrupt
        return run_unit(config, unit, *rest, **keywords)

    monkeypatch.setattr(gym, "run_unit", interrupted)
    assert cli.main([*args, "--out", str(cut)]) == 130
    monkeypatch.setattr(gym, "run_unit", run_unit)
    resolve_world.cache_clear()
    assert cli.main(["gym", "--resume", str(cut)]) == 0
    capsys.readouterr()
    resumed = json.loads((cut / "gym.json").read_text())
    expected = json.loads((whole / "gym.json").read_text())
    assert resumed["timing"]["units_resumed"] == 1
    for method in ("dqn", "factor-dqn"):
        for key in ("crashes_per_1000", "greedy_return", "curves"):
            assert resumed["methods"][method][key] == expected["methods"][method][key]


def test_a_slow_world_runs_its_units_in_processes_by_default_with_the_same_numbers(
    user_world, tmp_path, monkeypatch, capsys
):
    """Issue 42: where the env steps slowly (2 ms here) and the run is long enough (the bar
    lowered to 0 s, one core per unit assumed), the units go to one process per core by
    default; ``--cluster off`` keeps them here; the numbers are the same."""
    from factorq_trainers.runner import cluster

    monkeypatch.setattr(cluster, "PROCESSES_AFTER_S", 0.0)
    monkeypatch.setattr(cluster, "_cores", lambda: 2)
    monkeypatch.setenv("PYTHONPATH", str(tmp_path / "user"))  # the workers import the world too
    args = ["gym", "--world", f"{user_world}:SLOW", "--seeds", "2", "--steps", "30"]
    args += ["--eval-episodes", "1", "--methods", "dqn", "--curve-points", "3"]
    assert cli.main([*args, "--out", str(tmp_path / "default")]) == 0
    assert "the 2 units run in 2 processes" in capsys.readouterr().err
    assert cli.main([*args, "--cluster", "off", "--out", str(tmp_path / "here")]) == 0
    assert "processes" not in capsys.readouterr().err
    default = json.loads((tmp_path / "default" / "gym.json").read_text())
    here = json.loads((tmp_path / "here" / "gym.json").read_text())
    assert default["timing"]["where"] != here["timing"]["where"] == "in-process"
    for key in ("crashes_per_1000", "greedy_return", "curves"):
        assert default["methods"]["dqn"][key] == here["methods"]["dqn"][key]


@pytest.mark.parametrize(
    ("step_s", "steps", "workers"), [(1e-5, 10**6, 1), (2e-3, 10, 1), (2e-3, 10**4, 2)]
)
def test_only_a_slow_world_with_enough_steps_goes_to_processes(
    user_world, monkeypatch, step_s, steps, workers
):
    """The decision from the measured step (fixed here: a busy machine slows any measurement),
    the budget and the cores (2 here, at most one per unit)."""
    from factorq_trainers.commands.gym import command as gym
    from factorq_trainers.runner import cluster

    monkeypatch.setattr(cluster, "_cores", lambda: 2)
    monkeypatch.setattr(DeclaredWorld, "step_seconds", lambda self: step_s)
    config = gym.GymConfig(world=f"{user_world}:CLIFF", seeds=3, steps=steps, methods=("dqn",))
    assert gym.processes(config, gym.units(config))[0] == workers


def test_a_world_measures_its_own_step(user_world):
    slow = resolve_world(f"{user_world}:SLOW").step_seconds()
    assert slow >= 0.002  # it sleeps 2 ms a step: never less, however idle the machine


def test_a_users_own_world_runs_beside_the_grid_in_factorq_risk(user_world, tmp_path):
    out = tmp_path / "risk"
    args = ["risk", "--worlds", f"{user_world}:CLIFF", "--methods", "dqn", "--seeds", "1"]
    args += ["--steps", "60", "--learning-starts", "20", "--eval-episodes", "1", "--out", str(out)]
    assert cli.main(args) == 0
    summary = json.loads((out / "risk.json").read_text())
    assert summary["config"]["worlds"] == [f"{user_world}:CLIFF"]


@pytest.mark.parametrize(
    ("name", "message"),
    [
        ("no_such_module_here:CLIFF", "module 'no_such_module_here' does not import"),
        ("broken_user_world:CLIFF", "does not import (RuntimeError: the module is broken)"),
        ("cliff_user_world:NOWHERE", "module 'cliff_user_world' has no 'NOWHERE'"),
        ("cliff_user_world:NOT_A_WORLD", "names a 'int' object, not a factorq_envs.worlds"),
        ("cliff_user_world:CLIFF:x", "is not package.module:NAME"),
        (
            "atari",
            "is unknown: choose one of highway, minigrid-5x5, minigrid-6x6, minigrid-8x8, "
            "minigrid-16x16",
        ),
    ],
)
def test_a_bad_world_is_one_line_naming_it_before_any_work(
    user_world, tmp_path, capsys, name, message
):
    out = tmp_path / "out"
    assert cli.main(["gym", "--world", name, "--steps", "40", "--out", str(out)]) == 2
    error = capsys.readouterr().err.strip()
    assert message in error and name in error
    assert len(error.splitlines()) == 1
    assert not out.exists()
    with pytest.raises(WorldError, match="world '"):
        resolve_world(name)


def _install(site, module: str, entry_points: dict[str, str]) -> None:
    """A package installed into ``site`` (a folder on sys.path) adding ``entry_points``."""
    info = site / "user_worlds_pkg-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: user-worlds-pkg\nVersion: 1.0\n")
    lines = [f"{name} = {value}" for name, value in entry_points.items()]
    (info / "entry_points.txt").write_text("[factorq.worlds]\n" + "\n".join(lines) + "\n")
    (site / f"{module}.py").write_text(textwrap.dedent(USER_MODULE))


def test_an_installed_package_adds_worlds_through_the_entry_point_group(tmp_path, monkeypatch):
    site = tmp_path / "site"
    site.mkdir()
    entry_points = {"cliff": "pkg_cliff_world:CLIFF", "lost": "pkg_cliff_world:GONE"}
    entry_points["highway"] = "pkg_cliff_world:CLIFF"  # a built-in name is never shadowed
    _install(site, "pkg_cliff_world", entry_points)
    monkeypatch.syspath_prepend(str(site))
    try:
        assert worlds.names()[len(BUILT_IN) :] == ["cliff", "lost"]
        assert resolve_world("cliff").label == "CliffWalking-v1"
        assert resolve_world("highway") is BUILT_IN["highway"]
        with pytest.raises(WorldError, match="entry point 'pkg_cliff_world:GONE' of factorq"):
            resolve_world("lost")
        with pytest.raises(
            WorldError,
            match="choose one of highway, minigrid-5x5, minigrid-6x6, minigrid-8x8, "
            "minigrid-16x16, grid-10x10, grid-10x10-dynamic, corridor, highway-pairs, cliff, lost",
        ):
            resolve_world("atari")
    finally:
        import sys

        sys.modules.pop("pkg_cliff_world", None)
    monkeypatch.undo()
    assert "cliff" not in worlds.names()  # nothing left behind once the folder leaves sys.path


def _make(seed):
    raise AssertionError("never called")


@pytest.mark.parametrize(
    ("fields", "error", "message"),
    [
        ({"make": 3}, TypeError, "DeclaredWorld.make must be callable"),
        ({"label": ""}, TypeError, "DeclaredWorld.label must be a non-empty string"),
        ({"observation": 1}, TypeError, "DeclaredWorld.observation must be a non-empty"),
        ({"threshold": "high"}, TypeError, "DeclaredWorld.threshold must be a number"),
        ({"threshold": float("nan")}, ValueError, "threshold=nan must be finite"),
        ({"requires": (("minigrid",),)}, TypeError, "must be \\(module, extra\\) string pairs"),
        ({"survival": 1}, TypeError, "DeclaredWorld.survival must be a bool"),
        ({"max_steps": 0}, ValueError, "DeclaredWorld.max_steps=0 must be an integer >= 1"),
    ],
)
def test_a_declared_world_checks_its_fields(fields, error, message):
    with pytest.raises(error, match=message):
        DeclaredWorld(**{"make": _make, "label": "x", **fields})


@pytest.mark.parametrize("name", ["grid-10x10", "grid-10x10-dynamic", "corridor"])
def test_the_projects_own_worlds_are_declared_worlds_stepping_the_same_world(name):
    """``grid-10x10``, ``grid-10x10-dynamic`` and ``corridor`` in the registry: Gymnasium's
    checker accepts them, their oracle is the world's true dependency, and under the same
    actions they step the same world as ``FactoredGridGym`` itself (cells, sensors, collisions,
    task reward)."""
    import numpy as np
    from gymnasium.utils.env_checker import check_env

    from factorq_envs.corridor import Corridor
    from factorq_envs.grid_world import WorldConfig
    from factorq_envs.gymnasium_env import FactoredGridGym

    declared = resolve_world(name)
    check_env(declared.make(5), skip_render_check=True)
    env = declared.make(5)
    world = Corridor() if name == "corridor" else WorldConfig()
    native = FactoredGridGym(world=world, obstacle_period=1 if name == "grid-10x10-dynamic" else 0)
    assert env.dependency is not None
    assert bool((env.dependency == native.config.dependency).all())
    observation, _ = env.reset(seed=11)
    mine, _ = native.reset(seed=11)
    generator = np.random.default_rng(0)
    collisions = 0
    for _ in range(300):
        action = int(generator.integers(native.action_space.n))
        observation, reward, terminated, truncated, info = env.step(action)
        mine, native_reward, native_terminated, native_truncated, native_info = native.step(action)
        assert observation["cell"] == mine["cell"]
        assert (observation["sensors"] == mine["sensors"]).all()
        assert (observation["collision"] == mine["collision"]).all()
        assert info["task_reward"] == native_info["task_reward"] and reward == native_reward
        assert (terminated, truncated) == (native_terminated, native_truncated)
        collisions += int(info["collided"])
        if terminated or truncated:
            observation, _ = env.reset()
            mine, _ = native.reset()
    assert collisions > 0  # the comparison saw collisions
