"""What was tried: every public entry point fed bad input, and the one message it answers with.

One table, ``TRIED``: a row per fault with what was tried, the call, the exception and a pattern
its message must match. Messages name the option (as the caller spelled it), the value and what
is allowed. Command-line rows run ``factorq`` in process and pass when it exits 2 with exactly
one error line and no traceback (``CommandFailed``, its message that line); ``{file}``,
``{interrupted}`` and the like in their arguments are made fresh for the row. The per-module tests
check the same errors in context; this table is where the whole surface is seen at once.

Not validated, by design: the pure equations of ``factorq_torch.functional`` (they take tensors
from validated modules; the property tests cover their whole finite input range), and negative
seeds in ``rng.derive_keys`` (a key is defined for any integer; user-facing seeds are checked
where they enter).
"""

# ruff: noqa: E501  (the table below reads best one fault per line)

from __future__ import annotations

import contextlib
import io
import math
import shlex
import warnings
from pathlib import Path

import gymnasium
import pytest
import torch
from tensordict.nn import TensorDictSequential

from factorq_envs import FactoredGridEnv, WorldConfig
from factorq_envs.grid_world import static_layout
from factorq_torch.base import rng
from factorq_torch.base.config import AgentConfig, check_algorithm
from factorq_torch.collectors import OnlineCollector
from factorq_torch.objectives import FactorQLoss, TabularQLoss
from factorq_torch.policy import EpsilonGreedyPolicy, FactorQPolicy
from factorq_torch.tables import LocalRewardTable, TaskQTable
from factorq_trainers import cli, reports
from factorq_trainers.analysis.claims import compute_claims
from factorq_trainers.analysis.stats import t_critical
from factorq_trainers.commands.paper import command as paper
from factorq_trainers.commands.paper.config import PaperConfig
from factorq_trainers.compiled import fast
from factorq_trainers.methods.dqn import DQNConfig
from factorq_trainers.methods.experiment import ExperimentConfig
from factorq_trainers.runner import frame, kept

needs_fast = pytest.mark.skipif(not fast.is_available(), reason="fast backend unavailable")
# Prepended to `factorq paper` and `factorq compare` rows (later options win): should a check ever
# let a bad value through, the row runs a tiny experiment in its own directory, not the default.
SMALL = ["--seeds", "1", "--runs", "1", "--episodes", "1", "--size", "4", "--obstacles", "1"]
SMALL_COMPARE = ["--seeds", "1", "--steps", "1", "--size", "4", "--obstacles", "1"]


def _device_exists(device: str) -> bool:
    try:
        torch.empty(0, device=device)
    except Exception:
        return False
    return True


class CommandFailed(Exception):
    """``factorq`` exited 2 with one error line (the message is that line)."""


# -- things to feed the entry points ---------------------------------------------------------


def a_file(tmp: Path) -> str:
    path = tmp / "a_file.txt"
    path.write_text("not a directory")
    return str(path)


def an_interrupted_run(tmp: Path) -> str:
    """An interrupted ``factorq paper`` run's directory (its ``units/``, no unit finished) of the
    config ``--seeds 3 --size 6 --obstacles 4``."""
    out = tmp / "run"
    config = PaperConfig(seeds=3, size=6, obstacles=4, out=str(out))
    store = kept.UnitStore(out)
    store.start(paper.NAME, frame.plain(config), (unit["id"] for unit in paper.units(config)))
    return str(out)


def a_damaged_run_file(tmp: Path) -> str:
    out = an_interrupted_run(tmp)
    run_file = Path(out) / kept.UNITS_DIRECTORY / kept.RUN_FILE
    run_file.write_text(run_file.read_text()[:50])  # cut short
    return out


def a_finished_run(tmp: Path) -> str:
    out = tmp / "finished"
    out.mkdir()
    (out / "results.json").write_text("{}")
    return str(out)


def bad_json(tmp: Path) -> str:
    out = tmp / "bad"
    out.mkdir()
    (out / "results.json").write_text("{not json")
    return str(out)


_HELD: list[int] = []  # descriptors of locks held by this process for the rows below


def locked(make):
    """``make``'s directory with its output lock held by this process, as a live run holds it
    (``flock`` locks of two opens conflict even within one process)."""

    def made(tmp: Path) -> str:
        import fcntl
        import os

        out = Path(make(tmp))
        out.mkdir(exist_ok=True)
        (out / ".factorq.lock").write_text("4242")
        descriptor = os.open(out / ".factorq.lock", os.O_RDWR)
        fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
        _HELD.append(descriptor)
        return str(out)

    return made


def a_finished_comparison(tmp: Path) -> str:
    out = tmp / "compared"
    out.mkdir()
    (out / "comparison.json").write_text("{}")
    return str(out)


MADE = {
    "{locked}": locked(lambda tmp: str(tmp / "live")),
    "{locked-interrupted}": locked(an_interrupted_run),
    "{finished-comparison}": a_finished_comparison,
    "{under-file}": lambda tmp: a_file(tmp) + "/out",
    "{tmp}": str,
    "{missing}": lambda tmp: str(tmp / "missing"),
    "{file}": a_file,
    "{interrupted}": an_interrupted_run,
    "{damaged-run-file}": a_damaged_run_file,
    "{finished-run}": a_finished_run,
    "{bad-results}": bad_json,
}


def factorq(command: str, pattern: str) -> tuple:
    """A row: run ``factorq COMMAND`` in process, expect ``CommandFailed`` matching ``pattern``."""

    def call(tmp: Path) -> None:
        args = [MADE[arg](tmp) if arg in MADE else arg for arg in shlex.split(command)]
        if args[0] == "paper" and "--resume" not in args:
            args[1:1] = [*SMALL, "--out", str(tmp / "out")]
        if args[0] == "compare":
            args[1:1] = [*SMALL_COMPARE, "--methods", "q-learning", "--out", str(tmp / "out")]
        err, out = io.StringIO(), io.StringIO()
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
            code = cli.main(args)
        lines = err.getvalue().strip().splitlines()
        if code == 2 and len(lines) == 1 and "Traceback" not in err.getvalue():
            raise CommandFailed(lines[0])
        raise AssertionError(f"exit {code}; stderr {err.getvalue()!r}; stdout {out.getvalue()!r}")

    return (f"factorq {command}", call, CommandFailed, pattern)


def env_step(action: int) -> None:
    env = FactoredGridEnv(size=3, num_obstacles=1, batch_size=(1,))
    td = env.reset()
    td["action"] = torch.tensor([action])
    env.step(td)


def gym_make(**options) -> None:
    with warnings.catch_warnings():  # gymnasium warns before the env itself refuses
        warnings.simplefilter("ignore", UserWarning)
        gymnasium.make("FactoredGrid-v0", **options)


def gym_step(action: int) -> None:
    env = gymnasium.make("FactoredGrid-v0", size=3, num_obstacles=0).unwrapped
    env.reset(seed=0)
    env.step(action)


def collector(**options) -> OnlineCollector:
    env = options.pop("env", FactoredGridEnv(size=3, num_obstacles=1, batch_size=(2,)))
    table = TaskQTable(options.pop("tables", 2), num_cells=9, with_sensors=True)
    policy = TensorDictSequential(table, EpsilonGreedyPolicy(table.num_experiments))
    return OnlineCollector(
        env, policy, TabularQLoss(table), **{"runs": 1, "episodes": 1, **options}
    )


def batch(algorithm="factor-q", periods=(0,), world=None, runs=1, keys=1, **options):
    count = len(periods)
    return fast.ExperimentBatch(
        algorithm,
        torch.tensor(periods),
        WorldConfig(size=4, num_obstacles=2) if world is None else world,
        AgentConfig(),
        runs,
        1,
        rng.derive_keys(0, rng.STREAM_WORLD, keys * count),
        rng.derive_keys(0, rng.STREAM_POLICY, count),
        **options,
    )


def nan_table_to(what: str) -> None:
    """Feed a policy or a loss the tables of 2 experiments, experiment 1's holding NaN (task) or
    -inf (local)."""
    env = FactoredGridEnv(size=3, num_obstacles=1, batch_size=(2,))
    factor = what.startswith("factor")
    task = TaskQTable(2, num_cells=9, with_sensors=not factor)
    local = LocalRewardTable(2)
    with torch.no_grad():
        if factor:
            local.rho[1] = -math.inf
        else:
            task.table[1] = math.nan
    td = env.reset()
    if what == "policy":
        TensorDictSequential(task, EpsilonGreedyPolicy(2))(td)
    elif what == "factor-policy":
        TensorDictSequential(task, local, FactorQPolicy(2))(td)
    else:
        from torchrl.envs import TransformedEnv

        from factorq_envs.transforms import SplitLocalReward

        env = TransformedEnv(env, SplitLocalReward()) if factor else env
        td = env.reset()
        td["action"] = torch.zeros(2, dtype=torch.int64)
        td["exploratory"] = torch.zeros(2, dtype=torch.bool)
        td = env.step(td)
        (FactorQLoss(task, local) if factor else TabularQLoss(task))(td)


def resumed_config(tmp: Path, **given) -> None:
    out = an_interrupted_run(tmp)
    saved = kept.UnitStore(out).saved_run(paper.NAME)["config"]
    frame.resumed_config(saved, given, out, PaperConfig)


def fast_row(what: str, call, error: type, pattern: str):
    return pytest.param(what, call, error, pattern, marks=needs_fast, id=what)


# -- the table -------------------------------------------------------------------------------

RANGE = "is out of range: must be"


def env_action(action: int):
    from tensordict import TensorDict

    return TensorDict(action=torch.tensor(action))


def local_step(dependency: torch.Tensor) -> None:
    from tensordict import TensorDict

    LocalRewardTable(1, dependency=dependency)(
        TensorDict(sensors=torch.ones(1, 4, dtype=torch.bool), batch_size=[1])
    )


TRIED = [
    # factorq paper: every option
    factorq("paper --seeds 0", rf"--seeds=0 {RANGE} in \[1, 2147483647\]"),
    factorq("paper --seeds -3", rf"--seeds=-3 {RANGE} in \[1, 2147483647\]"),
    factorq("paper --seeds 2147483648", rf"--seeds=2147483648 {RANGE} in \[1, 2147483647\]"),
    factorq("paper --seeds 2.5", r"argument --seeds: invalid int value: '2.5'"),
    factorq("paper --seed -1", rf"--seed=-1 {RANGE} in \[0, 9223372036854775807\]"),
    factorq("paper --runs -2", rf"--runs=-2 {RANGE} in \[1, 2147483647\]"),
    factorq("paper --runs 1000000000000000000000000000000", rf"--runs=1000000000000000000000000000000 {RANGE} in \[1, 2147483647\]"),
    factorq("paper --episodes 0", rf"--episodes=0 {RANGE} in \[1, 2147483647\]"),
    factorq("paper --episodes 2147483648", rf"--episodes=2147483648 {RANGE} in \[1, 2147483647\]"),
    factorq("paper --episodes ten", r"argument --episodes: invalid int value: 'ten'"),
    factorq("paper --max-steps 0", rf"--max-steps=0 {RANGE} in \[1, 9223372036854775807\]"),
    factorq("paper --max-steps 18446744073709551616", rf"--max-steps=18446744073709551616 {RANGE} in \[1, 9223372036854775807\]"),
    factorq("paper --layout-seed -1", rf"--layout-seed=-1 {RANGE} in \[0, "),
    factorq("paper --size 1", rf"--size=1 {RANGE} in \[2, 1024\]"),
    factorq("paper --size 1000000000000000000000000000000", rf"--size=1000000000000000000000000000000 {RANGE} in \[2, 1024\]"),
    factorq("paper --obstacles -1", rf"--obstacles=-1 {RANGE} in \[0, 13\] for a 4x4 grid"),
    factorq("paper --size 3 --obstacles 7", rf"--obstacles=7 {RANGE} in \[0, 6\] for a 3x3 grid"),
    factorq(
        "paper --size 3 --obstacles 6",
        r"--obstacles=6 leaves no path from start to goal in a static 3x3 world: must be in \[0, 4\]",
    ),
    factorq("paper --epsilon 1.5", rf"--epsilon=1.5 {RANGE} in \[0.0, 1.0\]"),
    factorq("paper --epsilon -0.1", rf"--epsilon=-0.1 {RANGE} in \[0.0, 1.0\]"),
    factorq("paper --epsilon nan", r"argument --epsilon: 'nan' is not a finite number"),
    factorq("paper --gamma 1", rf"--gamma=1.0 {RANGE} in \[0.0, 1.0\)"),
    factorq("paper --gamma -0.5", rf"--gamma=-0.5 {RANGE} in \[0.0, 1.0\)"),
    factorq("paper --alpha 0", rf"--alpha=0.0 {RANGE} in \(0.0, 1.0\]"),
    factorq("paper --alpha 1.5", rf"--alpha=1.5 {RANGE} in \(0.0, 1.0\]"),
    factorq("paper --eta -1", rf"--eta=-1.0 {RANGE} in \[0.0, 1000000.0\]"),
    factorq("paper --g-min 0", rf"--g-min=0.0 {RANGE} in \(0.0, 1000000.0\]"),
    factorq("paper --g-min inf", r"argument --g-min: 'inf' is not a finite number"),
    factorq("paper --threads 0", rf"--threads=0 {RANGE} in \[1, 256\]"),
    factorq("paper --threads 100000", rf"--threads=100000 {RANGE} in \[1, 256\]"),
    factorq("paper --regimes static,windy", r"--regimes: 'windy' is unknown: choose from static, "),
    factorq("paper --regimes static --regimes static", r"--regimes: static given more than once"),
    factorq("paper --regimes ''", r"--regimes: '' is unknown: choose from static, semi-dynamic"),
    factorq("paper --methods sarsa", r"--methods: 'sarsa' is unknown: choose from q-learn"),
    factorq("paper --backend gpu", r"argument --backend: invalid choice: 'gpu'"),
    factorq("paper --body walker", r"--body='walker' is unknown: choose one of translate, heading"),
    factorq("paper --sensors eyes", r"--sensors='eyes' is unknown: choose one of cross, ring"),
    factorq("paper --distractors -1", rf"--distractors=-1 {RANGE} in \[0, 32\]"),
    factorq("paper --sensor-permutation -1", rf"--sensor-permutation=-1 {RANGE} in \[0, 9223372036854775807\]"),
    factorq("paper --sensor-permutation 100000000000000000000000000", rf"--sensor-permutation=100000000000000000000000000 {RANGE} in \[0, 9223372036854775807\]"),
    factorq("paper --sensor-noise 1.5", rf"--sensor-noise=1.5 {RANGE} in \[0.0, 1.0\]"),
    factorq("paper --sensors ring --distractors 20", r"q-learning: a Q-table of 16 cells x 1 headings x 2\*\*28 sensor patterns x 4 actions needs 17179869184 values per experiment, past the cap of 16777216"),
    factorq("paper --actuator-noise -0.1", rf"--actuator-noise=-0.1 {RANGE} in \[0.0, 1.0\]"),
    factorq("paper --device toaster", r"--device='toaster' is not a torch device \(e.g. cpu, "),
    factorq("paper --device meta", r"--device='meta' holds no data \(meta tensors have shapes only\): use cpu"),
    *[factorq(f"paper --device {device}", rf"--device='{device}' is not available on this machine \(.+\): use --device='cpu'") for device in ("cuda", "cuda:1", "mps") if not _device_exists(device)],
    factorq(
        "paper --backend fast --device cuda",
        r"--device='cuda' is not supported by backend 'fast' \(cpu\)",
    ),
    factorq("paper --out {file}", r"--out='.*a_file.txt' is an existing file: give a directory"),
    factorq("paper --sides 4", r"unrecognized arguments: --sides 4"),
    # factorq paper: one writer per --out, checked before any work (factorq_trainers.runner.outdir)
    factorq("paper --out {finished-run}", r"--out='.*finished' already holds results.json from an earlier run: pass --force to replace them, or choose another --out"),
    factorq("paper --backend modular --threads 2 --out {finished-run}", r"--out='.*finished' already holds results.json"),  # (its processes' notice waits for the run)
    factorq("paper --force --seeds 0", rf"--seeds=0 {RANGE} in \[1, 2147483647\]"),
    factorq("paper --out {locked}", r"--out='.*live' is in use by another factorq run \(pid 4242\): wait for it to finish, or choose another --out \(refusing to write to it at the same time\)"),
    factorq("paper --resume {locked-interrupted}", r"--out='.*run' is in use by another factorq run \(pid 4242\): .* \(refusing to resume it at the same time\)"),
    factorq("paper --out {under-file}", r"--out='.*a_file.txt/out' is not writable: Not a directory"),
    factorq("paper --out /proc/factorq-out", r"--out='/proc/factorq-out' is not writable: "),
    # factorq paper: shards and clusters (factorq_trainers.runner.frame, factorq_trainers.runner.cluster)
    factorq("paper --first-seed -1", rf"--first-seed=-1 {RANGE} in \[0, 2147483647\]"),
    factorq("paper --first-seed 2147483648", rf"--first-seed=2147483648 {RANGE} in \[0, 2147483647\]"),
    factorq("paper --shard-seeds 0", rf"--shard-seeds=0 {RANGE} in \[1, 2147483647\]"),
    factorq("paper --cluster local:100000", r"--cluster='local:100000' is out of range: at most local:256 workers"),
    factorq("paper --cluster remote", r"--cluster='remote' is not local, local:N with N >= 1 or off"),
    factorq("paper --scheduler host:8786", r"--scheduler='host:8786' is not an address like tcp://"),
    factorq("paper --connect-timeout 0", r"--connect-timeout=0.0 is out of range: must be in \(0, 86400\] seconds"),
    factorq("paper --worker-timeout 0", r"--worker-timeout=0.0 is out of range: must be in \(0, 86400\] seconds"),
    factorq("paper --scheduler evil://x", r"--scheduler='evil://x' is not a Dask scheduler address like tcp://host:8786 \(unknown address scheme 'evil'"),
    factorq("paper --scheduler tcp://127.0.0.1:9 --connect-timeout 0.5", r"scheduler tcp://127.0.0.1:9 refused the connection \d+ times in"),
    # factorq paper: resuming an interrupted run from its kept units (factorq_trainers.runner.kept)
    factorq(
        "paper --out {interrupted}",
        r"--out='.*run' holds the units of an interrupted run \(units/\): continue it with "
        r"--resume .*run, or pass --force to start over",
    ),
    factorq(
        "paper --resume {missing}",
        r"missing/units/run.json does not exist: nothing to resume: run `factorq paper` without "
        r"--resume",
    ),
    factorq("paper --resume {file}", r"a_file.txt/units/run.json does not exist: nothing to resume"),
    factorq("paper --resume {finished-run}", r"finished/units/run.json does not exist: nothing to"),
    factorq(
        "paper --resume {interrupted} --seeds 5 --regimes static",
        r"--resume='.*run' holds a run of a different config: --seeds=5 given, 3 kept; "
        r"--regimes=\['static'\] given, \['static', 'semi-dynamic', 'dynamic'\] kept \(leave these "
        r"options out to resume it, or start a new run with another --out\)",
    ),
    factorq(
        "paper --resume {interrupted} --shard-seeds 2",
        r"--shard-seeds=2 given, 100 kept",  # other units: refused, not mixed
    ),
    factorq("paper --resume {interrupted} --out {missing}", r"differs from the resumed directory"),
    factorq("paper --resume {damaged-run-file}", r"run file .*run.json .*: start the run over with --force"),
    # factorq compare: every option
    factorq("compare --seed -1", rf"--seed=-1 {RANGE} in \[0, 9223372036854775807\]"),
    factorq("compare --seeds 0", rf"--seeds=0 {RANGE} in \[1, 2147483647\]"),
    factorq("compare --seeds 2147483648", rf"--seeds=2147483648 {RANGE} in \[1, 2147483647\]"),
    factorq("compare --seeds 1.5", r"argument --seeds: invalid int value: '1.5'"),
    factorq("compare --steps 0", rf"--steps=0 {RANGE} in \[1, 2147483647\]"),
    factorq("compare --steps 18446744073709551616", rf"--steps=18446744073709551616 {RANGE} in \[1, 2147483647\]"),
    factorq("compare --regimes windy", r"--regimes: 'windy' is unknown: choose from static, "),
    factorq("compare --methods sarsa", r"--methods: 'sarsa' is unknown: choose from factor-q, "),
    factorq("compare --out ''", r"--out='' must be a directory path"),
    factorq("compare --logger wandb", r"argument --logger: invalid choice: 'wandb'"),
    factorq("compare --size 1", rf"--size=1 {RANGE} in \[2, 1024\]"),
    factorq("compare --size 1025", rf"--size=1025 {RANGE} in \[2, 1024\]"),
    factorq("compare --obstacles 99", rf"--obstacles=99 {RANGE} in \[0, 13\] for a 4x4 grid"),
    factorq("compare --size 3 --obstacles 6", r"--obstacles=6 leaves no path from start to goal"),
    factorq("compare --max-steps 0", rf"--max-steps=0 {RANGE} in \[1, 9223372036854775807\]"),
    factorq("compare --max-steps 9223372036854775808", rf"--max-steps=9223372036854775808 {RANGE} in \[1, 9223372036854775807\]"),
    factorq("compare --layout-seed -1", rf"--layout-seed=-1 {RANGE} in \[0, "),
    factorq("compare --threads 0", rf"--threads=0 {RANGE} in \[1, 256\]"),
    factorq("compare --threads 20000", rf"--threads=20000 {RANGE} in \[1, 256\]"),
    factorq("compare --body walker", r"--body='walker' is unknown: choose one of translate, heading"),
    factorq("compare --sensors eyes", r"--sensors='eyes' is unknown: choose one of cross, ring"),
    factorq("compare --distractors 33", rf"--distractors=33 {RANGE} in \[0, 32\]"),
    factorq("compare --sensor-permutation -1", rf"--sensor-permutation=-1 {RANGE} in \[0, 9223372036854775807\]"),
    factorq("compare --sensor-permutation 9223372036854775808", rf"--sensor-permutation=9223372036854775808 {RANGE} in \[0, 9223372036854775807\]"),
    factorq("compare --sensor-noise 1.5", rf"--sensor-noise=1.5 {RANGE} in \[0.0, 1.0\]"),
    factorq("compare --actuator-noise -0.1", rf"--actuator-noise=-0.1 {RANGE} in \[0.0, 1.0\]"),
    factorq("compare --sensors ring --distractors 20", r"q-learning: a Q-table of 16 cells x 1 headings x 2\*\*28 sensor patterns x 4 actions needs"),
    factorq("compare --cluster remote", r"--cluster='remote' is not local, local:N with N >= 1 or off"),
    factorq("compare --scheduler host:8786", r"--scheduler='host:8786' is not an address like tcp://"),
    factorq("compare --connect-timeout 0", r"--connect-timeout=0.0 is out of range: must be in \(0, 86400\] seconds"),
    factorq("compare --worker-timeout 1e9", r"--worker-timeout=1000000000.0 is out of range: must be in \(0, 86400\] seconds"),
    factorq("compare --out {finished-comparison}", r"--out='.*compared' already holds comparison.json from an earlier run: pass --force"),
    factorq("compare --force --seeds 0", rf"--seeds=0 {RANGE} in \[1, 2147483647\]"),
    factorq("compare --out {locked}", r"--out='.*live' is in use by another factorq run \(pid 4242\)"),
    factorq("compare --out /proc/factorq-out", r"--out='/proc/factorq-out' is not writable: "),
    factorq("compare --resume {missing}", r"missing/units/run.json does not exist: nothing to resume: run `factorq compare` without --resume"),
    factorq("compare --resume {finished-run}", r"units/run.json does not exist: nothing to resume"),
    factorq("compare --sides 4", r"factorq compare: error: unrecognized arguments: --sides 4"),
    # factorq report, factorq
    factorq("report {tmp}", r"holds no results file of a factorq command \(.*results\.json.*\)"),
    factorq("report {bad-results}", r"results.json is not valid JSON"),
    factorq("train", r"argument COMMAND: invalid choice: 'train'"),
    # trainers: the API under the commands
    ("PaperConfig(seeds=2.5)", lambda _: PaperConfig(seeds=2.5), TypeError, r"seeds must be an int, got 2.5 \(float\)"),
    ("PaperConfig(runs=True)", lambda _: PaperConfig(runs=True), TypeError, r"runs must be an int, got True \(bool\)"),
    ("PaperConfig(regimes=())", lambda _: PaperConfig(regimes=()), ValueError, r"regimes is empty: choose one or more of static"),
    ("PaperConfig(out='')", lambda _: PaperConfig(out=""), ValueError, r"out='' must be a directory path"),
    ("PaperConfig(device='meta')", lambda _: PaperConfig(device="meta"), ValueError, r"device='meta' holds no data"),
    ("DQNConfig(buffer_size=2**31)", lambda _: DQNConfig(buffer_size=2**31), ValueError, rf"buffer_size=2147483648 {RANGE} in \[1, 2147483647\]"),
    ("DQNConfig(hidden=(10**6,))", lambda _: DQNConfig(hidden=(10**6,)), ValueError, rf"hidden width=1000000 {RANGE} in \[1, 65536\]"),
    ("ExperimentConfig(steps=2**31)", lambda _: ExperimentConfig(steps=2**31), ValueError, rf"steps=2147483648 {RANGE} in \[1, 2147483647\]"),
    ("config_from_dict(unknown field)", lambda _: frame.config_from_dict(PaperConfig, {"seedz": 1}), TypeError, r"unexpected keyword argument 'seedz'"),
    ("resumed_config(other config)", lambda tmp: resumed_config(tmp, seeds=5), ValueError, r"resume='.*run' holds a run of a different config: seeds=5 given, 3 kept"),
    ("reports.regenerate(missing dir)", lambda tmp: reports.regenerate(tmp / "none"), FileNotFoundError, r"none holds no results file of a factorq command"),
    ("t_critical(0)", lambda _: t_critical(0), ValueError, r"df=0 must be >= 1"),
    ("compute_claims(seed counts differ)", lambda _: compute_claims({"a": {"per_seed": {"total_steps": [1]}}, "b": {"per_seed": {"total_steps": [1, 2]}}}), ValueError, r"cells have different numbers of seeds: \[1, 2\]"),
    # envs
    ("WorldConfig(size=1)", lambda _: WorldConfig(size=1), ValueError, rf"size=1 {RANGE} >= 2"),
    ("WorldConfig(size=3.0)", lambda _: WorldConfig(size=3.0), TypeError, r"size must be an int, got 3.0 \(float\)"),
    ("WorldConfig(num_obstacles=98)", lambda _: WorldConfig(num_obstacles=98), ValueError, rf"num_obstacles=98 {RANGE} in \[0, 97\] for a 10x10 grid with start, goal and agent kept free"),
    ("WorldConfig(obstacle_period=-1)", lambda _: WorldConfig(obstacle_period=-1), ValueError, rf"obstacle_period=-1 {RANGE} >= 0 \(0 static, k > 0 moving\)"),
    ("WorldConfig(max_steps=0)", lambda _: WorldConfig(max_steps=0), ValueError, rf"max_steps=0 {RANGE} >= 1"),
    ("WorldConfig(layout_seed=-1)", lambda _: WorldConfig(layout_seed=-1), ValueError, rf"layout_seed=-1 {RANGE} >= 0"),
    ("static_layout(no path)", lambda _: static_layout(WorldConfig(size=3, num_obstacles=6)), ValueError, r"num_obstacles=6 leaves no path from start to goal in a static 3x3 world: must be in \[0, 4\]"),
    ("FactoredGridEnv(batch_size=(0,))", lambda _: FactoredGridEnv(batch_size=(0,)), ValueError, rf"batch_size=\(0,\) {RANGE.replace('must be', 'every dimension must be')} >= 1"),
    ("FactoredGridEnv(periods of another batch)", lambda _: FactoredGridEnv(batch_size=(3,), obstacle_period=[0, 1]), ValueError, r"obstacle_period has 2 entries: a sequence must hold one period per world, 3 for this"),
    ("FactoredGridEnv(obstacle_period=-1)", lambda _: FactoredGridEnv(obstacle_period=-1), ValueError, rf"obstacle_period=-1 {RANGE} >= 0"),
    ("FactoredGridEnv(seed=-1)", lambda _: FactoredGridEnv(seed=-1), ValueError, rf"seed=-1 {RANGE} in \[0, {2**63 - 1}\]"),
    ("FactoredGridEnv(seed='a')", lambda _: FactoredGridEnv(seed="a"), TypeError, r"seed must be an int or None, got 'a' \(str\)"),
    ("FactoredGridEnv.set_seed(-1)", lambda _: FactoredGridEnv().set_seed(-1), ValueError, rf"seed=-1 {RANGE} in \[0, {2**63 - 1}\]"),
    ("FactoredGridEnv(experiment_offset=-1)", lambda _: FactoredGridEnv(experiment_offset=-1), ValueError, rf"experiment_offset=-1 {RANGE} >= 0"),
    ("FactoredGridEnv(body='walker')", lambda _: FactoredGridEnv(body="walker"), ValueError, r"body='walker' is unknown: choose one of translate, heading"),
    ("FactoredGridEnv(sensors='eyes')", lambda _: FactoredGridEnv(sensors="eyes"), ValueError, r"sensors='eyes' is unknown: choose one of cross, ring"),
    ("FactoredGridEnv(num_distractors=33)", lambda _: FactoredGridEnv(num_distractors=33), ValueError, rf"num_distractors=33 {RANGE} in \[0, 32\]"),
    ("FactoredGridEnv(sensor_permutation=(0, 0, 1, 2))", lambda _: FactoredGridEnv(sensor_permutation=(0, 0, 1, 2)), ValueError, r"sensor_permutation=\(0, 0, 1, 2\) is not a permutation: must hold each of 0..3 once \(4 sensors\)"),
    ("FactoredGridEnv(sensor_permutation='0123')", lambda _: FactoredGridEnv(sensor_permutation="0123"), TypeError, r"sensor_permutation must be None, an int seed or a sequence of ints, got '0123' \(str\)"),
    ("FactoredGridEnv(sensor_noise=nan)", lambda _: FactoredGridEnv(sensor_noise=math.nan), ValueError, rf"sensor_noise=nan {RANGE} in \[0.0, 1.0\]"),
    ("FactoredGridEnv(actuator_noise=2)", lambda _: FactoredGridEnv(actuator_noise=2), ValueError, rf"actuator_noise=2 {RANGE} in \[0.0, 1.0\]"),
    ("FactoredGridEnv(actuator_noise='a')", lambda _: FactoredGridEnv(actuator_noise="a"), TypeError, r"actuator_noise must be a number, got 'a' \(str\)"),
    ("FactoredGridEnv(body=heading).step(action=3)", lambda _: FactoredGridEnv(body="heading").step(env_action(3)), ValueError, rf"action=3 {RANGE} in \[0, 2\] \(0 forward, 1 turn-left, 2 turn-right\)"),
    ("LocalRewardTable(dependency=int)", lambda _: LocalRewardTable(1, dependency=torch.eye(4, dtype=torch.int64)), TypeError, r"dependency must be a bool tensor \[actuators, sensors\], got torch.int64"),
    ("LocalRewardTable(dependency=[4])", lambda _: LocalRewardTable(1, dependency=torch.ones(4, dtype=torch.bool)), ValueError, r"dependency has shape \[4\]: must be \[actuators, sensors\]"),
    ("LocalRewardTable(dependency of 17 parents)", lambda _: LocalRewardTable(1, dependency=torch.ones(1, 17, dtype=torch.bool)), ValueError, r"dependency gives an actuator 17 parent sensors: at most 16"),
    ("LocalRewardTable(dependency naming a missing sensor)", lambda _: local_step(torch.ones(4, 5, dtype=torch.bool)), ValueError, r"'sensors' has shape \[1, 4\] and dtype torch.bool, expected shape \[1, 5\]"),
    ("TaskQTable(2**24 states)", lambda _: TaskQTable(1, 100, with_sensors=True, num_sensors=20), ValueError, r"TaskQTable: a Q-table of 100 cells x 1 headings x 2\*\*20 sensor patterns x 4 actions needs 419430400 values per experiment, past the cap of 16777216"),
    ("FactoredGridEnv(device='toaster')", lambda _: FactoredGridEnv(device="toaster"), ValueError, r"device='toaster' is not a torch device"),
    ("FactoredGridEnv.step(action=7)", lambda _: env_step(7), ValueError, rf"action=7 {RANGE} in \[0, 3\] \(0 north, 1 west, 2 south, 3 east\)"),
    ("FactoredGridEnv.step(action=-1)", lambda _: env_step(-1), ValueError, rf"action=-1 {RANGE} in \[0, 3\]"),
    ("gymnasium.make(size=0)", lambda _: gym_make(size=0), ValueError, rf"size=0 {RANGE} >= 2"),
    ("gymnasium.make(render_mode='rgb')", lambda _: gym_make(render_mode="rgb"), ValueError, r"render_mode='rgb' is not supported: must be None or one of \['ansi', 'rgb_array'\]"),
    ("gymnasium env.step(7)", lambda _: gym_step(7), ValueError, rf"action=7 {RANGE} in \[0, 3\]"),
    # factorq_torch: config, tables, policies, losses, collector, streams
    ("AgentConfig(epsilon=1.5)", lambda _: AgentConfig(epsilon=1.5), ValueError, rf"epsilon=1.5 {RANGE} in \[0.0, 1.0\]"),
    ("AgentConfig(epsilon='high')", lambda _: AgentConfig(epsilon="high"), TypeError, r"epsilon must be a number, got 'high' \(str\)"),
    ("AgentConfig(gamma=1.0)", lambda _: AgentConfig(gamma=1.0), ValueError, rf"gamma=1.0 {RANGE} in \[0.0, 1.0\)"),
    ("AgentConfig(gamma=nan)", lambda _: AgentConfig(gamma=math.nan), ValueError, rf"gamma=nan {RANGE} in \[0.0, 1.0\)"),
    ("AgentConfig(alpha=0)", lambda _: AgentConfig(alpha=0.0), ValueError, rf"alpha=0.0 {RANGE} in \(0.0, 1.0\]"),
    ("AgentConfig(eta=-1)", lambda _: AgentConfig(eta=-1.0), ValueError, rf"eta=-1.0 {RANGE} in \[0.0, 1000000.0\]"),
    ("AgentConfig(g_min=0)", lambda _: AgentConfig(g_min=0.0), ValueError, rf"g_min=0.0 {RANGE} in \(0.0, 1000000.0\]"),
    ("check_algorithm('sarsa')", lambda _: check_algorithm("sarsa"), ValueError, r"algorithm='sarsa' is unknown: choose one of q-learning, factor-q"),
    ("TaskQTable(0, 4)", lambda _: TaskQTable(0, 4), ValueError, rf"num_experiments=0 {RANGE} >= 1"),
    ("TaskQTable(1, num_cells=0)", lambda _: TaskQTable(1, 0), ValueError, rf"num_cells=0 {RANGE} >= 1"),
    ("LocalRewardTable(-1)", lambda _: LocalRewardTable(-1), ValueError, rf"num_experiments=-1 {RANGE} >= 1"),
    ("EpsilonGreedyPolicy(epsilon=2)", lambda _: EpsilonGreedyPolicy(1, epsilon=2.0), ValueError, rf"epsilon=2.0 {RANGE} in \[0.0, 1.0\]"),
    ("EpsilonGreedyPolicy(seed=-1)", lambda _: EpsilonGreedyPolicy(1, seed=-1), ValueError, rf"seed=-1 {RANGE} >= 0"),
    ("EpsilonGreedyPolicy(offset=-2)", lambda _: EpsilonGreedyPolicy(1, offset=-2), ValueError, rf"offset=-2 {RANGE} >= 0"),
    ("EpsilonGreedyPolicy(keys of another S)", lambda _: EpsilonGreedyPolicy(2, keys=torch.zeros(3, dtype=torch.int64)), ValueError, r"keys has shape \[3\], expected \[2\] \(one stream key per experiment\)"),
    ("FactorQPolicy(g_min=0)", lambda _: FactorQPolicy(1, g_min=0.0), ValueError, rf"g_min=0.0 {RANGE} in \(0.0, "),
    ("EpsilonGreedyPolicy(NaN table)", lambda _: nan_table_to("policy"), ValueError, r"EpsilonGreedyPolicy: 'action_value' holds NaN or infinite values \(experiment 1 first\): a table or network diverged"),
    ("FactorQPolicy(infinite local table)", lambda _: nan_table_to("factor-policy"), ValueError, r"FactorQPolicy: 'local_value' holds NaN or infinite values \(experiment 1 first\)"),
    ("TabularQLoss(NaN table)", lambda _: nan_table_to("loss"), ValueError, r"TaskQTable \(read by the loss\): 'action_value' holds NaN or infinite values \(experiment 1 first\)"),
    ("FactorQLoss(infinite local table)", lambda _: nan_table_to("factor-loss"), ValueError, r"LocalRewardTable \(read by the loss\): 'local_value' holds NaN or infinite values"),
    ("TabularQLoss(gamma=1)", lambda _: TabularQLoss(TaskQTable(1, 4), gamma=1.0), ValueError, rf"gamma=1.0 {RANGE} in \[0.0, 1.0\)"),
    ("TabularQLoss(reduction='max')", lambda _: TabularQLoss(TaskQTable(1, 4), reduction="max"), ValueError, r"reduction='max' is unknown: choose one of \('sum', 'mean'\)"),
    ("TabularQLoss('table')", lambda _: TabularQLoss("table"), TypeError, r"task_value_network must be a TensorDict module .* got str"),
    ("FactorQLoss(local='table')", lambda _: FactorQLoss(TaskQTable(1, 4), "table"), TypeError, r"local_value_network must be a TensorDict module .* got str"),
    ("FactorQLoss(eta=-1)", lambda _: FactorQLoss(TaskQTable(1, 4), LocalRewardTable(1), eta=-1.0), ValueError, rf"eta=-1.0 {RANGE} in \[0.0, "),
    ("OnlineCollector(runs=0)", lambda _: collector(runs=0), ValueError, rf"runs=0 {RANGE} >= 1"),
    ("OnlineCollector(episodes=2.5)", lambda _: collector(episodes=2.5), TypeError, r"episodes must be an int, got 2.5"),
    ("OnlineCollector(env='env')", lambda _: collector(env="env"), TypeError, r"env must be a torchrl env \(EnvBase\), got str"),
    ("OnlineCollector(tables of another S)", lambda _: collector(tables=3), ValueError, r"env has batch_size \[2\] but TaskQTable holds S=3 experiments"),
    ("derive_keys(count=-1)", lambda _: rng.derive_keys(0, rng.STREAM_WORLD, -1), ValueError, rf"count=-1 {RANGE} >= 0"),
    ("probability_threshold(1.5)", lambda _: rng.probability_threshold(1.5), ValueError, rf"probability=1.5 {RANGE} in \[0, 1\]"),
    # factorq_trainers.compiled.fast
    fast_row("ExperimentBatch('sarsa')", lambda _: batch("sarsa"), ValueError, r"algorithm='sarsa' is unknown: choose one of q-learning, factor-q, random-walk"),
    fast_row("ExperimentBatch(runs=0)", lambda _: batch(runs=0), ValueError, rf"runs=0 {RANGE} >= 1"),
    fast_row("ExperimentBatch(threads=0)", lambda _: batch(threads=0), ValueError, rf"threads=0 {RANGE} >= 1"),
    fast_row("ExperimentBatch(periods=[-1])", lambda _: batch(periods=(-1,)), ValueError, r"periods must be >= 0 \(0 static, k > 0 moving\), got -1"),
    fast_row("ExperimentBatch(keys of another S)", lambda _: batch(keys=2), ValueError, r"world_keys has 2 entries but periods has 1"),
    fast_row("ExperimentBatch(world=dict)", lambda _: batch(world={"size": 4}), TypeError, r"world must be a WorldConfig, got dict"),
    fast_row("ExperimentBatch.advance(-1)", lambda _: batch().advance(-1), ValueError, rf"max_steps=-1 {RANGE} in \[0, 9223372036854775807\]"),
    fast_row("ExperimentBatch.load_state_dict(other)", lambda _: batch(periods=(0, 1)).load_state_dict(batch(periods=(1, 0)).state_dict()), ValueError, r"state\['periods'\] belongs to a different batch"),
]  # fmt: skip


def _what(row) -> str:
    return row.values[0] if hasattr(row, "values") else row[0]


@pytest.mark.parametrize(("what", "call", "error", "pattern"), TRIED, ids=map(_what, TRIED))
def test_bad_input_is_refused_with_one_message_naming_option_value_and_range(
    what, call, error, pattern, tmp_path
):
    with pytest.raises(error, match=pattern) as raised:
        call(tmp_path)
    assert "\n" not in str(raised.value), what
    assert not (tmp_path / "out").exists(), f"{what}: a run started despite the bad input"


@pytest.mark.parametrize("command", ["paper", "compare"])
def test_the_table_tries_every_option_of_factorq_paper_and_compare(command):
    tried = " ".join(what for what in map(_what, TRIED) if what.startswith(f"factorq {command}"))
    parser = cli.build_parser()
    commands = next(action for action in parser._actions if action.dest == "command")
    for action in commands.choices[command]._actions:
        for option in action.option_strings:
            if option.startswith("--") and option != "--help":
                assert option in tried, f"{option} has no row in the table"


@pytest.mark.parametrize(
    "bad, first",
    [
        (None, None),  # finite, but the sum overflows: the entry-by-entry check clears it
        (float("nan"), 2),
        (float("inf"), 1),
        (-float("inf"), 0),
    ],
)
def test_check_finite_decides_by_the_sum_and_falls_back_to_every_entry(bad, first):
    from factorq_torch.base.validation import check_finite

    largest = torch.finfo(torch.float32).max
    values = torch.full((3, 4), largest)  # every entry finite, the sum +inf
    if bad is not None:
        values = torch.zeros(3, 4)
        values[first, 1] = bad
        values[first + 1 :, 3] = bad
    if bad is None:
        assert check_finite("owner", "'key'", values) is values
        return
    with pytest.raises(
        ValueError, match=rf"owner: 'key' holds NaN .* \(experiment {first} first\)"
    ):
        check_finite("owner", "'key'", values)
