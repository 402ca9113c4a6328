"""The fast path covers every body (issue 11): the compiled kernel's generic loop equals the
modular torchrl path bit for bit on randomly drawn configurations (bodies, layouts, distractors,
permutations, sensor and actuator noise, worlds, grid sizes)."""

from __future__ import annotations

import random

import pytest

from factorq_trainers.commands.paper import command as paper
from factorq_trainers.commands.paper.config import PaperConfig
from factorq_trainers.compiled import fast
from factorq_trainers.runner.results import dumps as dumps_results

pytestmark = pytest.mark.skipif(
    not fast.is_available(), reason=f"fast path unavailable: {fast.unavailable_reason()}"
)


def draw_config(generator: random.Random) -> dict:
    return {
        "seeds": 2,
        "runs": 2,
        "episodes": 3,
        "size": generator.choice([3, 4, 5]),
        "obstacles": generator.choice([0, 1, 2]),
        "max_steps": generator.choice([40, 150]),
        "body": generator.choice(["translate", "heading"]),
        "sensors": generator.choice(["cross", "ring"]),
        "distractors": generator.choice([0, 1, 3]),
        "sensor_permutation": generator.choice([None, generator.randrange(1000)]),
        "sensor_noise": generator.choice([0.0, 0.1]),
        "actuator_noise": generator.choice([0.0, 0.2]),
        "epsilon": generator.choice([0.01, 0.2]),
    }


@pytest.mark.parametrize("draw", range(6))
def test_kernel_equals_the_modular_path_on_random_body_configurations(draw):
    options = draw_config(random.Random(draw))
    compiled = paper.run(PaperConfig(**options, backend="fast", threads=1))
    modular = paper.run(PaperConfig(**options, backend="modular"))
    assert compiled["timing"]["backend"] == "fast"
    assert modular["timing"]["backend"] == "modular"
    assert dumps_results(compiled["cells"]) == dumps_results(modular["cells"]), options


def test_auto_runs_every_body_on_the_fast_path():
    config = PaperConfig(body="heading", sensors="ring", distractors=4, sensor_permutation=1)
    assert paper.resolve_backend(config) == "fast"
    assert fast.unsupported_reason(config.world) is None


def test_kernel_results_for_a_body_do_not_depend_on_threads_or_chunking():
    options = {**draw_config(random.Random(11)), "body": "heading", "sensor_noise": 0.1}
    one = paper.run(PaperConfig(**options, backend="fast", threads=1))
    two = paper.run(PaperConfig(**options, backend="fast", threads=2))
    assert dumps_results(one["cells"]) == dumps_results(two["cells"])


def test_a_body_batch_resumes_exactly_from_its_state_dict():
    import torch

    from factorq_envs.grid_world import WorldConfig
    from factorq_torch.base.config import AgentConfig
    from factorq_torch.base.rng import STREAM_POLICY, STREAM_WORLD, derive_keys

    world = WorldConfig(
        size=5, num_obstacles=3, max_steps=100, body="heading", sensors="ring",
        num_distractors=2, sensor_permutation=4, sensor_noise=0.1, actuator_noise=0.1,
    )  # fmt: skip
    periods = torch.tensor([0, 10, 1])
    keys = derive_keys(0, STREAM_WORLD, 3), derive_keys(0, STREAM_POLICY, 3)

    def batch():
        return fast.ExperimentBatch(
            "factor-q", periods, world, AgentConfig(), 2, 4, *keys, threads=1
        )

    whole = batch()
    while not whole.done:
        whole.advance(1 << 40)
    first = batch()
    first.advance(97)
    resumed = batch()
    resumed.load_state_dict(first.state_dict())
    while not resumed.done:
        resumed.advance(50)
    for name, value in whole.metrics().items():
        assert torch.equal(value, resumed.metrics()[name]), name
    for name, value in whole.tables().items():
        assert torch.equal(value, resumed.tables()[name]), name


NOISY = {
    "size": 5, "obstacles": 3, "max_steps": 150, "body": "heading", "sensors": "ring",
    "distractors": 2, "sensor_permutation": 5, "sensor_noise": 0.1, "actuator_noise": 0.1,
    "epsilon": 0.05, "episodes": 8,
}  # fmt: skip


@pytest.mark.parametrize("draw", [0, 1, 2, 3, "noisy"])
def test_kernel_equals_the_reference_written_from_the_sensor_names(draw):
    import torch
    from reference import run_body_experiment  # tests/reference.py

    from factorq_envs.grid_world import static_layout
    from factorq_torch.base.config import AgentConfig
    from factorq_torch.base.rng import MASK64, STREAM_POLICY, STREAM_WORLD, derive_keys

    if draw == "noisy":
        options = {**draw_config(random.Random(50)), **NOISY}
    else:
        options = draw_config(random.Random(50 + draw))
    world = PaperConfig(**options).world
    agent = AgentConfig(epsilon=options["epsilon"])
    runs, episodes = 2, options["episodes"]
    periods = torch.tensor([0, 10, 1])
    world_keys = derive_keys(7, STREAM_WORLD, 3)
    policy_keys = derive_keys(7, STREAM_POLICY, 3)
    static = static_layout(world).tolist()
    for algorithm in ("q-learning", "factor-q"):
        batch = fast.ExperimentBatch(
            algorithm, periods, world, agent, runs, episodes, world_keys, policy_keys, threads=1
        )
        while not batch.done:
            batch.advance(1 << 40)
        metrics = batch.metrics()
        for index, period in enumerate(periods.tolist()):
            want = run_body_experiment(
                algorithm, period, world, agent, runs, episodes,
                int(world_keys[index]) & MASK64, int(policy_keys[index]) & MASK64, static,
            )  # fmt: skip
            for name in ("steps", "collisions", "greedy_collisions", "task_return"):
                got = metrics[name][index].tolist()
                assert got == getattr(want, name), (algorithm, period, name, options)


def _risk_metrics(world, agent, backend: str, seeds: int = 3, runs: int = 2, episodes: int = 2):
    """Factor-Q with ``agent``'s risk options on ``backend``: metrics and tables."""
    import torch

    from factorq_torch.base.rng import STREAM_POLICY, STREAM_WORLD, derive_keys
    from factorq_torch.collectors import OnlineCollector
    from factorq_trainers.methods import experiment

    periods = torch.tensor([0, 1, 10][:seeds])
    world_keys = derive_keys(5, STREAM_WORLD, seeds)
    policy_keys = derive_keys(5, STREAM_POLICY, seeds)
    if backend == "fast":
        batch = fast.ExperimentBatch(
            "factor-q", periods, world, agent, runs, episodes, world_keys, policy_keys, threads=1
        )
        metrics = batch.run()
        return metrics, batch.tables()["rho"]
    env = experiment.make_env(world, periods, world_keys)
    task, local = experiment.tabular_values("factor-q", seeds, world)
    env, policy, loss = experiment.online_agent(env, task, local, agent, policy_keys)
    collector = OnlineCollector(env, policy, loss, runs=runs, episodes=episodes)
    while not collector.done:
        collector.step()
    return dict(collector.metrics.items()), local.rho.detach().clone()


@pytest.mark.parametrize(
    ("body", "noise", "gate", "exploration"),
    [
        ("heading", 0.1, True, "uniform"),
        ("heading", 0.1, True, "risk-aware"),
        ("translate", 0.05, False, "risk-aware"),
        ("translate", 0.0, True, "risk-aware"),
    ],
)
def test_kernel_equals_the_modular_path_with_the_risk_gate_and_risk_aware_exploration(
    body, noise, gate, exploration
):
    import torch

    from factorq_torch.base.config import AgentConfig
    from factorq_trainers.methods.experiment import check_world_options

    world = check_world_options(
        4, 3, 60, 0, ("static", "dynamic"), {"body": body, "sensor_noise": noise}
    )
    # epsilon 0.3: many exploratory actions, so the mask's draw is exercised
    agent = AgentConfig(epsilon=0.3, risk_gate=gate, exploration=exploration)
    compiled, compiled_rho = _risk_metrics(world, agent, "fast")
    modular, modular_rho = _risk_metrics(world, agent, "modular")
    for name, values in compiled.items():
        assert torch.equal(values, modular[name]), name
    assert torch.equal(compiled_rho[..., : modular_rho.shape[-1]], modular_rho)
    assert int(compiled["collisions"].sum()) > 0  # the local tables were exercised


def test_the_risk_options_change_what_the_kernel_does():
    import torch

    from factorq_torch.base.config import AgentConfig
    from factorq_trainers.methods.experiment import check_world_options

    world = check_world_options(4, 3, 60, 0, ("static",), {"body": "heading", "sensor_noise": 0.1})
    paper_agent, _ = _risk_metrics(world, AgentConfig(epsilon=0.3), "fast")
    for options in ({"risk_gate": True}, {"exploration": "risk-aware"}):
        changed, _ = _risk_metrics(world, AgentConfig(epsilon=0.3, **options), "fast")
        assert any(not torch.equal(changed[k], paper_agent[k]) for k in changed), options


def test_risk_aware_exploration_is_refused_for_q_learning_naming_both():
    import torch

    from factorq_torch.base.config import AgentConfig
    from factorq_torch.base.rng import derive_keys
    from factorq_trainers.methods.experiment import check_world_options

    world = check_world_options(4, 0, 60, 0, ("static",))
    keys = derive_keys(0, 0, 1)
    with pytest.raises(ValueError, match=r"exploration='risk-aware'.*algorithm='q-learning'"):
        fast.ExperimentBatch(
            "q-learning",
            torch.tensor([0]),
            world,
            AgentConfig(exploration="risk-aware"),
            1,
            1,
            keys,
            keys,
        )


def test_arbitration_is_refused_on_the_compiled_path_and_reaches_the_modular_agent():
    """The kernel mirrors eqs. 2-3 as the paper writes them: an agent asking for arbitration is
    refused in one line there, never silently run without it; the modular agent gets it."""
    import torch

    from factorq_torch.base.config import AgentConfig
    from factorq_torch.base.rng import derive_keys
    from factorq_trainers.methods.experiment import (
        check_world_options,
        make_env,
        online_agent,
        tabular_values,
    )

    world = check_world_options(4, 0, 60, 0, ("static",))
    keys = derive_keys(0, 0, 1)
    agent = AgentConfig(arbitration=True)
    with pytest.raises(ValueError, match="arbitration is not on the compiled path"):
        fast.ExperimentBatch("factor-q", torch.tensor([0]), world, agent, 1, 1, keys, keys)
    task, local = tabular_values("factor-q", 1, world)
    env = make_env(world, torch.tensor([0]), keys)
    _, policy, loss = online_agent(env, task, local, agent, keys)
    assert policy[-1].arbitration and loss.arbitration
    assert policy[-1].gamma == loss.gamma == agent.gamma
