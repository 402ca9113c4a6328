"""Which sensors decide each highway action's crash? The structure learner on a random policy's
transitions, against the oracle written in ``factorq_envs.highway.ORACLE``.

A uniformly random policy drives ``highway-fast-v0`` through the adapter for ``--steps`` env
steps (the env's own episodes, reset on a crash or the time limit). Every transition (the six
time-to-collision sensors read before acting, the action, its crash) is counted by
``StructureLearner(prediction="committed")``, the learner the ``factor-q-learned`` method of
``factorq gym`` uses. Printed per action: its firings and crashes, the learner's committed parents
(or "open") beside the oracle's, and its crash rate with each sensor on and off; then, for each
action whose learned parents differ from the oracle's, the crash rate per pattern of the union of
both parent sets and of the sensor whose reading "on" is the most dangerous (what tells them
apart). ``--json`` writes the same as data.

    .venv/bin/python benchmarks/highway_structure.py --steps 2000 --seed 0

The numbers in docs/decisions.md ("Factor-Q on any Gymnasium env") came from this script. It needs
the ``highway`` extra; it is a measurement, not a test.
"""

from __future__ import annotations

import argparse
import itertools
import json
import time
from typing import Any

import numpy as np


def collect(steps: int, seed: int) -> dict[str, np.ndarray]:
    """``steps`` random-policy transitions: sensors before acting ``[N, K]`` bool, actions
    ``[N]``, crashes ``[N]`` bool."""
    from factorq_envs import highway

    env = highway.make_highway(seed=seed)
    generator = np.random.default_rng(seed)
    observation, _ = env.reset()
    sensors, actions, crashes = [], [], []
    for _ in range(steps):
        action = int(generator.integers(env.action_space.n))
        before = np.asarray(observation["sensors"], dtype=bool)
        observation, _, terminated, truncated, info = env.step(action)
        sensors.append(before)
        actions.append(action)
        crashes.append(bool(info["crashed"]))
        if terminated or truncated:
            observation, _ = env.reset()
    env.close()
    return {
        "sensors": np.stack(sensors),
        "actions": np.asarray(actions),
        "crashes": np.asarray(crashes),
    }


def learn(data: dict[str, np.ndarray]) -> tuple[list[list[int] | None], list[int]]:
    """The learner fed every transition once: per action its committed parents (sensor indices;
    None while open) and the firing at which it committed (-1: never)."""
    import torch

    from factorq_envs import highway
    from factorq_torch.structure import StructureLearner

    actions_count, sensors_count = len(highway.ACTUATOR_NAMES), len(highway.SENSOR_NAMES)
    learner = StructureLearner(
        1, num_actions=actions_count, num_sensors=sensors_count, prediction="committed"
    )
    committed_at = [-1] * actions_count
    for index, (readings, action, crashed) in enumerate(
        zip(data["sensors"], data["actions"], data["crashes"], strict=True)
    ):
        local = torch.zeros(1, actions_count)
        local[0, int(action)] = -highway.PENALTY if crashed else 0.0
        learner.update_running_mean(
            torch.as_tensor(readings).unsqueeze(0), torch.tensor([int(action)]), local
        )
        for a, done in enumerate(learner.is_committed()[0].tolist()):
            if done and committed_at[a] < 0:
                committed_at[a] = index + 1
    structure = learner.structure()[0]
    committed = learner.is_committed()[0].tolist()
    parents = [
        [k for k, on in enumerate(row) if on] if done else None
        for row, done in zip(structure.tolist(), committed, strict=True)
    ]
    return parents, committed_at


def _rate(crashes: np.ndarray) -> dict[str, Any]:
    return {"n": int(crashes.size), "rate": float(crashes.mean()) if crashes.size else None}


def report(data: dict[str, np.ndarray], parents: list[list[int] | None]) -> dict[str, Any]:
    """Per action: firings, crashes, learned and oracle parents, the crash rate with each sensor
    on and off, and (where they differ, or the most dangerous sensor is not the oracle's) per
    pattern of both parent sets and that sensor."""
    from factorq_envs import highway

    names, oracle = highway.SENSOR_NAMES, np.array(highway.ORACLE, dtype=bool)
    out = []
    for a, action in enumerate(highway.ACTUATOR_NAMES):
        fired = data["actions"] == a
        sensors, crashes = data["sensors"][fired], data["crashes"][fired]
        believed = [k for k in range(len(names)) if oracle[a, k]]
        entry: dict[str, Any] = {
            "action": action,
            "firings": int(fired.sum()),
            "crashes": int(crashes.sum()),
            "learned": None if parents[a] is None else [names[k] for k in parents[a]],
            "oracle": [names[k] for k in believed],
            "by_sensor": {
                names[k]: {
                    "on": _rate(crashes[sensors[:, k]]),
                    "off": _rate(crashes[~sensors[:, k]]),
                }
                for k in range(len(names))
            },
        }
        on_rates = [
            crashes[sensors[:, k]].mean() if sensors[:, k].any() else -1.0
            for k in range(len(names))
        ]
        strongest = int(np.argmax(on_rates))  # the sensor whose reading "on" is most dangerous
        entry["strongest"] = names[strongest]
        if sorted(parents[a] or []) != believed or strongest not in believed:
            union = sorted(set(parents[a] or []) | set(believed) | {strongest})
            entry["by_pattern"] = {
                ", ".join(f"{names[k]}={int(v)}" for k, v in zip(union, values, strict=True)): (
                    _rate(crashes[(sensors[:, union] == np.array(values, dtype=bool)).all(1)])
                )
                for values in itertools.product((0, 1), repeat=len(union))
            }
        out.append(entry)
    return {"actions": out}


def _print(result: dict[str, Any]) -> None:
    for entry in result["actions"]:
        learned = "open" if entry["learned"] is None else ", ".join(entry["learned"]) or "none"
        print(
            f"{entry['action']}: {entry['firings']} firings, {entry['crashes']} crashes; learned "
            f"{learned} (committed at firing {entry['committed_at']}); oracle "
            f"{', '.join(entry['oracle'])}"
        )
        for name, rates in entry["by_sensor"].items():
            on, off = rates["on"], rates["off"]
            if on["n"] and off["n"]:
                print(
                    f"    {name}: crash rate {on['rate']:.2f} on (n {on['n']}), "
                    f"{off['rate']:.2f} off (n {off['n']})"
                )
        for pattern, rate in entry.get("by_pattern", {}).items():
            shown = "-" if rate["rate"] is None else f"{rate['rate']:.2f}"
            print(f"    [{pattern}]: crash rate {shown} (n {rate['n']})")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=2000, help="random-policy env steps")
    parser.add_argument("--seed", type=int, default=0, help="the env's and the policy's seed")
    parser.add_argument("--json", help="write the result here as well")
    args = parser.parse_args()
    started = time.perf_counter()
    data = collect(args.steps, args.seed)
    parents, committed_at = learn(data)
    result = report(data, parents)
    for entry, at in zip(result["actions"], committed_at, strict=True):
        entry["committed_at"] = at
    result.update(
        steps=args.steps,
        seed=args.seed,
        crashes=int(data["crashes"].sum()),
        wall_s=time.perf_counter() - started,
    )
    print(
        f"{args.steps} random-policy steps, {result['crashes']} crashes, {result['wall_s']:.0f} s"
    )
    _print(result)
    if args.json:
        with open(args.json, "w") as handle:
            json.dump(result, handle, indent=1)


if __name__ == "__main__":
    main()
