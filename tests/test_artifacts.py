"""Agents as artifacts (issue 38, deliver 5): ``save_agent`` / ``load_agent`` of the tables, a
learned structure and a ``LocalRisk`` layer, the file checks at load, ``find_local_risk`` and
``RiskSummary.for_env``."""

import os

import pytest
import torch
from tensordict import TensorDict

import factorq_torch
from factorq_envs.torchrl_env import FactoredGridEnv
from factorq_torch.artifacts import AgentFileError, load_agent, save_agent
from factorq_torch.base.files import digest
from factorq_torch.neural import GatedLocalRewardNetwork, LocalRewardNetwork, TaskQNetwork
from factorq_torch.risk import LocalRisk, RiskSummary, find_local_risk, with_local_risk
from factorq_torch.structure import StructureLearner
from factorq_torch.tables import LocalRewardTable, TaskQTable


def _states_equal(first, second):
    one, two = first.state_dict(), second.state_dict()
    return list(one) == list(two) and all(
        one[name].dtype == two[name].dtype and torch.equal(one[name], two[name]) for name in one
    )


def _trained_learner():
    learner = StructureLearner(2, num_actions=2, num_sensors=3, pairs="pruned", window=20)
    generator = torch.Generator().manual_seed(1)
    for _ in range(80):  # sensor 1 decides actuator 0's collision, sensor 2 actuator 1's
        sensors = torch.rand(2, 3, generator=generator) < 0.5
        action = torch.randint(0, 2, (2,), generator=generator)
        reward = -torch.stack((sensors[:, 1], sensors[:, 2]), dim=1).float()
        learner.update_running_mean(sensors, action, reward)
    return learner


@pytest.fixture
def env():
    return FactoredGridEnv(size=5, num_obstacles=2, batch_size=(1,), seed=0)


def test_tables_and_learner_round_trip(tmp_path):
    generator = torch.Generator().manual_seed(0)
    task = TaskQTable(3, num_cells=9, with_sensors=True, num_headings=4, sparse_grad=True)
    with torch.no_grad():
        task.table.copy_(torch.randn(task.table.shape, generator=generator))
    dependency = torch.tensor([[True, True, False], [False, False, True]])
    local = LocalRewardTable(2, dependency=dependency, sensors_key="obs_sensors")
    local.rho.copy_(torch.randn(local.rho.shape, generator=generator))
    local.kappa.copy_(torch.randint(0, 9, local.kappa.shape, generator=generator))
    learner = _trained_learner()
    assert int((learner.committed >= 0).sum()) > 0  # something learned to carry over
    for module in (task, local, learner):
        path = save_agent(module, tmp_path / f"{type(module).__name__}.pt")
        loaded = load_agent(path)
        assert type(loaded) is type(module) and loaded is not module
        assert _states_equal(loaded, module)
    assert load_agent(tmp_path / "TaskQTable.pt").sparse_grad
    assert load_agent(tmp_path / "TaskQTable.pt").num_headings == 4
    assert load_agent(tmp_path / "LocalRewardTable.pt").sensors_key == "obs_sensors"
    rebuilt = load_agent(tmp_path / "StructureLearner.pt")
    assert torch.equal(rebuilt.structure(), learner.structure())
    assert (rebuilt.pairs, rebuilt.window) == ("pruned", 20)


def test_networks_round_trip_with_their_shapes_and_outputs(tmp_path):
    dependency = torch.tensor([[True, True, False], [False, False, True], [False, False, False]])
    networks = (
        TaskQNetwork(2, 9, with_proximity=True, num_sensors=3, hidden=(5, 3), seed=4),
        LocalRewardNetwork(2, dependency=dependency, hidden=(6,), bias=True, shared=False, seed=5),
        LocalRewardNetwork(1, activation="relu", zero_output=False, seed=6),
        GatedLocalRewardNetwork(1, num_actions=3, num_sensors=3, hidden=(4,), l1=0.01, seed=7),
    )
    generator = torch.Generator().manual_seed(2)
    for number, network in enumerate(networks):
        with torch.no_grad():  # trained-looking weights, none of them zero
            for parameter in network.parameters():
                parameter.copy_(torch.randn(parameter.shape, generator=generator))
        loaded = load_agent(save_agent(network, tmp_path / f"{number}.pt"))
        assert type(loaded) is type(network) and _states_equal(loaded, network)
        size = network.num_experiments
        sensors = torch.rand(size, network.num_sensors, generator=generator) < 0.5
        td = TensorDict(cell=torch.tensor([0, 8][:size]), sensors=sensors, batch_size=[size])
        key = network.out_keys[0]
        assert torch.equal(loaded(td.clone())[key], network(td.clone())[key])
    assert torch.equal(load_agent(tmp_path / "1.pt").parent_index, networks[1].parent_index)
    assert load_agent(tmp_path / "2.pt").network.activation is torch.relu
    assert load_agent(tmp_path / "3.pt").l1 == 0.01
    layer = LocalRisk(networks[3])
    assert _states_equal(load_agent(save_agent(layer, tmp_path / "layer.pt")), layer)


def test_a_layer_round_trips_with_its_provider_and_gives_the_same_outputs(tmp_path, env):
    for provider in (LocalRewardTable(1, dependency=env.dependency), _one_learner()):
        layer = LocalRisk(
            provider,
            actuator_names=env.config.actuator_names,
            sensor_names=env.config.sensor_names,
            eta=0.2,
            mask_threshold=0.3,
            out_key="combined",
        )
        if isinstance(provider, LocalRewardTable):
            provider.rho.copy_(-torch.rand(provider.rho.shape, generator=torch.Generator()))
        path = save_agent(layer, tmp_path / "layer.pt")
        loaded = load_agent(path, env=env)
        assert isinstance(loaded, LocalRisk) and type(loaded.provider) is type(provider)
        assert (loaded.eta, loaded.mask_threshold, loaded.out_key) == (0.2, 0.3, "combined")
        assert loaded.actuator_names == layer.actuator_names
        sensors = torch.tensor([[True, False, True, False], [False, True, True, True]])
        td = TensorDict(action_value=torch.randn(2, 4), sensors=sensors, batch_size=[2])
        mine, theirs = layer(td.clone()), loaded(td.clone())
        for key in ("combined", "risk_mask", "risk_normaliser"):
            assert torch.equal(mine[key], theirs[key])


def _one_learner():
    learner = StructureLearner(1, num_actions=4, num_sensors=4)
    for step in range(40):
        sensors = torch.tensor([[bool(step & 1), bool(step & 2), False, True]])
        learner.update_running_mean(sensors, torch.tensor([step % 4]), -sensors.float())
    return learner


def test_another_body_is_one_error_naming_both_sides(tmp_path, env):
    layer = with_local_risk(TaskQTable(1, num_cells=25), LocalRewardTable(1), env=env)
    path = save_agent(find_local_risk(layer), tmp_path / "layer.pt")
    other = FactoredGridEnv(size=5, num_obstacles=2, batch_size=(1,), body="heading", seed=0)
    with pytest.raises(AgentFileError) as caught:
        load_agent(path, env=other)
    message = str(caught.value)
    assert "\n" not in message and str(path) in message
    assert "north, west, south, east" in message and "forward, turn-left, turn-right" in message
    # a table saved with the env's names is checked the same way
    table_path = save_agent(LocalRewardTable(1), tmp_path / "table.pt", env=env)
    with pytest.raises(AgentFileError, match="turn-left"):
        load_agent(table_path, env=other)
    assert load_agent(table_path, env=env).num_actions == 4
    with pytest.raises(AgentFileError, match="the env has"):  # at save too
        save_agent(LocalRewardTable(1, num_actions=3), tmp_path / "x.pt", env=env)


def test_a_layer_without_names_is_checked_by_its_counts(tmp_path, env):
    path = save_agent(LocalRisk(LocalRewardTable(1)), tmp_path / "layer.pt")
    assert load_agent(path, env=env).actuator_names == (
        "actuator 0",
        "actuator 1",
        "actuator 2",
        "actuator 3",
    )
    other = FactoredGridEnv(size=5, num_obstacles=2, batch_size=(1,), body="heading", seed=0)
    with pytest.raises(AgentFileError, match=r"actuators \(4 unnamed\)"):
        load_agent(path, env=other)


def _rewrite(path, change):
    record = torch.load(path, weights_only=True)
    change(record)
    torch.save(record, path)


def test_another_version_or_an_edit_is_refused(tmp_path, monkeypatch):
    path = save_agent(LocalRewardTable(1), tmp_path / "table.pt")
    original = path.read_bytes()

    def older(record):
        record["package_version"] = "0.0.1"

    _rewrite(path, older)
    with pytest.raises(AgentFileError, match=r"written by factorq_torch '0\.0\.1'"):
        load_agent(path)

    def edited(record):
        record["content"]["state"]["rho"][0, 0, 0] = 5.0  # not signed again

    path.write_bytes(original)
    _rewrite(path, edited)
    with pytest.raises(AgentFileError, match="does not match its digest"):
        load_agent(path)

    def resigned(record):  # an edit signed again: the constructor and the strict load check it
        record["content"]["state"]["rho"] = torch.zeros(1, 3, 2)
        record["sha256"] = digest(record["content"])

    path.write_bytes(original)
    _rewrite(path, resigned)
    with pytest.raises(AgentFileError, match="cannot be rebuilt"):
        load_agent(path)

    def another_kind(record):
        record["content"]["kind"] = "os.system"
        record["sha256"] = digest(record["content"])

    path.write_bytes(original)
    _rewrite(path, another_kind)
    with pytest.raises(AgentFileError, match="unknown kind 'os.system'"):
        load_agent(path)
    path.write_bytes(original)
    assert load_agent(path).num_actions == 4


@pytest.mark.parametrize("keep", [0, 10, 200, -7])
def test_a_truncated_file_is_one_line_naming_it(tmp_path, keep):
    path = save_agent(LocalRewardTable(1), tmp_path / "table.pt")
    data = path.read_bytes()
    path.write_bytes(data[:keep] if keep >= 0 else data[:keep])
    with pytest.raises(AgentFileError) as caught:
        load_agent(path)
    assert str(path) in str(caught.value) and "\n" not in str(caught.value)


def test_a_flipped_byte_anywhere_is_refused_or_changes_nothing(tmp_path):
    """Bytes the zip container does not read (padding, names) may change; any change that
    reaches the content fails the digest: nothing else escapes as another exception."""
    layer = LocalRisk(LocalRewardTable(1))
    layer.provider.rho.fill_(-0.5)
    path = save_agent(layer, tmp_path / "layer.pt")
    data = path.read_bytes()
    refused = 0
    for position in range(0, len(data), 5):
        flipped = bytearray(data)
        flipped[position] ^= 0x41
        path.write_bytes(bytes(flipped))
        try:
            loaded = load_agent(path)
        except AgentFileError as error:
            assert "\n" not in str(error) and str(path) in str(error)
            refused += 1
        else:
            assert _states_equal(loaded, layer)
    assert refused > len(data) // 20  # the check is not vacuous


def test_a_link_a_fifo_a_directory_and_a_missing_file_are_refused(tmp_path):
    path = save_agent(LocalRewardTable(1), tmp_path / "table.pt")
    link = tmp_path / "link.pt"
    link.symlink_to(path)
    with pytest.raises(AgentFileError, match="symbolic link"):
        load_agent(link)
    fifo = tmp_path / "fifo.pt"
    os.mkfifo(fifo)
    with pytest.raises(AgentFileError, match="not a regular file"):
        load_agent(fifo)  # refused without blocking on the read
    with pytest.raises(AgentFileError, match="not a regular file"):
        load_agent(tmp_path)
    with pytest.raises(AgentFileError, match="does not exist"):
        load_agent(tmp_path / "missing.pt")
    other = tmp_path / "other.pt"
    torch.save({"format": "something else"}, other)
    with pytest.raises(AgentFileError, match="not a saved factorq agent"):
        load_agent(other)


def test_saving_anything_else_is_refused_and_leaves_no_file(tmp_path):
    with pytest.raises(TypeError, match="got Linear"):
        save_agent(torch.nn.Linear(2, 2), tmp_path / "net.pt")
    assert list(tmp_path.iterdir()) == []


def test_find_local_risk_finds_the_layer_by_type_or_says_there_is_none(env):
    provider = LocalRewardTable(1)
    policy = with_local_risk(TaskQTable(1, num_cells=25), provider, env=env)
    layer = find_local_risk(policy)
    assert isinstance(layer, LocalRisk) and layer.provider is provider
    assert find_local_risk(torch.nn.Sequential(policy)) is layer
    with pytest.raises(ValueError, match="holds no LocalRisk layer"):
        find_local_risk(TaskQTable(1, num_cells=25))
    with pytest.raises(ValueError, match="2 LocalRisk layers"):
        find_local_risk(torch.nn.ModuleList([policy, LocalRisk(provider)]))
    with pytest.raises(TypeError, match="takes a module"):
        find_local_risk("policy")


def test_risk_summary_takes_the_names_from_the_env(env):
    summary = RiskSummary.for_env(env, threshold=0.1)
    assert summary.actuator_names == ("north", "west", "south", "east")
    assert summary.threshold == 0.1
    with pytest.raises(ValueError, match="names no actuators"):
        RiskSummary.for_env(object())


def test_the_public_names():
    for name in ("save_agent", "load_agent", "AgentFileError", "find_local_risk"):
        assert name in factorq_torch.__all__ and getattr(factorq_torch, name) is not None
