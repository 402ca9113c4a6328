"""Issue 41 item 5: the red team's classes as properties. Every reader of a file factorq reads
(sweep files, results, checkpoints) refuses a hostile file of every kind (a FIFO, a
device, a directory, a link, a dangling link, an oversized sparse file, deep nesting, a
compressed bomb) with its own one-line error; a hostile peer at the scheduler address (any
bytes, any announced length, silence) is refused in one line within the timeout.

Bounded: each example runs under a deadline (``signal.setitimer``, restored after), so a reader
that blocked on a FIFO would fail the example instead of hanging the run; peers are loopback
servers of one connection each.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import struct
import tempfile
import threading
import zipfile
from datetime import timedelta
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from factorq_trainers.distributed import sweep_spec as sweep
from factorq_trainers.runner import cluster, reading, results

FUZZ = settings(
    max_examples=60,
    deadline=timedelta(seconds=30),
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)


@contextlib.contextmanager
def deadline(seconds: float):
    """Raise TimeoutError in this (main) thread after ``seconds``; the previous handler and timer
    are restored."""

    def expire(signum, frame):
        raise TimeoutError(f"no answer within {seconds} s")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


#: Every reader of a file, with the error it refuses with.
READERS = {
    "sweep toml": (".toml", sweep.read_spec_file, sweep.SweepError),
    "sweep yaml": (".yaml", sweep.read_spec_file, sweep.SweepError),
    "results": (".json", lambda p: results.read_json(p, ["config"], "run it"), ValueError),
}
KINDS = ("fifo", "zero", "urandom", "directory", "link", "dangling", "oversize", "deep", "bomb")


def _make(kind: str, path: Path, size: int, depth: int) -> Path:
    """A hostile file of ``kind`` at ``path`` (or the device it names)."""
    if kind == "fifo":
        os.mkfifo(path)
    elif kind in ("zero", "urandom"):
        return Path(f"/dev/{kind}")
    elif kind == "directory":
        path.mkdir()
    elif kind == "link":
        target = path.with_name("target" + path.suffix)
        target.write_text("{}")
        path.symlink_to(target)
    elif kind == "dangling":
        path.symlink_to(path.with_name("nowhere"))
    elif kind == "oversize":  # sparse: no disk used
        with open(path, "wb") as handle:
            handle.truncate(results.MAX_FILE_BYTES + size)
    elif kind == "deep":
        if path.suffix == ".toml":
            path.write_text(".".join(["a"] * depth) + " = 1\n")
        elif path.suffix == ".yaml":
            path.write_text("x: " + "[" * depth + "]" * depth)
        else:
            path.write_text('{"config": ' + "[" * depth + "]" * depth + "}")
    elif kind == "bomb":
        with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
            with archive.open("x.npy", "w", force_zip64=True) as member:
                chunk = bytes(2**20)
                for _ in range(size % 48 + 16):  # 16-63 MiB of zeros, a few kB deflated
                    member.write(chunk)
    return path


@FUZZ
@given(
    reader=st.sampled_from(sorted(READERS)),
    kind=st.sampled_from(KINDS),
    size=st.integers(1, 2**20),
    depth=st.integers(33, 20_000),
)
def test_a_hostile_file_of_any_kind_is_refused_by_every_reader_in_one_line(
    reader, kind, size, depth
):
    suffix, read, refusal = READERS[reader]
    with tempfile.TemporaryDirectory() as directory:
        path = _make(kind, Path(directory) / f"hostile{suffix}", size, depth)
        with deadline(60), pytest.raises((refusal, FileNotFoundError)) as raised:
            read(path)
    message = str(raised.value)
    assert "\n" not in message and message, (reader, kind, message)
    assert isinstance(raised.value, ValueError | FileNotFoundError)


@FUZZ
@given(text=st.text(max_size=200), dots=st.integers(0, 5000))
def test_toml_depth_bounds_tomllib_depth_on_any_text(text, dots):
    """What ``toml_depth`` lets through parses without going deeper than it said."""
    import tomllib

    document = text + "\n" + ".".join(["k"] * (dots + 1)) + " = 1\n"
    with deadline(60):
        bound = reading.toml_depth(document)
        if bound > reading.MAX_DEPTH:
            return
        try:
            parsed = tomllib.loads(document)
        except tomllib.TOMLDecodeError:
            return
    assert not reading.deeper_than(parsed, bound)


def _serve_once(reply: bytes) -> tuple[str, socket.socket, threading.Thread]:
    server = socket.create_server(("127.0.0.1", 0))
    server.settimeout(30)

    def answer():
        with contextlib.suppress(OSError):
            connection, _ = server.accept()
            with connection:
                connection.sendall(reply)

    thread = threading.Thread(target=answer, daemon=True)
    thread.start()
    return f"tcp://127.0.0.1:{server.getsockname()[1]}", server, thread


@settings(FUZZ, max_examples=30)
@given(
    body=st.binary(max_size=64),
    announced=st.none() | st.integers(0, 2**64 - 1),
)
def test_a_hostile_peer_is_refused_in_one_line_within_the_timeout(body, announced):
    reply = body if announced is None else struct.pack("Q", announced) + body
    address, server, thread = _serve_once(reply)
    try:
        with deadline(60), pytest.raises(cluster.ClusterError) as raised:
            cluster.probe_scheduler(address, 5)
    finally:
        server.close()
        thread.join(timeout=60)
    assert "\n" not in str(raised.value)
    assert f"{address} is not a Dask scheduler" in str(raised.value)
