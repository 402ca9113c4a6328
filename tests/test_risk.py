"""The local-risk layer for any Q-value actor (factorq_torch/risk.py, issue 26)."""

import dataclasses
import logging
import warnings

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.envs import TransformedEnv
from torchrl.modules import EGreedyModule, QValueActor, QValueModule

from factorq_envs import FactoredGridEnv, SplitLocalReward
from factorq_torch.functional import project_local
from factorq_torch.neural import GatedLocalRewardNetwork, LocalRewardNetwork
from factorq_torch.risk import (
    RISK_MASK,
    TASK_VALUE,
    LocalRisk,
    LocalRiskLoss,
    RiskSummary,
    with_local_risk,
)
from factorq_torch.structure import StructureLearner
from factorq_torch.tables import LocalRewardTable


@pytest.fixture(autouse=True, scope="module")
def quiet_torchrl():
    """torchrl's INFO lines (one per replay buffer) quieted for this module, its level put back
    after it (a level changed at import would stay for every later test of the worker)."""
    logger = logging.getLogger("torchrl")
    level = logger.level
    logger.setLevel(logging.WARNING)
    yield
    logger.setLevel(level)


def blocked_north_table(experiments: int = 1) -> LocalRewardTable:
    local = LocalRewardTable(experiments)
    local.rho[:, 0, 1] = -1.0  # north into a sensed obstacle: a collision
    return local


def step(q, sensors) -> TensorDict:
    q, sensors = torch.tensor(q), torch.tensor(sensors)
    return TensorDict(action_value=q, sensors=sensors, batch_size=q.shape[:-1])


# --- eqs. 2-3 ------------------------------------------------------------------------------


def test_combined_value_is_eqs_2_and_3_by_hand():
    # Q = (2, 1, 0, 1), rho = (-1, 0, 0, 0): a_hat = 0, Q_bar = 2/3, a_check = 0, P_bar = 0,
    # G = (2 - 2/3) / (0 + 1) * 1.1 = 1.4667, C = (2 - 1.4667, 1, 0, 1)
    risk = LocalRisk(blocked_north_table())
    td = risk(step([[2.0, 1.0, 0.0, 1.0]], [[True, False, False, False]]))
    g = (2.0 - 2.0 / 3.0) * 1.1
    expected = torch.tensor([[2.0 - g, 1.0, 0.0, 1.0]])
    assert torch.allclose(td["action_value"], expected)
    assert torch.equal(td[TASK_VALUE], torch.tensor([[2.0, 1.0, 0.0, 1.0]]))
    assert td[RISK_MASK].tolist() == [[False, True, True, True]]
    # nothing sensed: rho = 0, G = g_min, C = Q
    td = risk(step([[2.0, 1.0, 0.0, 1.0]], [[False] * 4]))
    assert torch.equal(td["action_value"], torch.tensor([[2.0, 1.0, 0.0, 1.0]]))
    assert td[RISK_MASK].all()


def test_the_online_step_reads_a_table_or_learner_as_its_forward_does():
    # the layer calls local_values on the sensors of a [S] step of a LocalRewardTable or
    # StructureLearner (no module call): the values its forward writes; anything else goes
    # through the provider (its hooks run, its errors name it)
    generator = torch.Generator().manual_seed(3)
    table = LocalRewardTable(2, dependency=torch.tensor([[1, 1, 0], [0, 0, 1]], dtype=torch.bool))
    table.rho.uniform_(-1.0, 0.0, generator=generator)
    learner = StructureLearner(2, num_actions=2, num_sensors=3)
    for _ in range(40):
        readings = torch.rand(2, 3, generator=generator) < 0.5
        action = torch.randint(0, 2, (2,), generator=generator)
        reward = -(readings[:, :2].any(-1, keepdim=True) & (action[:, None] == 0)).float()
        learner.update_running_mean(readings, action, reward.expand(2, 2).contiguous())
    for provider in (table, learner):
        risk = LocalRisk(provider, num_actions=2, batch_size=(2,))
        for _ in range(8):
            sensors = torch.rand(2, 3, generator=generator) < 0.5
            td = TensorDict(action_value=torch.randn(2, 2, generator=generator), sensors=sensors,
                            batch_size=[2])  # fmt: skip
            expected = provider(td.clone())["local_value"]
            assert torch.equal(risk(td.clone())["local_value"], expected)
        calls = []
        handle = provider.register_forward_hook(lambda *args, calls=calls: calls.append(1))
        risk(td.clone())
        handle.remove()
        assert calls == [1]  # with a hook: the module call
        with pytest.raises(ValueError, match=type(provider).__name__):
            risk(td.clone().set("sensors", sensors.float()))  # a float reading: its error


def test_mask_never_leaves_no_action():
    local = LocalRewardTable(1)
    local.rho[:, :, 1] = -1.0
    td = LocalRisk(local)(step([[0.0, 0.0, 0.0, 0.0]], [[True] * 4]))
    assert td[RISK_MASK].all()


@pytest.mark.parametrize("batch", [(), (5,), (3, 2)])
def test_one_provider_serves_any_batch_of_worlds(batch):
    """S = 1: one shared provider for every world (torchrl's one-agent recipe)."""
    generator = torch.Generator().manual_seed(0)
    sensors = torch.rand(*batch, 4, generator=generator) < 0.5
    q = torch.rand(*batch, 4, generator=generator)
    providers = [
        blocked_north_table(),
        LocalRewardNetwork(1, zero_output=False),
        GatedLocalRewardNetwork(1, num_actions=4, num_sensors=4),
        StructureLearner(1, num_actions=4, num_sensors=4),
    ]
    for provider in providers:
        td = TensorDict(action_value=q, sensors=sensors, batch_size=batch)
        out = LocalRisk(provider)(td)
        assert out["action_value"].shape == (*batch, 4)
        flat_sensors, flat_q = sensors.reshape(-1, 4), q.reshape(-1, 4)
        one_by_one = torch.stack(
            [
                LocalRisk(provider)(
                    step(flat_q[i : i + 1].tolist(), flat_sensors[i : i + 1].tolist())
                )["action_value"][0]
                for i in range(flat_q.shape[0])
            ]
        )
        assert torch.allclose(out["action_value"].reshape(-1, 4), one_by_one, atol=1e-6)


# --- with torchrl's modules -------------------------------------------------------------------


def grid(batch_size=(1,), keep_reward=True, **kwargs):
    base = FactoredGridEnv(size=4, num_obstacles=2, batch_size=batch_size, **kwargs)
    return TransformedEnv(base, SplitLocalReward(keep_reward=keep_reward))


def q_actor(env, values=None):
    """A QValueActor over the cell whose values are fixed (north best everywhere)."""
    values = torch.tensor([1.0, 0.5, 0.0, 0.0]) if values is None else values

    class Fixed(torch.nn.Module):
        def forward(self, cell):
            return values.expand(*cell.shape, 4).clone()

    return QValueActor(
        TensorDictModule(Fixed(), in_keys=["cell"], out_keys=["action_value"]),
        in_keys=["cell"],
        spec=env.action_spec_unbatched,
    )


def test_with_local_risk_splices_the_layer_before_qvaluemodule():
    env = grid(batch_size=(2,), seed=0)
    actor = with_local_risk(q_actor(env), blocked_north_table(), env=env)
    assert isinstance(actor.module[-1], QValueModule)
    assert isinstance(actor.module[-2], LocalRisk)
    td = env.reset()
    td["sensors"] = torch.tensor([[True, False, False, False], [False] * 4])
    td = actor(td)
    assert td["action"].tolist() == [1, 0]  # north blocked in world 0 only
    assert actor.module[-2].actuator_names == ("north", "west", "south", "east")


def test_egreedy_explores_only_among_actions_the_layer_allows():
    env = grid(batch_size=(64,), seed=0)
    actor = with_local_risk(q_actor(env), blocked_north_table(), env=env)
    explore = EGreedyModule(env.action_spec_unbatched, eps_init=1.0, action_mask_key=RISK_MASK)
    policy = TensorDictSequential(actor, explore)
    td = env.reset()
    td["sensors"] = torch.tensor([[True, False, False, False]]).expand(64, 4).clone()
    actions = torch.cat([policy(td.clone())["action"] for _ in range(10)])
    assert not (actions == 0).any() and set(actions.tolist()) == {1, 2, 3}


def test_local_risk_loss_trains_a_table_by_eq_5_and_a_network_by_regression():
    env = grid(batch_size=(8,), seed=1)
    torch.manual_seed(0)
    rollout = env.rollout(60, break_when_any_done=False)  # random actions: collisions
    table = LocalRewardTable(1)
    LocalRiskLoss(table)(rollout)
    assert int(table.kappa.sum()) == 8 * 60  # every transition counted once
    collided = rollout["next", "local_reward"].sum() < 0
    assert collided and torch.allclose(table.rho[0, :, 1], torch.full((4,), -1.0))
    assert table.rho[0, :, 0].eq(0).all()  # no collision where nothing is sensed
    network = LocalRewardNetwork(1)
    loss = LocalRiskLoss(network)
    optimizer = torch.optim.Adam(network.parameters(), lr=0.05)
    first = None
    for _ in range(150):
        value = loss(rollout)["loss_local"]
        first = value.item() if first is None else first
        optimizer.zero_grad()
        value.backward()
        optimizer.step()
    assert value.item() < 0.2 * first
    sensed = TensorDict(action_value=torch.zeros(1, 4), sensors=torch.ones(1, 4, dtype=torch.bool))
    assert (LocalRisk(network)(sensed)["local_value"] < -0.5).all()


def test_structure_learner_learns_the_dependency_through_the_loss():
    env = grid(batch_size=(8,), seed=2)
    torch.manual_seed(1)
    learner = StructureLearner(1, num_actions=4, num_sensors=4)
    loss = LocalRiskLoss(learner)
    for _ in range(2):
        loss(env.rollout(30, break_when_any_done=False))
    assert torch.equal(learner.structure()[0], env.base_env.dependency)


def test_one_provider_per_world_reads_a_rollout_of_experiments_first():
    env = grid(batch_size=(3,), seed=3)
    rollout = env.rollout(20, break_when_any_done=False)  # [3, 20]
    table = LocalRewardTable(3)
    LocalRiskLoss(table)(rollout)
    assert table.kappa.sum(dim=(1, 2)).tolist() == [20, 20, 20]
    for world in range(3):  # world w's transitions went to experiment w's table
        fired = rollout[world]["action"]
        assert table.kappa[world].sum(-1).tolist() == torch.bincount(fired, minlength=4).tolist()
    values = LocalRisk(table).local_values(rollout)
    assert values.shape == (3, 20, 4)
    for world in range(3):
        own = project_local(table.rho[world], rollout[world]["sensors"], table.dependency)
        assert torch.equal(values[world], own)


# --- bad input: one clear error at construction, naming both sides ---------------------------


def test_action_count_mismatch_names_both_sides():
    with pytest.raises(ValueError, match="3 actions .* 4 actuators"):
        LocalRisk(LocalRewardTable(1), num_actions=3)
    env = grid()
    actor = q_actor(env, torch.zeros(4))
    with pytest.raises(ValueError, match="4 actions .* 2 actuators"):
        with_local_risk(actor, LocalRewardTable(1, num_actions=2))


def test_dependency_of_the_wrong_shape_names_both_sides():
    with pytest.raises(ValueError, match=r"dependency has shape \[4, 3\].*\[4, 4\]"):
        LocalRisk(LocalRewardTable(1), dependency=torch.ones(4, 3, dtype=torch.bool))
    env = grid()
    provider = StructureLearner(1, num_actions=4, num_sensors=6)
    with pytest.raises(ValueError, match=r"env's dependency has shape \[4, 4\].*6 sensors"):
        with_local_risk(q_actor(env), provider, env=env)


def test_provider_of_another_batch_size_names_both_sides():
    env = grid(batch_size=(4,))
    with pytest.raises(ValueError, match=r"batch_size \[4\].*S=3"):
        with_local_risk(q_actor(env), LocalRewardTable(3), env=env)
    with_local_risk(q_actor(env), LocalRewardTable(4), env=env)  # one per world: fine
    with_local_risk(q_actor(env), LocalRewardTable(1), env=env)  # shared: fine


def test_batched_action_spec_gets_a_clear_error():
    env = grid(batch_size=(4,))
    actor = QValueActor(torch.nn.Linear(1, 4), in_keys=["x"], spec=env.action_spec)
    with pytest.raises(ValueError, match="action_spec_unbatched"):
        with_local_risk(actor, LocalRewardTable(1), env=env)


def test_not_a_provider_is_refused():
    with pytest.raises(TypeError, match="provider"):
        LocalRisk(torch.nn.Linear(4, 4))


# --- explanations ----------------------------------------------------------------------------


def test_explain_names_the_actuator_the_amount_and_the_sensor():
    env = grid()
    actor = with_local_risk(q_actor(env), blocked_north_table(), env=env)
    risk = actor.module[-2]
    td = env.reset()
    td["sensors"] = torch.tensor([[True, True, False, False]])
    td = actor(td)
    (entries,) = risk.explain(td)
    assert [entry["actuator"] for entry in entries] == ["north"]
    assert entries[0]["sensors"] == ["north"] and entries[0]["penalty"] < -0.05
    assert risk.explain_text(td) == [f"north: {entries[0]['penalty']:.2f}, north blocked"]
    summary = RiskSummary(risk.actuator_names)
    summary.update(td)
    report = summary.episode()
    assert report["penalised"]["north"] == 1 and report["overrides"] == 1
    assert report["mean_penalty"]["north"] == pytest.approx(entries[0]["penalty"])
    assert report["penalised"]["south"] == 0 and report["mean_penalty"]["south"] == 0.0
    assert "north x1" in RiskSummary.line(report)
    assert summary.episode()["steps"] == 0  # the next episode starts empty


def test_learned_structure_explains_with_the_committed_parents():
    learner = StructureLearner(1, num_actions=4, num_sensors=4)
    generator = torch.Generator().manual_seed(0)
    for _ in range(300):
        sensors = torch.rand(1, 4, generator=generator) < 0.5
        action = torch.randint(0, 4, (1,), generator=generator)
        reward = -(sensors.float())  # actuator a collides when sensor a reads 1
        learner.update_running_mean(sensors, action, reward)
    risk = LocalRisk(learner)
    td = risk(step([[0.0, 0.0, 1.0, 0.0]], [[False, False, True, False]]))
    (entries,) = risk.explain(td)
    assert entries[0]["actuator"] == "actuator 2" and entries[0]["sensors"] == ["sensor 2"]


def test_explain_names_sensors_of_a_provider_that_does_not_say_how_many():
    """A provider without ``num_sensors`` and a given dependency: the parents are named
    ``sensor k`` (explain raised TypeError, indexing the missing names)."""
    from tensordict.nn import TensorDictModuleBase

    class Provider(TensorDictModuleBase):
        num_experiments, num_actions = 1, 4

        def __init__(self) -> None:
            super().__init__()
            self.in_keys, self.out_keys = ["sensors"], ["local_value"]

        def forward(self, td):  # actuator a collides when sensor a reads 1
            td.set("local_value", -td.get("sensors").to(torch.float32))
            return td

    risk = LocalRisk(Provider(), dependency=torch.eye(4, dtype=torch.bool))
    assert risk.sensor_names is None
    (entries,) = risk.explain(risk(step([[0.0, 0.0, 1.0, 0.0]], [[True, True, False, False]])))
    assert [(e["actuator"], e["sensors"]) for e in entries] == [
        ("actuator 0", ["sensor 0"]),
        ("actuator 1", ["sensor 1"]),
    ]


# --- the recipe: torchrl's DQN alone vs DQN + local risk -------------------------------------


@pytest.mark.slow
@pytest.mark.float_sensitive  # a learned outcome of a network: tried under other CPU kernels
def test_dqn_with_local_risk_collides_far_less_in_training(one_thread):
    from factorq_trainers.commands.risk.command import run_unit
    from factorq_trainers.commands.risk.config import RiskConfig

    config = RiskConfig(
        steps=250, grid_size=4, grid_obstacles=2, learning_starts=50, eval_episodes=0
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        totals = {}
        for method in ("dqn", "dqn+risk"):
            totals[method] = sum(
                run_unit(config, {"world": "grid", "method": method, "seed": seed})[
                    "train_collisions"
                ]
                for seed in (0, 1)
            )
    assert totals["dqn"] >= 4 * max(1, totals["dqn+risk"]), totals


def test_risky_faces_mark_the_side_of_each_penalised_actuator():
    from factorq_envs.grid_world import WorldConfig
    from factorq_envs.render import mark_risk, render_rgb, risky_faces

    body = WorldConfig().body_spec
    faces = risky_faces(torch.tensor([-1.0, 0.0, -0.01, -0.3]), 0, body)
    assert faces == [(0, -1.0), (3, pytest.approx(-0.3))]  # north and east, not the small one
    frame = render_rgb(0, torch.zeros(4, dtype=torch.bool), 2, scale=12)
    marked = mark_risk(frame.copy(), 0, 2, faces, scale=12)
    changed = (marked != frame).any(-1)
    rows, cols = changed.nonzero()
    assert rows.min() == 12 and cols.max() == 23  # the agent's cell: its north and east edges
    assert changed.sum() > 0 and (marked[changed] == (245, 150, 20)).all()


# --- the side-by-side command module (trainers/commands/risk/command.py) ---------------


def test_risk_experiment_units_summary_and_report(tmp_path):
    from factorq_trainers.commands.risk import command as experiment
    from factorq_trainers.commands.risk import report as risk_report

    config = experiment.RiskConfig(
        worlds=("grid",), methods=("dqn", "dqn+risk", "sb3-dqn"), seeds=2
    )
    found = experiment.units(config)
    assert [unit["id"] for unit in found] == [
        "grid/dqn/0",
        "grid/dqn/1",
        "grid/dqn+risk/0",
        "grid/dqn+risk/1",
        "grid/sb3-dqn/0",
        "grid/sb3-dqn/1",
    ]
    minigrid = experiment.RiskConfig(worlds=("minigrid",), methods=("sb3-dqn",))
    assert experiment.units(minigrid) == []  # sb3 only on sb3_worlds

    def result(method, seed, collisions, final):
        return {
            "world": "grid",
            "method": method,
            "seed": seed,
            "train_collisions": collisions,
            "greedy_collisions": 0,
            "final_return": final,
            "greedy_success": 1.0,
            "steps_to_threshold": None if seed else 500,
            "wall_s": 1.0,
        }

    results = experiment.summarise(
        config,
        [
            result("dqn", 0, 200, -11.0),
            result("dqn", 1, 100, -12.0),
            result("dqn+risk", 0, 10, -10.0),
            result("dqn+risk", 1, 5, -11.0),
        ],
    )
    results["config"] = dataclasses.asdict(config)  # the runner's envelope adds it
    (ratio,) = results["ratios"]
    assert ratio["collision_ratio"] == pytest.approx(150.0 / 7.5)
    assert ratio["return_gain"] == pytest.approx(1.0)
    report = risk_report.markdown(results)
    assert "| grid | dqn | 150.0 |" in report and "20.0x" in report and "(1/2)" in report
    risk_report.figure(results, tmp_path / "risk.png")
    assert (tmp_path / "risk.png").stat().st_size > 0


@pytest.mark.parametrize(
    "field, value",
    [
        ("worlds", ("mars",)),
        ("methods", ("ppo",)),
        ("seeds", 0),
        ("tau", 2.0),
        ("sb3_worlds", ("highway",)),  # the sb3 methods run on the gymnasium grid only
    ],
)
def test_risk_experiment_config_names_the_bad_field(field, value):
    from factorq_trainers.commands.risk.config import RiskConfig

    with pytest.raises(ValueError, match=field):
        RiskConfig(**{field: value})


def test_any_value_network_a_dueling_head():
    class Dueling(torch.nn.Module):  # Q = V + A - mean(A)
        def __init__(self) -> None:
            super().__init__()
            self.value, self.advantage = torch.nn.Linear(6, 1), torch.nn.Linear(6, 4)

        def forward(self, observation):
            advantage = self.advantage(observation)
            return self.value(observation) + advantage - advantage.mean(-1, keepdim=True)

    from torchrl.data import Categorical

    torch.manual_seed(0)
    actor = QValueActor(Dueling(), in_keys=["observation"], spec=Categorical(4))
    acting = with_local_risk(actor, blocked_north_table())
    sensors = torch.tensor([[True, False, False, False]]).expand(32, 4)
    td = acting(TensorDict(observation=torch.randn(32, 6), sensors=sensors, batch_size=[32]))
    assert not (td["action"] == 0).any()  # north is never the choice where it is blocked
    assert (td[TASK_VALUE].argmax(-1) == 0).any()  # though the task values sometimes prefer it


def test_over_the_projects_task_table_it_is_factor_q_policys_combined_value():
    from factorq_torch.policy import FactorQPolicy
    from factorq_torch.tables import TaskQTable

    generator = torch.Generator().manual_seed(3)
    task, local = TaskQTable(4, num_cells=9), LocalRewardTable(4)
    with torch.no_grad():
        task.table.copy_(torch.randn(task.table.shape, generator=generator))
        local.rho.copy_(-torch.rand(local.rho.shape, generator=generator))
    td = TensorDict(
        cell=torch.tensor([0, 3, 5, 8]),
        sensors=torch.rand(4, 4, generator=generator) < 0.5,
        batch_size=[4],
    )
    layer = TensorDictSequential(task, LocalRisk(local))(td.clone())
    policy = TensorDictSequential(task, local, FactorQPolicy(4, epsilon=0.0))(td.clone())
    assert torch.equal(layer["action_value"], policy["combined_value"])  # the same functions


def test_factorq_risk_runs_through_the_runner_and_writes_its_files(tmp_path, capsys):
    # the command as a user types it: the runner's frame calls units, run_unit, summarise,
    # markdown and figure, and writes the three files under --out
    import json

    from factorq_torch.base import risk_text
    from factorq_torch.risk import RiskSummary
    from factorq_trainers import cli

    class Records(logging.Handler):  # torchrl's logger does not propagate: listen on it
        def __init__(self):
            super().__init__(logging.DEBUG)
            self.records = []

        def emit(self, record):
            self.records.append(record)

    torchrl_logger = logging.getLogger("torchrl")
    level, records = torchrl_logger.level, Records()
    torchrl_logger.addHandler(records)
    torchrl_logger.setLevel(logging.INFO)  # torchrl's default (quiet_torchrl quiets it)
    out = tmp_path / "risk"
    args = ["risk", "--worlds", "grid", "--methods", "dqn,dqn+risk", "--seeds", "1"]
    args += ["--steps", "60", "--learning-starts", "20", "--eval-episodes", "1", "--out", str(out)]
    args += ["--grid-size", "3", "--grid-obstacles", "1"]  # episodes that end within 60 steps
    try:
        assert cli.main(args) == 0, capsys.readouterr().err
        after = torchrl_logger.level
    finally:
        torchrl_logger.removeHandler(records)
        torchrl_logger.setLevel(level)
    # no torchrl INFO line during the command (its replay buffer logs one per unit), and
    # torchrl's own level back after it
    assert [r.getMessage() for r in records.records if r.levelno < logging.WARNING] == []
    assert after == logging.INFO
    assert {path.name for path in out.iterdir()} >= {"risk.json", "risk.md", "risk.png"}
    report = (out / "risk.md").read_text()
    assert "dqn+risk" in report
    # the layer's per-episode RiskSummary in the results, summed in the report
    results = json.loads((out / "risk.json").read_text())
    (episodes,) = results["risk_log"].values()  # the layered unit only
    assert episodes and sum(e["steps"] for e in episodes) <= 60
    assert set(episodes[0]["penalised"]) == {"north", "east", "south", "west"}
    (row,) = results["risk_rows"]
    assert row["method"] == "dqn+risk" and row["episodes"] == len(episodes)
    assert row["steps"] == sum(e["steps"] for e in episodes)
    assert "What the layer did" in report
    assert risk_text.summary_line(episodes[-1]) == RiskSummary.line(episodes[-1])
    assert f"- grid dqn+risk: {RiskSummary.line(episodes[-1])}" in report


# --- highway-env through the Gymnasium adapter (the highway extra) ----------------------------


def test_highway_world_reads_kinematics_and_sensors_and_masks_by_its_penalty():
    pytest.importorskip("highway_env")
    from factorq_envs import highway
    from factorq_trainers.commands.risk import methods as risk_methods
    from factorq_trainers.commands.risk.config import RiskConfig

    env = risk_methods.make_env(RiskConfig(worlds=("highway",)), "highway", 0)
    assert env.reward_key == "reward"  # the conventional reward, what the recipe reads
    encoder, width = risk_methods.features(env)
    assert encoder.out_keys == ["features"]  # the Kinematics stay under "observation"
    td = encoder(env.reset())
    assert width == 5 * 5 + 6 and td["features"].shape == (1, width)
    assert td["observation"].shape == (1, 5, 5)
    # "risky" is a crash more likely than not: half of highway's penalty 2/3
    assert risk_methods._penalty(env) == pytest.approx(highway.PENALTY)
    assert torch.equal(env.base_env.dependency, torch.tensor(highway.ORACLE))
    env.close()


def test_factorq_risk_runs_on_highway_through_the_runner(tmp_path, capsys):
    # a few steps of each torchrl method on highway-fast-v0: the files, a crash counted as a
    # collision, survival as success, the layer's log with highway's actuator names
    pytest.importorskip("highway_env")
    import json

    from factorq_trainers import cli

    out = tmp_path / "risk"
    args = ["risk", "--worlds", "highway", "--seeds", "1", "--steps", "36"]  # an episode ends by 30
    args += ["--learning-starts", "10", "--eval-episodes", "1", "--out", str(out)]
    assert cli.main(args) == 0, capsys.readouterr().err
    results = json.loads((out / "risk.json").read_text())
    rows = {row["method"]: row for row in results["rows"]}
    assert set(rows) == {"dqn", "dqn+risk", "dqn+risk-learned"}
    for row in rows.values():
        assert row["world"] == "highway" and 0 <= row["greedy_success"] <= 1
        assert row["greedy_collisions"] in (0.0, 1.0)  # one greedy episode: a crash ends it
        assert row["greedy_success"] == 1.0 - row["greedy_collisions"]
    episodes = results["risk_log"]["highway/dqn+risk/0"]
    assert set(episodes[0]["penalised"]) == set(
        ("LANE_LEFT", "IDLE", "LANE_RIGHT", "FASTER", "SLOWER")
    )
    # the learner's structure kept beside the declared oracle, and shown in the report
    found = results["structures"]["highway/dqn+risk-learned/0"]
    assert found["actuators"][0] == "LANE_LEFT" and found["oracle"][0] == ["left<1s", "left<3s"]
    assert len(found["parents"]) == 5
    report = (out / "risk.md").read_text()
    assert "| highway | dqn |" in report and "- highway/dqn+risk-learned/0: " in report
