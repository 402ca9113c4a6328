"""The fused fast path (factorq_trainers.compiled.fast and its C kernel) against the slow
reference and the pure-torch world and equations: equal bit for bit, whatever the chunking,
threads and batch."""

from __future__ import annotations

import io
import os
import stat
import threading

import kernel_probes  # tests/kernel_probes.py: pytest puts tests/ on sys.path
import pytest
import torch
from reference import run_experiment  # tests/reference.py: pytest puts tests/ on sys.path

from factorq_envs.grid_world import (
    WorldConfig,
    empty_state,
    reset_worlds,
    scatter_obstacles,
    static_layout,
    step_worlds,
)
from factorq_torch import functional
from factorq_torch.base.config import AgentConfig
from factorq_torch.base.keys import EPISODE_METRICS
from factorq_torch.base.rng import (
    MASK64,
    POLICY_DRAWS_PER_STEP,
    STREAM_POLICY,
    STREAM_WORLD,
    derive_keys,
    randint_from_bits,
    random_bits,
)
from factorq_trainers.compiled import fast, loader

pytestmark = pytest.mark.skipif(
    not fast.is_available(), reason=f"fast path unavailable: {fast.unavailable_reason()}"
)

METRICS = EPISODE_METRICS
SMALL_WORLD = WorldConfig(size=6, num_obstacles=5, max_steps=150)


def _keys(count: int, seed: int = 0, offset: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    return (
        derive_keys(seed, STREAM_WORLD, count, offset),
        derive_keys(seed, STREAM_POLICY, count, offset),
    )


def _bits(tensor: torch.Tensor) -> torch.Tensor:
    """Float32 tensors as their bit patterns, so that -0.0 != 0.0 and NaNs compare."""
    return tensor.view(torch.int32) if tensor.dtype == torch.float32 else tensor


def _assert_same(left: dict, right: dict) -> None:
    assert left.keys() == right.keys()
    for name in left:
        assert torch.equal(_bits(left[name]), _bits(right[name])), name


def _episodes_completed(batch: fast.ExperimentBatch) -> int:
    """Episodes finished so far, summed over the experiments, read from the saved state."""
    state = batch.state_dict()
    return int((state["run"] * batch.episodes + state["episode"]).sum())


def _finished(batch: fast.ExperimentBatch, chunk: int = 1 << 40) -> fast.ExperimentBatch:
    while not batch.done:
        batch.advance(chunk)
    return batch


def _batch(
    algorithm="factor-q",
    periods=(0, 10, 1),
    world=SMALL_WORLD,
    agent=None,
    runs=2,
    episodes=6,
    seed=0,
    offset=0,
    threads=1,
) -> fast.ExperimentBatch:
    world_keys, policy_keys = _keys(len(periods), seed, offset)
    return fast.ExperimentBatch(
        algorithm, torch.tensor(periods), world, agent or AgentConfig(), runs, episodes,
        world_keys, policy_keys, threads=threads,
    )  # fmt: skip


def _assert_equals_reference(batch: fast.ExperimentBatch, world, agent, runs, episodes) -> None:
    metrics, tables = batch.metrics(), batch.tables()
    periods = batch._tensors["periods"].tolist()
    static = static_layout(world).tolist() if 0 in periods else None
    world_keys, policy_keys = batch._tensors["world_keys"], batch._tensors["policy_keys"]
    for index, period in enumerate(periods):
        expected, expected_tables = run_experiment(
            batch.algorithm, period, world, agent, runs, episodes,
            int(world_keys[index]) & MASK64, int(policy_keys[index]) & MASK64, static,
        )  # fmt: skip
        for name in METRICS:
            got = metrics[name][index]
            want = torch.tensor(getattr(expected, name), dtype=got.dtype)
            assert torch.equal(_bits(got), _bits(want)), (index, name)
        q = torch.tensor(expected_tables["q"], dtype=torch.float32)
        assert torch.equal(_bits(tables["q"][index]), _bits(q)), index
        if batch.algorithm == "factor-q":
            rho = torch.tensor(expected_tables["rho"], dtype=torch.float32)
            assert torch.equal(_bits(tables["rho"][index]), _bits(rho)), index
            assert tables["kappa"][index].tolist() == expected_tables["kappa"], index


# --- equality with the reference implementation of the SPEC -----------------------------------


@pytest.mark.parametrize("algorithm", ["q-learning", "factor-q"])
@pytest.mark.parametrize("period", [0, 10, 1])
def test_kernel_equals_reference_bit_for_bit_metrics_and_tables(algorithm, period):
    runs, episodes = 2, 10
    batch = _finished(_batch(algorithm, (period, period), runs=runs, episodes=episodes, seed=3))
    assert int(batch.metrics()["steps"].min()) > 0
    _assert_equals_reference(batch, SMALL_WORLD, AgentConfig(), runs, episodes)


@pytest.mark.parametrize("algorithm", ["q-learning", "factor-q"])
def test_kernel_equals_reference_with_non_default_agent_and_truncation(algorithm):
    # Much exploration, short episodes (many are truncated and still bootstrap), period 3.
    world = WorldConfig(size=5, num_obstacles=4, max_steps=25, layout_seed=2)
    agent = AgentConfig(epsilon=0.3, gamma=0.6, alpha=0.55, eta=0.5, g_min=0.05)
    batch = _finished(_batch(algorithm, (0, 3, 1), world, agent, runs=3, episodes=8, seed=9))
    assert int((batch.metrics()["steps"] == world.max_steps).sum()) > 0  # truncations happened
    _assert_equals_reference(batch, world, agent, 3, 8)


@pytest.mark.parametrize(
    "world,agent",
    [
        (WorldConfig(size=2, num_obstacles=1, max_steps=5), AgentConfig(epsilon=1.0)),
        (WorldConfig(size=3, num_obstacles=0, max_steps=1), AgentConfig()),
        (WorldConfig(size=4, num_obstacles=6, max_steps=40), AgentConfig(epsilon=0.0)),
        (WorldConfig(size=7, num_obstacles=40, max_steps=60), AgentConfig(gamma=0.0)),
    ],
)
def test_kernel_equals_reference_at_the_edges_of_worlds_and_agents(world, agent):
    for algorithm in ("q-learning", "factor-q"):
        periods = (1, 2) if world.num_obstacles > 20 else (0, 1, 2)  # crowded: no static layout
        batch = _finished(_batch(algorithm, periods, world, agent, runs=2, episodes=5, seed=2))
        _assert_equals_reference(batch, world, agent, 2, 5)


def test_kernel_equations_equal_functional_on_random_rows_with_ties_and_zeros():
    generator = torch.Generator().manual_seed(0)
    rows = 20_000
    scale = torch.randint(0, 3, (rows, 4), generator=generator)  # many zeros, hence ties
    q = torch.round(torch.randn(rows, 4, generator=generator) * scale * 4) / 4
    counts = torch.randint(1, 4, (rows, 4), generator=generator).float()
    rho = -torch.randint(0, 3, (rows, 4), generator=generator).float() / counts
    for eta, g_min in ((0.1, 0.01), (0.5, 0.05), (0.0, 1e-3)):
        g, combined = kernel_probes.kernel_combined_values(q, rho, eta, g_min)
        expected_g = functional.normaliser(q, rho, eta, g_min)
        assert torch.equal(_bits(g), _bits(expected_g))
        expected = functional.combined_values(q, rho, expected_g)
        assert torch.equal(_bits(combined), _bits(expected))


def test_kernel_equations_equal_functional_on_infinities_nans_and_the_float_range():
    """The kernel's vectorised eq. 2 (and its cap to the float range) on the values where a
    scalar and a packed route could differ: +-0, +-inf, NaN, +-FLT_MAX, a subnormal."""
    big = torch.finfo(torch.float32).max
    values = torch.tensor([0.0, -0.0, 1.0, -1.0, big, -big, float("inf"), -float("inf")])
    values = torch.cat([values, torch.tensor([float("nan"), 1e-45, -3e38, 2.5])])
    generator = torch.Generator().manual_seed(1)
    q = values[torch.randint(0, len(values), (20_000, 4), generator=generator)]
    rho = values[torch.randint(0, len(values), (20_000, 4), generator=generator)]
    for eta, g_min in ((0.1, 0.01), (1e30, 0.01)):
        g, combined = kernel_probes.kernel_combined_values(q, rho, eta, g_min)
        expected_g = functional.normaliser(q, rho, eta, g_min)
        assert torch.equal(_bits(g), _bits(expected_g))
        expected = functional.combined_values(q, rho, expected_g)
        assert torch.equal(_bits(combined), _bits(expected))


@pytest.mark.parametrize("size,num_obstacles", [(2, 1), (3, 6), (10, 10), (10, 97), (64, 300)])
def test_kernel_scatter_equals_world_scatter_for_any_size(size, num_obstacles):
    key = derive_keys(5, STREAM_WORLD, 1)
    last = size * size - 1
    for scatter_index in range(6 if num_obstacles < 50 else 2):
        for agent in (0, last, 1, last // 2, last - 1):
            got = kernel_probes.kernel_scatter(size, num_obstacles, int(key), scatter_index, agent)
            expected = scatter_obstacles(
                key, torch.tensor([scatter_index]), torch.tensor([agent]), size, num_obstacles
            )[0]
            assert torch.equal(got, expected), (scatter_index, agent)


def test_random_walk_world_state_equals_world_py_after_every_step():
    world = WorldConfig(size=5, num_obstacles=4, max_steps=30, layout_seed=1)
    periods = torch.tensor([0, 3, 1])
    world_keys, policy_keys = _keys(3, seed=4)
    batch = fast.ExperimentBatch(
        fast.RANDOM_WALK, periods, world, AgentConfig(), 1, 1000, world_keys, policy_keys
    )
    static = static_layout(world)
    every = torch.ones(3, dtype=torch.bool)
    state = reset_worlds(empty_state(3, world.size), every, world_keys, periods, static, world)
    ended = 0
    for step in range(300):
        bits = random_bits(policy_keys, torch.tensor(step * POLICY_DRAWS_PER_STEP + 1))
        state, outcome = step_worlds(state, randint_from_bits(bits, 4), world_keys, periods, world)
        done = outcome.terminated | outcome.truncated
        ended += int(done.sum())
        state = reset_worlds(state, done, world_keys, periods, static, world)
        batch.advance(1)
        kernel = batch.state_dict()
        for name in ("cell", "obstacles", "bump", "episode_step", "scatters"):
            assert torch.equal(kernel[name], getattr(state, name)), (step, name)
    assert ended > 3 and _episodes_completed(batch) == ended


# --- invariances: chunking, threads, batch composition, resume -------------------------------


@pytest.mark.parametrize("algorithm", ["q-learning", "factor-q"])
def test_results_do_not_depend_on_advance_chunking(algorithm):
    world = WorldConfig()
    whole = _finished(_batch(algorithm, (0, 10, 1), world, episodes=4))
    for chunk in (1, 7, 1000):
        batch = _batch(algorithm, (0, 10, 1), world, episodes=4)
        completed = 0
        while not batch.done:
            completed += batch.advance(chunk if chunk > 1 else 1 + batch.total_steps % 5)
        assert completed == _episodes_completed(batch) == 3 * 2 * 4
        _assert_same(batch.state_dict(), whole.state_dict())


@pytest.mark.parametrize("algorithm", ["q-learning", "factor-q"])
def test_results_do_not_depend_on_thread_count(algorithm):
    periods = (0, 10, 1, 1, 10, 0, 1)
    one = _finished(_batch(algorithm, periods, WorldConfig(), episodes=5, threads=1), 3000)
    for threads in (2, 3, 8):
        many = _finished(_batch(algorithm, periods, WorldConfig(), episodes=5, threads=threads))
        _assert_same(many.state_dict(), one.state_dict())


def test_experiment_is_identical_alone_and_inside_a_batch():
    periods = (0, 10, 1, 10, 1, 0)
    together = _finished(_batch("factor-q", periods, WorldConfig(), episodes=5, threads=2))
    for index in (1, 4):
        alone = _finished(
            _batch("factor-q", periods[index : index + 1], WorldConfig(), episodes=5, offset=index)
        )
        for name, value in alone.state_dict().items():
            assert torch.equal(_bits(value[0]), _bits(together.state_dict()[name][index])), name


@pytest.mark.parametrize("algorithm", ["q-learning", "factor-q"])
def test_state_dict_round_trip_resumes_identically(algorithm):
    whole = _finished(_batch(algorithm, (0, 10, 1), WorldConfig(), episodes=4))
    first = _batch(algorithm, (0, 10, 1), WorldConfig(), episodes=4)
    for _ in range(3):
        first.advance(251)
    assert not first.done
    saved = first.state_dict()
    buffer = io.BytesIO()
    torch.save(saved, buffer)
    first.advance(5000)  # the saved copy must not follow the batch
    assert not torch.equal(saved["policy_counter"], first.state_dict()["policy_counter"])
    buffer.seek(0)
    resumed = _batch(algorithm, (0, 10, 1), WorldConfig(), episodes=4)
    resumed.load_state_dict(torch.load(buffer))
    assert _episodes_completed(resumed) == int((saved["run"] * 4 + saved["episode"]).sum())
    _assert_same(_finished(resumed, 1234).state_dict(), whole.state_dict())
    _assert_same(resumed.metrics(), whole.metrics())


def test_load_state_dict_rejects_another_batch_and_bad_entries():
    batch = _batch("factor-q", (0, 10, 1))
    other = _batch("factor-q", (0, 10, 1), seed=1).state_dict()
    with pytest.raises(ValueError, match="different batch"):
        batch.load_state_dict(other)
    state = batch.state_dict()
    with pytest.raises(KeyError, match="missing \\['cell'\\]"):
        batch.load_state_dict({k: v for k, v in state.items() if k != "cell"})
    with pytest.raises(ValueError, match="state\\['q'\\] has shape"):
        batch.load_state_dict({**state, "q": state["q"][:, :3]})
    with pytest.raises(ValueError, match="num_obstacles=5 per world"):
        batch.load_state_dict({**state, "obstacles": torch.zeros_like(state["obstacles"])})


def test_run_experiments_reports_progress_and_equals_a_finished_batch():
    reported = []
    world_keys, policy_keys = _keys(3)
    metrics = fast.run_experiments(
        "q-learning", torch.tensor([0, 10, 1]), SMALL_WORLD, AgentConfig(), 2, 6,
        world_keys, policy_keys, progress=reported.append,
    )  # fmt: skip
    assert sum(reported) == 3 * 2 * 6
    _assert_same(metrics, _finished(_batch("q-learning", (0, 10, 1))).metrics())


def test_done_and_episodes_completed_follow_the_experiments():
    batch = _batch("factor-q", (0, 1), runs=2, episodes=3)
    assert not batch.done and _episodes_completed(batch) == 0 and batch.advance(0) == 0
    completed = batch.advance(1 << 40)
    assert batch.done and completed == _episodes_completed(batch) == 2 * 2 * 3
    assert batch.advance(10) == 0
    metrics = batch.metrics()
    assert {name: metrics[name].shape for name in METRICS} == {n: (2, 2, 3) for n in METRICS}
    assert metrics["steps"].dtype == torch.int64 and metrics["task_return"].dtype == torch.float32


# --- argument checks ---------------------------------------------------------------------------


def _arguments(**changes) -> dict:
    world_keys, policy_keys = _keys(2)
    arguments = dict(
        algorithm="factor-q", periods=torch.tensor([0, 1]), world=SMALL_WORLD,
        agent=AgentConfig(), runs=2, episodes=3, world_keys=world_keys, policy_keys=policy_keys,
    )  # fmt: skip
    arguments.update(changes)
    return arguments


@pytest.mark.parametrize(
    "changes,error,message",
    [
        ({"algorithm": "sarsa"}, ValueError, "algorithm='sarsa' is unknown"),
        ({"periods": [0, 1]}, TypeError, "periods must be a torch.Tensor"),
        ({"periods": torch.tensor([0.0, 1.0])}, TypeError, "periods must have dtype torch.int64"),
        ({"periods": torch.zeros(2, 1, dtype=torch.int64)}, ValueError, "1-d tensor"),
        ({"periods": torch.tensor([0, -1])}, ValueError, "periods must be >= 0"),
        ({"world_keys": torch.zeros(3, dtype=torch.int64)}, ValueError, "world_keys has 3"),
        ({"policy_keys": torch.zeros(2, dtype=torch.int32)}, TypeError, "policy_keys must have"),
        ({"runs": 0}, ValueError, "runs=0 is out of range"),
        ({"episodes": 2.5}, TypeError, "episodes must be an int"),
        ({"threads": 0}, ValueError, "threads=0 is out of range"),
        ({"world": {"size": 10}}, TypeError, "world must be a WorldConfig"),
        ({"agent": None}, TypeError, "agent must be an AgentConfig"),
    ],
)
def test_bad_arguments_raise_errors_that_name_them(changes, error, message):
    with pytest.raises(error, match=message):
        fast.ExperimentBatch(**_arguments(**changes))


def test_bad_advance_budget_raises():
    batch = fast.ExperimentBatch(**_arguments())
    with pytest.raises(ValueError, match="max_steps=-1 is out of range"):
        batch.advance(-1)


# --- building ------------------------------------------------------------------------------------


def test_build_is_cached_and_a_second_load_does_not_recompile(tmp_path, monkeypatch):
    monkeypatch.setenv("FACTORQ_CACHE_DIR", str(tmp_path))
    _, first = loader._build()
    _, second = loader._build()
    assert first["compiled"] and not second["compiled"]
    assert first["path"] == second["path"] and os.path.dirname(first["path"]) == str(tmp_path)
    assert [path.suffix for path in tmp_path.iterdir()] == [".so"]


def test_concurrent_builds_into_one_cache_do_not_clash(tmp_path, monkeypatch):
    monkeypatch.setenv("FACTORQ_CACHE_DIR", str(tmp_path))
    results, errors = [], []

    def build():
        try:
            results.append(loader._build()[1]["path"])
        except Exception as error:  # reported below
            errors.append(error)

    workers = [threading.Thread(target=build) for _ in range(3)]
    for worker in workers:
        worker.start()
    for worker in workers:
        worker.join()
    assert not errors and len(set(results)) == 1
    assert [path.suffix for path in tmp_path.iterdir()] == [".so"]


def test_missing_compiler_makes_the_fast_path_unavailable_with_a_reason(tmp_path, monkeypatch):
    monkeypatch.setenv("FACTORQ_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv("FACTORQ_CC", "/nonexistent/cc")
    monkeypatch.setattr(loader, "_library", None)
    monkeypatch.setattr(loader, "_reason", None)
    assert not fast.is_available()
    assert "FACTORQ_CC='/nonexistent/cc' is not an executable C compiler" in (
        fast.unavailable_reason()
    )
    with pytest.raises(RuntimeError, match="fast path is unavailable"):
        fast.ExperimentBatch(**_arguments())


def test_failing_compiler_gives_its_error_as_the_reason(tmp_path, monkeypatch):
    compiler = tmp_path / "broken-cc"
    compiler.write_text('#!/bin/sh\n[ "$1" = --version ] && echo broken 1.0 && exit 0\n'
                        'echo "error: no space left" >&2\nexit 3\n')  # fmt: skip
    compiler.chmod(compiler.stat().st_mode | stat.S_IXUSR)
    monkeypatch.setenv("FACTORQ_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setenv("FACTORQ_CC", str(compiler))
    with pytest.raises(loader._Unavailable, match="failed \\(exit 3\\): error: no space left"):
        loader._build()
    assert list((tmp_path / "cache").iterdir()) == []  # no half-written file left behind


def test_an_interrupt_waits_for_the_helper_threads_before_leaving_advance():
    # Ctrl-C reaches the main thread's share of the work; the helpers still run the kernel on the
    # batch, which must stay alive until they return (leaving at once freed it under them: a
    # crash). The library is replaced by one whose main-thread call raises KeyboardInterrupt.
    batch = _batch(periods=(0, 10, 1, 0), threads=3)
    finished, main = [], threading.get_ident()

    class Interrupted:
        def fq_advance(self, *arguments):
            if threading.get_ident() == main:
                raise KeyboardInterrupt
            threading.Event().wait(0.3)  # a helper busy with its chunk
            finished.append(threading.get_ident())
            return 0

    batch._library = Interrupted()
    with pytest.raises(KeyboardInterrupt):
        batch.advance(10)
    assert len(finished) == 2  # both helpers had returned before advance raised
