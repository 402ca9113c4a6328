"""Issue 29 item 1: files the project creates are never opened through links. A link planted
where the lock, a temporary or an output belongs is refused in one line, and its target is left
as it was (the lock used to be opened through the link and the target truncated to a pid).
Item 2: kept configuration results (``OUT/configs/<digest>.json``) carry a content digest,
checked with their values when a sweep reuses them; a bad one is refused naming the file before
any work, and ``--force`` recomputes it (a run's kept units: tests/test_kept_units.py)."""

from __future__ import annotations

import json
import os

import pytest

from factorq_trainers.runner import outdir, results

PRECIOUS = b"a user's file, not ours\n"


@pytest.fixture
def victim(tmp_path):
    path = tmp_path / "precious.txt"
    path.write_bytes(PRECIOUS)
    return path


def one_line(error: pytest.ExceptionInfo) -> str:
    message = str(error.value)
    assert "\n" not in message
    return message


def test_a_link_planted_as_the_lock_is_refused_and_its_target_kept(tmp_path, victim):
    out = tmp_path / "out"
    out.mkdir()
    (out / outdir.LOCK_FILE).symlink_to(victim)
    with pytest.raises(outdir.LinkRefused) as error:
        with outdir.claim(out):
            pytest.fail("claimed through a link")
    assert "is a symbolic link where factorq writes its own file" in one_line(error)
    assert outdir.LOCK_FILE in str(error.value)
    assert victim.read_bytes() == PRECIOUS


def test_a_dangling_link_as_the_lock_creates_nothing_at_its_target(tmp_path):
    out, target = tmp_path / "out", tmp_path / "would-be-created"
    out.mkdir()
    (out / outdir.LOCK_FILE).symlink_to(target)
    with pytest.raises(outdir.LinkRefused):
        with outdir.claim(out):
            pass
    assert not target.exists()


def test_a_lock_that_is_not_a_regular_file_is_refused(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    os.mkfifo(out / outdir.LOCK_FILE)
    with pytest.raises(outdir.OutputDirError, match="is not a regular file: remove it"):
        with outdir.claim(out):
            pass


def test_the_lock_of_a_fresh_and_of_an_earlier_run_is_a_regular_file_with_our_pid(tmp_path):
    out = tmp_path / "out"
    for _ in range(2):  # created new, then reopened (no link)
        with outdir.claim(out) as path:
            (path / "kept").write_text("x")
            assert (path / outdir.LOCK_FILE).read_text() == str(os.getpid())
    assert not (out / outdir.LOCK_FILE).is_symlink()


def test_a_link_where_an_output_belongs_is_refused_even_with_force(tmp_path, victim):
    out = tmp_path / "out"
    out.mkdir()
    (out / "results.json").symlink_to(victim)
    with pytest.raises(outdir.LinkRefused, match="results.json"):
        with outdir.claim(out, outputs=["results.json"], force=True):
            pass
    assert victim.read_bytes() == PRECIOUS


def test_a_link_planted_at_a_temporarys_name_is_refused_and_its_target_kept(tmp_path, victim):
    path = tmp_path / "results.json"
    results.temporary_path(path).symlink_to(victim)
    with pytest.raises(outdir.LinkRefused) as error:
        results.write_atomic(path, lambda temporary: temporary.write_text("{}"))
    one_line(error)
    assert victim.read_bytes() == PRECIOUS
    assert not path.exists()
    # the link was removed with the temporaries: the next write goes through
    results.write_atomic(path, lambda temporary: temporary.write_text("{}"))
    assert path.read_text() == "{}" and victim.read_bytes() == PRECIOUS


def test_a_stale_regular_temporary_of_a_reused_pid_is_replaced(tmp_path):
    path = tmp_path / "results.json"
    results.temporary_path(path).write_text("half-written by a killed run")
    results.write_atomic(path, lambda temporary: temporary.write_text("new"))
    assert path.read_text() == "new"
    assert not results.temporary_path(path).exists()


def test_a_fifo_where_a_results_file_belongs_is_named_as_such_not_missing(tmp_path):
    from factorq_trainers import reports

    fifo = tmp_path / "results.json"
    os.mkfifo(fifo)
    fifo_refused = r"results.json is not a regular file \(a FIFO\): not a results file"
    with pytest.raises(ValueError, match=fifo_refused):
        results.read_json(fifo, ["config"], "run factorq paper")  # (reading it would block)
    with pytest.raises(ValueError, match="is not a regular file"):
        reports.find(tmp_path)


# --- kept configuration results (compare, dependencies, ... sweeps) ------------------------------


def _compare_result(seeds=3):
    """A compare configuration's result as a sweep keeps it (hand-made; two of three seeds
    reached the threshold)."""
    return {
        "schema_version": 1,
        "command": "compare",
        "config": {"seeds": seeds, "steps": 300, "out": "x"},
        "thresholds": {"static": {"shortest_path": 8, "threshold": 12.0}},
        "results": {
            "factor-q": {
                "static": {
                    "steps_to_threshold": 150.0,
                    "collisions": 5.0,
                    "greedy_collisions": 4.0,
                    "wall_s": 0.5,
                    "seeds_reached": 2,
                    "steps_to_threshold_per_seed": [120, None, 180],
                    "collisions_ci95": [3.0, 7.0],
                    "episodes": 5.0,
                }
            }
        },
        "curves": {
            "env_steps": [3.0, 6.0],
            "factor-q": {"static": {"steps": {"mean": [None, 4.5]}}},
        },
        "timing": {"method_wall_s": 0.5, "where": "in-process"},
    }


def _entry(results):
    return results["results"]["factor-q"]["static"]


def _kept_result(tmp_path, results=None):
    from factorq_trainers.runner import kept

    path = tmp_path / "0123456789abcdef.json"
    path.write_text(kept.dumps_sealed(results or _compare_result()))
    return kept, path


def _rewrite(path, change, sign):
    from factorq_trainers.runner import kept

    results = json.loads(path.read_text())
    change(results)
    if sign:
        results[kept.DIGEST_KEY] = kept.json_digest(results)
    path.write_text(json.dumps(results))


def test_a_kept_configuration_result_reads_back_as_it_was_written(tmp_path):
    kept, path = _kept_result(tmp_path)
    assert kept.read_sealed(path, "configuration file") == _compare_result()


@pytest.mark.parametrize(
    ("change", "sign", "message"),
    [
        (lambda r: _entry(r).update(collisions=500.0), False, "does not match its digest"),
        (lambda r: r.pop("content_sha256"), False, "has no digest"),
        (lambda r: _entry(r).update(collisions=float("nan")), True, "collisions holds nan, not a"),
        (lambda r: _entry(r).update(wall_s=float("inf")), True, "wall_s holds inf, not a finite"),
        (lambda r: _entry(r).update(collisions=10**400), True, "0, not a finite number"),
        (lambda r: _entry(r).update(greedy_collisions=-4.0), True, "holds -4.0, negative"),
        (lambda r: _entry(r)["collisions_ci95"].__setitem__(0, 1e999), True, "ci95.0. holds inf"),
        (lambda r: _entry(r).update(seeds_reached=2.5), True, "holds 2.5, not a whole count"),
        (lambda r: _entry(r).update(seeds_reached=3), True, "but 2 seeds reached the threshold"),
        (lambda r: _entry(r)["steps_to_threshold_per_seed"].pop(), True, "holds 2 seeds' steps"),
        (
            lambda r: r["curves"]["factor-q"]["static"]["steps"].update(mean=[1, -2]),
            True,
            "-2, neg",
        ),
        (lambda r: r.update(extra={"fraction_right": 1.5}), True, "1.5, not a fraction"),
        (lambda r: _entry(r).update(collisions="many"), True, "holds 'many', not a number"),
    ],
    ids=[
        "x100",
        "no-digest",
        "nan",
        "inf",
        "past-float",
        "negative",
        "infinite-interval",
        "fractional-count",
        "seeds-reached",
        "seed-missing",
        "negative-curve",
        "fraction",
        "text",
    ],
)
def test_an_edited_kept_configuration_result_is_refused_naming_the_file(
    tmp_path, change, sign, message
):
    from factorq_trainers.commands.compare import report as compare_report

    kept, path = _kept_result(tmp_path)
    _rewrite(path, change, sign)
    with pytest.raises(ValueError, match=message) as error:  # compare's own check included
        kept.read_sealed(path, "configuration file", check=compare_report.results_problem)
    assert str(path) in one_line(error) and "pass --force to recompute it" in str(error.value)


def test_a_kept_results_negative_return_and_settings_are_not_refused(tmp_path):
    """Only measured counts are range-checked: a return may be negative, so may the lower bound
    of a count's t interval, a config holds settings (the digest covers them)."""
    results = _compare_result()
    _entry(results)["return"] = -3.5
    _entry(results)["collisions_ci95"][0] = -1.5
    results["config"]["reward_collision"] = -1.0
    kept, path = _kept_result(tmp_path, results)
    assert kept.read_sealed(path, "configuration file") == results


def test_reusable_refuses_a_bad_kept_file_unless_forced(tmp_path):
    from factorq_trainers.runner import kept

    def check(path):
        return kept.read_sealed(path, "configuration file")

    assert not kept.reusable(tmp_path / "none.json", check, force=False)
    _, path = _kept_result(tmp_path)
    assert kept.reusable(path, check, force=False) and kept.reusable(path, check, force=True)
    path.write_text("{cut sho")
    with pytest.raises(ValueError, match="is unreadable .*pass --force to recompute it"):
        kept.reusable(path, check, force=False)
    assert not kept.reusable(path, check, force=True)  # recomputed by the caller


def _times_100(results):
    cell = next(iter(results["cells"].values()))
    cell["summary"]["collisions"]["mean"] *= 100


def _negative(results):
    cell = next(iter(results["cells"].values()))
    cell["per_seed"]["collisions"][0] = -4.0


@pytest.mark.parametrize(
    ("change", "sign", "message"),
    [(_times_100, False, "does not match its digest"), (_negative, True, "holds -4.0, negative")],
    ids=["x100", "negative-resealed"],
)
def test_a_paper_sweep_refuses_an_edited_kept_configuration_before_any_work_and_force_recomputes_it(
    tmp_path, change, sign, message
):
    from factorq_trainers.distributed import sweep, sweep_spec
    from factorq_trainers.runner import cluster

    class Counting(cluster.InProcess):
        def __init__(self) -> None:
            self.items: list = []

        def map(self, function, items, names):
            self.items += list(items)
            return super().map(function, items, names)

    spec = sweep_spec.SweepSpec(
        base=(("runs", 1), ("episodes", 3), ("size", 5), ("obstacles", 2), ("shard_seeds", 1)),
        grid=(("eta", (0.1, 0.2)),),
        seeds=2,
        out=str(tmp_path / "sweep"),
    )
    first = sweep.run_sweep(spec, cluster.InProcess())
    path = tmp_path / "sweep" / first["configurations"][1]["results_file"]
    _rewrite(path, change, sign)
    refused = Counting()
    with pytest.raises(ValueError, match=message) as error:
        sweep.run_sweep(spec, refused)
    assert str(path) in one_line(error) and "pass --force to recompute it" in str(error.value)
    assert refused.items == []  # refused before any work
    forced = Counting()
    again = sweep.run_sweep(spec, forced, force=True)
    assert forced.items == [spec.configurations()[1]]
    assert again["configurations"] == first["configurations"]
    assert again["timing"]["configurations_run_now"] == 1
