"""Figure 3 drawn by a helper process beside the experiment (so that ``factorq paper`` ends in 3 s).

``factorq paper`` starts it before the main process loads torch: meanwhile the helper loads
matplotlib on the other core, draws a made-up figure into memory (fonts, Pillow's encoder,
matplotlib's lazily built tables), prepares the frame of the default run's figure
(``paper_figure.prepare``) and waits for its one message: what the figure reads and the name of
``figure3.png``'s temporary, sent once the experiment is over. It draws there while the main
process writes ``results.json`` and ``report.md``, then exits; the main process renames the three
into place only after the helper exited 0 (``factorq_trainers.runner.results.write_all_atomic``).

One writer per output: the helper writes its one temporary; the main process owns every rename,
and ends the helper (and waits for it) before it removes the temporaries, falls back to drawing
in-process (where the helper could not start or failed: ``FigureProcessError``, a one-line notice)
or returns. The helper is in its own session: a Ctrl-C reaches the main process only, which ends
it. Run as ``python -m factorq_trainers.commands.paper.figure_process`` (``main``); nothing here
imports torch.
"""

from __future__ import annotations

import contextlib
import gc
import os
import pickle
import select
import signal
import subprocess
import sys
import tempfile
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any, BinaryIO

#: Seconds ``close`` waits for a helper it ended.
_REAP_SECONDS = 10.0


class FigureProcessError(RuntimeError):
    """The helper process did not draw the figure; the message says why."""


def command() -> list[str]:
    """The helper's command line: this module run by the same Python."""
    return [sys.executable, "-m", "factorq_trainers.commands.paper.figure_process"]


class FigureProcess:
    """The parent's handle on one helper: ``start``, then ``send`` and ``finish`` once; ``close``
    always (it ends a helper that is still running, and waits for it)."""

    def __init__(self, process: subprocess.Popen, errors: BinaryIO) -> None:
        self.process = process
        self._errors = errors  # the helper's stderr: read only when it failed
        self._sender: threading.Thread | None = None
        self._send_error: OSError | None = None
        self._path: str | None = None

    @classmethod
    def start(cls) -> FigureProcess | None:
        """Start a helper; None when it cannot be started (the figure is then drawn in-process)."""
        if not sys.executable or getattr(sys, "frozen", False):  # no Python to run it with
            return None
        try:
            errors = tempfile.TemporaryFile()
        except OSError:
            return None
        try:
            process = subprocess.Popen(
                command(),
                stdin=subprocess.PIPE,
                stdout=subprocess.DEVNULL,
                stderr=errors,
                start_new_session=True,  # a Ctrl-C at the terminal is the parent's to handle
            )
        except (OSError, ValueError, subprocess.SubprocessError):
            errors.close()
            return None
        return cls(process, errors)

    def send(
        self,
        results: dict[str, Any],
        path: str | os.PathLike,
        worlds: Sequence[str],
        algorithms: Sequence[str],
    ) -> None:
        """Have the helper draw ``paper_figure.draw(results, path, worlds, algorithms)``;
        returns at once (a thread feeds the pipe, which may be smaller than the message)."""
        if self._sender is not None:
            raise RuntimeError("a FigureProcess draws one figure")
        self._path = os.path.abspath(path)
        message = (results, self._path, list(worlds), list(algorithms))
        data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
        self._sender = threading.Thread(
            target=self._write, args=(data,), name="factorq-figure", daemon=True
        )
        self._sender.start()

    def _write(self, data: bytes) -> None:
        assert self.process.stdin is not None  # Popen(stdin=PIPE)
        try:
            self.process.stdin.write(data)
            self.process.stdin.close()  # end of the message
        except OSError as error:  # the helper died: finish says how
            self._send_error = error

    def finish(self, path: str | os.PathLike) -> None:
        """Wait for the helper to have drawn ``path`` (what ``send`` was given); raise
        ``FigureProcessError`` if it did not. The helper has exited when this returns or raises."""
        if self._sender is None or self._path is None or os.path.abspath(path) != self._path:
            self.close()
            raise FigureProcessError(f"the figure process was not asked to draw {path}")
        try:
            self._sender.join()
            code = self.process.wait()
        except BaseException:  # Ctrl-C while waiting: end the helper before anything is removed
            self.close()
            raise
        if code == 0 and self._send_error is None and Path(path).is_file():
            return
        if code == 0 and self._send_error:
            why = f"it could not be sent the curves ({self._send_error})"
        elif code == 0:
            why = f"it exited without writing {Path(path).name}"
        else:
            why = f"exit {code}" if code > 0 else f"killed by signal {-code}"
            last = self._last_error_line()
            why += f": {last}" if last else ""
        raise FigureProcessError(f"the figure process failed ({why})")

    def _last_error_line(self) -> str:
        try:
            self._errors.seek(0)
            lines = self._errors.read()[-4096:].decode(errors="replace").strip().splitlines()
        except (OSError, ValueError):
            return ""
        return lines[-1].strip() if lines else ""

    def close(self) -> None:
        """End the helper if it still runs, wait for it, release its pipe and error file."""
        if self.process.poll() is None:
            self.process.kill()  # it writes nothing but its temporary, which the caller removes
        with contextlib.suppress(subprocess.TimeoutExpired):
            self.process.wait(timeout=_REAP_SECONDS)
        if self._sender is not None:
            self._sender.join(timeout=_REAP_SECONDS)
        for stream in (self.process.stdin, self._errors):
            with contextlib.suppress(OSError):
                if stream is not None:
                    stream.close()


def main() -> int:
    """The helper: load matplotlib, warm it up, draw the one figure it is sent, exit."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent ends this process
    from factorq_trainers.commands.paper import figure as paper_figure

    gc.disable()  # collecting while modules load only costs time: they stay
    paper_figure.preload()
    stdin = sys.stdin.buffer
    prepared = None
    if not _readable(stdin):  # the curves are not here yet: warm up, then guess the figure
        paper_figure.warm_up()
        if not _readable(stdin):
            prepared = paper_figure.prepare(paper_figure.default_spec())
    gc.freeze()  # later collections skip all of the above
    gc.enable()
    data = stdin.read()
    if not data:  # the parent ended without a figure to draw (an error, Ctrl-C, --help)
        return 0
    results, path, worlds, algorithms = pickle.loads(data)
    paper_figure.draw(results, path, worlds, algorithms, prepared=prepared)
    return 0


def _readable(stream: BinaryIO) -> bool:
    return bool(select.select([stream], [], [], 0)[0])


if __name__ == "__main__":
    sys.exit(main())
