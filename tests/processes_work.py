"""Work for child processes in the tests of ``factorq_trainers.experiments.paper_processes`` (a
module the children import: pytest puts tests/ on sys.path, and the children get the parent's
sys.path)."""

from __future__ import annotations

import os
import signal
import time


class TwoArgumentError(Exception):
    """An exception that does not come back through pickling (it needs two arguments)."""

    def __init__(self, first: str, second: str) -> None:
        super().__init__(f"{first} and {second}")


def work(kind: str, argument, report):
    """What the test children do, by ``kind``."""
    if kind == "count":  # report `argument` episodes, one at a time, and return their number
        for _ in range(argument):
            report(1, 0)
            time.sleep(0.001)
        report(0, 1)
        return {"episodes": argument}
    if kind == "raise":
        raise ValueError(argument)
    if kind == "unpicklable":
        raise TwoArgumentError(argument, "more")
    if kind == "kill":
        os.kill(os.getpid(), signal.SIGKILL)
    if kind == "exit":
        os._exit(argument)
    if kind == "sleep":
        time.sleep(argument)
        return None
    raise AssertionError(kind)
