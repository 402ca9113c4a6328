"""factorq_torch in ordinary torchrl use (issue 13): any batch of transitions, replay buffers and
torchrl's Collector, the exploration switch, specs that compose, clear errors where they enter."""

from __future__ import annotations

import copy
import runpy
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictSequential
from timing import patience  # tests/timing.py: bounds that stretch with the load
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs import (
    Compose,
    InitTracker,
    ParallelEnv,
    RewardSum,
    SerialEnv,
    StepCounter,
    TransformedEnv,
)
from torchrl.envs.utils import ExplorationType, check_env_specs, set_exploration_type

from factorq_envs import ExperimentIndex, FactoredGridEnv, SplitLocalReward
from factorq_torch.collectors import OnlineCollector
from factorq_torch.objectives import FactorQLoss, TabularQLoss, tabular_optimizer
from factorq_torch.policy import EpsilonGreedyPolicy, FactorQPolicy
from factorq_torch.tables import LocalRewardTable, TaskQTable

ROOT = Path(__file__).resolve().parent.parent


def factorq(S: int, cells: int = 16, epsilon: float = 0.2, seed: int = 0):
    task, local = TaskQTable(S, num_cells=cells), LocalRewardTable(S)
    actor = TensorDictSequential(task, local, FactorQPolicy(S, seed=seed, epsilon=epsilon))
    return task, local, actor, FactorQLoss(task, local)


def split_env(S=4, seed=0, **world):
    world = {"size": 4, "num_obstacles": 3, "obstacle_period": 1, **world}
    base = FactoredGridEnv(**world, batch_size=(S,), seed=seed)
    return TransformedEnv(base, Compose(SplitLocalReward(), ExperimentIndex()))


def learn(loss, td):
    optimizer = tabular_optimizer(loss)
    loss(td)["loss_task"].backward()
    optimizer.step()
    optimizer.zero_grad()


def tables_of(task, local):
    return task.table.detach().clone(), local.rho.clone(), local.kappa.clone()


def assert_same_tables(first, second):
    for a, b in zip(first, second, strict=True):
        assert torch.equal(a, b)


# -- 1. any batch of transitions -----------------------------------------------------------------


def test_a_shuffled_minibatch_with_experiment_keys_equals_the_online_step_bit_for_bit():
    S = 4
    env = split_env(S)
    task, local, actor, loss = factorq(S)
    with torch.no_grad():
        data = env.rollout(40, actor, break_when_any_done=False)  # [S, T]
    learn(loss, data[:, 0])  # warm the tables up so the step below moves non-zero values
    step = data[:, 1]  # one online step of the S experiments, batch [S]
    assert torch.equal(step["experiment"], torch.arange(S))
    shuffled = step[torch.tensor([2, 0, 3, 1])]  # a minibatch: order lost, keys kept
    twin_task, twin_local = copy.deepcopy(task), copy.deepcopy(local)
    learn(loss, step)
    learn(FactorQLoss(twin_task, twin_local), shuffled)
    assert_same_tables(tables_of(task, local), tables_of(twin_task, twin_local))


def test_an_s_by_t_rollout_needs_no_experiment_key_and_equals_its_flattened_form():
    S = 3
    env = TransformedEnv(
        FactoredGridEnv(size=4, num_obstacles=3, batch_size=(S,)), SplitLocalReward()
    )
    task, local, actor, loss = factorq(S)
    with torch.no_grad():
        data = env.rollout(20, actor, break_when_any_done=False)  # [S, T], no "experiment"
    flat = data.reshape(-1)
    flat["experiment"] = torch.arange(S).repeat_interleave(20)
    twin_task, twin_local = copy.deepcopy(task), copy.deepcopy(local)
    learn(loss, data)
    learn(FactorQLoss(twin_task, twin_local), flat)
    assert_same_tables(tables_of(task, local), tables_of(twin_task, twin_local))
    assert int(local.kappa.sum()) == S * 20


def test_the_online_collector_gives_the_same_numbers_with_experiment_keys():
    results = []
    for transforms in (SplitLocalReward(), Compose(SplitLocalReward(), ExperimentIndex())):
        env = FactoredGridEnv(size=3, num_obstacles=2, obstacle_period=1, batch_size=(3,))
        task, local, actor, loss = factorq(3, cells=9)
        collector = OnlineCollector(
            TransformedEnv(env, transforms), actor, loss, runs=2, episodes=1
        )
        results.append((collector.run().clone(), *tables_of(task, local)))
    assert (results[0][0] == results[1][0]).all()
    assert_same_tables(results[0][1:], results[1][1:])


def test_duplicates_of_one_entry_move_it_by_the_mean_td_error_and_merge_the_running_mean():
    task, local = TaskQTable(1, num_cells=4), LocalRewardTable(1)
    with torch.no_grad():
        task.table[0, 0, 3] = 1.0  # Q(s, east) = 1
    # the same (s, a) twice, terminal, task rewards -1 and -3: TD errors 1 - (-1) = 2, 4
    td = TensorDict(
        cell=torch.tensor([0, 0]),
        sensors=torch.tensor([[True, False, False, True]] * 2),  # the east sensor is on
        action=torch.tensor([3, 3]),
        experiment=torch.tensor([0, 0]),
        next=TensorDict(
            cell=torch.tensor([1, 1]),
            sensors=torch.zeros(2, 4, dtype=torch.bool),
            reward=torch.tensor([[-1.0], [-3.0]]),
            local_reward=torch.tensor([[0.0, 0, 0, -1.0], [0.0, 0, 0, 0.0]]),
            terminated=torch.ones(2, 1, dtype=torch.bool),
            batch_size=[2],
        ),
        batch_size=[2],
    )
    learn(FactorQLoss(task, local), td)
    # Q <- Q - alpha * mean(TD error) = 1 - 0.2 * 3 = 0.4 (a sum would give 1 - 0.2 * 6)
    assert task.table[0, 0, 3].item() == pytest.approx(0.4)
    # eq. 5 with both rewards: kappa = 2, rho = mean(-1, 0) = -0.5
    assert local.kappa[0, 3, 1].item() == 2 and local.rho[0, 3, 1].item() == -0.5


def test_one_experiment_takes_any_batch_shape_and_an_unbatched_env():
    env = TransformedEnv(FactoredGridEnv(size=3, num_obstacles=1), SplitLocalReward())  # []
    task, local, actor, loss = factorq(1, cells=9)
    with torch.no_grad():
        data = env.rollout(30, actor, break_when_any_done=False)  # [T]
    learn(loss, data)
    learn(loss, data.reshape(5, 6))
    assert int(local.kappa.sum()) == 60


def test_tabular_q_learning_trains_from_replay_minibatches():
    S = 2
    env = FactoredGridEnv(size=4, num_obstacles=2, batch_size=(S,))
    env = TransformedEnv(env, ExperimentIndex())
    table = TaskQTable(S, num_cells=16, with_sensors=True)
    actor = TensorDictSequential(table, EpsilonGreedyPolicy(S, epsilon=0.3))
    buffer = ReplayBuffer(storage=LazyTensorStorage(1000), batch_size=32)
    with torch.no_grad():
        buffer.extend(env.rollout(50, actor, break_when_any_done=False).reshape(-1))
    loss = TabularQLoss(table)
    out = loss(buffer.sample())
    assert out["td_error"].shape == (32,)
    learn(loss, buffer.sample())
    assert (table.table != 0).any()


@pytest.mark.slow
def test_off_policy_example_learns_from_a_replay_buffer_filled_by_torchrl_collector():
    train = runpy.run_path(str(ROOT / "examples" / "offpolicy_replay.py"))["train"]
    result = train()
    steps, collisions = result["steps"], result["collisions"]
    # the first batch is exploration on empty tables: no episode ends, a third of steps collide
    assert collisions[0] > 0.15
    assert sum(collisions[-5:]) / 5 < collisions[0] / 4
    late = [s for s in steps[-5:] if s == s]  # NaN-free
    early = [s for s in steps[:5] if s == s]
    assert late and sum(late) / len(late) < 40
    assert not early or sum(late) / len(late) < sum(early) / len(early)
    assert result["greedy_steps"] == [8.0] * 4  # the shortest path of a 5x5 grid


# -- 2. exploration types ------------------------------------------------------------------------


@pytest.mark.parametrize("kind", [ExplorationType.DETERMINISTIC, ExplorationType.MODE])
def test_greedy_exploration_types_make_the_policy_greedy_with_random_ties(kind):
    policy = EpsilonGreedyPolicy(1000, epsilon=0.5)
    values = torch.tensor([[1.0, 3.0, 3.0, 0.0]]).expand(1000, 4)
    with set_exploration_type(kind):
        td = policy(TensorDict(action_value=values, batch_size=[1000]))
    assert not td["exploratory"].any()
    assert set(td["action"].tolist()) == {1, 2}  # both maxima, drawn at random


def test_random_exploration_type_and_the_default_explore_with_epsilon():
    values = torch.zeros(2000, 4)
    for context in (set_exploration_type(ExplorationType.RANDOM), torch.no_grad()):
        policy = FactorQPolicy(2000, epsilon=0.5)
        with context:
            td = policy(TensorDict(action_value=values, local_value=values, batch_size=[2000]))
        assert 0.45 < td["exploratory"].float().mean() < 0.55


# -- 3. specs that compose -----------------------------------------------------------------------


def composed(seed: int, S: int | None = 3):
    base = FactoredGridEnv(
        size=4, num_obstacles=3, obstacle_period=1, max_steps=40, batch_size=S, seed=seed
    )
    transforms = Compose(
        SplitLocalReward(),
        StepCounter(),
        InitTracker(),
        RewardSum(in_keys=["reward", "local_reward"]),
    )
    return TransformedEnv(base, transforms)


@pytest.mark.parametrize("seed", range(5))
def test_check_env_specs_passes_with_step_counter_reward_sums_and_init_tracker(seed):
    env = composed(seed)
    env.append_transform(ExperimentIndex())
    check_env_specs(env, seed=seed)
    data = env.rollout(100, break_when_any_done=False)
    assert data["next", "episode_local_reward"].min() < -1  # sums below the step's bound


def test_serial_env_of_single_worlds_passes_check_env_specs():
    env = SerialEnv(3, [lambda seed=seed: composed(seed, None) for seed in range(3)])
    check_env_specs(env, seed=0)
    env.close()


def test_parallel_env_of_single_worlds_passes_check_env_specs():
    makers = [lambda seed=seed: composed(seed, None) for seed in range(2)]
    env = ParallelEnv(2, makers, mp_start_method="fork")  # fork: no re-import of torch
    check_env_specs(env, seed=0)
    env.close()


def test_split_local_reward_as_a_replay_buffer_transform_splits_sampled_transitions():
    env = FactoredGridEnv(size=3, num_obstacles=1, batch_size=(2,))
    data = env.rollout(30, break_when_any_done=False).reshape(-1)
    buffer = ReplayBuffer(storage=LazyTensorStorage(100), transform=SplitLocalReward())
    buffer.extend(data)
    sample = buffer.sample(16)
    task = sample["next", "reward"] + sample["next", "collision"].sum(-1, keepdim=True)
    assert torch.equal(sample["next", "local_reward"], sample["next", "collision"])
    assert set(task.unique().tolist()) <= {-2.0, -1.0, 0.0, 1.0} and task.max() <= 0
    with pytest.raises(ValueError, match="already split"):
        SplitLocalReward()(sample)


# -- 6. clear errors -----------------------------------------------------------------------------


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_cuda_where_torch_has_none_is_refused_where_it_enters():
    for build in (
        lambda: FactoredGridEnv(device="cuda"),
        lambda: TaskQTable(1, num_cells=4, device="cuda"),
        lambda: LocalRewardTable(1, device="cuda:0"),
        lambda: FactorQPolicy(1, device="cuda"),
    ):
        with pytest.raises(ValueError, match="device='cuda(:0)?' is not available on this machine"):
            build()


def test_stepping_before_any_reset_is_refused():
    env = FactoredGridEnv(size=3, num_obstacles=1)
    with pytest.raises(RuntimeError, match="before any reset"):
        env.step(TensorDict(action=torch.tensor(0), batch_size=[]))


def test_a_table_smaller_than_the_env_is_refused_naming_num_cells():
    env = TransformedEnv(
        FactoredGridEnv(size=5, num_obstacles=3, batch_size=(2,)), SplitLocalReward()
    )
    task, local, actor, loss = factorq(2, cells=16)
    with pytest.raises(ValueError, match="num_cells=16 but the env has 25 cells"):
        OnlineCollector(env, actor, loss, runs=1, episodes=1)
    td = env.reset()
    td["cell"] = torch.tensor([24, 3])
    with pytest.raises(ValueError, match="num_cells=16 but received cell 24"):
        task(td)


def test_a_two_by_four_env_batch_given_to_eight_tables_names_the_batch_and_the_remedy():
    env = FactoredGridEnv(size=3, num_obstacles=1, batch_size=(2, 4))
    task, local, actor, loss = factorq(8, cells=9)
    with pytest.raises(ValueError, match=r"S=8 experiments .* batch_size \[2, 4\] .*'experiment'"):
        actor(env.reset())
    indexed = TransformedEnv(env, Compose(SplitLocalReward(), ExperimentIndex()))
    with torch.no_grad():
        data = indexed.rollout(5, actor, break_when_any_done=False)  # [2, 4, T]
    learn(loss, data)
    assert int(local.kappa.sum()) == 8 * 5


# -- 4. pictures ---------------------------------------------------------------------------------


def test_gymnasium_rgb_array_frames_show_the_world_and_pass_the_env_checker():
    import gymnasium
    from gymnasium.utils.env_checker import check_env

    import factorq_envs  # noqa: F401  (registers FactoredGrid-v0)

    env = gymnasium.make("FactoredGrid-v0", size=4, num_obstacles=3, render_mode="rgb_array")
    check_env(env.unwrapped)
    env.reset(seed=0)
    frame = env.render()
    assert frame.shape == (96, 96, 3) and frame.dtype == "uint8"
    env.step(0)  # north from the start: into the wall, a red bar on the north face
    bumped = env.render()
    assert (bumped[16:18, 16:32] == (220, 40, 40)).all()
    vector = gymnasium.make_vec("FactoredGrid-v0", num_envs=2, size=4, num_obstacles=3)
    assert vector.reset(seed=0)[0]["cell"].tolist() == [0, 0]
    vector.close()


def test_gymnasium_record_video_writes_a_clip(tmp_path):
    pytest.importorskip("moviepy", reason="RecordVideo writes with moviepy (the video extra)")
    import gymnasium
    from gymnasium.wrappers import RecordVideo

    import factorq_envs  # noqa: F401

    env = gymnasium.make("FactoredGrid-v0", size=4, num_obstacles=3, render_mode="rgb_array")
    env = RecordVideo(env, str(tmp_path), episode_trigger=lambda episode: True)
    env.reset(seed=0)
    for action in (2, 2, 2, 3, 3, 3):
        env.step(action)
    env.close()
    assert list(tmp_path.glob("*.mp4"))


def test_stable_baselines3_make_vec_env_renders_rgb_arrays():
    pytest.importorskip("stable_baselines3", reason="stable-baselines3 is not installed")
    from stable_baselines3.common.env_checker import check_env
    from stable_baselines3.common.env_util import make_vec_env

    import factorq_envs  # noqa: F401

    vector = make_vec_env("FactoredGrid-v0", n_envs=2, env_kwargs=dict(size=4, num_obstacles=3))
    vector.reset()
    assert vector.render().ndim == 3  # tiled rgb frames
    check_env(
        factorq_envs.gymnasium_env.FactoredGridGym(size=4, num_obstacles=3, render_mode="rgb_array")
    )


def test_torchrl_pixels_are_the_gymnasium_frames():
    import gymnasium

    import factorq_envs  # noqa: F401
    from factorq_envs import RenderPixels

    torchrl_env = TransformedEnv(FactoredGridEnv(size=4, num_obstacles=3, seed=0), RenderPixels())
    gym_env = gymnasium.make("FactoredGrid-v0", size=4, num_obstacles=3, render_mode="rgb_array")
    td = torchrl_env.reset()
    gym_env.reset(seed=0)
    for action in (0, 2, 3, 3):
        assert torch.equal(td["pixels"], torch.from_numpy(gym_env.render()))
        td["action"] = torch.tensor(action)
        td = torchrl_env.step(td)["next"]
        gym_env.step(action)
    check_env_specs(torchrl_env)


def test_the_video_example_writes_a_gif_of_greedy_frames(tmp_path):
    record = runpy.run_path(str(ROOT / "examples" / "video.py"))["record"]
    path = tmp_path / "clip.gif"
    frames = record(str(path), size=4, num_obstacles=2, episodes=3, max_frames=4)
    from PIL import Image

    with Image.open(path) as clip:
        assert clip.n_frames == frames and 2 <= frames <= 5
        assert clip.size == (2 * 6 * 16, 2 * 6 * 16)


# -- 5. imports and packaging --------------------------------------------------------------------


def test_the_package_exports_a_flat_public_api_loaded_on_first_use():
    import subprocess
    import sys

    code = (
        "import sys, factorq_torch.base.rng\n"
        "assert 'torchrl' not in sys.modules, 'the base layer pulled in torchrl'\n"
        "import factorq_torch\n"
        "from factorq_torch import FactorQLoss, TaskQTable, LocalRewardTable, FactorQPolicy\n"
        "from factorq_torch import OnlineCollector, EpsilonGreedyPolicy, TabularQLoss, keys\n"
        "assert all(hasattr(factorq_torch, name) for name in factorq_torch.__all__)\n"
        "assert 'envs' not in sys.modules, 'the agent imported the worlds'\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT, timeout=patience(120))
    for package in ("factorq_torch", "envs", "trainers"):
        assert (ROOT / package / "py.typed").exists()


def test_torchrl_gym_env_reads_the_task_and_local_rewards_from_info():
    from torchrl.data import Unbounded
    from torchrl.envs import GymEnv
    from torchrl.envs.libs.gym import default_info_dict_reader

    import factorq_envs  # noqa: F401

    env = GymEnv("FactoredGrid-v0", size=4, num_obstacles=3)
    spec = {
        "task_reward": Unbounded(shape=(), dtype=torch.float32),
        "local_reward": Unbounded(shape=(4,), dtype=torch.float32),
    }
    env.set_info_dict_reader(default_info_dict_reader(list(spec), spec=spec))
    check_env_specs(env)
    data = env.rollout(20, break_when_any_done=False)
    conventional = data["next", "task_reward"] + data["next", "local_reward"].sum(-1)
    assert torch.equal(conventional, data["next", "reward"].squeeze(-1))


def test_torchrl_video_recorder_records_the_pixels(tmp_path):
    from torchrl.record import VideoRecorder
    from torchrl.record.loggers.csv import CSVLogger

    from factorq_envs import RenderPixels

    logger = CSVLogger("run", log_dir=str(tmp_path), video_format="pt")  # no codec needed
    recorder = VideoRecorder(logger, tag="grid")
    world = FactoredGridEnv(size=4, num_obstacles=3)
    env = TransformedEnv(world, Compose(RenderPixels(), recorder))
    env.rollout(5)
    recorder.dump()
    (clip,) = (tmp_path / "run" / "videos").glob("grid_*.pt")
    video = torch.load(clip, weights_only=True)
    assert video.dtype == torch.uint8 and video.shape[-3:] == (3, 96, 96)  # [.., T, C, H, W]
