"""Speed and memory of the fused fast path (``factorq_trainers.compiled.fast``), printed as tables.

- kernel build: compile time (into an empty cache) and load time from the cache;
- throughput, env steps per second, at several batch sizes ``S`` (independent experiments), for
  three loops: ``env-only`` (the world with uniformly random actions, no learning),
  ``q-learning`` and ``factor-q`` (env step + policy + update), with 1 and 2 threads, and the
  modular torchrl path (``factorq_torch.collectors``) alongside where it is importable;
- wall time of the paper's default workload (SPEC section 4: 100 seeds x 3 worlds x 2 algorithms
  x 10 runs x 200 episodes) through ``ExperimentBatch``, with 1 and 2 threads;
- peak memory (RSS high-water mark) at the largest ``S``, each loop in a fresh process, and the
  RSS growth between two equal chunks of work (0: no per-step allocation).

Worlds are the paper's default 10x10 with 10 obstacles; the batch cycles through the three worlds
(static, semi-dynamic, dynamic), like the paper's experiment (``--world dynamic``: every world
dynamic, the README loop of issue 17's torchrl targets). The fast path's 2-thread Factor-Q and
paper-workload figures are also given as a ratio to ``NUMBA_ANCHOR``, the throughput of an
independent numba implementation of the same experiment measured on the project's 2-core machine
(issue 17, a quoted figure), and, where numba is importable (it is not a dependency: ``pip install
numba`` or the ``bench`` extra), to ``bench_numba_anchor.py``'s numba implementation measured in
this run on the same batches (``--no-numba`` skips it). ``--shared-anchor DIR`` adds a third
implementation, the numba code of another session (``fq_numba.py`` and ``common.py`` in ``DIR``;
its own streams and scatter, so its env steps differ): the paper workload at ``--anchor-seeds``
seeds per world (default 256 and 1024) runs on the fast path and on both numba anchors in
alternating rounds (``--rounds``, the order rotating), 2 threads, and the rates (per wall and per
CPU second), their spread and the ratios are printed with the load average (``--anchors-only``
prints only that table; ``--kernel-variant`` adds other builds of the kernel). The torchrl path
runs on ``--device`` (default ``cuda`` where one is present, else ``cpu``); on a GPU try
``--sizes 4096 16384 65536 262144 --no-paper``. Run from the repository root:

    .venv/bin/python benchmarks/bench_speed.py
    .venv/bin/python benchmarks/bench_speed.py --sizes 1 1024 --seconds 0.3 --no-paper
    .venv/bin/python benchmarks/bench_speed.py --world dynamic --loops factor-q --no-memory
    .venv/bin/python benchmarks/bench_speed.py --anchors-only --shared-anchor DIR --rounds 3

Timings are never asserted anywhere; not a package on purpose (the torchrl wheel installs a
top-level ``benchmarks``).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(ROOT))

from factorq_envs.grid_world import WorldConfig  # noqa: E402
from factorq_torch.base.config import AgentConfig  # noqa: E402
from factorq_torch.base.rng import STREAM_POLICY, STREAM_WORLD, derive_keys  # noqa: E402
from factorq_trainers.compiled import fast, loader  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_numba_anchor as numba_anchor  # noqa: E402  (measures only where numba imports)

LOOPS = {"env-only": fast.RANDOM_WALK, "q-learning": "q-learning", "factor-q": "factor-q"}
PAPER_PERIODS = (0, 10, 1)  # static, semi-dynamic, dynamic
#: Env steps per second of an independent numba implementation of the paper workload and of
#: Factor-Q at S = 1024 on 2 threads, on the project's 2-core machine (issue 17).
NUMBA_ANCHOR = 60.7e6
#: Worlds of a benchmark batch: "paper" cycles static/semi-dynamic/dynamic, "dynamic" is all 1.
WORLD = {"periods": PAPER_PERIODS}


def _periods(count: int, offset: int = 0) -> torch.Tensor:
    """[S] obstacle periods cycling the benchmark's worlds, from world ``offset``."""
    periods = torch.tensor(WORLD["periods"])
    return periods.roll(-offset).repeat(count // len(periods) + 1)[:count]


def _batch(loop: str, count: int, seed: int, threads: int, runs: int, episodes: int):
    return fast.ExperimentBatch(
        LOOPS[loop],
        _periods(count, offset=seed),  # a small S sees every world over successive batches
        WorldConfig(),
        AgentConfig(),
        runs,
        episodes,
        derive_keys(seed, STREAM_WORLD, count),
        derive_keys(seed, STREAM_POLICY, count),
        threads=threads,
    )


def _shape(count: int) -> tuple[int, int, int]:
    """(runs, episodes, steps per experiment per advance) for a batch of ``count``.

    Small batches run whole experiments (fresh batches until the time is up); large ones one
    long call (about 3000 steps per experiment, so that each experiment's tables are fetched
    from memory once per call, not once every few hundred steps), with short metrics.
    """
    if count <= 1024:
        return 10, 200, max(3000, 4_000_000 // count)
    return 1, 100, 3000


def fast_throughput(loop: str, count: int, threads: int, seconds: float) -> float:
    """Env steps per second of ``count`` experiments (fresh batches until ``seconds`` of work)."""
    runs, episodes, chunk = _shape(count)
    steps, elapsed, seed = 0, 0.0, 0
    while elapsed < seconds:
        batch = _batch(loop, count, seed, threads, runs, episodes)
        seed += 1
        while not batch.done and elapsed < seconds:
            before = batch.total_steps
            start = time.perf_counter()
            batch.advance(chunk)
            elapsed += time.perf_counter() - start
            steps += batch.total_steps - before
    return steps / elapsed


def numba_throughput(loop: str, count: int, threads: int) -> float | str:
    """Env steps per second of the numba anchor (``bench_numba_anchor``) on ``fast_throughput``'s
    first batch (same worlds, keys, runs and episodes), every experiment to its end."""
    if loop not in ("q-learning", "factor-q"):
        return "-"
    runs, episodes, _ = _shape(count)
    seconds, steps = numba_anchor.workload(
        loop, _periods(count).numpy(), threads, runs, episodes, seed=0
    )
    return steps / seconds


def modular_throughput(
    loop: str, count: int, threads: int, seconds: float, device: str = "cpu"
) -> float | str:
    """Env steps per second of the torchrl path (env + transform + policy + collector + loss) on
    ``device`` (``threads``: torch's intra-op threads, CPU only)."""
    if loop == "env-only":
        return "-"  # see benchmarks/bench_env.py
    try:
        from tensordict.nn import TensorDictSequential
        from torchrl.envs import TransformedEnv

        from factorq_envs import FactoredGridEnv, SplitLocalReward
        from factorq_torch.collectors import OnlineCollector
        from factorq_torch.objectives import FactorQLoss, TabularQLoss
        from factorq_torch.policy import EpsilonGreedyPolicy, FactorQPolicy
        from factorq_torch.tables import LocalRewardTable, TaskQTable
    except ImportError as error:
        return f"n/a ({error.name})"
    world, agent = WorldConfig(), AgentConfig()
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        env = FactoredGridEnv(
            size=world.size,
            num_obstacles=world.num_obstacles,
            obstacle_period=_periods(count).tolist(),
            max_steps=world.max_steps,
            batch_size=(count,),
            seed=0,
            device=device,
        )
        if loop == "factor-q":
            env = TransformedEnv(env, SplitLocalReward())
            task = TaskQTable(count, world.num_cells, device=device, sparse_grad=True)
            local = LocalRewardTable(count, device=device)
            chooser = FactorQPolicy(count, seed=0, epsilon=agent.epsilon, device=device)
            policy = TensorDictSequential(task, local, chooser)
            loss = FactorQLoss(task, local, gamma=agent.gamma, alpha=agent.alpha)
        else:
            task = TaskQTable(
                count, world.num_cells, with_sensors=True, device=device, sparse_grad=True
            )
            chooser = EpsilonGreedyPolicy(count, seed=0, epsilon=agent.epsilon, device=device)
            policy = TensorDictSequential(task, chooser)
            loss = TabularQLoss(task, gamma=agent.gamma, alpha=agent.alpha)
        collector = OnlineCollector(env, policy, loss, runs=10, episodes=200)
        for _ in range(3):  # warm-up
            collector.step()
        _synchronize(device)
        steps, start = 0, time.perf_counter()
        while time.perf_counter() - start < seconds and not collector.done:
            collector.step()
            steps += count
        _synchronize(device)
        return steps / (time.perf_counter() - start)
    except Exception as error:  # the modular path is optional here: report, do not fail
        return f"n/a ({type(error).__name__})"
    finally:
        torch.set_num_threads(previous)


def _synchronize(device: str) -> None:
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def build_times() -> tuple[float, float]:
    """(seconds to compile into an empty cache, seconds to load the cached build)."""
    with tempfile.TemporaryDirectory() as directory:
        os.environ["FACTORQ_CACHE_DIR"] = directory
        try:
            _, built = loader._build()
            start = time.perf_counter()
            _, cached = loader._build()
            load = time.perf_counter() - start
        finally:
            del os.environ["FACTORQ_CACHE_DIR"]
    assert built["compiled"] and not cached["compiled"]
    return built["seconds"], load


def kernel_variant(variant: str):
    """The kernel built from ``variant``: compiler flags added to the loader's, optionally after
    another source file of the same ABI (``old_kernel.c -march=native``), into a cache of its
    own."""
    words = variant.split()
    source = Path(words.pop(0)) if words and words[0].endswith(".c") else loader._SOURCE
    compiler = " ".join([*loader._compiler(), *words])
    directory = tempfile.mkdtemp(prefix="fq-kernel-variant-")
    saved = {name: os.environ.get(name) for name in ("FACTORQ_CC", "FACTORQ_CACHE_DIR")}
    os.environ.update(FACTORQ_CC=compiler, FACTORQ_CACHE_DIR=directory)
    default_source, loader._SOURCE = loader._SOURCE, source.resolve()
    try:
        library, _ = loader._build()
    finally:
        loader._SOURCE = default_source
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value
    return library


def paper_workload(threads: int, seeds: int = 100, library=None) -> dict[str, tuple[float, int]]:
    """{algorithm: (seconds, env steps)} for the paper's default experiment (on ``library``, a
    ``kernel_variant``, when given)."""
    periods = torch.tensor(PAPER_PERIODS).repeat_interleave(seeds)  # [3 * seeds]
    results = {}
    for algorithm in ("q-learning", "factor-q"):
        start = time.perf_counter()
        if library is not None:
            default, loader._library = loader._library, library
        batch = fast.ExperimentBatch(
            algorithm,
            periods,
            WorldConfig(),
            AgentConfig(),
            10,
            200,
            derive_keys(0, STREAM_WORLD, len(periods)),
            derive_keys(0, STREAM_POLICY, len(periods)),
            threads=threads,
        )
        if library is not None:
            loader._library = default
        while not batch.done:
            batch.advance(1 << 40)
        results[algorithm] = (time.perf_counter() - start, batch.total_steps)
    return results


def load_shared_anchor(directory: str):
    """The numba anchor of ``directory`` (its ``fq_numba.py`` and ``common.py``), imported and
    compiled; exits with one line saying why where numba or the files are missing."""
    if not numba_anchor.available():
        sys.exit(
            f"--shared-anchor {directory}: numba is not installed here, so the numba anchors "
            "cannot run (pip install numba, or the bench extra)"
        )
    folder = Path(directory).expanduser().resolve()
    missing = [name for name in ("fq_numba.py", "common.py") if not (folder / name).is_file()]
    if missing:
        sys.exit(f"--shared-anchor {directory}: no {' or '.join(missing)} in {folder}")
    import importlib.util

    modules = {}
    for name in ("common", "fq_numba"):  # fq_numba imports "common" by that name
        spec = importlib.util.spec_from_file_location(name, folder / f"{name}.py")
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
        modules[name] = module
    anchor = modules["fq_numba"]
    anchor.run_full([0], "parallel", runs=1, episodes=1)  # compile and warm up
    return anchor


def shared_paper_workload(anchor, threads: int, seeds: int) -> tuple[float, int]:
    """(seconds, env steps) of the shared anchor's paper workload: ``seeds`` seeds x its 3 worlds
    x 2 algorithms x its runs and episodes, in one ``many`` call on ``threads`` numba threads."""
    constants = anchor.C
    algos, periods, keys = anchor.jobs(range(seeds))
    out = np.zeros((len(keys), 3, constants.RUNS, constants.EPISODES), np.int32)
    layout = constants.static_layout()
    numba_anchor.numba.set_num_threads(threads)
    start = time.perf_counter()
    anchor.many(
        algos, periods, keys, layout, constants.N, constants.RUNS, constants.EPISODES,
        constants.MAX_STEPS, out,
    )  # fmt: skip
    return time.perf_counter() - start, int(out[:, 0].sum())


def _total(results: dict[str, tuple[float, int]]) -> tuple[float, int]:
    return sum(v[0] for v in results.values()), sum(v[1] for v in results.values())


def compare_anchors(
    anchor, sizes: list[int], rounds: int, threads: int = 2, variants: tuple[str, ...] = ()
) -> None:
    """The paper workload at each number of seeds in ``sizes`` on the fast path, this project's
    numba anchor, the shared one (``anchor``, if given) and the kernel ``variants``, ``rounds``
    times, alternating within a round (the order rotating from round to round). Each rate is
    given per wall second and per CPU second of the process (all its threads): on a machine
    shared with other work the wall rate follows the CPU share the process gets, the CPU rate
    much less. Then the ratios of the fast path per round, their median and range, and the load
    average around every round."""
    implementations = {
        "fast": lambda seeds: _total(paper_workload(threads, seeds)),
        "numba (project)": lambda seeds: _total(numba_anchor.paper_workload(threads, seeds)),
    }
    if anchor is not None:
        implementations["numba (shared)"] = lambda seeds: shared_paper_workload(
            anchor, threads, seeds
        )
    labels = {
        variant: "fast " + " ".join(Path(w).name for w in variant.split()) for variant in variants
    }
    for variant in variants:  # the kernel of another source or with more flags
        library = kernel_variant(variant)
        implementations[labels[variant]] = lambda seeds, library=library: _total(
            paper_workload(threads, seeds, library)
        )
    names = list(implementations)
    others = {"project": "numba (project)", "shared": "numba (shared)"}
    others = {key: name for key, name in others.items() if name in implementations}
    others.update({label[5:]: label for label in labels.values()})
    for name in names:  # compile (numba) and warm up, untimed
        implementations[name](1)
    print(f"numba threading layer: {numba_anchor.numba.threading_layer()}")
    print(f"\npaper workload against the numba anchors, {threads} threads, {rounds} rounds, "
          "implementations alternating (S: seeds per world; x 3 worlds x 2 algorithms x 10 runs "
          "x 200 episodes); env steps per wall second and per CPU second")  # fmt: skip
    width = max(17, *(len(name) + 2 for name in names))
    print(f"{'S':>5}{'round':>6}{'per':>5}" + "".join(f"{name:>{width}}" for name in names)
          + "".join(f"{'fast/' + key:>{width}}" for key in others) + f"{'load':>6}")  # fmt: skip
    summary = {}
    for count in sizes:
        rates = {clock: {name: [] for name in names} for clock in ("wall", "cpu")}
        ratios = {clock: {key: [] for key in others} for clock in ("wall", "cpu")}
        for index in range(rounds):
            load = os.getloadavg()[0]
            order = names[index % len(names) :] + names[: index % len(names)]
            for name in order:
                cpu = time.process_time()
                seconds, steps = implementations[name](count)
                cpu = time.process_time() - cpu
                rates["wall"][name].append(steps / seconds)
                rates["cpu"][name].append(steps / cpu)
            load = max(load, os.getloadavg()[0])  # the larger of before and after
            for clock in ("wall", "cpu"):
                for key, name in others.items():
                    ratios[clock][key].append(rates[clock]["fast"][-1] / rates[clock][name][-1])
                print(f"{count:>5}{index + 1:>6}{clock:>5}"
                      + "".join(f"{rates[clock][n][-1] / 1e6:>{width - 2}.1f} M" for n in names)
                      + "".join(f"{ratios[clock][k][-1]:>{width - 1}.2f}x" for k in others)
                      + (f"{load:>6.1f}" if clock == "wall" else ""))  # fmt: skip
        summary[count] = rates, ratios
    print("\nmedian [min - max] over the rounds")
    for count, (rates, ratios) in summary.items():
        for clock in ("wall", "cpu"):
            cells = [
                f"{name} {np.median(v) / 1e6:.1f} M [{min(v) / 1e6:.1f}-{max(v) / 1e6:.1f}]"
                for name, v in rates[clock].items()
            ]
            cells += [
                f"fast/{name} {np.median(v):.2f}x [{min(v):.2f}-{max(v):.2f}]"
                for name, v in ratios[clock].items()
            ]
            print(f"S={count}, per {clock} second: " + "; ".join(cells))


def _status_bytes(field: str) -> int:
    """A ``/proc/self/status`` memory figure (Linux; 0 elsewhere)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError):
        pass
    return 0


def _peak_bytes() -> int:
    """Peak RSS of this process image. ``getrusage``'s ``ru_maxrss`` also counts the parent's
    RSS at fork time on Linux, so ``VmHWM`` (this image only) is preferred where it exists."""
    return _status_bytes("VmHWM") or resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def memory_probe(loop: str, count: int) -> dict:
    """Run in a fresh process: peak RSS for ``count`` experiments and growth between chunks."""
    baseline = _peak_bytes()
    runs, episodes, chunk = _shape(count)
    batch = _batch(loop, count, 0, 2, runs, episodes)
    state = sum(tensor.nbytes for tensor in batch._tensors.values())
    batch.advance(chunk // 2)
    after_first = _status_bytes("VmRSS")
    batch.advance(chunk // 2)
    growth = _status_bytes("VmRSS") - after_first
    return {"baseline": baseline, "peak": _peak_bytes(), "state": state, "growth": growth}


def _memory(loop: str, count: int) -> dict:
    command = [sys.executable, __file__, "--memory-probe", loop, str(count)]
    output = subprocess.run(command, capture_output=True, text=True, check=True).stdout
    return json.loads(output.strip().splitlines()[-1])


def _machine(device: str) -> None:
    """The kernel's build and the machine's CPUs and load, as the tables' header."""
    info = loader.build_info()
    print(f"kernel: {Path(info['path']).name}, cc {' '.join(loader._FLAGS)}")
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    version = f", numba {numba_anchor.numba.__version__}" if numba_anchor.available() else ""
    print(f"machine: {os.cpu_count()} CPUs, load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}"
          f", torch {torch.__version__}{version}, torchrl path on {device}")  # fmt: skip


def _rate(value) -> str:
    if not isinstance(value, float):
        return str(value)
    return f"{value / 1e6:.2f} M" if value >= 1e6 else f"{value / 1e3:.2f} k"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1, 64, 1024, 16384])
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--seconds", type=float, default=0.5, help="work timed per cell")
    parser.add_argument("--no-modular", action="store_true", help="skip the torchrl path")
    parser.add_argument("--no-paper", action="store_true", help="skip the paper workload")
    parser.add_argument("--no-memory", action="store_true", help="skip the memory table")
    parser.add_argument("--loops", nargs="+", choices=list(LOOPS), default=list(LOOPS))
    parser.add_argument(
        "--world", choices=("paper", "dynamic"), default="paper", help="worlds of the batches"
    )
    parser.add_argument(
        "--device",
        default="cuda" if torch.cuda.is_available() else "cpu",
        help="device of the torchrl path (the fast path is CPU only)",
    )
    parser.add_argument(
        "--no-numba", action="store_true", help="do not measure the numba anchor (when installed)"
    )
    parser.add_argument(
        "--shared-anchor",
        metavar="DIR",
        help="folder of another numba anchor (fq_numba.py, common.py) to measure against",
    )
    parser.add_argument(
        "--anchor-seeds", type=int, nargs="+", default=[256, 1024], metavar="S",
        help="seeds per world of the paper workload against the anchors",
    )  # fmt: skip
    parser.add_argument("--rounds", type=int, default=3, help="rounds against the anchors")
    parser.add_argument(
        "--kernel-variant", action="append", default=[], metavar="FLAGS",
        help="also run the kernel built with FLAGS added (e.g. -march=native), or from another "
        "source file first in FLAGS (old_kernel.c [flags]), against the anchors",
    )  # fmt: skip
    parser.add_argument(
        "--anchors-only", action="store_true", help="only the paper workload against the anchors"
    )
    parser.add_argument("--memory-probe", nargs=2, metavar=("LOOP", "S"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.memory_probe:
        print(json.dumps(memory_probe(args.memory_probe[0], int(args.memory_probe[1]))))
        return
    if not fast.is_available():
        sys.exit(f"the fast path is unavailable: {fast.unavailable_reason()}")
    if args.world == "dynamic":
        WORLD["periods"] = (1,)
    anchor = load_shared_anchor(args.shared_anchor) if args.shared_anchor else None
    if args.anchors_only:
        if not numba_anchor.available():
            sys.exit(
                "--anchors-only: numba is not installed (pip install numba or the bench extra)"
            )
        _machine(args.device)
        if anchor is None:
            print("no --shared-anchor: the fast path against this project's numba anchor only")
        compare_anchors(anchor, args.anchor_seeds, args.rounds, variants=args.kernel_variant)
        return

    compile_seconds, load_seconds = build_times()
    print(f"kernel: compiled in {compile_seconds:.2f} s, loaded from the cache in "
          f"{load_seconds * 1e3:.1f} ms")  # fmt: skip
    _machine(args.device)
    worlds = "cycling static/semi/dynamic" if args.world == "paper" else "all dynamic"
    print(f"\nthroughput, env steps per second (10x10 worlds {worlds})")
    columns = [f"fast {t} thr" for t in args.threads]
    modular_threads = args.threads if torch.device(args.device).type == "cpu" else [1]
    if not args.no_modular:
        columns += [f"torchrl {t} thr" for t in modular_threads]
    measured = 2 in args.threads and numba_anchor.available() and not args.no_numba
    if 2 in args.threads:
        columns.append("fast 2 / 60.7 M")  # the anchor figure issue 17 quoted
    if measured:
        columns += ["numba 2 thr", "/ numba meas."]
    print(f"{'loop':<11}{'S':>7}" + "".join(f"{name:>16}" for name in columns))
    for loop in args.loops:
        for count in args.sizes:
            cells = [fast_throughput(loop, count, t, args.seconds) for t in args.threads]
            if not args.no_modular:
                cells += [
                    modular_throughput(loop, count, t, args.seconds, args.device)
                    for t in modular_threads
                ]
            if 2 in args.threads:
                ratio = cells[args.threads.index(2)] / NUMBA_ANCHOR
                cells.append(f"{ratio:.2f}x" if loop == "factor-q" else "-")
            if measured:
                anchor = numba_throughput(loop, count, 2)
                ratio = cells[args.threads.index(2)] / anchor if anchor != "-" else "-"
                cells += [anchor, f"{ratio:.2f}x" if ratio != "-" else ratio]
            print(f"{loop:<11}{count:>7}" + "".join(f"{_rate(cell):>16}" for cell in cells))

    if not args.no_paper:
        print("\npaper workload (100 seeds x 3 worlds x 10 runs x 200 episodes, per algorithm)")
        print(f"{'threads':>7}{'q-learning':>14}{'factor-q':>14}{'total':>10}{'env steps':>13}"
              f"{'steps/s':>12}{'/ 60.7 M':>9}")  # fmt: skip
        for threads in args.threads:
            results = paper_workload(threads)
            seconds = sum(value[0] for value in results.values())
            steps = sum(value[1] for value in results.values())
            times = results["q-learning"][0], results["factor-q"][0]
            print(f"{threads:>7}{times[0]:>12.2f} s{times[1]:>12.2f} s{seconds:>8.2f} s"
                  f"{steps:>13,}{steps / seconds / 1e6:>10.1f} M"
                  f"{steps / seconds / NUMBA_ANCHOR:>8.2f}x")  # fmt: skip
            if threads == 2 and measured:
                anchor = numba_anchor.paper_workload(threads)
                rate = sum(v[1] for v in anchor.values()) / sum(v[0] for v in anchor.values())
                print(f"{'':>7}numba anchor measured now: {rate / 1e6:.1f} M steps/s on 2 threads"
                      f" (same {sum(v[1] for v in anchor.values()):,} env steps): fast / numba "
                      f"{steps / seconds / rate:.2f}x")  # fmt: skip
    if anchor is not None:
        compare_anchors(anchor, args.anchor_seeds, args.rounds, variants=args.kernel_variant)
    if 2 in args.threads and not numba_anchor.available():
        print("\nnumba is not installed: the '/ numba' ratios are to the quoted anchor only "
              "(pip install numba, or the bench extra, to measure it in this run)")  # fmt: skip

    if args.no_memory:
        return
    count = max(args.sizes)
    print(f"\nmemory at S={count} (fresh process per loop, 2 threads)")
    print(f"{'loop':<11}{'import RSS':>12}{'peak RSS':>12}{'batch state':>13}{'RSS growth':>12}")
    for loop in LOOPS:
        memory = _memory(loop, count)
        mib = {name: value / 2**20 for name, value in memory.items()}
        print(f"{loop:<11}{mib['baseline']:>8.0f} MiB{mib['peak']:>8.0f} MiB"
              f"{mib['state']:>9.0f} MiB{mib['growth']:>8.1f} MiB")  # fmt: skip


if __name__ == "__main__":
    main()
