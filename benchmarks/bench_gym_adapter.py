"""The Gymnasium adapter's cost per env step over the env it wraps (issue 25: target < 1 ms at
S = 8).

Four paths step ``S`` copies of the same env with random actions, resetting finished envs by
mask (Gymnasium's vector envs with ``autoreset_mode=DISABLED``, as torchrl drives them):

- ``raw``: Gymnasium's ``SyncVectorEnv`` of the bare env;
- ``adapter``: the same vector env of ``FactorQEnv`` (the declaration's functions included:
  they are the adapter's work);
- ``torchrl raw``: torchrl's ``GymWrapper`` over the raw vector env (what torchrl itself costs);
- ``torchrl adapter``: ``declared_torchrl_env`` (GymWrapper over the adapters plus the dtype
  cast), stepped as a collector does (``step``, ``step_mdp``, partial reset).

Figures are milliseconds per env step (a batched step's time divided by ``S``) and the overhead of
each path over ``raw``. The default world is MiniGrid's Dynamic-Obstacles 8x8 (a fast env, so
the overhead is visible); ``--world highway`` needs the extra. Run from the repository root:

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_gym_adapter.py
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_gym_adapter.py --envs 8 --seconds 3

Not a package on purpose (the torchrl wheel installs a top-level ``benchmarks``).
"""

from __future__ import annotations

import argparse
import time
from functools import partial

import gymnasium
import numpy as np
import torch


def _minigrid(seed: int, adapted: bool):
    from factorq_envs.minigrid_adapter import env_id, make_minigrid, require_minigrid

    require_minigrid()
    if adapted:
        return make_minigrid(8, seed=seed)
    return gymnasium.make(env_id(8), disable_env_checker=True)


def _highway(seed: int, adapted: bool):
    from factorq_envs.highway import ENV_ID, make_highway, require_highway

    require_highway()
    if adapted:
        return make_highway(seed=seed)
    return gymnasium.make(ENV_ID, disable_env_checker=True)


WORLDS = {"minigrid": _minigrid, "highway": _highway}


def _vector(make, count: int, adapted: bool):
    return gymnasium.vector.SyncVectorEnv(
        [partial(make, seed, adapted) for seed in range(count)],
        autoreset_mode=gymnasium.vector.AutoresetMode.DISABLED,
    )


def time_gymnasium(vector, seconds: float) -> float:
    """Seconds per batched step of a Gymnasium vector env, finished envs reset by mask."""
    rng = np.random.default_rng(0)
    vector.reset(seed=0)
    actions = vector.action_space.n if hasattr(vector.action_space, "n") else None
    count = vector.num_envs
    high = actions or int(vector.single_action_space.n)
    steps, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        _, _, terminated, truncated, _ = vector.step(rng.integers(0, high, count))
        done = terminated | truncated
        if done.any():
            vector.reset(options={"reset_mask": done})
        steps += 1
    return (time.perf_counter() - start) / steps


def time_torchrl(env, seconds: float) -> float:
    """Seconds per batched step of a torchrl env: step, step_mdp, partial reset."""
    generator = torch.Generator().manual_seed(0)
    count = env.batch_size[0]
    high = int(env.action_spec.space.n)
    td = env.reset()
    steps, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        td["action"] = torch.randint(0, high, (count,), generator=generator)
        td = env.step_mdp(env.step(td))
        done = td.get("done")
        if bool(done.any()):
            td.set("_reset", done)
            td = env.reset(td)
        steps += 1
    return (time.perf_counter() - start) / steps


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", choices=tuple(WORLDS), default="minigrid")
    parser.add_argument("--envs", type=int, default=8, help="S, the envs stepped together")
    parser.add_argument("--seconds", type=float, default=3.0, help="time per path")
    args = parser.parse_args(argv)
    from torchrl.envs import GymWrapper

    from factorq_envs.declared_env import declared_torchrl_env

    torch.set_num_threads(1)
    make, count = WORLDS[args.world], args.envs
    figures = {
        "raw": time_gymnasium(_vector(make, count, False), args.seconds),
        "adapter": time_gymnasium(_vector(make, count, True), args.seconds),
        "torchrl raw": time_torchrl(
            GymWrapper(
                _vector(partial(_readable, make), count, False), categorical_action_encoding=True
            ),
            args.seconds,
        ),
        "torchrl adapter": time_torchrl(
            declared_torchrl_env(partial(_seeded, make), list(range(count)), exclude=_text(args)),
            args.seconds,
        ),
    }
    raw = figures["raw"] / count
    print(f"{args.world}, S = {count}: ms per env step (batched step / S), overhead over raw")
    print(f"{'path':<16} {'ms/step':>8} {'overhead ms':>12}")
    for name, seconds in figures.items():
        per_step = seconds / count
        print(f"{name:<16} {1e3 * per_step:8.3f} {1e3 * (per_step - raw):12.3f}")


def _readable(make, seed: int, adapted: bool):
    """The raw env as torchrl can read it: MiniGrid's mission (a ``MissionSpace``) left out."""
    env = make(seed, adapted)
    if isinstance(env.observation_space, gymnasium.spaces.Dict):
        kept = [k for k, space in env.observation_space.items() if k != "mission"]
        env = gymnasium.wrappers.FilterObservation(env, kept)
    return env


def _seeded(make, seed: int):
    return make(seed, True)


def _text(args) -> list[str]:
    return ["mission"] if args.world == "minigrid" else []


if __name__ == "__main__":
    main()
