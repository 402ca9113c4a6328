"""Every command's numbers at a tiny budget, to check that a refactoring changed none of them.

Runs each command of ``factorq`` once at a budget of seconds (one torch thread, in-process) into
``OUT/<command>/`` and, with ``--against OLD``, compares each results file's numbers with the
same file under ``OLD`` (a directory an earlier run of this script wrote, e.g. from a worktree
of the commit before): the configuration's ``out``, the software versions, the timing and every
measured time (keys ending ``_s`` or ``_per_s``) left out. Prints one line per command and
exits 1 if any differ. Run from the repository root (about a minute on one core):

    .venv/bin/python benchmarks/numbers_dump.py /tmp/before     # in a worktree of the old commit
    .venv/bin/python benchmarks/numbers_dump.py /tmp/after --against /tmp/before

Not a package on purpose (the torchrl wheel installs a top-level ``benchmarks``).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import re
import sys
from pathlib import Path
from typing import Any

#: Each command's tiny run, with every method it has where that stays cheap.
TINY = {
    "paper": ["--seeds", "4", "--shard-seeds", "2", "--runs", "2", "--episodes", "3",
              "--size", "5", "--obstacles", "3"],
    "compare": ["--seeds", "1", "--steps", "150", "--size", "4", "--obstacles", "1",
                "--regimes", "static,dynamic",
                "--methods", "factor-q,q-learning,dqn,factor-dqn"],
    "dependencies": ["--settings", "cross,heading", "--seeds", "2", "--runs", "2",
                     "--episodes", "2", "--methods", "factor-q-learned,factor-q,q-learning"],
    "minigrid": ["--seeds", "1", "--sizes", "5", "--steps", "60"],
    "gym": ["--world", "corridor", "--seeds", "2", "--steps", "60", "--eval-episodes", "1",
            "--methods", "dqn,factor-dqn,factor-dqn-learned"],
    "risk": ["--worlds", "grid,minigrid", "--methods", "dqn,dqn+risk,dqn+risk-learned",
             "--seeds", "1", "--steps", "80", "--learning-starts", "20", "--eval-episodes", "1",
             "--grid-size", "4", "--grid-obstacles", "2", "--minigrid-size", "5"],
    "transfer": ["--size", "6", "--obstacles", "4", "--source-size", "5",
                 "--source-obstacles", "3", "--seeds", "2", "--episodes", "6", "--early", "3",
                 "--source-episodes", "6", "--max-steps", "200"],
}  # fmt: skip


def numbers(value: Any) -> Any:
    """``value`` without the measured times and the run's own facts (module docstring)."""
    if isinstance(value, dict):
        return {
            key: numbers(item)
            for key, item in value.items()
            if key not in ("timing", "software", "out") and not re.fullmatch(r".*_(s|per_s)", key)
        }
    if isinstance(value, list):
        return [numbers(item) for item in value]
    return value


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, help="directory for every command's results")
    parser.add_argument("--against", type=Path, help="an earlier run's directory to compare with")
    parser.add_argument("--only", help="comma-separated commands (default: all)")
    args = parser.parse_args()
    import torch

    from factorq_trainers import cli

    torch.set_num_threads(1)

    commands = args.only.split(",") if args.only else list(TINY)
    differ = 0
    for command in commands:
        folder = args.out / command
        argv = [command, *TINY[command], "--out", str(folder), "--cluster", "off"]
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            code = cli.main(argv)
        if code:
            print(f"{command}: exit {code} ({' '.join(argv)})")
            differ += 1
            continue
        files = sorted(path.relative_to(folder) for path in folder.glob("*.json"))
        if args.against is None:
            print(f"{command}: {len(files)} results files")
            continue
        changed = [
            str(name)
            for name in files
            if not (args.against / command / name).is_file()
            or numbers(json.loads((folder / name).read_text()))
            != numbers(json.loads((args.against / command / name).read_text()))
        ]
        differ += bool(changed)
        print(f"{command}: " + (f"DIFFERENT: {', '.join(changed)}" if changed else "same numbers"))
    return 1 if differ else 0


if __name__ == "__main__":
    sys.exit(main())
