"""``compare``, ``dependencies`` and ``minigrid`` keep their numbers (as ``test_paper_figures``
does for ``paper``): the tabular methods' results at tiny budgets, stored in
``tests/data/command_figures.json`` by ``tests/command_figures.py`` before the commands moved onto
the runner, must come back exactly; the networks' (DQN, Factor-DQN) are float computations whose
last bits depend on the CPU, so only their results' structure is checked.
"""

from __future__ import annotations

import importlib.util
import json
import os

import command_figures
import pytest

from factorq_trainers.commands.compare import command as compare
from factorq_trainers.commands.dependencies import command as dependencies
from factorq_trainers.commands.minigrid import command as minigrid
from factorq_trainers.compiled import fast

STORED = json.loads(command_figures.DATA.read_text())
DEVNULL = {"out": os.devnull}


def _same(name: str, exact: dict) -> None:
    stored = STORED[name]
    if command_figures.digest(exact) != stored["sha256"]:  # the first difference, named
        assert exact == stored["exact"]
    assert command_figures.digest(exact) == stored["sha256"]


def test_compare_tabular_methods_give_the_stored_numbers(one_thread):
    results = compare.run(compare.CompareConfig(**STORED["compare"]["config"], **DEVNULL))
    _same("compare", command_figures.compare_exact(results))


@pytest.mark.skipif(not fast.is_available(), reason="fast backend unavailable")
def test_dependencies_give_the_stored_numbers():
    config = dependencies.DependenciesConfig(**STORED["dependencies"]["config"], **DEVNULL)
    _same("dependencies", command_figures.dependencies_exact(dependencies.run(config)))


@pytest.mark.skipif(importlib.util.find_spec("minigrid") is None, reason="minigrid extra missing")
def test_minigrid_tabular_methods_give_the_stored_numbers():
    config = minigrid.MiniGridConfig(**STORED["minigrid"]["config"], **DEVNULL)
    _same("minigrid", command_figures.minigrid_exact(minigrid.run(config)))


def test_the_networks_results_keep_their_structure(one_thread):
    config = compare.CompareConfig(
        seeds=2, steps=300, methods=("dqn", "factor-dqn"), regimes=("static",), **DEVNULL
    )
    results = compare.run(config)
    tabular = STORED["compare"]["exact"]["results"]["factor-q"]["static"]
    for method in ("dqn", "factor-dqn"):
        entry = results["results"][method]["static"]
        assert set(
            command_figures.compare_exact({"results": {"m": entry}, "curves": {}})["results"]["m"]
        ) == set(tabular)
        assert len(entry["steps_to_threshold_per_seed"]) == 2
        assert len(results["curves"][method]["static"]["steps"]["mean"]) == compare.CURVE_POINTS


@pytest.mark.skipif(importlib.util.find_spec("minigrid") is None, reason="minigrid extra missing")
def test_minigrid_networks_results_keep_their_structure():
    config = minigrid.MiniGridConfig(
        **{**STORED["minigrid"]["config"], "methods": ("dqn",), "seeds": 1}, **DEVNULL
    )
    entry = minigrid.run(config)["results"]["5"]["dqn"]
    tabular = STORED["minigrid"]["exact"]["results"]["5"]["q-learning"]
    assert set(entry["seeds"]) - {"found_forward_front"} == set(tabular["seeds"]) | {"wall_s"}
    assert set(entry["summary"]) <= set(tabular["summary"]) | {"wall_s"}
