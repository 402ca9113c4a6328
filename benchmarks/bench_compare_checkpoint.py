"""Cost of ``factorq compare``'s mid-method checkpoints (issue 14), printed as a table.

Per method: the checkpoint file's size taken mid-method, the time to save one (the run's own
``timing.checkpoints``: seconds spent saving / saves) and to load it back
(``compare.load_checkpoint``: digest, safe unpickling and every field's checks), and the run's
wall time with and without checkpoints. Run from the repository root:

    .venv/bin/python benchmarks/bench_compare_checkpoint.py
    .venv/bin/python benchmarks/bench_compare_checkpoint.py --steps 3000 --methods dqn

Timings are never asserted anywhere.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from factorq_trainers.experiments import compare


class _Stop(Exception):
    """Raised from the progress callback to leave a run with its last checkpoint on disk."""


def measure(method: str, steps: int, every: str, root: Path) -> dict[str, float]:
    config = compare.CompareConfig(methods=(method,), steps=steps, threads=1)
    out = root / f"{method}-full"
    full = compare.run(
        compare.CompareConfig(**{**vars(config), "out": str(out)}),
        checkpoints=True,
        checkpoint_every=every,
    )
    saves = full["timing"]["checkpoints"]
    plain = compare.run(compare.CompareConfig(**{**vars(config), "out": str(root / "plain")}))

    # a run cut near its end, to read back the checkpoint of a method in progress
    cut = root / f"{method}-cut"

    def progress(_method, done, total) -> None:
        if done >= total - 200:
            raise _Stop

    try:
        compare.run(
            compare.CompareConfig(**{**vars(config), "out": str(cut)}),
            progress,
            checkpoints=True,
            checkpoint_every=every,
        )
    except _Stop:
        pass
    file = cut / "checkpoint" / "checkpoint.pt"
    started = time.perf_counter()
    compare.load_checkpoint(cut)
    load = time.perf_counter() - started
    return {
        "mb": file.stat().st_size / 2**20,
        "save_ms": 1e3 * saves["save_s"] / max(1, saves["saved_mid_method"]),
        "load_ms": 1e3 * load,
        "wall": full["timing"]["wall_s"],
        "wall_plain": plain["timing"]["wall_s"],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=int, default=3000, help="env steps per experiment")
    parser.add_argument("--every", default="1s", help="checkpoint interval (episodes or 30s)")
    parser.add_argument(
        "--methods", nargs="+", default=["factor-q", "q-learning", "factor-dqn", "dqn"]
    )
    args = parser.parse_args()
    print(f"3 worlds x 3 seeds, --steps {args.steps}, --checkpoint-every {args.every}")
    print(f"{'method':<12}{'checkpoint':>12}{'save':>10}{'load':>10}{'wall':>9}{'no ckpt':>9}")
    with tempfile.TemporaryDirectory() as root:
        for method in args.methods:
            row = measure(method, args.steps, args.every, Path(root))
            print(
                f"{method:<12}{row['mb']:>9.2f} MB{row['save_ms']:>7.0f} ms"
                f"{row['load_ms']:>7.0f} ms{row['wall']:>8.1f}s{row['wall_plain']:>8.1f}s"
            )


if __name__ == "__main__":
    main()
