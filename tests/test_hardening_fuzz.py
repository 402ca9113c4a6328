"""Issue 29 item 7: a fuzz harness for what is read from disk. Arbitrary structure and values go
to the sweep file parser, the results reader and the checkpoint reader: each gives a valid result
or the project's own one-line error, never another exception, in bounded time.

Bounded for CI: a fixed number of examples each (``max_examples``), a generous per-example
``deadline`` (the machine may be loaded), no example database written to the tree.
"""

from __future__ import annotations

import io
import json
import tempfile
from datetime import timedelta
from pathlib import Path

import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from timing import patience  # tests/timing.py: bounds that stretch with the load

from factorq_trainers.distributed import sweep_spec
from factorq_trainers.runner import checkpoint, results

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
        "command": st.sampled_from([*sweep_spec.commands(), "nope"]) | scalars,
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


tensors = st.builds(
    lambda shape, dtype: torch.zeros(shape, dtype=dtype),
    st.lists(st.integers(0, 3), max_size=3),
    st.sampled_from([torch.float32, torch.int64, torch.bool]),
)
#: What ``torch.load(weights_only=True)`` can give back: containers, numbers, strings, tensors.
checkpoint_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**70), 2**70)
    | st.floats()
    | st.text(max_size=8)
    | tensors,
    lambda children: (
        st.lists(children, max_size=3)
        | st.dictionaries(st.text(max_size=8), children, max_size=3)
        | st.lists(children, max_size=3).map(tuple)
    ),
    max_leaves=16,
)


@FUZZ
@given(
    content=checkpoint_values
    | st.fixed_dictionaries(
        {name: checkpoint_values for name in checkpoint.Checkpoint._fields[1:]}
    ),
    signed=st.booleans(),
)
def test_a_checkpoint_of_any_structure_gives_a_checkpoint_or_a_checkpoint_error(content, signed):
    record = {"format": checkpoint.FORMAT, "version": checkpoint.FORMAT_VERSION}
    record["sha256"] = checkpoint.digest(content) if signed else "0" * 64
    with tempfile.TemporaryDirectory() as directory:
        out = Path(directory)
        path = checkpoint.directory_of(out) / checkpoint.LATEST
        path.parent.mkdir()
        buffer = io.BytesIO()
        torch.save({**record, "content": content}, buffer)
        path.write_bytes(buffer.getvalue())
        try:
            loaded = checkpoint.load(out)
        except checkpoint.CheckpointError as error:
            _one_line(error)
        else:
            assert isinstance(loaded, checkpoint.Checkpoint)


@FUZZ
@given(content=st.binary(max_size=400))
def test_a_checkpoint_of_any_bytes_is_a_checkpoint_error(content):
    with tempfile.TemporaryDirectory() as directory:
        path = Path(directory) / "checkpoint.pt"
        path.write_bytes(content)
        try:
            checkpoint.read_content(path, checkpoint.FORMAT)
        except checkpoint.CheckpointError as error:
            _one_line(error)


def test_the_harness_reaches_past_the_first_checks():
    """The readers accept what they should: a valid spec and results file built from the same
    pieces are read back (so the fuzzing above is not all refused at the door)."""
    spec = sweep_spec.spec_from_mapping({"grid": {"alpha": [0.1, 0.2]}, "seeds": 2}, "fuzz.toml")
    assert len(spec.configurations()) == 2
    assert _read(json.dumps({"command": "paper"}).encode()) == {"command": "paper"}


@FUZZ
@given(
    config=values.map(lambda value: json.dumps(value, allow_nan=True)) | st.text(max_size=40),
    arrays=st.dictionaries(
        st.sampled_from(["collisions", "total_steps", "x"]),
        st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=4),
        max_size=3,
    ),
    raw=st.none() | st.binary(max_size=200),
)
def test_a_shard_file_of_any_content_gives_metrics_or_a_value_error(config, arrays, raw):
    import numpy as np

    from factorq_trainers.experiments import paper_shards as shards
    from factorq_trainers.experiments.paper_config import PaperConfig

    with tempfile.TemporaryDirectory() as directory:
        path = Path(directory) / "000000-000001.npz"
        if raw is None:
            numbers = {key: np.array(value) for key, value in arrays.items()}
            with open(path, "wb") as handle:
                np.savez(handle, __config__=np.array(config), **numbers)
        else:
            path.write_bytes(raw)
        try:
            metrics = shards.load(path, PaperConfig(seeds=1))
        except ValueError as error:
            _one_line(error)
        else:
            assert isinstance(metrics, dict)
