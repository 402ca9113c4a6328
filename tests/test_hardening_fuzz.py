"""Issue 29 item 7: a fuzz harness for what is read from disk. Arbitrary structure and values go
to the sweep file parser, the results reader and a run's kept units: each
gives a valid result or the project's own one-line error, never another exception, in bounded
time.

Bounded for CI: a fixed number of examples each (``max_examples``), a generous per-example
``deadline`` (the machine may be loaded), no example database written to the tree.
"""

from __future__ import annotations

import json
import tempfile
from datetime import timedelta
from pathlib import Path

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from timing import patience  # tests/timing.py: bounds that stretch with the load

from factorq_trainers.distributed import sweep_spec
from factorq_trainers.runner import registry, results

FUZZ = settings(
    max_examples=150,
    deadline=timedelta(seconds=patience(5)),
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)

scalars = (
    st.none()
    | st.booleans()
    | st.integers()
    | st.integers(min_value=-(10**400), max_value=10**400)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=12)
)
#: JSON-like values of any shape: what a parsed TOML, YAML or JSON document can hold.
values = st.recursive(
    scalars,
    lambda children: (
        st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=8), children, max_size=4)
    ),
    max_leaves=24,
)
FIELDS = list(sweep_spec.sweepable_fields("paper"))[:12] + ["seeds", "unknown_field"]
fields = st.sampled_from(FIELDS)
#: Sweep documents near the valid ones, so the checks past the first are reached too.
specs = st.fixed_dictionaries(
    {},
    optional={
        "command": st.sampled_from([*registry.commands(), "nope"]) | scalars,
        "seeds": scalars,
        "shard_seeds": scalars,
        "out": st.sampled_from(["sweep-out", "", "/dev/null"]) | scalars,
        "base": st.dictionaries(fields, scalars, max_size=3) | values,
        "grid": st.dictionaries(fields, st.lists(scalars, max_size=3), max_size=3) | values,
        "configs": st.lists(st.dictionaries(fields, scalars, max_size=2), max_size=3) | values,
    },
)


def _one_line(error: Exception) -> None:
    assert str(error) and "\n" not in str(error), repr(error)


@FUZZ
@given(document=specs | values)
def test_a_sweep_document_gives_a_spec_or_a_sweep_error(document):
    try:
        spec = sweep_spec.spec_from_mapping(document, "fuzz.toml")
    except sweep_spec.SweepError as error:
        _one_line(error)
    else:
        assert isinstance(spec, sweep_spec.SweepSpec)


@FUZZ
@given(text=st.text(max_size=300), suffix=st.sampled_from([".toml", ".yaml"]))
def test_a_sweep_file_of_any_text_gives_a_spec_or_a_sweep_error(text, suffix):
    with tempfile.TemporaryDirectory() as directory:
        path = Path(directory) / f"spec{suffix}"
        path.write_text(text)
        try:
            sweep_spec.spec_from_mapping(sweep_spec.read_spec_file(path), str(path))
        except sweep_spec.SweepError as error:
            _one_line(error)


def _read(content: bytes):
    with tempfile.TemporaryDirectory() as directory:
        path = Path(directory) / "results.json"
        path.write_bytes(content)
        try:
            return results.read_json(path, ["command"], "run a command")
        except ValueError as error:
            _one_line(error)
            return None


@FUZZ
@given(document=values | st.dictionaries(st.just("command") | st.text(max_size=6), values))
def test_a_results_file_of_any_json_gives_the_results_or_a_value_error(document):
    text = json.dumps(document, allow_nan=True)
    read = _read(text.encode())
    if read is not None:
        assert isinstance(read, dict) and "command" in read


@FUZZ
@given(content=st.binary(max_size=400))
def test_a_results_file_of_any_bytes_gives_the_results_or_a_value_error(content):
    _read(content)


def test_the_harness_reaches_past_the_first_checks():
    """The readers accept what they should: a valid spec and results file built from the same
    pieces are read back (so the fuzzing above is not all refused at the door)."""
    spec = sweep_spec.spec_from_mapping({"grid": {"alpha": [0.1, 0.2]}, "seeds": 2}, "fuzz.toml")
    assert len(spec.configurations()) == 2
    assert _read(json.dumps({"command": "paper"}).encode()) == {"command": "paper"}


#: Numbers as a kept unit may hold them: mostly counts, some of every other kind.
unit_numbers = st.one_of(*[st.integers(0, 5)] * 12, scalars)


def _unit_lists(items):
    """Mostly one item (the unit's one seed, world), some of any length."""
    one = st.lists(items, min_size=1, max_size=1)
    return st.one_of(one, one, one, one, one, st.lists(items, max_size=2))


#: Paper unit results near the valid ones (``paper.UNIT_RESULT``'s shape), so that the checks past
#: the schema (``paper.check_unit``) are reached too.
paper_units = st.fixed_dictionaries(
    {
        "algorithm": st.sampled_from(["factor-q", "q-learning"]) | scalars,
        "backend": st.sampled_from(["fast", "modular"]) | scalars,
        "env_steps": unit_numbers,
        "worlds": _unit_lists(
            st.fixed_dictionaries(
                {
                    "world": st.one_of(*[st.just("static")] * 4, st.just("dynamic"), scalars),
                    "run_sums": st.fixed_dictionaries(
                        {
                            name: _unit_lists(unit_numbers)
                            for name in ("total_steps", "collisions", "greedy_collisions")
                        }
                    ),
                    "task_return": _unit_lists(unit_numbers),
                    "curve_sums": st.fixed_dictionaries(
                        {
                            name: _unit_lists(st.lists(unit_numbers, min_size=2, max_size=3))
                            for name in ("steps", "collisions", "greedy_collisions")
                        }
                    ),
                }
            )
        ),
    }
)


def _paper_unit_store(directory: str):
    """A one-unit paper run started in ``directory``: its config, its unit, its store, and the
    check ``--resume`` gives its kept units."""
    import functools

    from factorq_trainers.commands.paper import command as paper
    from factorq_trainers.runner import frame, kept

    config = paper.PaperConfig(
        seeds=1, runs=1, episodes=2, regimes=("static",), methods=("factor-q",), out=directory
    )
    (unit,) = paper.units(config)
    store = kept.UnitStore(directory)
    store.start(paper.NAME, frame.plain(config), [unit["id"]])
    return config, unit, store, functools.partial(paper.check_unit, config)


@FUZZ
@given(result=paper_units | values, raw=st.none() | st.binary(max_size=200))
def test_a_kept_paper_unit_of_any_content_is_reused_and_summarised_or_refused_in_one_line(
    result, raw
):
    """A unit file kept sealed and tied to its run (so the checks reach its values), or any bytes:
    ``--resume`` reuses it only if the paper can summarise it, else refuses it in one line."""
    from factorq_trainers.commands.paper import command as paper
    from factorq_trainers.runner import frame, kept

    with tempfile.TemporaryDirectory() as directory:
        config, unit, store, check = _paper_unit_store(directory)
        if raw is None:
            store.keep(unit, frame.through_json(result))
        else:
            kept.unit_path(store.directory, unit["id"]).write_bytes(raw)
        try:
            found = store.finished([unit], paper.UNIT_RESULT, False, check)
        except ValueError as error:
            _one_line(error)
        else:
            summary = paper.summarise(config, [found[unit["id"]]])
            assert set(summary["cells"]) == {"static/factor-q"}


def test_a_valid_kept_paper_unit_is_reused():
    """The fuzzing above is not all refused at the door: a unit as ``run_unit`` gives it is."""
    from factorq_trainers.commands.paper import command as paper

    with tempfile.TemporaryDirectory() as directory:
        _, unit, store, check = _paper_unit_store(directory)
        result = {
            "algorithm": "factor-q",
            "backend": "fast",
            "env_steps": 9,
            "worlds": [
                {
                    "world": "static",
                    "run_sums": {"total_steps": [9], "collisions": [2], "greedy_collisions": [1]},
                    "task_return": [-7.5],
                    "curve_sums": {
                        "steps": [[5, 4]],
                        "collisions": [[2, 0]],
                        "greedy_collisions": [[1, 0]],
                    },
                }
            ],
        }
        store.keep(unit, result)
        assert store.finished([unit], paper.UNIT_RESULT, False, check) == {unit["id"]: result}
