"""Work items run side by side, each in a child process of its own (``factorq paper --backend
modular`` runs each algorithm in its own process).

``Children(work, items, progress)`` calls ``work(*args, report)`` for every ``name -> args`` of
``items`` in a child process of its own; ``wait()`` returns ``{name: result}`` in the order of
``items``, and ``poll()`` lets the parent do work of its own meanwhile (``run_each``: start and
wait).

- **Processes, started fresh.** The modular path steps its batch from Python, so two threads
  share one interpreter lock (measured 0.54x of running one after the other). A child is a new
  interpreter, ``python -m factorq_trainers.experiments.paper_processes``: not a ``fork`` (forking a
  process that already runs torch's OpenMP threads is unsafe), and not ``multiprocessing``'s
  ``spawn`` either, which re-runs the parent's main script in every child: a script calling
  ``paper.run`` without an ``if __name__ == "__main__":`` guard would then fail in its children.
  The child gets the parent's ``sys.path`` and the pickled ``work`` and ``args`` on its stdin,
  and sends its messages on a pipe of its own (``multiprocessing.connection.Connection``).
- **Progress.** ``report(episodes, experiments)`` in a child adds to a tally that is sent at
  most every ``PROGRESS_SECONDS`` (and once at the end); the parent passes each message on to
  ``progress`` (in ``poll`` and ``wait``). What travels (``work``'s arguments, its result, its
  error) is pickled: plain data and numpy arrays.
- **Errors.** An exception in ``work`` is raised in the parent, as the same type with the same
  message where it pickles (else a ``RuntimeError`` naming its type), with the child's traceback
  as a note. A child that ends without a result (killed, a crash) is a ``WorkerError`` naming
  the item and its exit code or signal: its pipe reads end-of-file then, so the parent, which
  waits on the pipes (and looks at the processes every ``_POLL_SECONDS``), never waits on a child
  that is gone.
- **Ctrl-C and the end.** The children run in sessions of their own, so a Ctrl-C at the terminal
  reaches the parent only. On any way out of the ``with Children(...)`` block (results, an
  error, a ``KeyboardInterrupt``) the parent ends the children that still run (SIGTERM, then
  SIGKILL after ``_REAP_SECONDS``) and waits for them, then lets the exception propagate. A child
  whose parent died unannounced stops at its next report.
"""

from __future__ import annotations

import os
import pickle
import signal
import subprocess
import sys
import time
import traceback
from collections.abc import Callable, Mapping
from multiprocessing.connection import Connection, wait
from typing import Any, NamedTuple

#: Seconds between two progress messages of a child, at most (none while nothing progressed).
PROGRESS_SECONDS = 0.2
#: Seconds the parent waits for a child it ended (SIGTERM) before killing it (SIGKILL).
_REAP_SECONDS = 5.0
#: Seconds between two looks at the children when no message arrives.
_POLL_SECONDS = 1.0

Report = Callable[[int, int], None]


class WorkerError(ChildProcessError):
    """A child process ended without sending its result; the message names its item and how it
    ended. An ``OSError`` (``ChildProcessError``): the CLI reports it as one line, as it does a
    full disk."""


def available() -> bool:
    """Whether child processes can be started here (a Python to run them with)."""
    return bool(sys.executable) and not getattr(sys, "frozen", False)


class _Child(NamedTuple):
    process: subprocess.Popen
    connection: Connection  # the parent's (reading) end of the child's pipe


class Children:
    """``work(*args, report)`` for every ``name -> args`` of ``items``, each call in a child
    process of its own, all started at once; ``progress(episodes, experiments)`` receives what the
    children report while ``poll`` or ``wait`` runs. ``work`` must be a module-level function (the
    child imports it). Use as a context manager: leaving it ends the children that still run and
    waits for them, whatever happened.
    """

    def __init__(
        self,
        work: Callable[..., Any],
        items: Mapping[str, tuple[Any, ...]],
        progress: Report,
    ) -> None:
        self.names = list(items)
        self.progress = progress
        self.results: dict[str, Any] = {}
        self._children: dict[str, _Child] = {}
        self._polled = time.monotonic()
        try:
            for name, args in items.items():
                self._children[name] = _start(work, tuple(args))
        except BaseException:
            self.close()
            raise

    @property
    def pids(self) -> dict[str, int]:
        """The children's process ids, by item name."""
        return {name: child.process.pid for name, child in self._children.items()}

    def __enter__(self) -> Children:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def poll(self, every: float = 0.0) -> None:
        """Pass on the progress received, keep the results; raise a child's error, or a
        ``WorkerError`` for a child that ended without a result. Returns at once (and does
        nothing if the last call was less than ``every`` seconds ago)."""
        if time.monotonic() - self._polled < every:
            return
        self._polled = time.monotonic()
        ready = wait(self._running_connections(), timeout=0)
        self._read(ready)

    def wait(self) -> dict[str, Any]:
        """Wait for every child's result (passing progress on): ``{name: result}`` in the order
        of ``items``; raises as ``poll`` does."""
        while len(self.results) < len(self.names):
            self._read(wait(self._running_connections(), timeout=_POLL_SECONDS))
        return {name: self.results[name] for name in self.names}

    def close(self) -> None:
        """End the children that still run and wait for every one (no process left behind)."""
        for child in self._children.values():
            if child.process.poll() is None:
                child.process.terminate()
        for child in self._children.values():
            try:
                child.process.wait(timeout=_REAP_SECONDS)
            except subprocess.TimeoutExpired:
                child.process.kill()
                child.process.wait()
            child.connection.close()

    def _running_connections(self) -> list[Connection]:
        return [
            child.connection for name, child in self._children.items() if name not in self.results
        ]

    def _read(self, ready: list[Any]) -> None:
        for name, child in self._children.items():
            if name in self.results:
                continue
            state, result = "waiting", None
            if child.connection in ready:
                state, result = _receive(child.connection, self.progress)
            elif child.process.poll() is not None:  # it ended: read what it sent before
                state, result = _receive(child.connection, self.progress)
                state = "closed" if state == "waiting" else state
            if state == "result":
                self.results[name] = result
            elif state == "closed":
                raise WorkerError(_ended(name, child.process))


def run_each(
    work: Callable[..., Any],
    items: Mapping[str, tuple[Any, ...]],
    progress: Report,
) -> dict[str, Any]:
    """``{name: work(*args, report)}`` for every ``name -> args`` of ``items``, each in a child
    process of its own, all at once (``Children``)."""
    with Children(work, items, progress) as children:
        return children.wait()


def _start(work: Callable[..., Any], args: tuple[Any, ...]) -> _Child:
    """A child process running ``work(*args, report)``."""
    payload = pickle.dumps((work, args), protocol=pickle.HIGHEST_PROTOCOL)
    read, write = os.pipe()
    try:
        # The parent's import path as the child's PYTHONPATH too, so that ``-m`` finds this
        # module however the parent found it (an installed package or a path added at run time).
        path = os.pathsep.join(entry for entry in sys.path if entry)
        process = subprocess.Popen(
            [sys.executable, "-m", "factorq_trainers.experiments.paper_processes", str(write)],
            stdin=subprocess.PIPE,
            pass_fds=(write,),
            start_new_session=True,  # a Ctrl-C at the terminal is the parent's to handle
            env={**os.environ, "PYTHONPATH": path},
        )
    except BaseException:
        os.close(read)
        raise
    finally:
        os.close(write)  # the child holds the only writing end: end-of-file once it is gone
    child = _Child(process, Connection(read, writable=False))
    assert process.stdin is not None  # Popen(stdin=PIPE)
    try:  # sys.path first: unpickling ``work`` imports its module
        process.stdin.write(pickle.dumps((list(sys.path), payload)))
        process.stdin.close()
    except OSError:  # the child is gone already: its pipe says so
        pass
    return child


def _receive(connection: Connection, progress: Report) -> tuple[str, Any]:
    """Read every message waiting on ``connection``: progress is passed on, an error raised.
    ``("result", result)`` once the result arrived, ``("closed", None)`` if the child's end is
    closed without one (it ended), else ``("waiting", None)``."""
    while connection.poll():
        try:
            kind, *payload = connection.recv()
        except (EOFError, OSError):  # the child's end is closed (or a message was cut short)
            return "closed", None
        if kind == "progress":
            progress(*payload)
        elif kind == "result":
            return "result", payload[0]
        else:  # "error"
            error, text = payload
            error.add_note(text)
            raise error
    return "waiting", None


def _ended(name: str, process: subprocess.Popen) -> str:
    """Why ``process`` (of item ``name``) has no result: its exit code or signal."""
    try:
        code = process.wait(timeout=_REAP_SECONDS)
    except subprocess.TimeoutExpired:
        return f"the process running {name} closed its pipe without sending its results"
    if code < 0:
        try:
            how = f"was killed by signal {signal.Signals(-code).name} (exit code {code})"
        except ValueError:
            how = f"was killed by signal {-code} (exit code {code})"
    else:
        how = f"exited with exit code {code}"
    return f"the process running {name} {how} before sending its results"


# --------------------------------------------------------------------------------------------
# In the child


class _Reporter:
    """``report(episodes, experiments)`` of a child: tallies, sent at most every
    ``PROGRESS_SECONDS``; stops the child if its parent is gone."""

    def __init__(self, connection: Connection) -> None:
        self.connection = connection
        self.parent = os.getppid()
        self.episodes = 0
        self.experiments = 0
        self.sent = time.monotonic()

    def __call__(self, episodes: int, experiments: int) -> None:
        self.episodes += int(episodes)
        self.experiments += int(experiments)
        if time.monotonic() - self.sent >= PROGRESS_SECONDS:
            self.flush()

    def flush(self) -> None:
        if os.getppid() != self.parent:  # the parent died unannounced: nobody waits for us
            os._exit(1)
        if self.episodes or self.experiments:
            self.connection.send(("progress", self.episodes, self.experiments))
            self.episodes = self.experiments = 0
        self.sent = time.monotonic()


def child_main(fd: int) -> None:
    """What a child runs: read ``work`` and its arguments on stdin, call ``work(*args, report)``,
    send its result or its error on ``fd``."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent ends this process
    connection = Connection(fd, readable=False)
    path, payload = pickle.loads(sys.stdin.buffer.read())
    sys.path[:] = path
    report = _Reporter(connection)
    try:
        work, args = pickle.loads(payload)
        result = work(*args, report)
        report.flush()
        message: tuple[Any, ...] = ("result", result)
    except BaseException as error:  # noqa: BLE001 - every error goes to the parent
        message = ("error", _portable(error), _traceback_note(error))
    connection.send(message)
    connection.close()


def _portable(error: BaseException) -> BaseException:
    """``error`` as it comes through pickling if that keeps its type and message, else a
    RuntimeError naming its type (its traceback, cause and context stay in the note)."""
    try:
        copy = pickle.loads(pickle.dumps(error))
        if type(copy) is type(error) and str(copy) == str(error):
            return copy
    except Exception:  # noqa: BLE001, S110 - an exception that does not pickle
        pass
    return RuntimeError(f"{type(error).__name__}: {error}")


def _traceback_note(error: BaseException) -> str:
    lines = traceback.format_exception(error)
    return f"raised in child process {os.getpid()}:\n" + "".join(lines).rstrip()


if __name__ == "__main__":
    from factorq_trainers.experiments.paper_processes import (
        child_main as _main,  # the module, not __main__
    )

    _main(int(sys.argv[1]))
