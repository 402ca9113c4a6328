"""Every unit command resumes one way (issue 37): interrupted after its first unit (exit 130, the
unit kept), ``--resume OUT`` runs only the rest, and the results equal an uninterrupted run's
(``paper`` and ``compare`` are also killed with SIGKILL in ``test_paper_units.py`` and
``test_compare_resume.py``)."""

from __future__ import annotations

import json
import re

import pytest

from factorq_trainers import cli
from factorq_trainers.runner import registry

#: Each command's tiny run (seconds), with at least two units.
TINY = {
    "paper": ["--seeds", "4", "--shard-seeds", "2", "--runs", "2", "--episodes", "3",
              "--size", "5", "--obstacles", "3"],
    "compare": ["--seeds", "1", "--steps", "200", "--size", "4", "--obstacles", "1",
                "--regimes", "static,dynamic", "--methods", "factor-q,q-learning"],
    "dependencies": ["--settings", "cross,heading", "--seeds", "2", "--runs", "2",
                     "--episodes", "2", "--methods", "factor-q-learned,factor-q"],
    "minigrid": ["--seeds", "1", "--sizes", "5", "--steps", "60",
                 "--methods", "factor-q,q-learning"],
    "risk": ["--worlds", "grid", "--methods", "dqn,dqn+risk", "--seeds", "1",
             "--steps", "60", "--learning-starts", "20", "--eval-episodes", "1",
             "--grid-size", "3", "--grid-obstacles", "1"],
    "transfer": ["--size", "6", "--obstacles", "4", "--source-size", "5",
                 "--source-obstacles", "3", "--seeds", "2", "--episodes", "6", "--early", "3",
                 "--source-episodes", "6", "--max-steps", "200"],
}  # fmt: skip


def _without_times(value):
    """``value`` without the wall times measured inside it (a unit's ``wall_s``, ...)."""
    if isinstance(value, dict):
        return {
            k: _without_times(v) for k, v in value.items() if not re.fullmatch(r".*(_s|_per_s)", k)
        }
    if isinstance(value, list):
        return [_without_times(v) for v in value]
    return value


def _numbers(path) -> dict:
    results = json.loads(path.read_text())
    kept = {k: v for k, v in results.items() if k not in ("timing", "config", "software")}
    return _without_times(kept)


def test_every_unit_command_is_covered():
    assert set(TINY) | {"gym"} == set(registry.commands())  # gym: test_declared_worlds.py


@pytest.mark.parametrize("name", sorted(TINY))
def test_an_interrupted_command_resumes_to_its_uninterrupted_results(
    name, tmp_path, monkeypatch, capsys
):
    if name == "minigrid":
        pytest.importorskip("minigrid")
    module = registry.load(name)
    files = registry.commands()[name].files
    whole = tmp_path / "whole"
    assert cli.main([name, *TINY[name], "--cluster", "off", "--out", str(whole)]) == 0, (
        capsys.readouterr().err
    )
    real, ran = module.run_unit, []

    def once(config, unit, *rest, **keywords):
        if ran:
            raise KeyboardInterrupt
        ran.append(unit["id"])
        return real(config, unit, *rest, **keywords)

    cut = tmp_path / "cut"
    monkeypatch.setattr(module, "run_unit", once)
    assert cli.main([name, *TINY[name], "--cluster", "off", "--out", str(cut)]) == 130
    monkeypatch.setattr(module, "run_unit", real)
    capsys.readouterr()
    assert cli.main([name, "--resume", str(cut), "--cluster", "off"]) == 0, capsys.readouterr().err
    resumed = json.loads((cut / files["json"]).read_text())
    assert resumed["timing"]["units_resumed"] == 1
    assert resumed["timing"]["units"] >= 2
    assert _numbers(cut / files["json"]) == _numbers(whole / files["json"])
