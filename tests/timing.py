"""Wall-clock bounds that hold on a busy machine.

A test waits on events (a line on a pipe, a process's exit, a file); where it must still bound a
wait, so that a hang fails instead of stalling the suite, the bound is ``patience(seconds)``:
``seconds`` is what the wait may take on an idle machine of this project's size, with room to
spare, and it is stretched by how oversubscribed the cores are now (the load average over the core
count), so that the same test passes under a load of 4x the core count (docs/decisions.md, "Tests
that hold on any machine"). A bound is never the assertion of a speed: speed is measured by
benchmarks.
"""

from __future__ import annotations

import os


def load_factor() -> float:
    """How many runnable tasks share each core now (at least 1)."""
    cores = os.cpu_count() or 1
    try:
        load = max(os.getloadavg()[:2])  # the last one and five minutes: a spike still counts
    except OSError:  # no load average on this platform
        return 1.0
    return max(1.0, load / cores)


def patience(seconds: float) -> float:
    """``seconds`` on an idle machine, stretched by the cores' oversubscription now (x2 margin)."""
    return seconds * 2.0 * load_factor()
