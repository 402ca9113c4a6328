"""The pieces every experiment is built from: keys, world options, env, agents, episode records."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import TransformedEnv

from factorq_torch.base.config import AgentConfig
from factorq_torch.base.rng import STREAM_POLICY, STREAM_WORLD, derive_keys
from factorq_torch.objectives import FactorQLoss, TabularQLoss
from factorq_trainers.methods import experiment


def test_keys_are_numbered_3i_plus_w_and_per_variant_v_times_that_plus_v():
    labels = [("dynamic", 0), ("static", 1), ("semi-dynamic", 2)]
    world = derive_keys(7, STREAM_WORLD, 9)  # slots 3 i + w: 0*3 + 2, 1*3 + 0, 2*3 + 1
    assert torch.equal(experiment.experiment_keys(7, STREAM_WORLD, labels), world[[2, 3, 7]])
    policy = derive_keys(7, STREAM_POLICY, 16)  # slots 2 (3 i + w) + 1 for the second variant
    keys = experiment.experiment_keys(7, STREAM_POLICY, labels, ("a", "b"), "b")
    assert torch.equal(keys, policy[[5, 7, 15]])


def test_world_options_are_named_as_the_config_spells_them():
    with pytest.raises(ValueError, match=r"obstacles=7 is out of range: must be in \[0, 6\]"):
        experiment.check_world_options(3, 7, 10, 0, ())
    with pytest.raises(ValueError, match="obstacles=6 leaves no path from start to goal"):
        experiment.check_world_options(3, 6, 10, 0, ("static",))
    experiment.check_world_options(3, 6, 10, 0, ("dynamic",))  # moving worlds need no path
    with pytest.raises(TypeError, match="obstacles must be an int"):
        experiment.check_world_options(3, 2.5, 10, 0, ())
    with pytest.raises(ValueError, match=r"layout_seed=-1 is out of range: must be in \[0, 9"):
        experiment.check_world_options(3, 1, 10, -1, ())


def test_env_has_one_period_and_one_given_world_key_per_experiment():
    world = experiment.check_world_options(4, 2, 50, 0, ())
    keys = torch.tensor([11, 22, 33])
    env = experiment.make_env(world, [0, 10, 1], keys)
    assert env.batch_size == torch.Size([3]) and env.periods.tolist() == [0, 10, 1]
    assert torch.equal(env.world_keys, keys)


def test_factor_q_learns_from_the_split_reward_and_q_learning_from_the_plain_one():
    world = experiment.check_world_options(4, 2, 50, 0, ())
    keys = torch.arange(2)
    for algorithm, loss_type, split in (
        ("q-learning", TabularQLoss, False),
        ("factor-q", FactorQLoss, True),
    ):
        env = experiment.make_env(world, [0, 1], keys)
        task, local = experiment.tabular_values(algorithm, 2, world)
        assert (local is not None) == split
        env, policy, loss = experiment.online_agent(env, task, local, AgentConfig(), keys)
        assert isinstance(env, TransformedEnv) == split and isinstance(loss, loss_type)
        td = policy(env.reset())
        assert td["action"].shape == (2,) and td["exploratory"].dtype == torch.bool


def test_experiment_config_names_the_option_and_its_range():
    with pytest.raises(ValueError, match="regimes: 'windy' is unknown"):
        experiment.ExperimentConfig(regimes=("static", "windy"))
    with pytest.raises(ValueError, match="obstacles=200 is out of range"):
        experiment.ExperimentConfig(obstacles=200)


def test_recorder_counts_greedy_collisions_only_on_non_exploratory_actions():
    recorder = experiment.EpisodeRecorder([("static", 0), ("dynamic", 0)])

    def step(bump, exploratory, done, reward, boxed_in=(False, False)):
        next_td = TensorDict(
            bump=torch.tensor(bump),
            reward=torch.tensor(reward).unsqueeze(-1),
            collision=-torch.tensor(bump, dtype=torch.float32),
            done=torch.tensor(done).unsqueeze(-1),
            batch_size=[2],
        )
        proximity = torch.tensor(bump) | torch.tensor(boxed_in).unsqueeze(-1)  # sensed, then hit
        td = TensorDict(
            exploratory=torch.tensor(exploratory), proximity=proximity, next=next_td, batch_size=[2]
        )
        recorder.update(td, epsilon=0.1, loss=torch.tensor([1.0, float("nan")]))

    no_bump, north = [False] * 4, [True, False, False, False]
    step([north, north], [True, False], [False, False], [-2.0, -2.0])  # exploratory / greedy
    step([no_bump, north], [False, False], [True, False], [0.0, -2.0], (False, True))  # boxed in
    traces = recorder.traces()
    first = traces[0]
    assert first["steps"].tolist() == [2] and first["env_steps"].tolist() == [2]
    assert first["collisions"].tolist() == [1] and first["greedy_collisions"].tolist() == [0]
    assert first["task_return"].tolist() == [-1.0]  # conventional -2 + 0, collisions removed
    assert first["loss"].tolist() == [1.0]
    assert traces[1]["steps"].size == 0  # unfinished: no episode, but its collisions count
    assert traces[1]["total_collisions"] == 2 and traces[1]["total_greedy_collisions"] == 2
    assert traces[1]["total_boxed_in_greedy_collisions"] == 1  # all four sensors set
