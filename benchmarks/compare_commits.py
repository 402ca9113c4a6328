"""This tree's speed against another commit's: the main benchmarks, alternating in one run.

Run it before you stop (issue 42): it catches a change that makes a path slower, which a lone
timing on a shared machine cannot. The other commit's files are exported beside the working tree
(``git archive`` into a temporary folder, or ``--base-dir``, an existing checkout), and each tree
gets a worker process of this interpreter whose ``factorq_torch``, ``factorq_envs`` and
``factorq_trainers`` are that tree's (links to its folders first on ``PYTHONPATH``; the
installed dependencies are shared, so only the code differs). Each worker builds every benchmark
once, then the two are asked for one timed block of each benchmark in turn, the order reversed
every other round, so that a change in the machine's load hits both alike:

- ``paper``: the compiled fast path, the paper's worlds and algorithms (``--seeds`` experiments
  per world, 10 runs x 200 episodes, 1 thread), env steps per second;
- ``readme``: the torchrl path's README loop (``benchmarks/bench_readme_loop.py``: the dynamic
  world at ``S = --size``, ``OnlineCollector`` of Factor-Q, 1 thread), ms per batched step;
- ``layer-oracle`` and ``layer-learned``: the local-risk layer of one agent (``LocalRisk``'s
  forward and ``LocalRiskLoss``'s update per env step, a ``LocalRewardTable`` with the world's
  dependency or a ``StructureLearner``), microseconds per step;
- ``adapter``: a Gymnasium env through the declaration adapter (MiniGrid Dynamic-Obstacles 8x8,
  ``S = 8``, as torchrl's ``MiniGridEnv``; needs the ``minigrid`` extra), ms per batched step.

A benchmark that one tree cannot build (an older commit without it, a missing extra) is reported
and skipped. For each it prints both trees' medians and the speed ratio ``base time / this
time`` per round (above 1: this tree is faster), its median and range, by process CPU time (what
the load moves least) and by wall time. Run from the repository root:

    .venv/bin/python benchmarks/compare_commits.py              # against the fork point of main
    .venv/bin/python benchmarks/compare_commits.py HEAD         # your uncommitted changes only
    .venv/bin/python benchmarks/compare_commits.py 2c84ba2 --only readme --rounds 7
    .venv/bin/python benchmarks/compare_commits.py --base-dir ../other-checkout

The default run takes about a minute. Nothing asserted; not a package on purpose (the torchrl
wheel installs a top-level ``benchmarks``).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
import tomllib
from collections.abc import Callable, Sequence
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
BENCHMARKS = ("paper", "readme", "layer-oracle", "layer-learned", "adapter")
#: What one block's units are, and how a time per unit is shown.
UNITS = {
    "paper": ("M env steps/s", lambda seconds: 1e-6 / seconds),
    "readme": ("ms per step", lambda seconds: 1e3 * seconds),
    "layer-oracle": ("us per step", lambda seconds: 1e6 * seconds),
    "layer-learned": ("us per step", lambda seconds: 1e6 * seconds),
    "adapter": ("ms per step", lambda seconds: 1e3 * seconds),
}
#: The installed package names and the folders they come from, when pyproject.toml does not say.
DEFAULT_PACKAGES = {
    "factorq_torch": "factorq_torch",
    "factorq_envs": "envs",
    "factorq_trainers": "trainers",
}


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    """The command line (the worker's own flag is ``--worker``)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "base",
        nargs="?",
        help="the commit to compare with (default: the fork point of main, else HEAD)",
    )
    parser.add_argument("--base-dir", help="an existing checkout to compare with instead")
    parser.add_argument("--rounds", type=int, default=3, help="timed blocks per tree and benchmark")
    parser.add_argument(
        "--only",
        nargs="+",
        choices=BENCHMARKS,
        default=list(BENCHMARKS),
        metavar="NAME",
        help=f"the benchmarks to run (default: all of {', '.join(BENCHMARKS)})",
    )
    parser.add_argument("--seeds", type=int, default=10, help="paper: experiments per world")
    parser.add_argument("--size", type=int, default=1024, help="readme: S, the batch")
    parser.add_argument("--steps", type=int, default=20, help="readme: steps per block")
    parser.add_argument("--calls", type=int, default=300, help="layer: steps per block")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.base and args.base_dir:
        parser.error("give a commit or --base-dir, not both")
    for name in ("rounds", "seeds", "size", "steps", "calls"):
        if getattr(args, name) < 1:
            parser.error(f"--{name}={getattr(args, name)} must be at least 1")
    return args


def speedups(this: Sequence[float], base: Sequence[float]) -> tuple[float, float, float]:
    """``(median, lowest, highest)`` of the per-round ratios ``base / this`` of two trees' times
    per unit (above 1: ``this`` is faster). Rounds pair up in order."""
    if len(this) != len(base) or not this:
        raise ValueError(f"{len(this)} and {len(base)} rounds: expected as many, at least one")
    ratios = [old / new for new, old in zip(this, base, strict=True)]
    return statistics.median(ratios), min(ratios), max(ratios)


def package_folders(tree: Path) -> dict[str, Path]:
    """``{installed name: folder}`` of a checkout's three packages, from its ``pyproject.toml``
    (``[tool.setuptools.package-dir]``; the folder of the same name otherwise)."""
    folders = dict(DEFAULT_PACKAGES)
    pyproject = tree / "pyproject.toml"
    if pyproject.is_file():
        setuptools = tomllib.loads(pyproject.read_text()).get("tool", {}).get("setuptools", {})
        folders.update(
            {
                name: folder
                for name, folder in setuptools.get("package-dir", {}).items()
                if name in folders
            }
        )
    found = {name: tree / folder for name, folder in folders.items()}
    missing = [str(path) for path in found.values() if not (path / "__init__.py").is_file()]
    if missing:
        raise SystemExit(f"{tree}: no package at {', '.join(missing)}")
    return found


def link_packages(tree: Path, folder: Path) -> Path:
    """A folder of links ``installed name -> the tree's folder`` (to put first on the path)."""
    folder.mkdir(parents=True, exist_ok=True)
    for name, source in package_folders(tree).items():
        (folder / name).symlink_to(source.resolve(), target_is_directory=True)
    return folder


def export_commit(commit: str, folder: Path) -> Path:
    """The files of ``commit`` (this repository's) in ``folder``, by ``git archive``."""
    folder.mkdir(parents=True, exist_ok=True)
    archive = subprocess.run(
        ["git", "-C", str(ROOT), "archive", "--format=tar", commit],
        capture_output=True,
        check=False,
    )
    if archive.returncode != 0:
        raise SystemExit(f"git archive {commit}: {archive.stderr.decode().strip()}")
    subprocess.run(["tar", "-x", "-C", str(folder)], input=archive.stdout, check=True)
    return folder


def default_base() -> str:
    """The fork point of ``main`` (HEAD where there is no ``main`` or HEAD is on it)."""
    found = subprocess.run(
        ["git", "-C", str(ROOT), "merge-base", "HEAD", "main"],
        capture_output=True,
        text=True,
        check=False,
    )
    return found.stdout.strip() if found.returncode == 0 else "HEAD"


def describe(commit: str) -> str:
    """``abc1234 subject`` of a commit of this repository."""
    shown = subprocess.run(
        ["git", "-C", str(ROOT), "log", "-1", "--format=%h %s", commit],
        capture_output=True,
        text=True,
        check=False,
    )
    return shown.stdout.strip()[:72] or commit


# -- the worker: one tree's packages, one benchmark block per request --------------------------


def _paper(args: argparse.Namespace) -> Callable[[], int]:
    import torch

    from factorq_envs import WorldConfig
    from factorq_torch.base.config import AgentConfig
    from factorq_torch.base.rng import STREAM_POLICY, STREAM_WORLD, derive_keys

    try:
        from factorq_trainers.compiled import fast
    except ImportError:  # before trainers/ was split by concern
        from factorq_trainers import fast  # type: ignore[no-redef]

    periods = torch.tensor([0, 10, 1]).repeat_interleave(args.seeds)

    def block() -> int:
        total = 0
        for algorithm in ("q-learning", "factor-q"):
            batch = fast.ExperimentBatch(
                algorithm,
                periods,
                WorldConfig(),
                AgentConfig(),
                10,
                200,
                derive_keys(0, STREAM_WORLD, len(periods)),
                derive_keys(0, STREAM_POLICY, len(periods)),
                threads=1,
            )
            while not batch.done:
                batch.advance(1 << 40)
            total += batch.total_steps
        return total

    return block


def _readme(args: argparse.Namespace) -> Callable[[], int]:
    from tensordict.nn import TensorDictSequential
    from torchrl.envs import TransformedEnv

    from factorq_envs import FactoredGridEnv, SplitLocalReward
    from factorq_torch.collectors import OnlineCollector
    from factorq_torch.objectives import FactorQLoss
    from factorq_torch.policy import FactorQPolicy
    from factorq_torch.tables import LocalRewardTable, TaskQTable

    count = args.size
    base = FactoredGridEnv(
        size=10, num_obstacles=10, obstacle_period=1, batch_size=(count,), seed=0
    )
    env = TransformedEnv(base, SplitLocalReward())
    task, local = TaskQTable(count, 100, sparse_grad=True), LocalRewardTable(count)
    policy = TensorDictSequential(task, local, FactorQPolicy(count, seed=0))
    collector = OnlineCollector(env, policy, FactorQLoss(task, local), runs=10, episodes=200)
    for _ in range(5):  # warm-up
        collector.step()

    def block() -> int:
        for _ in range(args.steps):
            collector.step()
        return args.steps

    return block


def _layer(learned: bool, args: argparse.Namespace) -> Callable[[], int]:
    import torch
    from torchrl.envs import TransformedEnv

    from factorq_envs import FactoredGridEnv, SplitLocalReward
    from factorq_torch.risk import LocalRisk, LocalRiskLoss
    from factorq_torch.structure import StructureLearner
    from factorq_torch.tables import LocalRewardTable

    base = FactoredGridEnv(size=10, num_obstacles=10, obstacle_period=1, batch_size=(1,), seed=0)
    env = TransformedEnv(base, SplitLocalReward(keep_reward=True))
    dependency = base.dependency
    actions, sensors = dependency.shape
    provider = (
        StructureLearner(1, num_actions=actions, num_sensors=sensors)
        if learned
        else LocalRewardTable(1, dependency=dependency)
    )
    layer, loss = LocalRisk(provider, num_actions=actions), LocalRiskLoss(provider)
    torch.manual_seed(0)
    steps = env.rollout(200, break_when_any_done=False)  # [1, 200]: random actions
    transitions = [steps[:, index] for index in range(steps.shape[1])]  # [1] each
    values = torch.linspace(-1.0, 1.0, actions).unsqueeze(0)  # [1, A], the task values
    position = 0

    def block() -> int:
        nonlocal position
        with torch.no_grad():
            for _ in range(args.calls):
                transition = transitions[position % len(transitions)]
                position += 1
                acting = transition.select("sensors").set("action_value", values.clone())
                layer(acting)
                loss(transition)
        return args.calls

    return block


def _adapter(args: argparse.Namespace) -> Callable[[], int]:
    import torch

    from factorq_envs.minigrid_torchrl import MiniGridEnv

    env = MiniGridEnv(8, seeds=list(range(8)))
    generator = torch.Generator().manual_seed(0)
    high = int(env.action_spec.space.n)
    state = {"td": env.reset()}

    def block() -> int:
        td = state["td"]
        for _ in range(args.steps):
            td["action"] = torch.randint(0, high, (8,), generator=generator)
            td = env.step_mdp(env.step(td))
            done = td.get("done")
            if bool(done.any()):
                td.set("_reset", done)
                td = env.reset(td)
        state["td"] = td
        return args.steps

    return block


WORKLOADS = {
    "paper": _paper,
    "readme": _readme,
    "layer-oracle": lambda args: _layer(False, args),
    "layer-learned": lambda args: _layer(True, args),
    "adapter": _adapter,
}


def worker(args: argparse.Namespace) -> None:
    """Answer the parent's requests on the original stdout, one JSON line each: ``{"setup":
    name}`` builds a benchmark (``{"ok": true}`` or ``{"error": text}``), ``{"run": name}``
    times one block (``{"units", "cpu", "wall"}``). Everything else printed goes to stderr."""
    import logging
    import warnings

    import torch

    # The packages must come from this tree only: an editable install's finder (appended to
    # sys.meta_path) would find a module this tree lacks in the installed tree instead.
    sys.meta_path[:] = [
        finder
        for finder in sys.meta_path
        if not getattr(finder, "__module__", "").startswith("__editable__")
    ]
    protocol = os.fdopen(os.dup(1), "w")
    os.dup2(2, 1)  # a library's print (or C code's) must not break the protocol
    warnings.filterwarnings("ignore")
    logging.getLogger("torchrl").setLevel(logging.WARNING)
    torch.set_num_threads(1)
    blocks: dict[str, Callable[[], int]] = {}
    for line in sys.stdin:
        request = json.loads(line)
        if "setup" in request:
            name = request["setup"]
            try:
                blocks[name] = WORKLOADS[name](args)
                blocks[name]()  # warm-up block
                answer: dict = {"ok": True}
            except Exception as error:  # an older tree without the benchmark, a missing extra
                answer = {"error": f"{type(error).__name__}: {error}"[:300]}
        else:
            block = blocks[request["run"]]
            cpu, wall = time.process_time(), time.perf_counter()
            units = block()
            answer = {
                "units": units,
                "cpu": time.process_time() - cpu,
                "wall": time.perf_counter() - wall,
            }
        protocol.write(json.dumps(answer) + "\n")
        protocol.flush()


# -- the parent -------------------------------------------------------------------------------


class Worker:
    """A worker process whose packages are ``tree``'s (through ``links``)."""

    def __init__(self, tree: Path, links: Path, argv: Sequence[str]) -> None:
        environment = dict(os.environ)
        environment["PYTHONPATH"] = os.pathsep.join(
            [str(links), *filter(None, [environment.get("PYTHONPATH")])]
        )
        environment.setdefault("OMP_NUM_THREADS", "1")
        self.process = subprocess.Popen(
            [sys.executable, str(Path(__file__).resolve()), "--worker", *argv],
            cwd=tree,
            env=environment,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )

    def ask(self, request: dict) -> dict:
        assert self.process.stdin is not None and self.process.stdout is not None
        self.process.stdin.write(json.dumps(request) + "\n")
        self.process.stdin.flush()
        line = self.process.stdout.readline()
        if not line:
            raise SystemExit(f"a worker ended (exit code {self.process.wait()}): see above")
        return json.loads(line)

    def close(self) -> None:
        if self.process.stdin is not None:
            self.process.stdin.close()
        self.process.wait()


def _worker_argv(args: argparse.Namespace) -> list[str]:
    return [
        f"--seeds={args.seeds}",
        f"--size={args.size}",
        f"--steps={args.steps}",
        f"--calls={args.calls}",
    ]


def compare(args: argparse.Namespace, base_tree: Path, label: str, scratch: Path) -> None:
    trees = {"this": ROOT, "base": base_tree}
    workers = {
        name: Worker(tree, link_packages(tree, scratch / f"links-{name}"), _worker_argv(args))
        for name, tree in trees.items()
    }
    try:
        print(f"this: the working tree {ROOT}\nbase: {label}")
        print(f"{args.rounds} rounds, alternating; ratio = base time / this time (> 1: faster)")
        names = []
        for name in args.only:
            answers = {tree: worker.ask({"setup": name}) for tree, worker in workers.items()}
            failed = {
                tree: answer["error"] for tree, answer in answers.items() if "error" in answer
            }
            if failed:
                for tree, error in failed.items():
                    print(f"{name}: skipped, the {tree} tree cannot run it ({error})")
                continue
            names.append(name)
        times = {
            (name, tree, clock): [] for name in names for tree in trees for clock in ("cpu", "wall")
        }
        for round_index in range(args.rounds):
            order = list(workers.items())
            if round_index % 2:
                order.reverse()
            for name in names:
                for tree, worker in order:
                    answer = worker.ask({"run": name})
                    for clock in ("cpu", "wall"):
                        times[name, tree, clock].append(answer[clock] / answer["units"])
        print(
            "| benchmark | unit | this (CPU) | base (CPU) | ratio, CPU: median [range] "
            "| ratio, wall: median [range] |"
        )
        print("| --- | --- | ---: | ---: | ---: | ---: |")
        for name in names:
            unit, show = UNITS[name]
            cells = []
            for clock in ("cpu", "wall"):
                middle, low, high = speedups(times[name, "this", clock], times[name, "base", clock])
                cells.append(f"{middle:.3f}x [{low:.3f}-{high:.3f}]")
            this = show(statistics.median(times[name, "this", "cpu"]))
            base = show(statistics.median(times[name, "base", "cpu"]))
            print(f"| {name} | {unit} | {this:.3f} | {base:.3f} | {cells[0]} | {cells[1]} |")
    finally:
        for worker in workers.values():
            worker.close()


def main(argv: Sequence[str] | None = None) -> None:
    args = parse_args(argv)
    if args.worker:
        worker(args)
        return
    scratch = Path(tempfile.mkdtemp(prefix="factorq-compare-"))
    try:
        if args.base_dir:
            base_tree = Path(args.base_dir).resolve()
            label = f"the checkout {base_tree}"
        else:
            commit = args.base or default_base()
            base_tree = export_commit(commit, scratch / "base")
            label = describe(commit)
        compare(args, base_tree, label, scratch)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


if __name__ == "__main__":
    main()
