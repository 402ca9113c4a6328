"""``factorq dependencies`` (issue 12): the experiment, its files, its options, its env hook."""

from __future__ import annotations

import dataclasses
import json

import pytest
import torch
from torchrl.envs import TransformedEnv

from factorq_envs import FactoredGridEnv
from factorq_envs.grid_world import WorldConfig
from factorq_envs.permutation import PermuteSensors, permuted_dependency
from factorq_torch.base.config import AgentConfig
from factorq_torch.base.rng import derive_keys
from factorq_trainers import cli
from factorq_trainers.commands.dependencies import command as dependencies
from factorq_trainers.commands.dependencies import config as dependencies_config
from factorq_trainers.commands.dependencies import methods as dependencies_methods
from factorq_trainers.commands.dependencies import report as dependencies_report
from factorq_trainers.compiled import fast
from factorq_trainers.runner import frame

TINY = dict(seeds=2, size=4, obstacles=2, runs=2, episodes=1, change_run=1, max_steps=200)


def test_permute_sensors_reorders_each_experiment_and_can_be_redrawn():
    base = FactoredGridEnv(size=3, num_obstacles=0, batch_size=(2,))
    orders = torch.tensor([[1, 2, 3, 0], [0, 1, 2, 3]])
    transform = PermuteSensors(orders)
    env = TransformedEnv(base, transform)
    raw = base.reset()["sensors"]
    assert torch.equal(env.reset()["sensors"], raw.gather(-1, orders))
    transform.set_permutations(torch.tensor([[0, 1, 2, 3], [3, 2, 1, 0]]), torch.tensor([0, 1]) > 0)
    assert torch.equal(env.reset()["sensors"][1], raw[1].flip(0))
    with pytest.raises(ValueError, match="permutation"):
        PermuteSensors(torch.tensor([[0, 0, 1, 2]]))


def test_permuted_dependency_follows_the_order():
    dependency = torch.eye(3, dtype=torch.bool)
    got = permuted_dependency(dependency, torch.tensor([[2, 0, 1]]))
    # agent's sensor j is sensor order[j]: actuator 2's sensor 2 arrives as sensor 0
    assert got[0].nonzero().tolist() == [[0, 1], [1, 2], [2, 0]]


def test_compiled_path_takes_a_dependency_and_the_true_one_changes_nothing():
    world = WorldConfig(size=5, num_obstacles=3, sensors="ring")
    arguments = (torch.zeros(3, dtype=torch.int64), world, AgentConfig(), 2, 2)
    keys = (derive_keys(0, 1, 3), derive_keys(0, 2, 3))
    plain = fast.run_experiments("factor-q", *arguments, *keys)
    same = fast.run_experiments("factor-q", *arguments, *keys, dependency=world.dependency)
    assert all(torch.equal(plain[name], same[name]) for name in plain)
    joint = fast.run_experiments(
        "factor-q", *arguments, *keys, dependency=torch.ones(4, 8, dtype=torch.bool)
    )
    assert int(joint["steps"].sum()) > 0


def test_a_tiny_experiment_writes_its_three_files(tmp_path):
    config = dependencies.DependenciesConfig(
        **TINY, settings=("cross", "ring-24", "change"), out=str(tmp_path)
    )
    results = dependencies.run(config)
    paths = frame.write_outputs(dependencies, results, tmp_path)
    assert {path.name for path in paths.values()} == {
        "dependencies.json",
        "dependencies.md",
        "dependencies.png",
    }
    saved = json.loads(paths["json"].read_text())
    cross = saved["settings"]["cross"]
    assert set(cross["methods"]) == {"factor-q-learned", "factor-q", "factor-q-joint", "q-learning"}
    assert "samples_until_right_median" in cross["structure"]
    assert "collisions" in cross["against_oracle"]
    assert (
        "factor-q-joint" in saved["skipped"]["ring-24"]
        and "q-learning" in saved["skipped"]["ring-24"]
    )
    assert "change" not in saved["skipped"]  # the joint table runs through the change too
    assert "factor-q-joint" in saved["settings"]["change"]["methods"]
    assert "| cross |" in paths["report"].read_text()


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"bayes_factor": 1.0}, "bayes_factor=1.0 must be > 1"),
        ({"max_parents": 3}, "max_parents=3 is past the cap"),
        ({"settings": ("nope",)}, "settings"),
        ({"change_run": 5, "runs": 5}, "change_run"),
        ({"prior_a": 0.0}, "prior_a=0.0 must be a finite number > 0"),
        ({"prior_b": -1.0}, "prior_b=-1.0 must be a finite number > 0"),
        ({"prior_a": float("inf")}, "prior_a=inf must be a finite number > 0"),
        ({"prior_b": 0.1}, "prior_b=0.1: the compiled path .* multiple of 1/1024"),
        ({"prior_a": 2.0**20}, "prior_a=1048576.0: the compiled path"),
        ({"reopen_factor": 1.0}, "reopen_factor=1.0 is out of range"),
        ({"reopen_factor": float("nan")}, "reopen_factor=nan is out of range"),
        ({"noisy_reopen_factor": 0.5}, "noisy_reopen_factor=0.5 is out of range"),
    ],
)
def test_bad_options_are_one_clear_error(options, message):
    with pytest.raises(ValueError, match=message):
        dependencies.DependenciesConfig(**options)


def test_a_body_without_local_rewards_is_refused(monkeypatch):
    monkeypatch.setitem(
        dependencies_config.SETTINGS, "cross", {"body": "translate", "sensors": "cross"}
    )
    no_collisions = torch.zeros(4, 4, dtype=torch.bool)
    monkeypatch.setattr(WorldConfig, "dependency", property(lambda self: no_collisions))
    with pytest.raises(ValueError, match="without local rewards"):
        dependencies.DependenciesConfig(settings=("cross",))


def test_cli_refuses_a_bayes_factor_of_one(capsys):
    assert cli.main(["dependencies", "--bayes-factor", "1"]) == 2
    assert "--bayes-factor=1.0 must be > 1" in capsys.readouterr().err


def test_cli_refuses_a_reopen_factor_of_one_and_reports_a_given_one(capsys, tmp_path):
    assert cli.main(["dependencies", "--reopen-factor", "1"]) == 2
    assert "--reopen-factor=1.0 is out of range" in capsys.readouterr().err
    config = dependencies.DependenciesConfig(reopen_factor=1e4)
    assert dependencies_methods._learner_options(config)["reopen_factor"] == 1e4
    results = {"config": dataclasses.asdict(config), "timing": {"wall_s": 1.0}}
    results["settings"] = {}
    assert "reopening at Bayes factor 10000" in dependencies_report.markdown(results)
    assert "at 10000 once sensors read wrong" in dependencies_report.markdown(results)
    config = dependencies.DependenciesConfig(noisy_reopen_factor=None)
    results["config"] = dataclasses.asdict(config)
    assert "once sensors read wrong" not in dependencies_report.markdown(results)
    assert dependencies_methods._learner_options(config)["noisy_reopen_factor"] is None


def test_cli_refuses_a_prior_the_compiled_path_cannot_take(capsys):
    assert cli.main(["dependencies", "--prior-a", "0.1"]) == 2
    assert "--prior-a=0.1: the compiled path" in capsys.readouterr().err
    # the modular path takes it (nothing runs: the check is the config's)
    config = dependencies.DependenciesConfig(prior_a=0.1, path="modular")
    assert dependencies_methods._learner_options(config)["prior_a"] == 0.1


def test_the_priors_reach_the_learner(tmp_path):
    """A sharper prior is a different learner: the same worlds give other structure metrics."""
    common = dict(TINY, settings=("cross",), methods=("factor-q-learned",), out=str(tmp_path))
    plain = dependencies_methods.run_learned(dependencies.DependenciesConfig(**common), "cross")
    sharp = dependencies_methods.run_learned(
        dependencies.DependenciesConfig(**common, prior_a=1 / 16, prior_b=1 / 16), "cross"
    )
    assert not torch.equal(plain["_state"]["log_marginal"], sharp["_state"]["log_marginal"])


def test_cli_keeps_earlier_results_unless_forced(tmp_path, capsys):
    (tmp_path / "dependencies.json").write_text("{}")
    assert cli.main(["dependencies", "--out", str(tmp_path)]) == 2
    assert "already holds dependencies.json from an earlier run" in capsys.readouterr().err
    assert (tmp_path / "dependencies.json").read_text() == "{}"


@pytest.mark.float_sensitive
def test_dqn_is_opt_in_and_runs_on_the_oracles_budget(tmp_path):
    config = dependencies.DependenciesConfig(
        **{**TINY, "max_steps": 30},
        settings=("cross", "change"),
        methods=("factor-q", "dqn"),
        out=str(tmp_path),
    )
    assert "dqn" not in dependencies.DependenciesConfig().methods
    results = dependencies.run(config)
    entry = results["settings"]["cross"]["methods"]["dqn"]
    oracle = results["settings"]["cross"]["methods"]["factor-q"]
    assert entry["step_budget"] == round(oracle["steps_per_run"] * TINY["runs"])
    assert entry["collisions_per_experiment"] >= 0
    assert "dqn" in results["skipped"]["change"]
    assert "DQN in cross: a budget of" in dependencies_report.markdown(results)


def test_unknown_methods_and_predictions_are_refused():
    with pytest.raises(ValueError, match="methods"):
        dependencies.DependenciesConfig(methods=("nope",))
    with pytest.raises(ValueError, match="prediction='nope'"):
        dependencies.DependenciesConfig(prediction="nope")


def test_the_noisy_settings_have_many_sensors_and_the_likelihood_reaches_the_learner(tmp_path):
    # issue 27: ring sensors and 12 distractors (20 sensors) at 5% and 10% sensor noise
    config = dependencies.DependenciesConfig(**TINY, out=str(tmp_path))
    for name, noise in (("ring-12-noise-5", 0.05), ("ring-12-noise-10", 0.10)):
        world = config.world_of(name)
        assert (world.num_sensors, world.sensor_noise) == (20, noise)
    assert dependencies.DependenciesConfig().likelihood == "mixture"
    common = dict(TINY, settings=("noise-10",), methods=("factor-q-learned",), out=str(tmp_path))
    states = {
        likelihood: dependencies_methods.run_learned(
            dependencies.DependenciesConfig(**common, likelihood=likelihood), "noise-10"
        )["_state"]
        for likelihood in ("mixture", "pattern")
    }
    # the same worlds: the counts of the first firings agree, the log marginals do not
    assert not torch.equal(states["mixture"]["log_marginal"], states["pattern"]["log_marginal"])
    with pytest.raises(ValueError, match="likelihood='nope'"):
        dependencies.DependenciesConfig(likelihood="nope")


def test_the_gated_network_is_opt_in_and_reports_its_structure(tmp_path, one_thread):
    config = dependencies.DependenciesConfig(
        **{**TINY, "max_steps": 30, "runs": 1},
        settings=("cross",),
        methods=("factor-q", "factor-q-gated"),
        out=str(tmp_path),
    )
    assert "factor-q-gated" not in dependencies.DependenciesConfig().methods
    results = dependencies.run(config)
    gated = results["settings"]["cross"]["gated_structure"]
    assert 0.0 <= gated["fraction_right_at_end"] <= 1.0
    world = config.world_of("cross")  # at most every (actuator, sensor) wrong
    assert 0 <= gated["hamming_at_end_mean"] <= world.num_actuators * world.num_sensors
    assert "collisions" in results["settings"]["cross"]["gated_against_oracle"]
    assert "| cross, gated network |" in dependencies_report.markdown(results)


def test_a_settings_streams_derive_from_its_content_not_its_position(monkeypatch):
    config = dependencies.DependenciesConfig(seeds=2, runs=2, change_run=1)
    before = {name: config.setting_stream(name) for name in config.settings}
    assert len(set(before.values())) == len(before)  # change differs from cross by its change
    custom = dependencies.DependenciesConfig(body="translate", sensors="cross", seeds=2)
    assert custom.settings == ("custom",)
    assert custom.setting_stream("custom") == before["cross"]  # the same content
    monkeypatch.setattr(
        dependencies_config,
        "SETTINGS",
        {"new": {"body": "heading"}, **dependencies_config.SETTINGS},
    )
    assert {name: config.setting_stream(name) for name in config.settings} == before


def test_body_options_declare_the_custom_setting(tmp_path):
    config = dependencies.DependenciesConfig(
        **TINY, body="heading", distractors=2, out=str(tmp_path)
    )
    assert config.settings == ("custom",)
    world = config.world_of("custom")
    assert world.num_headings == 4 and world.num_sensors == 4 + 2
    with pytest.raises(ValueError, match="declare the setting 'custom'"):
        dependencies.DependenciesConfig(settings=("cross",), sensor_noise=0.1)
    with pytest.raises(ValueError, match="'custom' needs"):
        dependencies.DependenciesConfig(settings=("custom",))


def test_the_summary_shows_the_absolute_task_measures_beside_the_ratios():
    # two experiments, one run of two episodes each: a truncated episode (1,000 steps, return
    # -1,000) and three that reached the goal (return -steps + 1)
    config = dependencies.DependenciesConfig(**TINY, out="unused")
    metrics = {
        "steps": torch.tensor([[[1000, 10]], [[20, 30]]]),
        "task_return": torch.tensor([[[-1000.0, -9.0]], [[-19.0, -29.0]]]),
        "collisions": torch.zeros(2, 1, 2, dtype=torch.int64),
        "greedy_collisions": torch.zeros(2, 1, 2, dtype=torch.int64),
    }
    gated = {"metrics": metrics, "right_at_end": [True, True], "hamming_at_end": [0, 0]}
    runs = {"factor-q": {"metrics": metrics}, "q-learning": {"metrics": metrics}}
    summary = dependencies.summarise_setting(config, "cross", {**runs, "factor-q-gated": gated})
    oracle = summary["methods"]["factor-q"]
    assert oracle["steps_per_episode"] == (1000 + 10 + 20 + 30) / 4  # 265
    assert oracle["fraction_truncated"] == 0.25
    absolute = summary["gated_against_oracle"]["absolute"]
    assert absolute["steps_per_episode"] == {"factor-q-gated": 265.0, "factor-q": 265.0}
    assert absolute["fraction_truncated"] == {"factor-q-gated": 0.25, "factor-q": 0.25}
    del summary["methods"]["factor-q-gated"], summary["gated_structure"]
    del summary["gated_against_oracle"]
    text = dependencies_report.markdown(
        {
            "config": dataclasses.asdict(config),
            "settings": {"cross": summary},
            "methods": {"factor-q": "Factor-Q", "q-learning": "Q-learning"},  # the labels
            "timing": {"wall_s": 1.0},
        }
    )
    assert "| cross | Factor-Q | 0 | 0 | 530 | 265 | 25% |" in text
    assert "uniform exploration" in text


def test_every_setting_runs_in_each_regime_with_the_numbers_of_a_run_of_that_regime(tmp_path):
    """``--regimes static,dynamic``: one entry per setting x regime, keyed ``setting/regime``;
    each equals the entry of a run of that regime alone (its worlds are keyed by the regime)."""
    common = dict(TINY, settings=("cross",), methods=("factor-q", "q-learning"))
    config = dependencies.DependenciesConfig
    both = dependencies.run(config(**common, regimes=("static", "dynamic"), out=str(tmp_path)))
    assert list(both["settings"]) == ["cross/static", "cross/dynamic"]
    for regime in ("static", "dynamic"):
        alone = dependencies.run(config(**common, regimes=(regime,), out=str(tmp_path / regime)))
        assert list(alone["settings"]) == ["cross"]
        assert alone["settings"]["cross"] == both["settings"][f"cross/{regime}"]
    static, dynamic = (both["settings"][f"cross/{r}"]["methods"] for r in ("static", "dynamic"))
    assert static != dynamic  # the regime reaches the worlds
    with pytest.raises(ValueError, match="regimes"):
        config(**common, regimes=("windy",))
