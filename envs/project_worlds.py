"""The project's own worlds (the paper's grid, the corridor) as declared worlds: stepped by
``FactoredGridGym``, seen through the adapter (``FactorQEnv``) like any Gymnasium env, so that
``factorq gym --world grid-10x10`` and ``factorq risk --worlds corridor`` reach them by name
(``factorq_envs.worlds``' registry).

The adapter adds its own ``cell``, ``heading``, ``sensors``, ``bump`` and ``collision``; the
world's observation reaches it as one float32 vector (``FlatObservation``: one-hot cell, one-hot
heading where there are several, the sensors), which is what the networks read, and the
``Declaration`` reads the rest back from that vector and the world's ``info``.
"""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np

from factorq_envs.gymnasium_adapter import Declaration, FactorQEnv, Transition
from factorq_envs.gymnasium_env import FactoredGridGym

#: The kinds of project world, by name.
KINDS = ("grid", "corridor")


class FlatObservation(gymnasium.ObservationWrapper):
    """A project world's observation as one float32 vector: one-hot cell, one-hot heading where
    there are several, the sensors."""

    def __init__(self, env: FactoredGridGym) -> None:
        super().__init__(env)
        config = env.config
        self.cells, self.headings = config.num_cells, config.num_headings
        self.first_sensor = self.cells + (self.headings if self.headings > 1 else 0)
        size = self.first_sensor + config.num_sensors
        self.observation_space = gymnasium.spaces.Box(0.0, 1.0, (size,), np.float32)

    def observation(self, observation: dict[str, Any]) -> np.ndarray:
        parts = [np.eye(self.cells, dtype=np.float32)[int(observation["cell"])]]
        if self.headings > 1:
            parts.append(np.eye(self.headings, dtype=np.float32)[int(observation["heading"])])
        parts.append(np.asarray(observation["sensors"], dtype=np.float32))
        return np.concatenate(parts)


def project_declaration(env: FlatObservation) -> Declaration:
    """What Factor-Q reads from ``env``: the sensors, a collision charged to the actuator that
    fired (the world's own ``local_reward``), the cell and heading, the task reward, and the
    world's true dependency (the oracle)."""
    config = env.env.config  # type: ignore[attr-defined]
    cells, headings, first = env.cells, env.headings, env.first_sensor

    def state(step: Transition) -> int | tuple[int, int]:
        cell = int(np.argmax(step.observation[:cells]))
        if headings == 1:
            return cell
        return cell, int(np.argmax(step.observation[cells:first]))

    return Declaration(
        num_sensors=config.num_sensors,
        sensors=lambda step: step.observation[first:] > 0.5,
        collision=lambda step: bool(step.info["local_reward"].any()),
        charge=lambda step: int(np.argmin(step.info["local_reward"])),
        actuator_names=tuple(config.actuator_names),
        task_state=state,
        num_cells=cells,
        num_headings=headings,
        task_reward=lambda step: float(step.info["task_reward"]),
        dependency=tuple(tuple(bool(b) for b in row) for row in config.dependency.tolist()),
    )


def declared_project_world(kind: str, period: int, seed: int) -> FactorQEnv:
    """The ``kind`` world (``KINDS``: its default config) with obstacle period ``period``, as a
    ``FactorQEnv`` whose first reset uses ``seed``."""
    world: Any
    if kind == "grid":
        from factorq_envs.grid_world import WorldConfig

        world = WorldConfig()
    elif kind == "corridor":
        from factorq_envs.corridor import Corridor

        world = Corridor()
    else:
        raise ValueError(f"kind={kind!r} is unknown: choose one of {', '.join(KINDS)}")
    env = FlatObservation(FactoredGridGym(world=world, obstacle_period=period))
    return FactorQEnv(env, project_declaration(env), seed=seed)
