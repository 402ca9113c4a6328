"""``factorq transfer`` (issue 40, deliver 1): a body model learned once in a source task and
carried into a new one, against learning from scratch; through the runner, on the fast and the
modular path alike, and from a file saved with ``save_agent``."""

from __future__ import annotations

import json
import os

import pytest

from factorq_trainers import cli
from factorq_trainers.commands.transfer import command as transfer
from factorq_trainers.compiled import fast

SMALL = dict(
    size=6, obstacles=4, source_size=5, source_obstacles=3, seeds=4, episodes=8, early=3,
    source_episodes=10, max_steps=200,
)  # fmt: skip


def _args(options: dict) -> list[str]:
    args = []
    for name, value in options.items():
        text = ",".join(value) if isinstance(value, tuple) else str(value)
        args += [f"--{name.replace('_', '-')}", text]
    return args


def test_the_command_writes_its_report_and_the_body_model_saves_the_learning_collisions(
    tmp_path, capsys
):
    out = tmp_path / "out"
    assert cli.main(["transfer", *_args(SMALL), "--out", str(out)]) == 0
    results = json.loads((out / "transfer.json").read_text())
    assert set(results["results"]) == {"static", "semi-dynamic", "dynamic"}
    static = results["results"]["static"]
    assert set(static) == set(transfer.DEFAULT_METHODS)
    # A body model that knows every actuator's risk (rho = -1 where its sensor reads an obstacle,
    # eq. 5 after one collision) and risk-aware exploration: no collision in a static world, where
    # every collision is one the sensors foresee; from scratch, each actuator learns by colliding.
    assert static["factor-q-body"]["early_collisions"]["range"] == [0.0, 0.0]
    assert static["factor-q"]["early_collisions"]["range"][0] >= 1
    assert static["q-learning"]["early_collisions"]["mean"] > static["factor-q"][
        "early_collisions"]["mean"]  # fmt: skip
    assert results["body_against_fresh"]["factor-q-body"]["static"]["target_met"] is True
    report = (out / "transfer.md").read_text()
    assert "## Target: dynamic" in report and "| Factor-Q, carried body model |" in report
    assert "- Factor-Q, carried body model: no collisions in the first 3 episodes" in report
    assert (out / "transfer.png").stat().st_size > 0
    capsys.readouterr()


@pytest.mark.skipif(not fast.is_available(), reason="the compiled kernel is not available here")
@pytest.mark.parametrize("unit", [0, 1, 2])  # factor-q, factor-q-body, q-learning (dynamic)
def test_the_fast_and_the_modular_path_give_the_same_numbers(unit):
    options = {**SMALL, "regimes": ("dynamic",), "episodes": 3, "early": 1, "size": 5}
    options.update(obstacles=2, source_size=4, source_obstacles=1, source_episodes=3)
    fast_config = transfer.TransferConfig(**options)
    modular = transfer.TransferConfig(**options, path="modular")
    chosen = transfer.units(fast_config)[unit]
    one = transfer.run_unit(fast_config, chosen)
    other = transfer.run_unit(modular, chosen)
    assert (one["path"], other["path"]) == ("fast", "modular")
    for name in ("early_collisions", "late_collisions", "late_steps", "collisions_per_episode"):
        assert one[name] == other[name], name


def test_a_saved_body_model_is_carried_as_the_source_task_would_have_been(tmp_path, capsys):
    from factorq_torch.artifacts import save_agent

    config = transfer.TransferConfig(**SMALL, regimes=("dynamic",), methods=("factor-q-body",))
    path = save_agent(transfer.train_body_model(config), tmp_path / "body.pt")
    unit = transfer.units(config)[0]
    learned = transfer.run_unit(config, unit)
    carried = transfer.run_unit(
        transfer.TransferConfig(**SMALL, regimes=("dynamic",), body_model=str(path)), unit
    )
    assert (learned["body_from"], carried["body_from"]) == ("source task", "file")
    assert carried["early_collisions"] == learned["early_collisions"]
    assert carried["collisions_per_episode"] == learned["collisions_per_episode"]


def _refused(tmp_path, capsys, extra: list[str], *words: str) -> None:
    out = tmp_path / "refused"
    assert cli.main(["transfer", *_args(SMALL), *extra, "--out", str(out)]) == 2
    error = capsys.readouterr().err.strip()
    assert len(error.splitlines()) == 1 and "Traceback" not in error, error
    for word in words:
        assert word in error, error
    assert not (out / "transfer.json").exists()


def test_a_body_model_of_another_body_is_refused_naming_both(tmp_path, capsys):
    from factorq_torch.artifacts import save_agent

    heading = transfer.TransferConfig(**SMALL, body="heading")
    path = save_agent(transfer.train_body_model(heading), tmp_path / "heading.pt")
    _refused(tmp_path, capsys, ["--body-model", str(path)], str(path), "the env has", "body")


def test_a_body_model_of_another_seed_count_or_through_a_link_is_refused(tmp_path, capsys):
    from factorq_torch.artifacts import save_agent

    five = transfer.TransferConfig(**{**SMALL, "seeds": 5})
    path = save_agent(transfer.train_body_model(five), tmp_path / "five.pt")
    _refused(tmp_path, capsys, ["--body-model", str(path)], "holds 5 experiments")
    link = tmp_path / "link.pt"
    os.symlink(path, link)
    _refused(tmp_path, capsys, ["--body-model", str(link)], str(link))


@pytest.mark.parametrize(
    ("extra", "words"),
    [
        (["--early", "9"], "early=9"),
        (["--regimes", "windy"], "--regimes: 'windy' is unknown"),
        (["--source-obstacles", "40"], "--source-obstacles=40 is out of range"),
        (["--methods", "dqn"], "--methods: 'dqn' is unknown"),
    ],
)
def test_bad_options_are_one_line_naming_the_option(tmp_path, capsys, extra, words):
    _refused(tmp_path, capsys, extra, words)


def test_the_learned_structure_is_carried_whole_and_saves_as_an_artifact(tmp_path):
    """The structure learner's whole evidence goes into the target (its samples go on counting
    from the source's), and the learner saved by ``save_agent`` loads back the same."""
    import torch

    from factorq_torch.artifacts import load_agent, save_agent

    options = {**SMALL, "regimes": ("static",), "episodes": 2, "early": 1, "size": 5}
    options.update(obstacles=2, source_size=4, source_obstacles=1, source_episodes=2, seeds=2)
    config = transfer.TransferConfig(
        **options, methods=("factor-q-learned", "factor-q-learned-body")
    )
    assert transfer.work(config, transfer.units(config)[1]) == 2 * (2 + 2)
    learner = transfer.train_body_model(config, learned=True)
    assert bool((learner.samples > 0).all())  # every actuator fired in the source task
    again = load_agent(save_agent(learner, tmp_path / "learner.pt"))
    for name, value in learner.state_dict().items():
        assert torch.equal(again.state_dict()[name], value), name
    state = {name: value.detach() for name, value in learner.state_dict().items()}
    _, carried, path = transfer.run_batch(
        config, "factor-q", config.target_world, "static", 2, body=state, learned=True
    )
    assert path == "modular"
    assert bool((carried["samples"] > learner.samples).all())  # it went on from the source's
