"""The DQN baseline: torchrl's pieces on the batched worlds, its exploration flag, its keys."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from factorq_torch.base.rng import STREAM_WORLD
from factorq_trainers.methods import dqn, experiment

#: outcomes that depend on float rounding: `make test` reruns these under other CPU kernels
pytestmark = pytest.mark.float_sensitive


def test_exploratory_egreedy_flags_exactly_the_actions_the_epsilon_branch_drew():
    torch.manual_seed(0)
    explore = dqn.ExploratoryEGreedy(eps_init=0.5, eps_end=0.5, annealing_num_steps=1)
    greedy = torch.full((4000,), 2)
    td = explore(TensorDict(action=greedy.clone(), batch_size=[4000]))
    action, exploratory = td["action"], td["exploratory"]
    assert torch.equal(action[~exploratory], greedy[~exploratory])  # greedy where not drawn
    assert 0.45 < exploratory.float().mean() < 0.55  # drawn with probability eps
    # A drawn action is uniform over all four, the greedy one included (still exploratory).
    counts = torch.bincount(action[exploratory], minlength=4).float() / exploratory.sum()
    assert (counts > 0.2).all() and (counts < 0.3).all()


def test_exploratory_egreedy_anneals_itself_once_per_call():
    explore = dqn.ExploratoryEGreedy(eps_init=1.0, eps_end=0.2, annealing_num_steps=4)
    td = TensorDict(action=torch.zeros(3, dtype=torch.int64), batch_size=[3])
    for expected in (0.8, 0.6, 0.4, 0.2, 0.2):
        explore(td.clone())
        assert float(explore.eps) == pytest.approx(expected)


def test_experiment_keys_do_not_depend_on_what_else_is_selected():
    everything = experiment.ExperimentConfig(seed=4, seeds=3)
    dynamic_only = experiment.ExperimentConfig(seed=4, seeds=3, regimes=("dynamic",))
    all_keys = dqn.batch_keys(everything, STREAM_WORLD, "dqn")
    assert torch.equal(dqn.batch_keys(dynamic_only, STREAM_WORLD, "dqn"), all_keys[6:])
    other_method = dqn.batch_keys(everything, STREAM_WORLD, "factor-dqn")
    assert not torch.equal(other_method, all_keys)


def test_config_names_the_option_and_its_range():
    with pytest.raises(ValueError, match=r"lr=0 is out of range: must be in \(0.0, 1.0\]"):
        dqn.DQNConfig(lr=0)
    with pytest.raises(ValueError, match="eps_end=0.5 is out of range: must be <= eps_start=0.2"):
        dqn.DQNConfig(eps_start=0.2, eps_end=0.5)
    with pytest.raises(TypeError, match="batch_size must be an int"):
        dqn.DQNConfig(batch_size=1.5)


def test_dqn_learns_a_tiny_static_world_better_than_random(one_thread):
    experiments = experiment.ExperimentConfig(
        seeds=2, regimes=("static",), steps=1500, size=4, obstacles=2, seed=3
    )
    config = dqn.DQNConfig(learning_starts=100, train_every=1, exploration_fraction=0.3)
    results = dqn.run(config, experiments)
    # A uniformly random walk from corner to corner of a 4x4 grid takes ~40 steps on average
    # (the first episodes here, at epsilon ~1, are such walks); the shortest path is 6.
    for trace in results["traces"]:
        last = trace["steps"][trace["env_steps"] > 1200]
        assert last.size > 0 and last.mean() < 15
        assert np.all(np.diff(trace["env_steps"]) > 0)  # env steps so far, per episode
        assert trace["steps"].sum() <= experiments.steps == trace["total_env_steps"]
        assert trace["epsilon"][-1] == pytest.approx(config.eps_end)
        assert np.isfinite(trace["loss"][-1])
