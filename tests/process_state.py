"""A pytest plugin that fails the test which leaves process state changed (``-p process_state``
in pyproject's ``addopts``, so that it guards every item: tests, module doctests, the README).

A test that changes process state and leaves it changed makes every later test of the same worker
depend on it: a SIGINT disposition left at SIG_IGN is inherited by every child the worker starts
(a Ctrl-C test then hangs), a cwd or an environment variable moves later paths and options, a
thread left running competes for the cores, a changed thread count or grad mode changes what
later tests compute. ``process_state_guard`` takes the state before each test and after it: a
difference fails that test (at teardown, naming what leaked) and is put back, so that the next
test starts clean whichever ran before it (docs/decisions.md, "Tests that hold on any machine").
"""

from __future__ import annotations

import importlib
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Generator

import pytest
import torch
from timing import patience

#: Libraries that change process state when first imported (environment variables, loggers of
#: their own): imported before the first test, so that the test which happens to import them
#: first is not blamed for it. Optional ones are skipped where their extra is not installed.
PREIMPORTED = ("tensordict", "torchrl", "gymnasium", "distributed")


def pytest_configure(config: pytest.Config) -> None:
    for name in PREIMPORTED:
        try:
            importlib.import_module(name)
        except ImportError:
            pass


#: Seconds a thread started by a test may take to finish after it on an idle machine (stretched
#: by the load: ``timing.patience``); an event, not a limit: join returns as soon as the thread
#: ends, only a thread left running waits this long, and fails (``FACTORQ_TEST_THREAD_GRACE``:
#: another figure, for the guard's own test).
THREAD_GRACE_SECONDS = float(os.environ.get("FACTORQ_TEST_THREAD_GRACE", "5"))

_SIGNALS = sorted(
    signal.Signals(number)
    for number in signal.valid_signals()
    if number not in (signal.SIGKILL, signal.SIGSTOP) and number < signal.SIGRTMIN
)


def _logger_state() -> dict[str, tuple]:
    loggers = {"": logging.getLogger()}
    loggers.update(
        (name, logger)
        for name, logger in logging.Logger.manager.loggerDict.items()
        if isinstance(logger, logging.Logger)
    )
    return {
        name: (logger.level, tuple(logger.handlers), logger.propagate, logger.disabled)
        for name, logger in loggers.items()
    }


#: Environment variables that are not the tests' state: pytest's own, one tensordict writes when
#: its ``set_capture_non_tensor_stack`` context ends (``"None"``, read only at its import), and
#: pygame's banner switch, which gymnasium and highway-env set to different values at import.
NOT_STATE = frozenset(
    {"PYTEST_CURRENT_TEST", "CAPTURE_NONTENSOR_STACK", "PYGAME_HIDE_SUPPORT_PROMPT"}
)


def _process_state() -> dict[str, object]:
    umask = os.umask(0o022)
    os.umask(umask)
    return {
        "signal dispositions": {sig.name: signal.getsignal(sig) for sig in _SIGNALS},
        "blocked signals": signal.pthread_sigmask(signal.SIG_BLOCK, []),
        "working directory": os.getcwd(),
        "environment variables": {
            name: value for name, value in os.environ.items() if name not in NOT_STATE
        },
        "umask": umask,
        "torch threads": torch.get_num_threads(),
        "torch grad mode": torch.is_grad_enabled(),
        "torch default dtype": torch.get_default_dtype(),
        "torch deterministic algorithms": torch.are_deterministic_algorithms_enabled(),
        "loggers": _logger_state(),
    }


def _differences(before: dict, after: dict, imported: set[str]) -> dict[str, str]:
    """What changed, in words, by kind of state. A logger created during the test counts only if
    it has a level or a handler of its own and is not the logger of a module first imported
    during the test (that is the module's import, not the test)."""
    found = {}
    for kind, old in before.items():
        new = after[kind]
        if old == new:
            continue
        if isinstance(old, dict):
            keys = set(old) | (set(new) if kind != "loggers" else set())
            changed = sorted(key for key in keys if old.get(key) != new.get(key))
            if kind == "loggers":
                changed += sorted(
                    name
                    for name, (level, handlers, _, _) in new.items()
                    if name not in old
                    and name not in imported
                    and (level != logging.NOTSET or handlers)
                )
            if changed:
                found[kind] = ", ".join(changed)
        else:
            found[kind] = f"{old!r} -> {new!r}"
    return found


def _restore(before: dict) -> None:
    for name, handler in before["signal dispositions"].items():
        if handler is not None and signal.getsignal(signal.Signals[name]) is not handler:
            signal.signal(signal.Signals[name], handler)
    signal.pthread_sigmask(signal.SIG_SETMASK, before["blocked signals"])
    os.chdir(before["working directory"])
    for name in set(os.environ) - set(before["environment variables"]) - NOT_STATE:
        del os.environ[name]
    os.environ.update(before["environment variables"])
    os.umask(before["umask"])
    torch.set_num_threads(before["torch threads"])
    torch.set_grad_enabled(before["torch grad mode"])
    torch.set_default_dtype(before["torch default dtype"])
    torch.use_deterministic_algorithms(before["torch deterministic algorithms"])
    loggers = before["loggers"]
    for name in _logger_state().keys() - loggers.keys():  # made during the test: as made
        loggers[name] = (logging.NOTSET, (), True, False)
    for name, (level, handlers, propagate, disabled) in loggers.items():
        logger = logging.getLogger(name or None)
        logger.setLevel(level)
        logger.handlers[:] = handlers
        logger.propagate, logger.disabled = propagate, disabled


#: Threads that live as long as the process by their library's design, started on first use and
#: shared by every later user (never one test's leftover): tqdm's monitor, the fast path's pool
#: (kept between calls: trainers/compiled/fast.py), Dask's event loop and offload pool of a
#: client in this process.
PROCESS_THREADS = ("tqdm_monitor", "factorq-fast_", "IO loop", "Dask-Offload_")


#: Threads already reported as left running (a thread cannot be put back): reported once.
_REPORTED: set[threading.Thread] = set()


def _leaked_threads(before: set[threading.Thread]) -> list[str]:
    new = [
        thread
        for thread in threading.enumerate()
        if thread not in before
        and thread not in _REPORTED
        and not thread.name.startswith(PROCESS_THREADS)
    ]
    deadline = time.monotonic() + patience(THREAD_GRACE_SECONDS)
    for thread in new:
        thread.join(max(0.0, deadline - time.monotonic()))
    running = [thread for thread in new if thread.is_alive()]
    _REPORTED.update(running)
    return sorted(thread.name for thread in running)


def _guard(what: str, check_threads: bool = True) -> Generator[None, None, None]:
    """Take the state, run ``what`` (a test, or a module with its module-scoped fixtures), fail
    it if the state changed, and put the state back."""
    threads, modules = set(threading.enumerate()), set(sys.modules)
    before = _process_state()
    yield
    leaks = _differences(before, _process_state(), set(sys.modules) - modules)
    if leaks:
        _restore(before)
    running = _leaked_threads(threads) if check_threads else []
    if running:
        leaks["threads still running"] = ", ".join(running)
    if leaks:
        changed = "; ".join(f"{kind}: {detail}" for kind, detail in leaks.items())
        pytest.fail(f"{what} left process state changed: {changed}", pytrace=False)


@pytest.fixture(autouse=True)
def process_state_guard(request: pytest.FixtureRequest) -> Generator[None, None, None]:
    """Fail the test that leaves process state changed (and put it back); see above. A test
    marked ``module_threads`` starts threads that belong to a module-scoped fixture (a cluster
    that restarts a worker the test killed): the module's guard checks those, when the fixture
    has ended."""
    marked = request.node.get_closest_marker("module_threads") is not None
    torch.manual_seed(_torch_seed(request.config))
    yield from _guard(request.node.nodeid, check_threads=not marked)


def _torch_seed(config: pytest.Config) -> int:
    """The seed of torch's global generator at the start of every test, so that no test draws
    what an earlier one left: pytest-randomly's seed of this run (it reseeds ``random`` and numpy
    the same way; ``--randomly-seed=N`` replays it), or 0 without it (``-p no:randomly``)."""
    try:
        seed = config.getoption("randomly_seed")
    except ValueError:  # the plugin is not loaded
        return 0
    return seed if isinstance(seed, int) else 0


@pytest.fixture(autouse=True, scope="module")
def module_state_guard(request: pytest.FixtureRequest) -> Generator[None, None, None]:
    """The same around a module, so that a module-scoped fixture which leaves state changed
    fails too (at the teardown of the module's last test)."""
    yield from _guard(f"module {request.node.nodeid} (its module-scoped fixtures)")
