"""``factorq sweep`` in-process: the spec, bad input, resumption, outputs, and ``paper`` options."""

from __future__ import annotations

import builtins
import contextlib
import io
import json
import signal
import subprocess
import sys
import time
from dataclasses import fields, replace

import pytest
from timing import patience  # tests/timing.py: bounds that stretch with the load

from factorq_trainers import cli
from factorq_trainers.commands.paper import command as paper
from factorq_trainers.compiled import fast
from factorq_trainers.distributed import sweep, sweep_spec
from factorq_trainers.distributed.sweep_spec import SweepError, SweepSpec
from factorq_trainers.runner import cluster
from factorq_trainers.runner import results as result_files

needs_fast = pytest.mark.skipif(not fast.is_available(), reason="fast backend unavailable")
BASE = (("runs", 1), ("episodes", 4), ("size", 5), ("obstacles", 3), ("shard_seeds", 2))
SPEC_TOML = """
seeds = 3
[base]
shard_seeds = 2
runs = 1
episodes = 4
size = 5
[grid]
obstacles = [2, 3]
eta = [0.05, 0.1]
"""


class CountingExecutor(cluster.InProcess):
    """In-process, counting the items it runs."""

    def __init__(self) -> None:
        self.items: list = []

    def map(self, function, items, names):
        self.items += list(items)
        return super().map(function, items, names)


def _spec(tmp_path, **changes) -> SweepSpec:
    values = {
        "base": BASE,
        "grid": (("eta", (0.05, 0.1)),),
        "seeds": 3,
        "out": str(tmp_path / "sweep"),
    }
    return SweepSpec(**{**values, **changes})


def test_every_paper_config_field_but_the_sweeps_own_is_sweepable():
    assert sweep_spec.reserved_fields("paper") == ("seeds", "out")
    names = [f.name for f in fields(paper.PaperConfig) if f.name not in ("seeds", "out")]
    assert list(sweep_spec.sweepable_fields()) == names
    assert "shard_seeds" in sweep_spec.sweepable_fields()  # a config field: units of its seeds


def test_grid_axes_are_crossed_with_the_configs_list(tmp_path):
    spec = _spec(
        tmp_path,
        grid=(("eta", (0.05, 0.1)), ("obstacles", (2, 3))),
        configs=((("size", 5),), (("size", 6),)),
        base=(("runs", 1), ("episodes", 2)),
    )
    points = spec.points()
    assert len(points) == 8
    assert points[0] == {"size": 5, "eta": 0.05, "obstacles": 2}
    assert points[-1] == {"size": 6, "eta": 0.1, "obstacles": 3}
    assert spec.axes == ["eta", "obstacles", "size"]
    assert [c.seeds for c in spec.configurations()] == [3] * 8


@pytest.mark.parametrize(
    ("document", "message"),
    [
        ({"grid": {"etta": [0.1]}}, "unknown field 'etta' in grid; sweepable: size, obstacles"),
        ({"base": {"seeds": 4}, "grid": {"eta": [0.1]}}, "'seeds' in base (the sweep sets it"),
        ({"grid": {"eta": [0.1, -1.0]}}, "configuration 1 (eta=-1.0): eta=-1.0"),
        ({"grid": {"obstacles": [2.5]}}, "obstacles must be an int"),
        ({"grid": {"eta": []}}, "grid axis 'eta' needs a non-empty list"),
        ({"grid": {"eta": [0.1, 0.1]}}, "grid axis 'eta' repeats a value"),
        ({"grid": {"eta": 0.1}}, "grid axis 'eta' must be a list"),
        ({"grid": {"eta": [0.1]}, "colour": "red"}, "unknown key(s) 'colour'"),
        ({"grid": {"eta": [0.1]}, "a\nb": 1}, "unknown key(s) 'a\\nb'; known"),  # one line
        ({"base": {"eta": {"a": 1}}, "grid": {"size": [5]}}, "field 'eta' in base holds {'a': 1}"),
        ({"grid": {"eta": [{"x": 1}]}}, "field 'eta' in grid holds {'x': 1}: a table is not"),
        (
            {"grid": {"eta": [0.1]}, "configs": [{"size": 5}, {"size": 5}]},
            "configurations 0 (size=5, eta=0.1) and 1 (size=5, eta=0.1) are the same",
        ),
        ({"grid": {"eta": [0.1]}, "command": "dependencies"}, "unknown field 'eta' in grid"),
        ({"grid": {"prior_a": [0.1]}, "command": "dependencies"}, "configuration 0 (prior_a=0.1)"),
        ({"grid": {"runs": [2]}, "shard_seeds": 1}, "unknown key(s) 'shard_seeds'; known"),
        (
            {"base": {"shard_seeds": 1}, "command": "dependencies"},
            "unknown field 'shard_seeds' in base",
        ),
        ({"grid": {"eta": [0.1]}, "command": "tune"}, "command='tune' is not one of compare, "),
        ({"grid": {"stepz": [1]}, "command": "compare"}, "unknown field 'stepz' in grid"),
        ({"grid": {"eta": [0.1]}, "command": "compare"}, "unknown field 'eta' in grid"),
        ({"base": {"dqn": {}}, "command": "compare"}, "'dqn' in base is a nested config"),
        ({"grid": {"steps": [1, 0]}, "command": "compare"}, "configuration 1 (steps=0)"),
        ({"grid": {"methods": [["sarsa"]]}, "command": "compare"}, "configuration 0 (methods"),
        ({"base": {"logger": "csv"}, "command": "compare"}, "'logger' in base (the sweep sets"),
        ({"base": {"shard_seeds": 1}, "command": "compare"}, "unknown field 'shard_seeds'"),
        ({"grid": {"shard_seeds": [2, 0]}}, "configuration 1 (shard_seeds=0): shard_seeds=0 is"),
    ],
)
def test_a_bad_spec_is_refused_naming_the_field_or_value(document, message):
    with pytest.raises((SweepError, ValueError, TypeError)) as raised:
        sweep_spec.spec_from_mapping(document, "sweep.toml")
    assert message in str(raised.value)
    assert str(raised.value).startswith("sweep.toml: ") and "\n" not in str(raised.value)


def test_bad_input_on_the_command_line_is_one_line_exit_2_and_nothing_written(tmp_path, capsys):
    spec_file = tmp_path / "bad.toml"
    spec_file.write_text('[grid]\nregimes = [["static"], ["windy"]]\n')
    out = tmp_path / "sweep"
    for argv in (
        [str(spec_file), "--out", str(out)],
        ["--grid", "eta=0.1,abc", "--out", str(out)],
        ["--grid", "colour=red", "--out", str(out)],
        ["--set", "eta", "--grid", "eta=0.1", "--out", str(out)],
        ["--out", str(out)],
        [str(tmp_path / "missing.toml")],
        ["--grid", "eta=0.1", "--cluster", "remote", "--out", str(out)],
        ["--grid", "eta=0.1", "--shard-seeds", "2", "--out", str(out)],  # (--set shard_seeds=2)
        ["--grid", "eta=0.1", "--cluster", "local:2", "--scheduler", "tcp://x:1"],
    ):
        assert cli.main(["sweep", *argv]) == 2, argv
        error = capsys.readouterr().err
        assert error.count("\n") == 1 and error.startswith("factorq sweep: error: "), error
    assert not out.exists()


def test_a_cluster_without_the_extra_names_the_extra(tmp_path, capsys, monkeypatch):
    real_import = builtins.__import__

    def no_dask(name, *args, **kwargs):
        if name == "distributed" or name.startswith("distributed."):
            raise ImportError(f"No module named {name!r}")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_dask)
    out = tmp_path / "sweep"
    argv = ["sweep", "--grid", "eta=0.1,0.2", "--cluster", "local:2", "--out", str(out)]
    assert cli.main(argv) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1
    assert "needs the 'distributed' extra: pip install 'factorq-torch[distributed]'" in error
    assert not out.exists()
    paper_out = tmp_path / "paper"
    assert cli.main(["paper", "--cluster", "local", "--out", str(paper_out)]) == 2
    assert "'distributed' extra" in capsys.readouterr().err
    assert not paper_out.exists()


@needs_fast
def test_a_sweep_writes_its_table_and_a_figure_per_axis(tmp_path, capsys):
    spec_file = tmp_path / "sweep.toml"
    spec_file.write_text(SPEC_TOML)
    out = tmp_path / "sweep"
    assert cli.main(["sweep", str(spec_file), "--out", str(out)]) == 0
    written = sorted(path.name for path in out.iterdir() if path.name != ".factorq.lock")
    assert written == ["configs", "sweep-eta.png", "sweep-obstacles.png", "sweep.json", "sweep.md"]
    result = json.loads((out / "sweep.json").read_text())
    assert result["axes"] == ["obstacles", "eta"]
    assert [row["values"] for row in result["configurations"]][1] == {"obstacles": 2, "eta": 0.1}
    assert result["timing"]["configurations_total"] == 4
    assert len(list((out / "configs").glob("*.json"))) == 4  # one kept file per configuration
    row = (out / "sweep.md").read_text().splitlines()[6]
    assert row.startswith("| 2 | 0.05 | static | q-learning | ")


@needs_fast
def test_a_sweep_cell_equals_the_paper_run_of_its_configuration(tmp_path):
    spec = _spec(tmp_path)
    result = sweep.run_sweep(spec, cluster.InProcess())
    config = spec.configurations()[1]
    expected = paper.run(replace(config, out=str(tmp_path / "paper")))
    cell = result["configurations"][1]["cells"]["dynamic/factor-q"]
    assert cell["per_seed"] == expected["cells"]["dynamic/factor-q"]["per_seed"]
    assert cell["collisions"] == expected["cells"]["dynamic/factor-q"]["summary"]["collisions"]


@needs_fast
def test_a_killed_sweep_resumes_running_only_the_missing_configurations_with_the_same_numbers(
    tmp_path,
):
    spec = _spec(tmp_path)
    first = CountingExecutor()
    complete = sweep.run_sweep(spec, first)
    assert first.items == spec.configurations()  # one task per configuration
    lost = tmp_path / "sweep" / complete["configurations"][1]["results_file"]
    lost.unlink()  # as if the sweep had been killed before this configuration finished
    again = CountingExecutor()
    resumed = sweep.run_sweep(spec, again)
    assert again.items == [first.items[1]]
    assert resumed["configurations"] == complete["configurations"]
    assert resumed["timing"]["configurations_run_now"] == 1


@needs_fast
def test_paper_shard_seeds_in_process_writes_the_same_results_as_a_plain_run(tmp_path, capsys):
    options = ["--seeds", "5", "--runs", "1", "--episodes", "4", "--size", "5"]
    assert cli.main(["paper", *options, "--out", str(tmp_path / "plain")]) == 0
    assert cli.main(["paper", *options, "--shard-seeds", "2", "--out", str(tmp_path / "cut")]) == 0
    plain = json.loads((tmp_path / "plain" / "results.json").read_text())
    cut = json.loads((tmp_path / "cut" / "results.json").read_text())
    assert isinstance(cut["timing"]["threads"], int) and cut["timing"]["threads"] >= 1
    assert cut["timing"]["units"] == 6 and plain["timing"]["units"] == 2  # 2 algorithms x 3, 1
    assert (cut["config"]["shard_seeds"], plain["config"]["shard_seeds"]) == (2, 100)
    for results in (plain, cut):
        results.pop("timing")
        results["config"].pop("out")
        results["config"].pop("shard_seeds")
    assert cut == plain
    assert not (tmp_path / "cut" / "units").exists()  # the kept units go with the results


#: ``factorq sweep ARGV...`` in a child that, once its first configuration is kept, touches the
#: file ``argv[1]`` and stalls before the next: a SIGKILL then lands between two configurations,
#: whatever the load (no race against a poll).
STALL_AFTER_ONE = """
import pathlib, sys, time
from factorq_trainers import cli
from factorq_trainers.distributed import sweep
real, kept, ran = sweep._units_task, pathlib.Path(sys.argv[1]), []
def units_task(command, config):
    if ran:
        kept.touch()
        time.sleep(3600)
    ran.append(config)
    return real(command, config)
sweep._units_task = units_task
sys.exit(cli.main(sys.argv[2:]))
"""


@needs_fast
def test_a_sweep_killed_with_sigkill_resumes_from_its_kept_configurations_with_the_same_numbers(
    tmp_path,
):
    out, one_kept = tmp_path / "killed", tmp_path / "one-kept"
    argv = ["--grid", "eta=0.05,0.1,0.2", "--seeds", "4", "--out", str(out)]
    command = [sys.executable, "-c", STALL_AFTER_ONE, str(one_kept), "sweep", *argv]
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + patience(120)
        while not one_kept.exists() and time.monotonic() < deadline:
            assert process.poll() is None, "the sweep ended before any configuration was kept"
            time.sleep(0.05)
        process.send_signal(signal.SIGKILL)
    finally:
        process.wait(timeout=patience(60))
    assert process.returncode == -signal.SIGKILL
    assert len(list(out.glob("configs/*.json"))) == 1 and not (out / "sweep.json").exists()
    assert cli.main(["sweep", *argv]) == 0  # the same command again resumes
    resumed = json.loads((out / "sweep.json").read_text())
    assert resumed["timing"]["configurations_run_now"] == 2
    spec = sweep_spec.SweepSpec(grid=(("eta", (0.05, 0.1, 0.2)),), seeds=4, out=str(out))
    fresh = sweep.run_sweep(replace(spec, out=str(tmp_path / "fresh")), cluster.InProcess())
    for row in (*resumed["configurations"], *fresh["configurations"]):
        row["config"].pop("out")
    assert resumed["configurations"] == json.loads(result_files.dumps(fresh))["configurations"]


COMPARE_TOML = """
command = "compare"
seeds = 1
[base]
steps = 300
regimes = ["static"]
methods = ["factor-q", "q-learning"]
size = 5
obstacles = 2
"""


def _without_wall_s(value):
    if isinstance(value, dict):
        return {k: _without_wall_s(v) for k, v in value.items() if k not in ("wall_s", "timing")}
    if isinstance(value, list):
        return [_without_wall_s(v) for v in value]
    return value


def test_every_compare_config_field_but_nested_and_the_sweeps_own_is_sweepable():
    from factorq_trainers.commands.compare import command as compare

    skipped = {*sweep_spec.reserved_fields("compare"), "agent", "dqn", "factor_dqn"}
    names = [f.name for f in fields(compare.CompareConfig) if f.name not in skipped]
    assert list(sweep_spec.sweepable_fields("compare")) == names
    assert sweep_spec.nested_fields("compare") == ["agent", "dqn", "factor_dqn"]


def test_a_compare_sweep_cell_equals_factorq_compare_and_resumes(tmp_path, capsys):
    from factorq_trainers.commands.compare import command as compare

    spec_file = tmp_path / "compare.toml"
    spec_file.write_text(COMPARE_TOML)
    out = tmp_path / "sweep"
    assert cli.main(["sweep", str(spec_file), "--grid", "seed=0,1", "--out", str(out)]) == 0
    written = sorted(path.name for path in out.iterdir() if path.name != ".factorq.lock")
    assert written == ["configs", "sweep-seed.png", "sweep.json", "sweep.md"]
    result = json.loads((out / "sweep.json").read_text())
    assert result["command"] == "compare" and result["axes"] == ["seed"]
    spec = sweep_spec.spec_from_mapping(
        {**sweep_spec.read_spec_file(spec_file), "grid": {"seed": [0, 1]}}
    )
    config = spec.configurations()[1]
    expected = json.loads(result_files.dumps(compare.run(replace(config, out=str(tmp_path / "c")))))
    row = result["configurations"][1]
    stored = json.loads((out / row["results_file"]).read_text())
    assert len(stored.pop("content_sha256")) == 64  # checked when the file is reused
    tie = {"command": "compare", "config_sha256": sweep_spec.config_digest(config)}
    assert stored.pop("kept_for") == tie  # a file of another configuration is refused
    assert stored["config"].pop("out") == str(out) and expected["config"].pop("out")
    assert _without_wall_s(stored) == _without_wall_s(expected)
    cell = row["cells"]["static/factor-q"]
    assert cell["collisions"]["mean"] == expected["results"]["factor-q"]["static"]["collisions"]
    assert set(cell) >= {"steps_to_threshold", "greedy_collisions", "avoidable_greedy_collisions"}
    table = (out / "sweep.md").read_text()
    header = "| seed | world | algorithm | steps to threshold | collisions | greedy collisions |\n"
    assert header in table
    # resumption: a lost configuration file is the only work of the next run
    (out / row["results_file"]).unlink()
    again = CountingExecutor()
    resumed = sweep.run_sweep(replace(spec, out=str(out)), again)
    assert [item.seed for item in again.items] == [1]  # one task: the lost configuration
    assert resumed["timing"]["configurations_run_now"] == 1
    assert _without_wall_s(json.loads(result_files.dumps(resumed))["configurations"]) == (
        _without_wall_s(result["configurations"])
    )
    # a kept result whose numbers were edited (its digest kept) is refused before any work
    edited = json.loads((out / row["results_file"]).read_text())
    edited["results"]["factor-q"]["static"]["collisions"] *= 100
    (out / row["results_file"]).write_text(json.dumps(edited))
    refused = CountingExecutor()
    with pytest.raises(ValueError, match="does not match its digest .* pass --force to recompute"):
        sweep.run_sweep(replace(spec, out=str(out)), refused)
    assert refused.items == []


DEPENDENCIES_TOML = """
command = "dependencies"
seeds = 2
[base]
settings = ["cross", "change"]
methods = ["factor-q-learned", "factor-q"]
runs = 2
size = 4
obstacles = 2
max_steps = 150
change_run = 1
"""


def test_every_dependencies_config_field_but_seeds_and_out_is_sweepable():
    from factorq_trainers.commands.dependencies import command as dependencies

    names = [f.name for f in fields(dependencies.DependenciesConfig)]
    assert list(sweep_spec.sweepable_fields("dependencies")) == [
        name for name in names if name not in ("seeds", "out")
    ]


def test_a_dependencies_sweep_cell_equals_factorq_dependencies_and_resumes(tmp_path):
    from factorq_trainers.commands.dependencies import command as dependencies

    spec_file = tmp_path / "dependencies.toml"
    spec_file.write_text(DEPENDENCIES_TOML)
    out = tmp_path / "sweep"
    argv = ["sweep", str(spec_file), "--grid", "prior_a=1,0.25", "--out", str(out)]
    assert cli.main(argv) == 0
    result = json.loads((out / "sweep.json").read_text())
    assert result["command"] == "dependencies" and result["axes"] == ["prior_a"]
    grid = {"prior_a": [1.0, 0.25]}
    spec = sweep_spec.spec_from_mapping({**sweep_spec.read_spec_file(spec_file), "grid": grid})
    config = spec.configurations()[1]
    expected = json.loads(result_files.dumps(dependencies.run(replace(config, out="unused"))))
    row = result["configurations"][1]
    stored = json.loads((out / row["results_file"]).read_text())
    assert len(stored.pop("content_sha256")) == 64  # checked when the file is reused
    tie = {"command": "dependencies", "config_sha256": sweep_spec.config_digest(config)}
    assert stored.pop("kept_for") == tie  # a file of another configuration is refused
    assert stored["config"].pop("out") == str(out) and expected["config"].pop("out")
    assert _without_wall_s(stored) == _without_wall_s(expected)
    cell = row["cells"]["change/factor-q-learned"]
    learned = expected["settings"]["change"]
    assert (
        cell["collisions"]["mean"]
        == learned["methods"]["factor-q-learned"]["collisions_per_experiment"]
    )
    assert cell["collisions_vs_oracle"]["mean"] == learned["against_oracle"]["collisions"]["ratio"]
    assert row["cells"]["change/factor-q"]["fraction_right_within_target"]["mean"] is None
    assert "| prior_a | world | algorithm | collisions |" in (out / "sweep.md").read_text()
    # resumption: a lost configuration file is the only work of the next run
    (out / row["results_file"]).unlink()
    again = CountingExecutor()
    resumed = sweep.run_sweep(replace(spec, out=str(out)), again)
    assert again.items == [replace(config, out=str(out))]
    assert resumed["timing"]["configurations_run_now"] == 1
    assert _without_wall_s(json.loads(result_files.dumps(resumed))["configurations"]) == (
        _without_wall_s(result["configurations"])
    )
    # a kept configuration file edited or cut short: refused naming it before any work, in one
    # line without a traceback; --force recomputes it
    kept = out / row["results_file"]
    good = json.loads(kept.read_text())
    edited = json.loads(kept.read_text())
    edited["settings"]["change"]["methods"]["factor-q-learned"]["collisions_per_experiment"] *= 100
    for bad in ('{"settings": {"change": {}}}', "garbage{", json.dumps(edited)):
        kept.write_text(bad)
        refused = CountingExecutor()
        with pytest.raises(ValueError, match="configuration file .* pass --force to recompute"):
            sweep.run_sweep(replace(spec, out=str(out)), refused)
        assert refused.items == []
    (out / "sweep.json").unlink()
    (out / "sweep.md").unlink()  # (an --out with them is refused without --force)
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        assert cli.main(argv) == 1
    message = f"configuration file {kept} does not match its digest (edited or damaged): pass"
    assert message in err.getvalue() and "Traceback" not in err.getvalue()
    with contextlib.redirect_stderr(io.StringIO()), contextlib.redirect_stdout(io.StringIO()):
        assert cli.main([*argv, "--force"]) == 0
    recomputed = json.loads(kept.read_text())
    assert recomputed.pop("content_sha256") != good.pop("content_sha256")  # (timing differs)
    assert _without_wall_s(recomputed) == _without_wall_s(good)


def test_bad_compare_input_on_the_command_line_is_one_line_exit_2_and_nothing_written(
    tmp_path, capsys
):
    out = tmp_path / "sweep"
    for argv in (
        ["--command", "compare", "--grid", "eta=0.1", "--out", str(out)],
        ["--command", "compare", "--grid", "steps=100,abc", "--out", str(out)],
        ["--command", "compare", "--set", "agent=x", "--grid", "steps=9", "--out", str(out)],
        ["--command", "compare", "--grid", "methods=factor-q,sarsa", "--out", str(out)],
        ["--command", "dependencies", "--grid", "steps=9", "--out", str(out)],
        ["--command", "dependencies", "--grid", "prior_b=0.3", "--out", str(out)],
    ):
        assert cli.main(["sweep", *argv]) == 2, argv
        error = capsys.readouterr().err
        assert error.count("\n") == 1 and error.startswith("factorq sweep: error: "), error
    assert not out.exists()
