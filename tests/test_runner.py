"""The runner (issue 24): the registry, the frame (a toy command declared as units: resume per
unit, refusals, the envelope), ``factorq report`` without torch, and docs/architecture.md naming
every command."""

from __future__ import annotations

import json
import subprocess
import sys
import types
from dataclasses import dataclass
from pathlib import Path

import pytest

from factorq_trainers import cli
from factorq_trainers.runner import frame, kept, options, registry

ROOT = Path(__file__).resolve().parent.parent


@dataclass(frozen=True)
class ToyConfig:
    seeds: int = options.option(3, "Units.")
    fail_at: int = options.option(-1, "Unit index that raises KeyboardInterrupt (-1: none).")
    out: str = options.option("results/toy", "Directory.")

    def __post_init__(self) -> None:
        if self.seeds < 1:
            raise ValueError(f"seeds={self.seeds} must be >= 1")


def _toy_module(calls: list[str]) -> types.ModuleType:
    """A command declared as the protocol says, counting the units it runs."""
    toy = types.ModuleType("toy_command")
    toy.NAME, toy.CONFIG = "toy", ToyConfig
    toy.UNIT_RESULT = {"value": kept.NUMBER, "inf?": kept.NUMBER}
    toy.units = lambda config: [{"id": f"seed-{s}", "seed": s} for s in range(config.seeds)]

    def run_unit(config, unit, progress=None):
        if unit["seed"] == config.fail_at:
            raise KeyboardInterrupt
        calls.append(unit["id"])
        return {"value": unit["seed"] * 10 + 0.5, "inf": float("inf")}

    toy.run_unit = run_unit
    toy.summarise = lambda config, outcomes: {"values": [o["value"] for o in outcomes]}
    toy.markdown = lambda results: f"# toy\n{results['values']}\n"
    return toy


def _execute(module, argv: list[str]) -> int:
    parser = frame.Parser(prog="factorq toy")
    options.add_options(parser, module.CONFIG)
    frame.add_frame_options(parser)
    return frame.execute(module, parser, parser.parse_args(argv))


def test_every_command_is_registered_and_listed_without_importing_it():
    names = set(registry.commands())
    assert {"paper", "compare", "dependencies", "minigrid"} <= names
    code = (
        "import sys\nfrom factorq_trainers.runner import registry\n"
        "registry.commands()\nfrom factorq_trainers import cli\ncli.build_parser(command='x')\n"
        "assert 'torch' not in sys.modules, 'listing the commands imported torch'\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_a_command_runs_units_writes_the_envelope_and_resumes_per_unit(tmp_path, capsys):
    calls: list[str] = []
    toy = _toy_module(calls)
    out = tmp_path / "toy"
    assert _execute(toy, ["--seeds", "3", "--fail-at", "2", "--out", str(out)]) == 130
    assert calls == ["seed-0", "seed-1"] and not (out / "toy.json").exists()
    assert "--resume" in capsys.readouterr().err
    # a fresh run into the interrupted one's --out is refused, a resume runs only the rest
    assert _execute(toy, ["--out", str(out)]) == 2
    assert "interrupted run" in capsys.readouterr().err
    assert _execute(toy, ["--resume", str(out), "--fail-at", "9"]) == 2  # not the saved config
    assert "fail_at" in capsys.readouterr().err.replace("-", "_")
    calls.clear()
    saved = json.loads((out / "units" / "run.json").read_text())
    assert saved["config"]["fail_at"] == 2
    # the saved config fails at unit 2: resume it with a declaration that no longer fails
    fixed = _toy_module(calls)
    fixed.run_unit = lambda config, unit, progress=None: {"value": unit["seed"] * 10 + 0.5}
    assert _execute(fixed, ["--resume", str(out)]) == 0
    results = json.loads((out / "toy.json").read_text())
    assert results["values"] == [0.5, 10.5, 20.5]
    assert results["timing"]["units"] == 3 and results["timing"]["units_resumed"] == 2
    assert {"schema_version", "command", "config", "software"} <= set(results)
    assert results["command"] == "toy" and not (out / "units").exists()
    assert (out / "toy.md").read_text() == "# toy\n[0.5, 10.5, 20.5]\n"


def test_an_edited_kept_unit_is_refused_on_resume_naming_it(tmp_path, capsys):
    toy = _toy_module([])
    out = tmp_path / "toy"
    assert _execute(toy, ["--seeds", "3", "--fail-at", "2", "--out", str(out)]) == 130
    unit = kept.unit_path(out / "units", "seed-1")
    record = json.loads(unit.read_text())
    assert record["result"]["value"] == 10.5 and len(record["content_sha256"]) == 64
    record["result"]["value"] = 1050.0  # edited, its digest kept
    unit.write_text(json.dumps(record))
    capsys.readouterr()
    fixed = _toy_module([])
    fixed.run_unit = lambda config, unit, progress=None: {"value": unit["seed"] * 10 + 0.5}
    assert _execute(fixed, ["--resume", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert f"unit file {unit} does not match its digest (edited or damaged)" in err[0]
    assert "pass --force (with --resume) to recompute it" in err[0]
    # as it says: that unit runs again, the other is reused
    assert _execute(fixed, ["--resume", str(out), "--force"]) == 0
    results = json.loads((out / "toy.json").read_text())
    assert results["values"] == [0.5, 10.5, 20.5] and results["timing"]["units_resumed"] == 1


def test_an_uninterrupted_run_equals_a_resumed_one_and_run_in_process(tmp_path):
    calls: list[str] = []
    toy = _toy_module(calls)
    assert _execute(toy, ["--out", str(tmp_path / "a")]) == 0
    whole = json.loads((tmp_path / "a" / "toy.json").read_text())
    here = frame.run_in_process(toy, ToyConfig(out=str(tmp_path / "a")))
    assert here["values"] == whole["values"] == [0.5, 10.5, 20.5]
    assert _execute(toy, ["--out", str(tmp_path / "a")]) == 2  # earlier results kept
    assert _execute(toy, ["--out", str(tmp_path / "a"), "--force"]) == 0


def test_bad_options_are_one_line_naming_the_option(tmp_path, capsys):
    assert _execute(_toy_module([]), ["--seeds", "0", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--seeds=0 must be >= 1" in err[0]


def test_a_declaration_without_unit_ids_is_its_authors_bug():
    toy = _toy_module([])
    toy.units = lambda config: [{"seed": 0}]
    with pytest.raises(RuntimeError, match="string 'id'"):
        frame.checked_units(toy, ToyConfig())


def test_reports_import_no_torch():
    """``factorq report`` imports the reports package and each command's report module: none may
    load torch (a command whose module imports torch puts its ``markdown`` and ``figure`` in
    the ``report.py`` of its folder, ``trainers/commands/<name>/``)."""
    code = (
        "import sys, pkgutil, importlib\nimport factorq_trainers.reports as reports\n"
        "from factorq_trainers.runner import registry\n"
        "names = [f'{reports.__name__}.{m.name}' for m in pkgutil.iter_modules(reports.__path__)]\n"
        "names += [entry.report for entry in registry.commands().values()]\n"
        "for name in names:\n"
        "    importlib.import_module(name)\n"
        "    assert 'torch' not in sys.modules, f'{name} imports torch: move markdown and figure "
        "to the report.py of its folder'\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_report_redraws_dependencies_without_torch(tmp_path):
    results = {
        "schema_version": 1,
        "command": "dependencies",
        "config": {
            "seeds": 2, "runs": 1, "episodes": 1, "regimes": ["static"], "size": 6, "obstacles": 4,
            "bayes_factor": 300.0, "prior_a": 0.25, "prior_b": 0.25, "candidate_prior": "sparse",
            "max_steps": 1000,
        },
        "timing": {"wall_s": 1.0},
        "settings": {"cross": {"methods": {"factor-q": {
            "collisions_per_experiment": 1.0, "greedy_collisions_per_experiment": 0.0,
            "steps_per_run": 9.0, "collisions_per_episode": [1.0],
        }}}},
        "skipped": {},
        "methods": {"factor-q": "oracle pairing"},
    }  # fmt: skip
    (tmp_path / "dependencies.json").write_text(json.dumps(results))
    code = (
        "import sys\nfrom factorq_trainers import cli\n"
        f"assert cli.main(['report', {str(tmp_path)!r}]) == 0\n"
        "assert 'torch' not in sys.modules, 'factorq report imported torch'\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, capture_output=True)
    assert "| cross | oracle pairing |" in (tmp_path / "dependencies.md").read_text()
    assert (tmp_path / "dependencies.png").stat().st_size > 0


def test_the_obstacle_regimes_load_without_torch_and_the_grid_runs_them():
    code = (
        "import sys\nfrom factorq_envs.regimes import REGIME_PERIODS, REGIMES\n"
        "assert 'torch' not in sys.modules, 'factorq_envs.regimes imported torch'\n"
        "print(REGIMES, REGIME_PERIODS)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True)
    assert out.stdout.strip() == (
        "('static', 'semi-dynamic', 'dynamic') {'static': 0, 'semi-dynamic': 10, 'dynamic': 1}"
    )


def test_architecture_names_every_registered_command():
    text = (ROOT / "docs" / "architecture.md").read_text()
    for name, entry in registry.commands().items():
        path = "trainers/" + entry.module.removeprefix("factorq_trainers.").replace(".", "/")
        assert f"`factorq {name}`" in text and f"{path}.py" in text, name
    for name in registry.BUILT_IN:
        assert f"`factorq {name}`" in text, name


def test_the_cli_knows_every_registered_command(capsys):
    assert cli.main(["--help"]) == 0
    listed = capsys.readouterr().out
    assert all(name in listed for name in (*registry.commands(), *registry.BUILT_IN))


def test_every_registered_command_can_be_swept_and_one_without_cells_is_refused(monkeypatch):
    from factorq_trainers.distributed import sweep_spec

    for name in registry.commands():
        assert sweep_spec.check_command(name) == name
    monkeypatch.setattr(registry, "commands", lambda: dict.fromkeys(("paper", "toy")))
    monkeypatch.setattr(sweep_spec, "_reports_of", lambda command: types.ModuleType("toy_report"))
    with pytest.raises(
        sweep_spec.SweepError, match="'toy' cannot be swept: toy_report declares no"
    ):
        sweep_spec.check_command("toy")
