"""Instructions per env step of the fast path's kernel and the numba anchors, counted by valgrind.

Timings on a shared machine move with its load; instruction counts do not. Each implementation
runs in its own process under ``valgrind --tool=callgrind``; around each measured workload a tiny
helper library (compiled here from ``valgrind/callgrind.h``) zeroes the counters and dumps them,
so a count holds the workload only (no interpreter start, import or JIT compilation). The
workload: ``--seeds`` experiments of each (world, algorithm) of the paper (10 runs x 200
episodes, 10x10 worlds, 10 obstacles), one thread:

- ``fast``: ``ExperimentBatch.advance`` (the kernel's ``fq_advance``);
- ``project``: ``benchmarks/bench_numba_anchor.py``'s ``_run`` (the same streams: the same steps);
- ``shared`` (with ``--shared-anchor DIR``): the numba anchor of another session in ``DIR``
  (``fq_numba.py``'s ``many``; its own streams and scatter, so other trajectories and lengths).

It prints instructions per env step for each (world, algorithm) and for the paper mix, and with
``--phases`` splits the kernel's instructions by the step's phases: each instruction the kernel
executed is mapped (``addr2line -i`` on a ``-g`` build of the same source and flags) to the line of
``run_experiment`` it belongs to, inlined callees included, and a call (``scatter``, ``memset``)
counts where it is made; the phases are the loop's sections (act, world step, learn, episode
bookkeeping) and the call's set-up and write-back. The numba anchors are split by ablation only:
the static world's steps against the moving ones (the scatter), Q-learning's against Factor-Q's.

    .venv/bin/python benchmarks/bench_instructions.py --shared-anchor ../shared/anchors/numba
    .venv/bin/python benchmarks/bench_instructions.py --phases --implementations fast

Needs valgrind and its headers (``valgrind/callgrind.h``), and numba for the anchors (the
``bench`` extra). Slow: about 50x native speed plus the imports under valgrind (minutes). Nothing
asserted; not a package on purpose (the torchrl wheel installs a top-level ``benchmarks``).
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(ROOT))

KERNEL = ROOT / "trainers" / "compiled" / "_kernel.c"
COMBOS = [(period, algorithm) for period in (0, 10, 1) for algorithm in ("q-learning", "factor-q")]
WORLD_NAMES = {0: "static", 10: "semi-dynamic", 1: "dynamic"}
HELPER = r"""
#include <valgrind/callgrind.h>
void fq_count_zero(void) { CALLGRIND_ZERO_STATS; }
void fq_count_dump(const char *name) { CALLGRIND_DUMP_STATS_AT(name); }
"""


def _helper(directory: Path) -> ctypes.CDLL:
    """The zero/dump helper (no-ops outside valgrind)."""
    source, library = directory / "count.c", directory / "count.so"
    source.write_text(HELPER)
    subprocess.run(["cc", "-O1", "-shared", "-fPIC", str(source), "-o", str(library)], check=True)
    helper = ctypes.CDLL(str(library))
    helper.fq_count_dump.argtypes = [ctypes.c_char_p]
    return helper


def _fast_workload(period: int, algorithm: str, seeds: int, source: str | None):
    import torch

    from factorq_envs.grid_world import WorldConfig
    from factorq_torch.base.config import AgentConfig
    from factorq_torch.base.rng import STREAM_POLICY, STREAM_WORLD, derive_keys
    from factorq_trainers.compiled import fast, loader

    if source is not None:  # another kernel source (e.g. an older one), same ABI
        loader._SOURCE = Path(source).resolve()

    def make(runs: int, episodes: int):
        return fast.ExperimentBatch(
            algorithm,
            torch.full((seeds,), period),
            WorldConfig(),
            AgentConfig(),
            runs,
            episodes,
            derive_keys(0, STREAM_WORLD, seeds),
            derive_keys(0, STREAM_POLICY, seeds),
            threads=1,
        )

    batch = make(10, 200)

    def run() -> int:
        batch.advance(1 << 40)
        return batch.total_steps

    return run


def _project_workload(period: int, algorithm: str, seeds: int):
    import numba
    import numpy as np

    sys.path.insert(0, str(ROOT / "benchmarks"))
    import bench_numba_anchor as anchor

    numba.set_num_threads(1)
    anchor._run.enable_caching()  # compiled once outside valgrind (count's warm-up run)
    code = {"q-learning": anchor.Q_LEARNING, "factor-q": anchor.FACTOR_Q}[algorithm]
    inputs = anchor._inputs(np.full(seeds, period), 0)
    order = np.arange(seeds)

    def call(runs: int, episodes: int) -> int:
        counts = np.zeros((seeds, runs, episodes, 3), np.int64)
        returns = np.zeros((seeds, runs, episodes), np.float32)
        anchor._run(code, runs=runs, episodes=episodes, order=order, counts_out=counts,
                    return_out=returns, **inputs)  # fmt: skip
        return int(counts[..., 0].sum())

    call(1, 1)  # compile
    return lambda: call(10, 200)


def _shared_workload(directory: str, period: int, algorithm: str, seeds: int):
    import numba
    import numpy as np

    sys.path.insert(0, directory)
    import common
    import fq_numba

    numba.set_num_threads(1)
    fq_numba.experiment.enable_caching()  # compiled once outside valgrind (count's warm-up run)
    fq_numba.many.enable_caching()
    name = {"q-learning": "q", "factor-q": "factorq"}[algorithm]
    algos = np.full(seeds, common.ALGOS.index(name))
    periods, keys = np.full(seeds, period, np.int64), np.arange(seeds, dtype=np.int64)
    layout = common.static_layout()

    def call(runs: int, episodes: int) -> int:
        out = np.zeros((seeds, 3, runs, episodes), np.int32)
        fq_numba.many(algos.astype(np.int64), periods, keys, layout, common.N, runs, episodes,
                      common.MAX_STEPS, out)  # fmt: skip
        return int(out[:, 0].sum())

    call(1, 1)  # compile
    return lambda: call(common.RUNS, common.EPISODES)


def inner(args: argparse.Namespace) -> None:
    """Under valgrind: each (world, algorithm) workload between a zero and a dump."""
    with tempfile.TemporaryDirectory() as directory:
        helper = _helper(Path(directory))
        steps = {}
        for period, algorithm in COMBOS:
            if args.inner == "fast":
                run = _fast_workload(period, algorithm, args.seeds, args.kernel_source)
            elif args.inner == "project":
                run = _project_workload(period, algorithm, args.seeds)
            else:
                run = _shared_workload(args.shared_anchor, period, algorithm, args.seeds)
            name = f"{algorithm}-{period}"
            helper.fq_count_zero()
            steps[name] = run()
            helper.fq_count_dump(name.encode())
    Path(args.steps_file).write_text(json.dumps(steps))


def _totals(path: Path) -> int:
    for line in path.read_text().splitlines():
        if line.startswith(("totals:", "summary:")):
            return int(line.split()[1])
    raise ValueError(f"no totals in {path}")


def _dumps(prefix: Path) -> dict[str, Path]:
    """{dump name: file} of a callgrind run's dumps (``desc: Trigger: Client Request: NAME``)."""
    found = {}
    for path in prefix.parent.glob(prefix.name + "*"):
        match = re.search(r"^desc: Trigger: Client Request: (\S+)$", path.read_text(), re.M)
        if match:
            found[match.group(1)] = path
    return found


def count(implementation: str, seeds: int, directory: Path, anchor: str | None, phases: bool,
          kernel_cc: str | None = None, kernel_source: str | None = None,
          ) -> tuple[dict[str, int], dict[str, Path]]:  # fmt: skip
    """Run one implementation under callgrind: ({combo: env steps}, {combo: dump file})."""
    prefix = directory / f"{implementation}.out"
    steps_file = directory / f"{implementation}.steps.json"
    command = ["valgrind", "--tool=callgrind", f"--callgrind-out-file={prefix}"]
    if phases:
        command += ["--dump-instr=yes", "--dump-line=no"]
    command += [sys.executable, __file__, "--inner", implementation, "--seeds", str(seeds)]
    command += ["--steps-file", str(steps_file)]
    if anchor:
        command += ["--shared-anchor", anchor]
    if kernel_source:
        command += ["--kernel-source", kernel_source]
    # One thread everywhere (no thread pool spinning while counted), numba's code cached.
    environment = dict(os.environ, PYTHONHASHSEED="0", OMP_NUM_THREADS="1", NUMBA_NUM_THREADS="1")
    environment["NUMBA_CACHE_DIR"] = str(directory / "numba-cache")
    if implementation != "fast":
        # numba keys its cache on the CPU it sees, and valgrind's CPUID shows another one:
        # name the host's CPU for both runs, so that the counted run loads what the warm-up
        # compiled (the same code as natively) instead of compiling under valgrind (very slow).
        from llvmlite import binding

        environment.setdefault("NUMBA_CPU_NAME", binding.get_host_cpu_name())
        environment.setdefault("NUMBA_CPU_FEATURES", binding.get_host_cpu_features().flatten())
    if kernel_cc is not None:  # a -g build of the kernel, in a cache of its own
        environment.update(FACTORQ_CC=kernel_cc, FACTORQ_CACHE_DIR=str(directory / "cache"))
    # compile (numba's code, the kernel) into the caches at native speed first
    warm = command[command.index(sys.executable) :]
    subprocess.run(warm, capture_output=True, text=True, env=environment, check=True)
    result = subprocess.run(command, capture_output=True, text=True, env=environment)
    if result.returncode != 0:
        sys.exit(f"{implementation} under valgrind failed:\n{result.stderr[-3000:]}")
    return json.loads(steps_file.read_text()), _dumps(prefix)


def _phase_of_lines() -> list[tuple[int, str]]:
    """(first line, phase) of run_experiment's sections in _kernel.c, in order."""
    lines = KERNEL.read_text().splitlines()
    start = next(n for n, text in enumerate(lines, 1) if "int64_t run_experiment(" in text)
    marks = [(start, "call set-up")]
    for name, phase in (
        ("for (; budget > 0", "act"),
        ("--- world step", "world step"),
        ("--- learn ---", "learn"),
        ("--- episode bookkeeping", "episode bookkeeping"),
        ("#undef SENSE", "call write-back"),
    ):
        marks.append((next(n for n in range(start, len(lines)) if name in lines[n - 1]), phase))
    return marks


def _line(place: str) -> int:
    """The line of addr2line's ``file:line`` or ``file:line (discriminator n)``; 0 if unknown."""
    number = place.rsplit(":", 1)[-1].split()[0]
    return int(number) if number.isdigit() else 0


def kernel_phases(dump: Path) -> dict[str, int]:
    """The kernel's instructions in ``dump`` by phase of run_experiment (see the docstring)."""
    objects: dict[str, str] = {}
    functions: dict[str, str] = {}
    costs: dict[str, dict[int, int]] = defaultdict(lambda: defaultdict(int))
    obj = function = kernel = ""
    address = 0
    pending_call = False
    subposition = re.compile(r"^([+-]\d+|\*|0x[0-9a-f]+)\s+(\d+)")

    def named(table: dict[str, str], value: str) -> str:
        match = re.match(r"\((\d+)\)(?: (.*))?", value)
        if not match:
            return value
        if match.group(2) is not None:
            table[match.group(1)] = match.group(2)
        return table[match.group(1)]

    loops = ("run_q_learning", "run_factor_q")
    for line in dump.read_text().splitlines():
        if line.startswith("ob="):
            obj = named(objects, line[3:])
        elif line.startswith("cob="):
            named(objects, line[4:])
        elif line.startswith("fn="):
            function = named(functions, line[3:])
        elif line.startswith("cfn="):
            named(functions, line[4:])
        elif line.startswith("calls="):
            pending_call = True  # the next line: the call site and the callee's inclusive cost
        else:
            match = subposition.match(line)
            if not match:
                continue
            step, cost = match.groups()
            if step.startswith("0x"):
                address = int(step, 16)
            elif step != "*":
                address += int(step)
            if "_kernel" not in obj:
                pending_call = False
                continue
            if pending_call:  # a call made by the loop counts where it is made
                pending_call = False
                if function in loops:
                    costs[function][address] += int(cost)
            elif function in loops or function == "fq_advance":  # self cost
                costs[function][address] += int(cost)
            kernel = obj
    marks = _phase_of_lines()
    phases: dict[str, int] = defaultdict(int)
    for function, by_address in costs.items():
        if function == "fq_advance":  # its loop over the experiments
            phases["call write-back"] += sum(by_address.values())
            continue
        addresses = sorted(by_address)
        output = subprocess.run(
            ["addr2line", "-i", "-f", "-e", kernel, *(hex(a) for a in addresses)],
            capture_output=True, text=True, check=True,
        ).stdout.splitlines()  # fmt: skip
        # -i prints the inline chain per address, innermost first, ending with the function
        # the address is in; the frame "run_experiment file:line" holds the loop's line.
        chains, chain = [], []
        for name, place in zip(output[::2], output[1::2], strict=True):
            chain.append((name, place))
            if name in ("run_q_learning", "run_factor_q"):
                chains.append(chain)
                chain = []
        for address, chain in zip(addresses, chains, strict=True):
            line = next((_line(place) for name, place in chain if name == "run_experiment"), 0)
            phase = "unattributed"
            for first, name in marks:
                if line >= first:
                    phase = name
            phases[phase] += by_address[address]
    return dict(phases)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=3, help="experiments per (world, algorithm)")
    parser.add_argument(
        "--implementations", nargs="+", choices=("fast", "project", "shared"),
        default=["fast", "project", "shared"],
    )  # fmt: skip
    parser.add_argument("--shared-anchor", metavar="DIR", help="the other session's numba anchor")
    parser.add_argument("--phases", action="store_true", help="the kernel's instructions by phase")
    parser.add_argument("--keep", metavar="DIR", help="keep callgrind's files in DIR")
    parser.add_argument(
        "--kernel-source", metavar="FILE", help="count this kernel source instead (same ABI)"
    )
    parser.add_argument("--inner", choices=("fast", "project", "shared"), help=argparse.SUPPRESS)
    parser.add_argument("--steps-file", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.inner:
        inner(args)
        return
    if shutil.which("valgrind") is None:
        sys.exit("valgrind is not installed (apt-get install valgrind)")
    if not Path("/usr/include/valgrind/callgrind.h").exists():
        print("valgrind/callgrind.h not in /usr/include: the helper may not compile")
    implementations = [i for i in args.implementations if i != "shared" or args.shared_anchor]
    if "shared" in args.implementations and not args.shared_anchor:
        print("no --shared-anchor DIR: the shared anchor is left out")
    if args.shared_anchor:
        args.shared_anchor = str(Path(args.shared_anchor).expanduser().resolve())
    directory = Path(args.keep or tempfile.mkdtemp(prefix="fq-callgrind-"))
    directory.mkdir(parents=True, exist_ok=True)
    per_step: dict[str, dict[str, float]] = {}
    totals: dict[str, tuple[int, int]] = {}
    phase_table: dict[str, dict[str, int]] = {}
    for implementation in implementations:
        kernel_cc = None
        if implementation == "fast" and args.phases:
            kernel_cc = f"{os.environ.get('FACTORQ_CC', 'cc')} -g"
        source = args.kernel_source and str(Path(args.kernel_source).resolve())
        steps, dumps = count(
            implementation, args.seeds, directory, args.shared_anchor, args.phases, kernel_cc,
            source if implementation == "fast" else None,
        )  # fmt: skip
        per_step[implementation] = {}
        instructions_all = steps_all = 0
        for name, taken in steps.items():
            instructions = _totals(dumps[name])
            per_step[implementation][name] = instructions / taken
            instructions_all += instructions
            steps_all += taken
            if implementation == "fast" and args.phases:
                phase_table[name] = kernel_phases(dumps[name])
                phase_table[name]["steps"] = taken
        totals[implementation] = instructions_all, steps_all
    print(f"instructions per env step (callgrind, {args.seeds} experiments per (world, "
          "algorithm), 10 runs x 200 episodes, 1 thread)")  # fmt: skip
    print(f"{'world':<14}{'algorithm':<12}" + "".join(f"{i:>10}" for i in implementations))
    for period, algorithm in COMBOS:
        name = f"{algorithm}-{period}"
        print(f"{WORLD_NAMES[period]:<14}{algorithm:<12}"
              + "".join(f"{per_step[i][name]:>10.1f}" for i in implementations))  # fmt: skip
    print(f"{'paper mix':<26}" + "".join(
        f"{totals[i][0] / totals[i][1]:>10.1f}" for i in implementations))  # fmt: skip
    print(f"{'env steps':<26}" + "".join(f"{totals[i][1]:>10,}" for i in implementations))
    if phase_table:
        order = ["act", "world step", "learn", "episode bookkeeping", "call set-up",
                 "call write-back", "unattributed"]  # fmt: skip
        print("\nthe kernel's instructions per env step by phase of the step")
        print(f"{'world':<14}{'algorithm':<12}" + "".join(f"{p[:12]:>13}" for p in order))
        for period, algorithm in COMBOS:
            row = phase_table[f"{algorithm}-{period}"]
            print(f"{WORLD_NAMES[period]:<14}{algorithm:<12}" + "".join(
                f"{row.get(p, 0) / row['steps']:>13.1f}" for p in order))  # fmt: skip
    print(f"\ncallgrind files in {directory}" if args.keep else "")
    summary = {"per_step": per_step, "totals": totals, "phases": phase_table}
    (directory / "summary.json").write_text(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
