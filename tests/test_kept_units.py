"""Kept units (issue 37 deliver 2, issue 41's first bullet): every file in ``OUT/units/`` is
sealed, tied to its command, its configuration and its unit, and its result checked against the
command's ``UNIT_RESULT`` before any unit runs. The red team's cases, each forged the way an
attacker would (edit the JSON, then reseal it: ``content_sha256`` is the SHA-256 of the rest as
canonical JSON, ``kept.json_digest``), must be refused in one line naming the file and
``--force``, with no traceback, a non-zero exit and no unit run."""

from __future__ import annotations

import json
import shutil
import types
from dataclasses import dataclass

import pytest

from factorq_trainers.runner import frame, kept, options


@dataclass(frozen=True)
class UnitsConfig:
    seeds: int = options.option(3, "Units.")
    seed: int = options.option(0, "First seed.")
    out: str = options.option("results/units", "Directory.")


def _command(calls: list[str], stop_at: int = -1) -> types.ModuleType:
    """A command whose units repeat their seed in their result (as ``risk``'s do) and whose
    summary reads every declared key (as ``dependencies``' reads ``skipped``); unit ``stop_at``
    raises KeyboardInterrupt."""
    command = types.ModuleType("units_command")
    command.NAME, command.CONFIG = "units", UnitsConfig
    command.UNIT_RESULT = {
        "seed": kept.COUNT,
        "collisions": kept.COUNT,
        "success": kept.FRACTION,
        "skipped": {"*": kept.TEXT},
    }
    command.units = lambda config: [
        {"id": f"unit-{i}", "seed": config.seed + i} for i in range(config.seeds)
    ]

    def run_unit(config, unit, progress=None):
        if unit["id"] == f"unit-{stop_at}":
            raise KeyboardInterrupt
        calls.append(unit["id"])
        return {
            "seed": unit["seed"],
            "collisions": 10 + unit["seed"],
            "success": 0.5,
            "skipped": {},
        }

    command.run_unit = run_unit
    command.summarise = lambda config, outcomes: {
        "seeds": [o["seed"] for o in outcomes],
        "collisions": [float(o["collisions"]) for o in outcomes],
        "skipped": [len(o["skipped"]) for o in outcomes],
    }
    return command


def _execute(command: types.ModuleType, argv: list[str]) -> int:
    parser = frame.Parser(prog="factorq units")
    options.add_options(parser, command.CONFIG)
    frame.add_frame_options(parser)
    return frame.execute(command, parser, parser.parse_args(argv))


def _interrupted(tmp_path, capsys):
    """An interrupted run: units 0 and 1 (seeds 0 and 1) kept, unit 2 not run."""
    out = tmp_path / "run"
    assert _execute(_command([], stop_at=2), ["--out", str(out)]) == 130
    capsys.readouterr()
    return out


def _reseal(path, edit) -> None:
    """Edit the kept JSON at ``path`` and seal it again, as anyone can."""
    record = json.loads(path.read_text())
    edit(record)
    record.pop(kept.DIGEST_KEY, None)
    record[kept.DIGEST_KEY] = kept.json_digest(record)
    path.write_text(json.dumps(record))


def _refused(out, capsys, path, *words: str) -> None:
    """``--resume out`` is refused in one line naming ``path`` and ``--force``, before any unit
    runs and without changing a kept file."""
    before = {p.name: p.read_bytes() for p in (out / "units").iterdir()}
    calls: list[str] = []
    assert _execute(_command(calls), ["--resume", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert str(path) in err[0] and "--force" in err[0] and "Traceback" not in err[0], err[0]
    for word in words:
        assert word in err[0], err[0]
    assert calls == []  # refused before any work
    assert {p.name: p.read_bytes() for p in (out / "units").iterdir()} == before


def _unit(out, index: int):
    return kept.unit_path(out / "units", f"unit-{index}")


def _result(path) -> dict:
    return json.loads(path.read_text())["result"]


def test_a_resumed_run_reads_its_kept_units_and_equals_an_uninterrupted_one(tmp_path, capsys):
    out = _interrupted(tmp_path, capsys)
    calls: list[str] = []
    assert _execute(_command(calls), ["--resume", str(out)]) == 0
    assert calls == ["unit-2"]
    assert _execute(_command([]), ["--out", str(tmp_path / "whole")]) == 0
    resumed = json.loads((out / "units.json").read_text())
    whole = json.loads((tmp_path / "whole" / "units.json").read_text())
    assert resumed["collisions"] == whole["collisions"] == [10.0, 11.0, 12.0]


def test_an_edited_run_file_is_refused(tmp_path, capsys):
    """The red team: edit run.json's seed and resume (it was reported as seed 7, exit 0)."""
    out = _interrupted(tmp_path, capsys)
    run = out / "units" / "run.json"
    record = json.loads(run.read_text())
    record["config"]["seed"] = 7
    run.write_text(json.dumps(record))
    _refused(out, capsys, run, "does not match its digest")


def test_a_resealed_run_file_of_another_seed_is_refused(tmp_path, capsys):
    out = _interrupted(tmp_path, capsys)
    run = out / "units" / "run.json"
    _reseal(run, lambda record: record["config"].update(seed=7))
    _refused(out, capsys, run, "another configuration")


def test_a_run_file_resealed_with_its_tie_leaves_its_units_refused(tmp_path, capsys):
    """Even with run.json's tie forged too, the units say which configuration they are of."""
    out = _interrupted(tmp_path, capsys)
    run = out / "units" / "run.json"

    def retie(record):
        record["config"]["seed"] = 7
        record[kept.TIE_KEY] = kept.tie("units", record["config"])

    _reseal(run, retie)
    _refused(out, capsys, _unit(out, 0), "another configuration")


def test_a_unit_of_another_command_is_refused(tmp_path, capsys):
    out = _interrupted(tmp_path, capsys)
    path = _unit(out, 1)
    _reseal(path, lambda record: record[kept.TIE_KEY].update(command="risk"))
    _refused(out, capsys, path, "factorq units")


@pytest.mark.parametrize(
    ("value", "words"),
    [
        (-999, ("result/collisions holds -999, negative",)),
        (float("nan"), ("result/collisions holds nan, not a finite number",)),
        (2.5, ("not a whole count",)),
        ("many", ("result/collisions holds 'many', not a number",)),
        (None, ("result/collisions holds None",)),
        (10**400, ("not a finite number",)),  # JSON's digits past a float (was an OverflowError)
    ],
    ids=["negative", "nan", "fractional", "string", "null", "past-float"],
)
def test_a_resealed_unit_with_an_impossible_value_is_refused(tmp_path, capsys, value, words):
    """The red team: -999 collisions, NaN (reported, exit 0), a string ("could not convert
    string to float" naming no file)."""
    out = _interrupted(tmp_path, capsys)
    path = _unit(out, 1)
    _reseal(path, lambda record: record["result"].update(collisions=value))
    _refused(out, capsys, path, *words)


def test_a_resealed_unit_with_a_fraction_above_one_is_refused(tmp_path, capsys):
    out = _interrupted(tmp_path, capsys)
    path = _unit(out, 0)
    _reseal(path, lambda record: record["result"].update(success=1e308))
    _refused(out, capsys, path, "not a fraction in [0, 1]")


@pytest.mark.parametrize(
    ("result", "words"),
    [
        ({}, ("result lacks 'seed'",)),
        ("a string", ("not a mapping",)),
        ({"seed": 1, "collisions": 3, "success": 0.5, "skipped": {}, "extra": 1}, ("'extra'",)),
    ],
    ids=["empty", "string", "undeclared-key"],
)
def test_a_resealed_unit_without_its_declared_keys_is_refused(tmp_path, capsys, result, words):
    """The red team: ``result={}`` crashed with KeyError: 'skipped' after the other units ran."""
    out = _interrupted(tmp_path, capsys)
    path = _unit(out, 1)
    _reseal(path, lambda record: record.update(result=result))
    _refused(out, capsys, path, *words)


def test_a_unit_relabelled_as_another_is_refused(tmp_path, capsys):
    """The red team: one unit's result relabelled as another's (its label inside the result)."""
    out = _interrupted(tmp_path, capsys)
    path = _unit(out, 1)
    _reseal(path, lambda record: record["result"].update(seed=0))
    _refused(out, capsys, path, "seed is 0", "'unit-1'")


def test_a_unit_file_copied_to_another_units_place_is_refused(tmp_path, capsys):
    """Unit 0's file at unit 2's place, resealed: its tie names unit 0."""
    out = _interrupted(tmp_path, capsys)
    target = _unit(out, 2)
    shutil.copy(_unit(out, 0), target)
    _reseal(target, lambda record: None)
    _refused(out, capsys, target, "kept for unit 'unit-0'")


def test_force_with_resume_recomputes_a_refused_unit_and_keeps_the_others(tmp_path, capsys):
    out = _interrupted(tmp_path, capsys)
    _reseal(_unit(out, 1), lambda record: record["result"].update(collisions=-999))
    calls: list[str] = []
    assert _execute(_command(calls), ["--resume", str(out), "--force"]) == 0
    assert calls == ["unit-1", "unit-2"]
    assert json.loads((out / "units.json").read_text())["collisions"] == [10.0, 11.0, 12.0]


def test_a_unit_result_that_breaks_its_declaration_is_the_commands_bug(tmp_path):
    command = _command([])
    command.run_unit = lambda config, unit, progress=None: {"seed": unit["seed"]}
    with pytest.raises(RuntimeError, match="does not fit UNIT_RESULT: result lacks 'collisions'"):
        frame.run_in_process(command, UnitsConfig(out=str(tmp_path)))


def test_a_kept_unit_of_a_real_command_is_checked_against_its_schema(tmp_path, capsys):
    """``factorq dependencies --resume`` with a kept unit holding ``{}`` (the red team's
    KeyError: 'skipped' after the other settings ran): refused before any setting runs."""
    from factorq_trainers.cli import main
    from factorq_trainers.commands.dependencies import command as dependencies

    config = dependencies.DependenciesConfig(settings=("cross", "heading"), out=str(tmp_path / "d"))
    units = dependencies.units(config)
    store = kept.UnitStore(config.out)
    store.start("dependencies", frame.plain(config), [unit["id"] for unit in units])
    store.keep(units[0], {})
    path = kept.unit_path(store.directory, units[0]["id"])
    assert main(["dependencies", "--resume", config.out]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(path) in err[0] and "lacks 'summary'" in err[0], err
    assert "--force" in err[0]


def test_schema_kinds_by_hand():
    assert kept.schema_problem({"a": [1, None]}, {"a": [(None, kept.COUNT)]}) is None
    assert (
        kept.schema_problem({"a": [1, None]}, {"a": [kept.COUNT]})
        == "result/a[1] holds None, not a number"
    )
    assert kept.schema_problem({}, {"a?": kept.NUMBER}) is None
    assert kept.schema_problem({"x": True}, {"*": kept.FLAG}) is None
    assert kept.schema_problem({"x": 1}, {"*": kept.FLAG}) == "result/x holds 1, not true or false"
    assert kept.schema_problem(-0.5, kept.NUMBER) is None
    assert kept.schema_problem(-0.5, kept.NON_NEGATIVE) == "result holds -0.5, negative"
    assert kept.schema_problem(True, kept.NUMBER) == "result holds True, not a number"
    assert kept.schema_problem(None, kept.FRACTION) is None  # non-finite numbers are written null
    assert kept.schema_problem(None, kept.FINITE) == "result holds None, not a number"
    assert kept.schema_problem(-2.5, kept.FINITE) is None
    assert kept.schema_problem(0, kept.POSITIVE) == "result holds 0, not a count >= 1"
    assert kept.schema_problem(1.5, kept.POSITIVE) == "result holds 1.5, not a whole count"
    names = frozenset(("static", "dynamic"))
    assert kept.schema_problem("static", names) is None
    assert kept.schema_problem(["x"], names) == "result holds ['x'], not one of dynamic, static"
    assert kept.schema_problem([1, 2], [kept.NUMBER, 2]) is None
    assert kept.schema_problem([1], [kept.NUMBER, 2]) == "result holds 1 items, not 2"
    declared = {"n": kept.COUNT, "*": kept.TEXT}  # declared keys, any others of the "*" schema
    assert kept.schema_problem({"n": 1, "label": "a"}, declared) is None
    assert kept.schema_problem({"n": -1}, declared) == "result/n holds -1, negative"
    assert kept.schema_problem({"n": 1, "x": 2}, declared) == "result/x holds 2, not a text"
    assert kept.schema_problem({"x": "a"}, declared) == "result lacks 'n'"


# --- factorq report: the results file's values and command checked before drawing -------------


def _dependencies_file(directory, **changes) -> None:
    results = {
        "schema_version": 1,
        "command": "dependencies",
        "config": {"seeds": 2},
        "settings": {"cross": {"structure": {"fraction_right_at_end": 0.5}}},
        **changes,
    }
    directory.mkdir(exist_ok=True)
    (directory / "dependencies.json").write_text(json.dumps(results))


@pytest.mark.parametrize(
    ("changes", "words"),
    [
        (
            {"settings": {"cross": {"structure": {"fraction_right_at_end": 1e308}}}},
            "fraction_right_at_end holds 1e+308, not a fraction in [0, 1]",
        ),
        ({"command": "risk"}, "written by command 'risk', not `factorq dependencies`"),
    ],
    ids=["fraction", "another-command"],
)
def test_factorq_report_refuses_impossible_values_and_another_commands_file(
    tmp_path, capsys, changes, words
):
    from factorq_trainers.cli import main

    _dependencies_file(tmp_path, **changes)
    assert main(["report", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0] and str(tmp_path / "dependencies.json") in err[0]
    assert not (tmp_path / "dependencies.md").exists()


# --- sweeps: a configuration's kept result is tied to its command and configuration ------------


def test_a_sweeps_kept_result_of_another_configuration_is_refused(tmp_path):
    """A configuration's file copied to another's place (its name is that configuration's
    digest) and resealed: its tie names the configuration it was computed for."""
    from factorq_trainers.commands.dependencies import command as dependencies
    from factorq_trainers.distributed import sweep
    from factorq_trainers.distributed.sweep_spec import config_digest

    first = dependencies.DependenciesConfig(seeds=2)
    second = dependencies.DependenciesConfig(seeds=3)
    results = {"schema_version": 1, "command": "dependencies", "config": {"seeds": 2}}
    path = sweep.config_result_path(tmp_path, second)
    path.write_text(kept.dumps_sealed(results, kept.tie("dependencies", config_digest(first))))
    with pytest.raises(ValueError, match="was kept for another configuration") as error:
        sweep._pending_configs(tmp_path, [second], False, "dependencies")
    assert str(path) in str(error.value) and "--force" in str(error.value)
    assert sweep._pending_configs(tmp_path, [second], True, "dependencies") == [second]
    path.write_text(kept.dumps_sealed(results, kept.tie("dependencies", config_digest(second))))
    assert sweep._pending_configs(tmp_path, [second], False, "dependencies") == []
    with pytest.raises(ValueError, match="kept by command 'dependencies', not `factorq risk`"):
        sweep._pending_configs(tmp_path, [second], False, "risk")


def test_factorq_report_refuses_a_results_file_written_before_versioning(tmp_path, capsys):
    from factorq_trainers.cli import main

    _dependencies_file(tmp_path)
    results = json.loads((tmp_path / "dependencies.json").read_text())
    del results["schema_version"]
    (tmp_path / "dependencies.json").write_text(json.dumps(results))
    assert main(["report", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "has no schema_version: run" in err[0]


def test_a_commands_own_results_check_is_applied_by_factorq_report(tmp_path):
    """``factorq report`` checks a results file with its command's report's ``results_problem``
    too (compare's: ``seeds_reached`` counts the seeds that reached the threshold)."""
    from factorq_trainers import reports

    entry = {"steps_to_threshold_per_seed": [120, None], "seeds_reached": 2}
    data = {
        "schema_version": 1,
        "command": "compare",
        "config": {"seeds": 2},
        "results": {"factor-q": {"static": entry}},
    }
    path = tmp_path / "comparison.json"
    with pytest.raises(ValueError, match="seeds_reached is 2, but 1 seeds reached") as error:
        reports.check_results(path, "compare", data)
    assert str(path) in str(error.value)
    entry["seeds_reached"] = 1
    reports.check_results(path, "compare", data)  # consistent: accepted
