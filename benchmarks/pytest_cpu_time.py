"""CPU seconds per test (this process and the children it waited for), for trimming the suite.

Wall times (``--durations``) mislead on a shared machine and hide threads that spin; CPU time
says what a test costs. As a pytest plugin, each process (each xdist worker) writes
``build/test_cpu/<worker>.json``; run as a script, it prints the costliest tests and files:

    PYTHONPATH=benchmarks .venv/bin/python -m pytest -n auto -p pytest_cpu_time
    .venv/bin/python benchmarks/pytest_cpu_time.py --most 40
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import resource
import time
from collections.abc import Generator
from pathlib import Path
from typing import Any

import pytest

OUT = Path("build") / "test_cpu"
_rows: list[tuple[float, float, str]] = []


def _cpu() -> float:
    own, children = (
        resource.getrusage(resource.RUSAGE_SELF),
        resource.getrusage(resource.RUSAGE_CHILDREN),
    )
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: Any, nextitem: Any) -> Generator[None, None, None]:
    cpu, wall = _cpu(), time.monotonic()
    yield
    _rows.append((_cpu() - cpu, time.monotonic() - wall, item.nodeid))


def pytest_sessionfinish(session: Any) -> None:
    if _rows:
        OUT.mkdir(parents=True, exist_ok=True)
        worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
        (OUT / f"{worker}.json").write_text(json.dumps(_rows))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--most", type=int, default=30, help="rows of each table")
    args = parser.parse_args()
    rows = [row for path in sorted(OUT.glob("*.json")) for row in json.loads(path.read_text())]
    if not rows:
        raise SystemExit(f"no {OUT}/*.json: run pytest with -p pytest_cpu_time first")
    print(
        f"{len(rows)} tests, {sum(r[0] for r in rows):.0f} CPU s, {sum(r[1] for r in rows):.0f} s"
    )
    for cpu, wall, name in sorted(rows, reverse=True)[: args.most]:
        print(f"{cpu:7.1f} CPU s {wall:7.1f} s  {name}")
    files: collections.Counter[str] = collections.Counter()
    for cpu, _, name in rows:
        files[name.split("::")[0]] += cpu
    for name, cpu in files.most_common(args.most):
        print(f"{cpu:7.1f} CPU s  {name}")


if __name__ == "__main__":
    main()
