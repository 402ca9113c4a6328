"""The local-risk layer for Stable-Baselines3's DQN (factorq_torch/integrations/sb3.py).

Skipped without the ``sb3`` extra."""

import importlib
import sys

import gymnasium
import numpy as np
import pytest
import torch

pytest.importorskip("stable_baselines3")

from stable_baselines3 import DQN  # noqa: E402
from stable_baselines3.common.callbacks import BaseCallback  # noqa: E402

import factorq_envs  # noqa: E402, F401  (registers FactoredGrid-v0)
from factorq_torch.integrations.sb3 import LocalRiskDQN, LocalRiskPolicy  # noqa: E402
from factorq_torch.structure import StructureLearner  # noqa: E402
from factorq_torch.tables import LocalRewardTable  # noqa: E402


@pytest.fixture(autouse=True)
def sb3_logs_in_tmp(tmp_path, monkeypatch):
    """SB3's default logger makes a ``SB3-<time>`` folder per model in the temp dir: the models
    these tests build directly (as a user would) log under pytest's ``tmp_path`` instead."""
    monkeypatch.setenv("SB3_LOGDIR", str(tmp_path / "sb3-logs"))


def test_the_commands_sb3_models_leave_no_log_folder(tmp_path, monkeypatch):
    from factorq_trainers.methods.units import sb3_dqn

    monkeypatch.delenv("SB3_LOGDIR")
    monkeypatch.setattr("tempfile.tempdir", str(tmp_path))
    settings = dict(hidden=(8,), learning_starts=8, batch_size=4, buffer_size=64, train_every=1)
    sb3_dqn(settings, grid(), "MultiInputPolicy", seed=0).learn(16)
    assert list(tmp_path.iterdir()) == []
    DQN("MultiInputPolicy", grid(), learning_starts=8).learn(16)  # SB3's own default: a folder
    assert [path.name[:4] for path in tmp_path.iterdir()] == ["SB3-"]


def grid(**kwargs):
    settings = dict(size=4, num_obstacles=2, obstacle_period=1)
    return gymnasium.make("FactoredGrid-v0", **{**settings, **kwargs})


def oracle(env) -> LocalRewardTable:
    return LocalRewardTable(1, dependency=env.unwrapped.config.dependency)


class Collisions(BaseCallback):
    def __init__(self) -> None:
        super().__init__()
        self.count = 0

    def _on_step(self) -> bool:
        self.count += sum(bool((info["local_reward"] < 0).any()) for info in self.locals["infos"])
        return True


def test_the_greedy_action_maximises_the_combined_value():
    env = grid()
    provider = oracle(env)
    provider.rho[0, 0, 1] = -1.0  # north into a sensed obstacle
    model = LocalRiskDQN("MultiInputPolicy", env, provider=provider, seed=0)
    with torch.no_grad():  # north the task's best action everywhere
        last = model.policy.q_net.q_net[-1]
        last.weight.zero_()
        last.bias.copy_(torch.tensor([1.0, 0.5, 0.0, 0.0]))
    obs, _ = env.reset(seed=0)
    obs["sensors"] = np.array([1, 0, 0, 0], dtype=obs["sensors"].dtype)
    action, _ = model.predict(obs, deterministic=True)
    assert int(action) == 1
    obs["sensors"] = np.zeros(4, dtype=obs["sensors"].dtype)
    assert int(model.predict(obs, deterministic=True)[0]) == 0
    obs["sensors"] = np.array([1, 0, 0, 0], dtype=obs["sensors"].dtype)
    model.exploration_rate = 1.0
    explored = {int(model.predict(obs)[0]) for _ in range(60)}
    assert explored == {1, 2, 3}  # random actions avoid the risky one


def test_the_callback_trains_the_provider_from_info_local_reward():
    env = grid()
    provider = LocalRewardTable(1)
    model = LocalRiskDQN("MultiInputPolicy", env, provider=provider, learning_starts=10_000)
    collisions = Collisions()
    model.learn(200, callback=collisions)  # warm-up only: random (masked) actions
    assert int(provider.kappa.sum()) == 200  # every step once
    assert collisions.count >= 1  # before the first, nothing is known to be risky
    sensed = provider.kappa[0, :, 1] > 0
    assert torch.equal(provider.rho[0, :, 1][sensed], torch.full((int(sensed.sum()),), -1.0))
    assert provider.rho[0, :, 0].eq(0).all()


def test_learn_takes_every_callback_form_sb3_takes():
    """A function ``(locals, globals) -> bool`` is a callback in SB3: it is called every step
    beside the layer's (it raised AttributeError: LocalRiskDQN put it in a CallbackList as is)."""
    env = grid()
    model = LocalRiskDQN("MultiInputPolicy", env, provider=LocalRewardTable(1), learning_starts=100)
    steps = []
    model.learn(20, callback=lambda local, variables: steps.append(local["infos"]) or True)
    assert len(steps) == 20
    collisions = Collisions()
    model.learn(20, callback=[collisions, lambda local, variables: True])
    assert int(model.policy.risk.provider.kappa.sum()) == 40  # the layer's callback ran too


def test_bad_input_is_named_at_construction():
    env = grid()
    with pytest.raises(ValueError, match="provider"):
        LocalRiskDQN("MultiInputPolicy", env)
    with pytest.raises(ValueError, match="S=2"):
        LocalRiskDQN("MultiInputPolicy", env, provider=LocalRewardTable(2))
    with pytest.raises(ValueError, match="4 actions .* 3 actuators"):
        LocalRiskDQN("MultiInputPolicy", env, provider=LocalRewardTable(1, num_actions=3))
    learner = StructureLearner(1, num_actions=4, num_sensors=6)
    with pytest.raises(ValueError, match="4 sensors .* 6"):
        LocalRiskDQN("MultiInputPolicy", env, provider=learner)
    with pytest.raises(TypeError, match="LocalRiskPolicy"):
        LocalRiskDQN("MlpPolicy", env, provider=oracle(env))


def test_a_missing_extra_gets_a_clear_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "stable_baselines3", None)
    monkeypatch.delitem(sys.modules, "factorq_torch.integrations.sb3", raising=False)
    module = importlib.import_module("factorq_torch.integrations.sb3")  # imports: docs, doctests
    with pytest.raises(ImportError, match=r"factorq-torch\[sb3\]"):
        module.LocalRiskDQN("MultiInputPolicy", grid(), provider=LocalRewardTable(1))


@pytest.mark.slow
@pytest.mark.float_sensitive  # a learned outcome of a network: tried under other CPU kernels
def test_sb3_dqn_with_local_risk_collides_far_less(one_thread):
    settings = dict(learning_starts=50, exploration_fraction=0.3, train_freq=4, seed=0)
    counts = {}
    for name in ("dqn", "risk"):
        env = grid()
        if name == "dqn":
            model = DQN("MultiInputPolicy", env, **settings)
        else:
            model = LocalRiskDQN("MultiInputPolicy", env, provider=oracle(env), **settings)
        callback = Collisions()
        model.learn(300, callback=callback)
        counts[name] = callback.count
    assert counts["dqn"] >= 4 * max(1, counts["risk"]), counts
    assert isinstance(model.policy, LocalRiskPolicy)


def test_save_and_load_keep_the_provider(tmp_path):
    env = grid()
    model = LocalRiskDQN("MultiInputPolicy", env, provider=LocalRewardTable(1), learning_starts=50)
    model.learn(100)
    model.save(tmp_path / "model.zip")
    loaded = LocalRiskDQN.load(tmp_path / "model.zip", env=env)
    provider = loaded.policy.risk.provider
    assert int(provider.kappa.sum()) == 100
    assert torch.equal(provider.rho, model.policy.risk.provider.rho)
    obs, _ = env.reset(seed=1)
    assert model.predict(obs, deterministic=True)[0] == loaded.predict(obs, deterministic=True)[0]
