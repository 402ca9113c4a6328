"""Fixtures shared by the tests, and the thread count of a run.

``FACTORQ_TEST_THREADS=N`` runs the whole session with ``torch.set_num_threads(N)`` (tests that
ask for ``one_thread`` still get one): with ``ATEN_CPU_CAPABILITY`` it is how the float-sensitive
tests are tried on another machine's arithmetic (docs/decisions.md, "Tests that hold on any
machine"). Without it, each pytest-xdist worker takes its share of the cores (one each when there
are as many workers as cores, as ``make test`` starts them): torch's default of every core per
worker only oversubscribes them (measured: a third of the suite's CPU time spent spinning).
Tests of several threads ask for them explicitly (the kernel's ``threads``).
"""

import importlib.util
import os
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parent.parent


def pytest_configure(config):
    threads = os.environ.get("FACTORQ_TEST_THREADS")
    if threads:
        if not threads.isdigit() or int(threads) < 1:
            raise pytest.UsageError(f"FACTORQ_TEST_THREADS={threads!r} is not a thread count >= 1")
        torch.set_num_threads(int(threads))
    elif os.environ.get("PYTEST_XDIST_WORKER"):  # set by pytest-xdist in its workers
        workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
        torch.set_num_threads(max(1, torch.get_num_threads() // workers))


@pytest.fixture
def one_thread():
    """One intra-op thread: on tiny tensors more threads only contend (DESIGN section 6)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="session")
def script():
    """``script("benchmarks/x.py")``: a file of the repository that is not in a package (a
    benchmark, an example, a docs helper) imported as a module, definitions run."""

    def load(relative: str):
        path = ROOT / relative
        spec = importlib.util.spec_from_file_location(f"{path.stem}_under_test", path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module

    return load
