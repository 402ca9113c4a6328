"""The online collector: the batched torchrl modules against the slow per-experiment reference."""

from __future__ import annotations

import pytest
import reference  # tests/reference.py: pytest puts tests/ on sys.path (no __init__.py)
import torch
from tensordict.nn import TensorDictSequential
from torchrl.envs import TransformedEnv

from factorq_envs import FactoredGridEnv, SplitLocalReward
from factorq_envs.grid_world import WorldConfig, static_layout
from factorq_torch.base.config import AgentConfig
from factorq_torch.base.rng import MASK64, STREAM_POLICY, STREAM_WORLD, derive_keys
from factorq_torch.collectors import OnlineCollector
from factorq_torch.objectives import FactorQLoss, TabularQLoss
from factorq_torch.policy import EpsilonGreedyPolicy, FactorQPolicy
from factorq_torch.tables import LocalRewardTable, TaskQTable


def build(algorithm, periods, world, agent, seed, runs, episodes, progress=None):
    """Env, modules and collector of ``len(periods)`` experiments of one algorithm."""
    batch = len(periods)
    env = FactoredGridEnv(
        size=world.size,
        num_obstacles=world.num_obstacles,
        obstacle_period=list(periods),
        max_steps=world.max_steps,
        layout_seed=world.layout_seed,
        batch_size=(batch,),
        seed=seed,
    )
    if algorithm == "factor-q":
        env = TransformedEnv(env, SplitLocalReward())
        task = TaskQTable(batch, world.num_cells)
        local = LocalRewardTable(batch)
        chooser = FactorQPolicy(
            batch, seed=seed, epsilon=agent.epsilon, eta=agent.eta, g_min=agent.g_min
        )
        policy = TensorDictSequential(task, local, chooser)
        loss = FactorQLoss(
            task, local, gamma=agent.gamma, alpha=agent.alpha, eta=agent.eta, g_min=agent.g_min
        )
    else:
        task, local = TaskQTable(batch, world.num_cells, with_sensors=True), None
        policy = TensorDictSequential(
            task, EpsilonGreedyPolicy(batch, seed=seed, epsilon=agent.epsilon)
        )
        loss = TabularQLoss(task, gamma=agent.gamma, alpha=agent.alpha)
    collector = OnlineCollector(env, policy, loss, runs=runs, episodes=episodes, progress=progress)
    return collector, task, local


@pytest.mark.parametrize("algorithm", ["factor-q", "q-learning"])
def test_batched_collector_reproduces_the_reference_loop_bit_for_bit(algorithm):
    # Mixed worlds in one batch; a high epsilon and a short max_steps exercise exploration,
    # truncation (which still bootstraps) and termination.
    periods = [0, 1, 3, 0, 2]
    world = WorldConfig(size=5, num_obstacles=4, max_steps=40, layout_seed=3)
    agent = AgentConfig(epsilon=0.2)
    seed, runs, episodes = 11, 2, 5
    collector, task, local = build(algorithm, periods, world, agent, seed, runs, episodes)
    metrics = collector.run()
    world_keys = derive_keys(seed, STREAM_WORLD, len(periods))
    policy_keys = derive_keys(seed, STREAM_POLICY, len(periods))
    static = static_layout(world).tolist()
    truncations = 0
    for i, period in enumerate(periods):
        expected, tables = reference.run_experiment(
            algorithm,
            period,
            world,
            agent,
            runs,
            episodes,
            int(world_keys[i]) & MASK64,
            int(policy_keys[i]) & MASK64,
            static,
        )
        for name in ("steps", "collisions", "greedy_collisions"):
            assert torch.equal(metrics[name][i], torch.tensor(getattr(expected, name))), name
        assert torch.equal(
            metrics["task_return"][i], torch.tensor(expected.task_return, dtype=torch.float32)
        )
        assert torch.equal(task.table[i].detach(), torch.tensor(tables["q"]))
        if local is not None:
            assert torch.equal(local.rho[i], torch.tensor(tables["rho"]))
            assert torch.equal(local.kappa[i], torch.tensor(tables["kappa"]))
        truncations += sum(s == world.max_steps for run in expected.steps for s in run)
    assert truncations > 0  # the budget does exercise truncated episodes


def small(algorithm="factor-q", periods=(1, 1), runs=2, episodes=3, seed=0, progress=None):
    world = WorldConfig(size=4, num_obstacles=2, max_steps=30)
    return build(
        algorithm, periods, world, AgentConfig(epsilon=0.1), seed, runs, episodes, progress
    )


def test_local_tables_carry_over_runs_and_count_every_step():
    collector, _, local = small(runs=3, episodes=2)
    metrics = collector.run()
    # one eq. 5 visit per step of every run: kappa was never reset between runs
    assert torch.equal(local.kappa.sum(dim=(1, 2)), metrics["steps"].sum(dim=(1, 2)))


def test_the_task_table_is_reset_at_each_run_boundary_of_that_experiment_only():
    collector, task, _ = small(runs=3, episodes=2)
    masks = []
    reset_task = collector._reset_task

    def recording(mask):
        masks.append(mask.clone())
        reset_task(mask)

    collector._reset_task = recording
    collector.run()
    # 2 boundaries per experiment (between runs 0-1 and 1-2), none after the last run
    assert torch.stack(masks).sum(dim=0).tolist() == [2, 2]
    assert any(int(mask.sum()) == 1 for mask in masks)  # experiments reach them at their own pace


def test_a_finished_experiment_stops_changing_while_the_others_go_on():
    collector, task, local = small(periods=(1, 1), runs=1, episodes=3, seed=2)
    world = collector.env.base_env
    chooser = collector.policy[-1]
    snapshot = None
    for _ in collector:
        finished = collector.finished.nonzero().flatten().tolist()
        if snapshot is None and len(finished) == 1:
            i = finished[0]
            state = tuple(t[i].clone() for t in world.world_state)
            snapshot = (
                i,
                state,
                task.table[i].detach().clone(),
                local.rho[i].clone(),
                local.kappa[i].clone(),
                chooser.counter[i].clone(),
            )
    assert snapshot is not None, "both experiments finished on the same step: change the seed"
    i, state, table, rho, kappa, counter = snapshot
    assert all(torch.equal(t[i], s) for t, s in zip(world.world_state, state, strict=True))
    assert torch.equal(task.table[i].detach(), table)
    assert torch.equal(local.rho[i], rho) and torch.equal(local.kappa[i], kappa)
    assert torch.equal(chooser.counter[i], counter)


def test_iteration_yields_transitions_and_resumes_exactly_where_it_stopped():
    collector, _, _ = small(runs=2, episodes=2)
    straight, _, _ = small(runs=2, episodes=2)
    for count, td in enumerate(collector, start=1):  # noqa: B007 (td is used below)
        if count == 25:
            break
    assert torch.is_grad_enabled()  # no no_grad leaked out of the generator
    assert td["collector", "mask"].dtype == torch.bool and ("next", "local_reward") in td.keys(True)
    assert td["collector", "run"].shape == td["collector", "episode"].shape == (2,)
    steps = sum(1 for _ in collector)  # a new iteration continues
    assert steps > 0 and collector.done
    metrics = straight.run()
    for name in metrics.keys():
        assert torch.equal(collector.metrics[name], metrics[name]), name
    with pytest.raises(RuntimeError, match="every experiment has finished"):
        collector.step()


def test_progress_reports_every_episode_and_experiment_once():
    calls = []
    collector, _, _ = small(
        algorithm="q-learning", runs=2, episodes=3, progress=lambda *a: calls.append(a)
    )
    collector.run()
    assert sum(e for e, _ in calls) == 2 * 2 * 3 and sum(x for _, x in calls) == 2


def test_collector_state_round_trips_through_state_dict():
    collector, _, _ = small(runs=1, episodes=2)
    collector.run()
    other, _, _ = small(runs=1, episodes=2, seed=5)
    other.load_state_dict(collector.state_dict())
    assert other.done and torch.equal(other.metrics["steps"], collector.metrics["steps"])


# -- bad input ---------------------------------------------------------------------------------


def test_tables_built_for_another_batch_size_than_the_env_are_refused():
    env = FactoredGridEnv(size=3, num_obstacles=1, batch_size=(3,))
    table = TaskQTable(2, num_cells=9, with_sensors=True)
    policy = TensorDictSequential(table, EpsilonGreedyPolicy(2))
    with pytest.raises(ValueError, match="env has batch_size \\[3\\] but TaskQTable holds S=2"):
        OnlineCollector(env, policy, TabularQLoss(table), runs=1, episodes=1)


def test_bad_budgets_and_env_shapes_are_refused():
    env = FactoredGridEnv(size=3, num_obstacles=1, batch_size=(2,))
    table = TaskQTable(2, num_cells=9, with_sensors=True)
    policy = TensorDictSequential(table, EpsilonGreedyPolicy(2))
    with pytest.raises(ValueError, match="runs=0 is out of range"):
        OnlineCollector(env, policy, TabularQLoss(table), runs=0, episodes=1)
    with pytest.raises(TypeError, match="episodes must be an int"):
        OnlineCollector(env, policy, TabularQLoss(table), runs=1, episodes=2.5)
    flat = FactoredGridEnv(size=3, num_obstacles=1, batch_size=(2, 1))
    with pytest.raises(ValueError, match="one batch dimension"):
        OnlineCollector(flat, policy, TabularQLoss(table), runs=1, episodes=1)


@pytest.mark.slow
def test_factorq_avoids_collisions_far_better_than_qlearning_and_both_learn_the_path(one_thread):
    # 4 seeds of the paper's static world, 1 run of 20 episodes each (~25 s on one thread).
    world = WorldConfig(size=10, num_obstacles=10)
    results = {}
    for algorithm in ("q-learning", "factor-q"):
        collector, _, _ = build(algorithm, [0] * 4, world, AgentConfig(), 0, 1, 20)
        results[algorithm] = collector.run()
    greedy = {name: m["greedy_collisions"].sum(-1).float().mean() for name, m in results.items()}
    # measured: about 320 for Q-learning, 4 for Factor-Q
    assert greedy["factor-q"] * 10 < greedy["q-learning"], greedy
    for name, metrics in results.items():
        steps = metrics["steps"][:, 0].float()  # [seeds, episodes]
        # measured: first five ~220 steps, last five ~90-105
        assert steps[:, -5:].mean() < 0.75 * steps[:, :5].mean(), (name, steps.mean(0))


HOST_READS = ("item", "__bool__", "nonzero", "tolist", "__int__", "__float__", "__index__")


@pytest.mark.parametrize("algorithm", ["factor-q", "q-learning"])
def test_no_host_synchronisation_creeps_into_the_step(algorithm, monkeypatch):
    # Every read of a tensor's value on the host (a device-to-host sync on a GPU) made by our own
    # code while the loop runs is recorded by its function. Allowed: the collector's one read of
    # its counts per step, and the CPU-only reads: the collector's list of the experiments that
    # ended an episode, the exact action check, the finite-value checks of the policy and the
    # loss (values and rewards) and the index checks of the loss and the tables (actions, cells:
    # one aminmax each; on a GPU: compaction on the device and device-side asserts, no host read).
    # torchrl's own env machinery is not ours to change and is not counted.
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    ours = tuple(str(root / folder) for folder in ("envs", "factorq_torch"))
    reads: dict[str, int] = {}
    collector, _, _ = small(algorithm, periods=(0, 10, 1, 1), runs=2, episodes=3)
    collector.step()  # the first reset and the static layout are set-up, not the step

    def recording(name):
        original = getattr(torch.Tensor, name)

        def read(self, *args, **kwargs):
            caller = sys._getframe(1).f_code
            if caller.co_filename.startswith(ours):
                where = f"{Path(caller.co_filename).name}:{caller.co_name}"
                where += f":{name}" if name in ("tolist", "nonzero") else ""
                reads[where] = reads.get(where, 0) + 1
            return original(self, *args, **kwargs)

        return read

    for name in HOST_READS:
        monkeypatch.setattr(torch.Tensor, name, recording(name))
    steps = 0
    while not collector.done:
        collector.step()
        steps += 1
    monkeypatch.undo()
    assert reads.pop("collectors.py:_record:tolist") == steps
    assert 0 < reads.pop("collectors.py:ended_rows:nonzero") < steps  # CPU: episodes ended
    assert reads.pop("torchrl_env.py:_check_action", 0) <= steps
    # policy; loss: s, s', rewards, and the updated Q(s, a) (an overflow refused, issue 41)
    assert reads.pop("validation.py:check_finite", 0) <= 9 * steps
    assert reads.pop("validation.py:check_indices", 0) <= 4 * steps  # loss and tables' indices
    assert reads == {}


def test_a_hook_on_the_loss_keeps_the_loss_running_as_a_module_with_the_same_numbers():
    # The collector's direct tabular step skips the loss's forward; a forward hook (a trainer
    # reading td_error) gets it back, and the tables end the same either way.
    # Without a hook of ours the direct step is taken (torchrl's own pre-hook on every loss does
    # not count): the loss's forward never runs.
    results, seen, forwards = [], [], []
    for hooked in (False, True):
        collector, _, _ = small("factor-q", periods=(0, 10, 1, 1), runs=1, episodes=2)
        loss = collector.loss
        original = loss.forward
        loss.forward = lambda td, o=original, h=hooked: forwards.append(h) or o(td)
        if hooked:
            loss.register_forward_hook(lambda m, i, out: seen.append(out["td_error"]))
        collector.run()
        results.append(loss.task_value_network.table.detach().clone())
    assert seen and torch.equal(results[0], results[1])
    assert forwards and set(forwards) == {True}


@pytest.mark.parametrize("algorithm", ["factor-q", "q-learning"])
def test_restarts_by_reset_mask_give_the_transitions_of_restarts_by_the_reset_entry(algorithm):
    # The collector restarts FactoredGridEnv's worlds with reset(td, reset_mask=...) (torchrl then
    # updates with the env's whole answer); a "_reset" entry makes torchrl merge under the mask.
    # Every transition, every entry (root and "next", done flags and collisions of the worlds
    # left alone, finished experiments included), must be the same; truncations happen too.
    by_keyword, _, _ = small(algorithm, periods=(0, 1, 10), runs=2, episodes=3, seed=4)
    by_entry, _, _ = small(algorithm, periods=(0, 1, 10), runs=2, episodes=3, seed=4)
    assert by_keyword._mask_keyword
    by_entry._mask_keyword = False  # this collector restarts by the "_reset" entry
    steps = 0
    for expected, got in zip(by_entry, by_keyword, strict=True):
        steps += 1
        assert set(expected.keys(True, True)) == set(got.keys(True, True))
        for key in expected.keys(True, True):
            assert torch.equal(expected[key], got[key]), (steps, key)
    assert steps > 20 and by_keyword.done
    truncated = by_entry.metrics["steps"] == 30
    assert bool(truncated.any()), "no episode was truncated: change the seed"


def test_the_ended_experiments_are_found_alike_with_and_without_a_host_read():
    from factorq_torch.collectors import ended_rows

    generator = torch.Generator().manual_seed(3)
    for size in (1, 7, 300):
        for _ in range(20):
            ended = torch.rand(size, generator=generator) < 0.3
            count = int(ended.sum())
            on_device = ended_rows(ended, count, on_host=False)
            assert torch.equal(on_device, ended_rows(ended, count, on_host=True))
            assert on_device.tolist() == [i for i, flag in enumerate(ended.tolist()) if flag]
