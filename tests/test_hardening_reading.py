"""Hardening, round three (issue 41, item 1): one reader for every file factorq reads.

Files that are not files (FIFOs, devices, directories, links), files too large or too deep to
parse, and archives that expand to gigabytes are refused in one line naming the file, before any
parsing. Cases that used to hang or exhaust memory run in a child process with a timeout (a
regression fails the test instead of hanging it) and a memory limit.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

import pytest

from factorq_torch.base.validation import check_names
from factorq_trainers.distributed import sweep_spec as sweep
from factorq_trainers.runner import reading, results

#: The cases that hung (a FIFO, a device, TOML's dotted keys, a quadratic duplicate check) or ran
#: out of memory before the fix: each prints ``name<TAB>outcome`` in a child process.
_CHILD = textwrap.dedent(
    """
    import os, resource, sys, time
    resource.setrlimit(resource.RLIMIT_AS, (16 * 2**30, 16 * 2**30))  # /dev/zero read whole
    from pathlib import Path
    from factorq_torch.base.validation import check_names
    from factorq_trainers.distributed import sweep
    from factorq_trainers.runner import kept

    tmp = Path(sys.argv[1])

    def attempt(name, call):
        start = time.monotonic()
        try:
            call()
            outcome = "accepted"
        except BaseException as error:
            outcome = f"{type(error).__name__}: {error}"
        outcome = " ".join(outcome.split())[:300]
        print(f"{name}\\t{time.monotonic() - start:.1f}\\t{outcome}", flush=True)

    os.mkfifo(tmp / "fifo.toml")
    attempt("fifo sweep file", lambda: sweep.read_spec_file(tmp / "fifo.toml"))
    attempt("/dev/zero", lambda: sweep.read_spec_file("/dev/zero"))
    attempt("/dev/urandom", lambda: sweep.read_spec_file("/dev/urandom"))
    (tmp / "dotted.toml").write_text(".".join(["a"] * 16_000) + " = 1")
    attempt("dotted toml", lambda: sweep.read_spec_file(tmp / "dotted.toml"))
    (tmp / "dotted200k.toml").write_text(".".join(["a"] * 100_000) + " = 1")
    attempt("dotted toml 200 KB", lambda: sweep.read_spec_file(tmp / "dotted200k.toml"))
    (tmp / "header.toml").write_text("[" + ".".join(["a"] * 16_000) + "]\\nx = 1\\n")
    attempt("dotted table header", lambda: sweep.read_spec_file(tmp / "header.toml"))
    out = tmp / "run"
    (out / "units").mkdir(parents=True)
    os.mkfifo(out / "units" / "run.json")
    attempt("fifo run file", lambda: kept.UnitStore(out).saved_run("paper"))
    worlds = ["static"] * 10**6
    attempt("10**6 worlds", lambda: check_names("worlds", worlds, ("static", "dynamic")))
    """
)


@pytest.fixture(scope="module")
def child_outcomes(tmp_path_factory):
    """``{case: outcome}`` of ``_CHILD``, run once with a generous timeout (a busy machine)."""
    tmp = tmp_path_factory.mktemp("hostile")
    try:
        done = subprocess.run(
            [sys.executable, "-c", _CHILD, str(tmp)],
            capture_output=True,
            text=True,
            timeout=300,
            check=False,
        )
        stdout = done.stdout
    except subprocess.TimeoutExpired as expired:
        stdout = (expired.stdout or b"").decode() if isinstance(expired.stdout, bytes) else ""
    outcomes = {}
    for line in stdout.splitlines():
        name, _, outcome = line.split("\t", 2)
        outcomes[name] = outcome
    return outcomes


@pytest.mark.parametrize(
    ("case", "expected"),
    [
        ("fifo sweep file", r"SweepError: sweep file .*fifo.toml is not a regular file \(a FIFO\)"),
        ("/dev/zero", r"SweepError: sweep file /dev/zero is not a regular file \(a character"),
        ("/dev/urandom", r"SweepError: sweep file /dev/urandom is not a regular file"),
        ("dotted toml", r"SweepError: sweep file .*dotted.toml nests deeper than 32 levels"),
        ("dotted toml 200 KB", r"SweepError: sweep file .*dotted200k.toml nests deeper than 32"),
        ("dotted table header", r"SweepError: sweep file .*header.toml nests deeper than 32"),
        ("fifo run file", r"ValueError: run file .*run.json is unreadable \(.*not a regular file"),
        ("10**6 worlds", r"ValueError: worlds: static given more than once"),
    ],
)
def test_files_that_used_to_hang_are_refused_in_one_line(child_outcomes, case, expected):
    import re

    assert case in child_outcomes, f"{case}: no answer (hung or crashed); got {child_outcomes}"
    assert re.search(expected, child_outcomes[case]), child_outcomes[case]


def test_a_link_is_refused_by_every_reader_naming_its_target(tmp_path):
    target = tmp_path / "real.toml"
    target.write_text("[base]\nepisodes = 3\n")
    link = tmp_path / "spec.toml"
    link.symlink_to(target)
    with pytest.raises(sweep.SweepError, match=r"spec.toml is a symbolic link \(to .*real.toml\)"):
        sweep.read_spec_file(link)
    (tmp_path / "real.json").write_text('{"config": {}}')
    (tmp_path / "results.json").symlink_to(tmp_path / "real.json")
    with pytest.raises(ValueError, match="results.json is a symbolic link"):
        results.read_json(tmp_path / "results.json", ["config"], "make it")


def test_a_directory_is_refused_where_a_file_belongs(tmp_path):
    (tmp_path / "spec.toml").mkdir()
    with pytest.raises(sweep.SweepError, match=r"spec.toml is not a regular file \(a directory\)"):
        sweep.read_spec_file(tmp_path / "spec.toml")


def test_toml_depth_counts_dotted_keys_and_headers_but_not_strings_numbers_or_comments():
    assert reading.toml_depth("a.b.c = 1") == 3
    assert reading.toml_depth("[a.b]\nc.d = 2") == 1 + 2
    assert reading.toml_depth('a = "x.y.z.w"\nb = 1.5 # p.q.r.s.t') == 2  # the number: 2 parts
    assert reading.toml_depth('"a.b".c = 1') == 2
    assert reading.toml_depth("a = [[1], [2]]") == 2 + 1


def _bomb(path: Path, members: dict[str, tuple[bytes, int]]) -> None:
    """A zip whose members hold ``header`` then ``zeros`` zero bytes, deflated."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for name, (header, zeros) in members.items():
            with archive.open(name, "w", force_zip64=True) as member:
                member.write(header)
                chunk = bytes(2**20)
                for start in range(0, zeros, len(chunk)):
                    member.write(chunk[: min(len(chunk), zeros - start)])


def _npy_header(shape: tuple[int, ...]) -> bytes:
    from io import BytesIO

    from numpy.lib import format as npy

    buffer = BytesIO()
    npy.write_array_header_1_0(buffer, {"descr": "<f8", "fortran_order": False, "shape": shape})
    return buffer.getvalue()


def test_an_oversized_file_is_refused_unread(tmp_path):
    path = tmp_path / "big.json"
    path.write_text(json.dumps({"a": "x" * 100}))
    with pytest.raises(reading.ReadError, match=r"big.json is \d+ bytes, more than the 50 allowed"):
        reading.read_json(path, "", 50)


def test_the_duplicate_check_names_each_duplicate_once():
    names = ["static", "dynamic"] * 3
    with pytest.raises(ValueError, match="dynamic, static given more than once"):
        check_names("worlds", names, ("static", "semi-dynamic", "dynamic"))
    assert check_names("worlds", ["dynamic", "static"], ("static", "dynamic")) == (
        "static",
        "dynamic",
    )


def test_a_lock_holder_is_read_without_following_links(tmp_path):
    from factorq_trainers.runner import outdir

    (tmp_path / "pid").write_text("123")
    (tmp_path / outdir.LOCK_FILE).symlink_to(tmp_path / "pid")
    assert outdir._holder(tmp_path / outdir.LOCK_FILE) == "another factorq run"
    os.unlink(tmp_path / outdir.LOCK_FILE)
