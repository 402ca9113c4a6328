"""The paper's experiment: config validation, keys, run() on tiny budgets, the modular path."""

from __future__ import annotations

import json
import math
from dataclasses import fields

import numpy as np
import pytest
import torch

from factorq_envs.regimes import REGIMES
from factorq_torch.base.config import ALGORITHMS
from factorq_trainers.commands.paper import command as paper
from factorq_trainers.commands.paper import drivers as paper_drivers
from factorq_trainers.commands.paper.config import PaperConfig
from factorq_trainers.commands.paper.schema import results_problem
from factorq_trainers.compiled import fast, loader
from factorq_trainers.runner import frame
from factorq_trainers.runner.results import SCHEMA_VERSION
from factorq_trainers.runner.results import dumps as dumps_results

needs_fast = pytest.mark.skipif(not fast.is_available(), reason="fast backend unavailable")
TINY = {"seeds": 2, "runs": 2, "episodes": 3, "size": 5, "obstacles": 3}


# --------------------------------------------------------------------------------------------
# Config


@pytest.mark.parametrize(
    ("options", "error", "message"),
    [
        ({"seeds": 0}, ValueError, "seeds=0 is out of range: must be in [1, 2147483647]"),
        ({"seeds": -3}, ValueError, "seeds=-3"),
        ({"runs": 0}, ValueError, "runs=0"),
        ({"episodes": -1}, ValueError, "episodes=-1"),
        ({"seed": -1}, ValueError, "seed=-1"),
        ({"max_steps": 0}, ValueError, "max_steps=0"),
        ({"seeds": 2.5}, TypeError, "seeds must be an int"),
        ({"runs": True}, TypeError, "runs must be an int"),
        ({"regimes": ("static", "windy")}, ValueError, "'windy' is unknown"),
        ({"regimes": ("static", "static")}, ValueError, "static given more than once"),
        ({"regimes": ()}, ValueError, "regimes is empty"),
        ({"methods": ("sarsa",)}, ValueError, "'sarsa' is unknown"),
        ({"size": 1}, ValueError, "size=1"),
        ({"size": 3, "obstacles": 7}, ValueError, "obstacles=7 is out of range: must be in [0, 6]"),
        ({"size": 3, "obstacles": 6}, ValueError, "obstacles=6"),  # no static layout with a path
        ({"obstacles": -1}, ValueError, "obstacles=-1"),
        ({"epsilon": 1.5}, ValueError, "epsilon=1.5"),
        ({"gamma": 1.0}, ValueError, "gamma=1.0"),
        ({"alpha": 0.0}, ValueError, "alpha=0.0"),
        ({"g_min": 0.0}, ValueError, "g_min=0.0"),
        ({"threads": 0}, ValueError, "threads=0"),
        ({"backend": "gpu"}, ValueError, "backend='gpu' is unknown"),
        ({"device": "toaster"}, ValueError, "device='toaster' is not a torch device"),
        ({"backend": "fast", "device": "cuda"}, ValueError, "not supported by backend 'fast'"),
    ],
)
def test_config_rejects_invalid_values_naming_option_and_range(options, error, message):
    with pytest.raises(error) as raised:
        PaperConfig(**options)
    assert message in str(raised.value)


def test_config_rejects_an_out_that_is_an_existing_file(tmp_path):
    existing = tmp_path / "results.txt"
    existing.write_text("not a directory")
    with pytest.raises(ValueError, match="is an existing file"):
        PaperConfig(out=str(existing))


def test_config_defaults_are_the_papers_experiment_with_100_seeds():
    config = PaperConfig()
    assert (config.seeds, config.runs, config.episodes) == (100, 10, 200)
    assert (config.size, config.obstacles, config.max_steps) == (10, 10, 10_000)
    assert config.regimes == ("static", "semi-dynamic", "dynamic")
    assert config.methods == ("q-learning", "factor-q")
    assert config.agent.epsilon == 0.01 and config.agent.gamma == 0.9 and config.agent.alpha == 0.2


def test_config_takes_names_in_any_order_or_comma_separated_and_keeps_canonical_order():
    assert PaperConfig(regimes="dynamic, static").regimes == ("static", "dynamic")
    assert PaperConfig(methods=["factor-q", "q-learning"]).methods == (
        "q-learning",
        "factor-q",
    )


def test_every_config_field_has_a_one_line_doc_for_help():
    for field in fields(PaperConfig):
        assert field.metadata.get("doc"), f"{field.name} has no docstring"
        assert "\n" not in field.metadata["doc"]


def test_config_round_trips_through_its_json_dict():
    config = PaperConfig(seeds=3, regimes=("static",), threads=2)
    data = json.loads(json.dumps(frame.plain(config)))
    assert frame.config_from_dict(PaperConfig, data) == config


# --------------------------------------------------------------------------------------------
# Keys


def test_keys_of_a_seed_and_world_do_not_depend_on_what_else_is_selected():
    full = PaperConfig(seeds=3)
    part = PaperConfig(seeds=5, regimes=("dynamic",))
    for algorithm in ("q-learning", "factor-q"):
        periods, world_keys, policy_keys = paper_drivers.experiment_keys(full, algorithm)
        part_periods, part_world, part_policy = paper_drivers.experiment_keys(part, algorithm)
        # full is ordered world-major: dynamic is the third block of 3 seeds
        assert torch.equal(periods[6:], torch.ones(3, dtype=periods.dtype))
        assert torch.equal(world_keys[6:], part_world[:3])
        assert torch.equal(policy_keys[6:], part_policy[:3])
        assert torch.equal(part_periods, torch.ones(5, dtype=periods.dtype))


def test_both_algorithms_share_world_keys_but_not_policy_keys():
    config = PaperConfig(seeds=4)
    _, world_q, policy_q = paper_drivers.experiment_keys(config, "q-learning")
    _, world_f, policy_f = paper_drivers.experiment_keys(config, "factor-q")
    assert torch.equal(world_q, world_f)  # common random numbers for the worlds
    assert len(set(policy_q.tolist()) | set(policy_f.tolist())) == 2 * policy_q.numel()
    assert len(set(world_q.tolist())) == world_q.numel()


# --------------------------------------------------------------------------------------------
# run() on tiny budgets


@pytest.fixture(scope="module")
def tiny_results():
    if not fast.is_available():
        pytest.skip("fast backend unavailable")
    return paper.run(PaperConfig(**TINY))


@needs_fast
def test_run_returns_the_results_schema(tiny_results):
    seeds, episodes = TINY["seeds"], TINY["episodes"]
    assert list(tiny_results) == [
        "schema_version",
        "command",
        "config",
        "software",
        "timing",
        "cells",
        "claims",
        "statistics",
    ]
    assert tiny_results["schema_version"] == SCHEMA_VERSION
    assert results_problem(tiny_results) is None
    assert tiny_results["config"] == frame.plain(PaperConfig(**TINY))
    assert list(tiny_results["cells"]) == [
        f"{world}/{algorithm}" for world in REGIMES for algorithm in ALGORITHMS
    ]
    for cell in tiny_results["cells"].values():
        for name in ("total_steps", "collisions", "greedy_collisions", "task_return"):
            assert len(cell["per_seed"][name]) == seeds
            assert set(cell["summary"][name]) == {"mean", "ci95"}
        for name in ("steps", "collisions", "greedy_collisions"):
            for key in ("curves", "curves_ci_low", "curves_ci_high"):
                assert len(cell[key][name]) == episodes
        # a run's total steps is the sum of its episodes' steps: the curve sums to it
        assert math.isclose(sum(cell["curves"]["steps"]), np.mean(cell["per_seed"]["total_steps"]))
        greedy, collisions = cell["per_seed"]["greedy_collisions"], cell["per_seed"]["collisions"]
        assert all(g <= c for g, c in zip(greedy, collisions, strict=True))
    assert list(tiny_results["claims"]) == ["C1", "C2", "C3", "C4", "C5"]
    for claim in tiny_results["claims"].values():
        assert isinstance(claim["pass"], bool)
        assert {"value", "ci95", "detail", "statement", "threshold", "measures"} <= set(claim)
    assert tiny_results["timing"]["wall_s"] > 0
    assert {"python", "torch", "torchrl", "numpy", "platform"} <= set(tiny_results["software"])


@needs_fast
def test_same_seed_gives_identical_results_apart_from_timing(tiny_results):
    again = paper.run(PaperConfig(**TINY, threads=1))  # the thread count changes nothing either
    first, second = dict(tiny_results), dict(again)
    first.pop("timing"), second.pop("timing")
    first["config"] = second["config"] = None  # threads differs in the config only
    assert dumps_results(first) == dumps_results(second)


@needs_fast
def test_another_seed_gives_other_numbers(tiny_results):
    other = paper.run(PaperConfig(**TINY, seed=1))
    assert other["cells"] != tiny_results["cells"]


@needs_fast
def test_a_seeds_results_do_not_depend_on_the_number_of_seeds_or_worlds(tiny_results):
    more = paper.run(PaperConfig(**{**TINY, "seeds": 3, "regimes": ("dynamic",)}))
    for algorithm in ("q-learning", "factor-q"):
        few = tiny_results["cells"][f"dynamic/{algorithm}"]["per_seed"]
        many = more["cells"][f"dynamic/{algorithm}"]["per_seed"]
        for name, values in few.items():
            assert many[name][:2] == values


@needs_fast
def test_run_reports_progress_up_to_every_episode_and_experiment():
    reports: list[int] = []
    paper.run(PaperConfig(**{**TINY, "regimes": ("static",)}), progress=reports.append)
    assert all(episodes >= 0 for episodes in reports)
    assert sum(reports) == 2 * TINY["seeds"] * TINY["runs"] * TINY["episodes"]


def test_modular_torchrl_backend_gives_the_same_results_as_the_fast_path(tiny_results):
    # The same keys drive both: the collector (env + tables + policy + loss) and the C kernel
    # must agree exactly on every per-seed number, curve and claim.
    modular = paper.run(PaperConfig(**TINY, backend="modular"))
    assert modular["timing"]["backend"] == "modular"
    assert tiny_results["timing"]["backend"] == "fast"
    first, second = dict(tiny_results), dict(modular)
    for results in (first, second):
        results.pop("timing")
    first["config"] = second["config"] = None  # the backend field differs in the config only
    assert dumps_results(first) == dumps_results(second)


def test_without_a_compiler_auto_says_why_once_and_records_what_ran(monkeypatch, capsys):
    # No compiler: auto runs the modular path, says so once at the start (why, how long, how to
    # get the fast path) and results.json records the backend and the threads actually used.
    monkeypatch.setattr(loader, "_load", lambda: None)
    monkeypatch.setattr(loader, "_reason", "no C compiler found (test)")
    config = PaperConfig(**{**TINY, "regimes": ("static",), "threads": None})
    results = paper.run(config)
    err = capsys.readouterr().err
    assert err.count("the compiled fast path is unavailable (no C compiler found (test))") == 1
    assert "roughly" in err and "FACTORQ_CC" in err
    timing = results["timing"]
    assert timing["backend"] == "modular"
    assert timing["threads"] == 1  # the modular path's one intra-op thread per unit
    assert timing["fast_unavailable"] == "no C compiler found (test)"
    assert results_problem(results) is None
