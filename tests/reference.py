"""A slow, independent implementation of SPEC sections 1-4: one experiment, plain Python loops.

Written straight from the SPEC with no tensors, so the batched modules and the compiled fast
path can be tested against it for *equality*. Arithmetic on table values is done in numpy
float32 scalars (the tables' dtype) and the random draws come from the same counter streams
(``factorq_torch.base.rng``, Python-int version), so equal results are expected bit for bit.

``run_body_experiment`` does the same for any body of issue 11, deriving the sensors, each
actuator's parent sensor and the moves from the sensor and actuator *names* alone (not from
``factorq_envs.body``'s offsets and dependency).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from factorq_envs.grid_world import COL_DELTA, ROW_DELTA, WorldConfig
from factorq_torch.base.config import AgentConfig
from factorq_torch.base.rng import POLICY_DRAWS_PER_STEP, probability_threshold, random_bits_int

F = np.float32
FMAX = np.finfo(F).max
A = 4


def scatter(key: int, index: int, agent: int, size: int, k: int) -> list[bool]:
    """Floyd's algorithm over the cells other than start, goal and the agent."""
    n = size * size
    allowed = [c for c in range(n) if c not in (0, n - 1, agent)]
    chosen: set[int] = set()
    m = len(allowed)
    for draw, j in enumerate(range(m - k, m)):
        t = (random_bits_int(key, index * k + draw) * (j + 1)) >> 32
        chosen.add(j if t in chosen else t)
    blocked = [False] * n
    for position in chosen:
        blocked[allowed[position]] = True
    return blocked


def blocked_faces(cell: int, blocked: list[bool], size: int) -> list[bool]:
    row, col = divmod(cell, size)
    faces = []
    for d_row, d_col in zip(ROW_DELTA, COL_DELTA, strict=True):
        r, c = row + d_row, col + d_col
        faces.append(not (0 <= r < size and 0 <= c < size) or blocked[r * size + c])
    return faces


def normaliser(q: list, rho: list, eta: float, g_min: float):
    a_hat = max(range(A), key=lambda a: (q[a], -a))  # first maximum
    q_bar = F(0)
    for a in range(A):
        if a != a_hat:
            q_bar = q_bar + q[a]
    x = q[a_hat] - q_bar / F(A - 1)
    a_check = min(range(A), key=lambda a: (rho[a], a))  # first minimum
    p_bar = F(0)
    for a in range(A):
        if a != a_check:
            p_bar = p_bar + rho[a]
    y = p_bar / F(A - 1) - rho[a_check]
    if not y > 0:
        return F(g_min)
    g = x / y * F(1 + eta)
    return min(g, FMAX) if g >= F(g_min) else F(g_min)


def combined(q: list, g, local: list) -> list:
    return [min(max(q[a] + g * local[a], -FMAX), FMAX) for a in range(A)]


def select(values: list, epsilon: float, key: int, counter: int) -> tuple[int, bool]:
    explore_bits, action_bits, tie_bits = (
        random_bits_int(key, counter * POLICY_DRAWS_PER_STEP + j) for j in range(3)
    )
    if explore_bits < probability_threshold(epsilon):
        return (action_bits * A) >> 32, True
    best = max(values)
    ties = [a for a in range(A) if values[a] == best]
    return ties[(tie_bits * len(ties)) >> 32], False


@dataclass
class Metrics:
    steps: list = field(default_factory=list)  # [runs][episodes]
    collisions: list = field(default_factory=list)
    greedy_collisions: list = field(default_factory=list)
    task_return: list = field(default_factory=list)


def run_experiment(
    algorithm: str,
    period: int,
    world: WorldConfig,
    agent: AgentConfig,
    runs: int,
    episodes: int,
    world_key: int,
    policy_key: int,
    static_obstacles: list[bool],
) -> tuple[Metrics, dict]:
    """Run one experiment; return its metrics and final tables (``q``, ``rho``, ``kappa``).

    ``world_key`` / ``policy_key`` are unsigned 64-bit ints (``key & MASK64`` of a derived key).
    """
    size, k, n = world.size, world.num_obstacles, world.num_cells
    goal = n - 1
    num_states = n * 16 if algorithm == "q-learning" else n
    rho = [[F(0), F(0)] for _ in range(A)]  # [actuator][sensor value]
    kappa = [[0, 0] for _ in range(A)]
    policy_counter = 0
    scatters = 0
    metrics = Metrics()
    q = None
    for _run in range(runs):
        q = [[F(0)] * A for _ in range(num_states)]  # task table reset every run
        for name in ("steps", "collisions", "greedy_collisions", "task_return"):
            getattr(metrics, name).append([])
        for _episode in range(episodes):
            cell, step = 0, 0
            if period == 0:
                blocked = list(static_obstacles)
            else:
                blocked = scatter(world_key, scatters, 0, size, k) if k else [False] * n
                scatters += 1 if k else 0
            steps = collisions = greedy_collisions = 0
            task_return = F(0)
            while True:
                prox = blocked_faces(cell, blocked, size)
                pattern = sum(int(bit) << i for i, bit in enumerate(prox))
                if algorithm == "q-learning":
                    state = cell * 16 + pattern
                    values = q[state]
                else:
                    state = cell
                    local = [rho[i][int(prox[i])] for i in range(A)]
                    g = normaliser(q[state], local, agent.eta, agent.g_min)
                    values = combined(q[state], g, local)
                action, exploratory = select(values, agent.epsilon, policy_key, policy_counter)
                policy_counter += 1
                # world step: move or collide, reward, maybe scatter, new observation
                collided = prox[action]
                if not collided:
                    cell += ROW_DELTA[action] * size + COL_DELTA[action]
                step += 1
                terminated = cell == goal
                truncated = not terminated and step >= world.max_steps
                task_reward = F(-1) + F(terminated)
                local_reward = F(-1) if collided else F(0)
                if period > 0 and k and not terminated and step % period == 0:
                    blocked = scatter(world_key, scatters, cell, size, k)
                    scatters += 1
                next_prox = blocked_faces(cell, blocked, size)
                # learning
                if algorithm == "q-learning":
                    reward = task_reward + local_reward
                    next_pattern = sum(int(bit) << i for i, bit in enumerate(next_prox))
                    next_values = q[cell * 16 + next_pattern]
                else:
                    reward = task_reward
                    next_local = [rho[i][int(next_prox[i])] for i in range(A)]
                    g_next = normaliser(q[cell], next_local, agent.eta, agent.g_min)
                    next_values = combined(q[cell], g_next, next_local)
                target = reward if terminated else reward + F(agent.gamma) * max(next_values)
                q[state][action] = q[state][action] + F(agent.alpha) * (target - q[state][action])
                if algorithm == "factor-q":  # eq. 5 after eq. 4, on the sensor read before acting
                    o = int(prox[action])
                    kappa[action][o] += 1
                    rho[action][o] = rho[action][o] + (local_reward - rho[action][o]) / F(
                        kappa[action][o]
                    )
                steps += 1
                collisions += int(collided)
                greedy_collisions += int(collided and not exploratory)
                task_return = task_return + task_reward
                if terminated or truncated:
                    break
            metrics.steps[-1].append(steps)
            metrics.collisions[-1].append(collisions)
            metrics.greedy_collisions[-1].append(greedy_collisions)
            metrics.task_return[-1].append(float(task_return))
    return metrics, {"q": q, "rho": rho, "kappa": kappa}


# -- any body (issue 11), written from the sensor and actuator *names* ------------------------

STEP_OF = {0: (-1, 0), 1: (0, -1), 2: (1, 0), 3: (0, 1)}  # north, west, south, east
TURNS_OF = {
    "north": 0,
    "west": 1,
    "south": 2,
    "east": 3,
    "front": 0,
    "left": 1,
    "back": 2,
    "right": 3,
}


def _normaliser_n(q: list, rho: list, eta: float, g_min: float):
    n = len(q)
    a_hat = max(range(n), key=lambda a: (q[a], -a))
    q_bar = F(0)
    for a in range(n):
        if a != a_hat:
            q_bar = q_bar + q[a]
    x = q[a_hat] - q_bar / F(n - 1)
    a_check = min(range(n), key=lambda a: (rho[a], a))
    p_bar = F(0)
    for a in range(n):
        if a != a_check:
            p_bar = p_bar + rho[a]
    y = p_bar / F(n - 1) - rho[a_check]
    if not y > 0:
        return F(g_min)
    g = x / y * F(1 + eta)
    return min(g, FMAX) if g >= F(g_min) else F(g_min)


def _select_n(values: list, epsilon: float, key: int, counter: int) -> tuple[int, bool]:
    n = len(values)
    explore_bits, action_bits, tie_bits = (
        random_bits_int(key, counter * POLICY_DRAWS_PER_STEP + j) for j in range(3)
    )
    if explore_bits < probability_threshold(epsilon):
        return (action_bits * n) >> 32, True
    best = max(values)
    ties = [a for a in range(n) if values[a] == best]
    return ties[(tie_bits * len(ties)) >> 32], False


def run_body_experiment(
    algorithm: str,
    period: int,
    world: WorldConfig,
    agent: AgentConfig,
    runs: int,
    episodes: int,
    world_key: int,
    policy_key: int,
    static_obstacles: list[bool],
) -> Metrics:
    """One experiment of any body: the sensors, the parents of each actuator and the moves are
    derived here from the names alone (``front-left`` = one step ahead, one to the left)."""
    from factorq_torch.base.rng import substream_key_int

    size, k, n = world.size, world.num_obstacles, world.num_cells
    goal = n - 1
    names, actuators = world.sensor_names, world.actuator_names
    count, num_actions = len(names), len(actuators)
    layout_order = list(world.permutation)  # agent's sensor j = layout sensor layout_order[j]
    distractors = world.num_distractors
    keys = {s: substream_key_int(world_key, s) for s in (1, 2, 3)}
    parent_name = {a: {"forward": "front"}.get(a, a) for a in actuators}
    parents = [
        [j for j, name in enumerate(names) if name == parent_name[a]] for a in actuators
    ]  # turns have none: no sensor is called turn-left
    headings = 4 if "forward" in actuators else 1
    noise = probability_threshold(world.sensor_noise)
    slip = probability_threshold(world.actuator_noise)

    def blocked_at(cell, heading, name, blocked):
        row, col = divmod(cell, size)
        for part in name.split("-"):
            d_row, d_col = STEP_OF[(TURNS_OF[part] + heading) % 4]
            row, col = row + d_row, col + d_col
        return not (0 <= row < size and 0 <= col < size) or blocked[row * size + col]

    def observe(cell, heading, blocked, tick):
        raw = [None] * count  # in layout order, distractors last
        for j, name in enumerate(names):
            index = layout_order[j]
            if name.startswith("distractor"):
                d = int(name.split("-")[1])
                raw[index] = bool(random_bits_int(keys[1], tick * distractors + d) >> 31)
            else:
                raw[index] = blocked_at(cell, heading, name, blocked)
        if world.sensor_noise > 0:
            raw = [
                b ^ (random_bits_int(keys[2], tick * count + i) < noise) for i, b in enumerate(raw)
            ]
        return [raw[layout_order[j]] for j in range(count)]

    def pattern(readings, a):
        return sum(int(readings[k_]) << r for r, k_ in enumerate(parents[a]))

    rho = [[F(0)] * (1 << len(parents[a])) for a in range(num_actions)]
    kappa = [[0] * (1 << len(parents[a])) for a in range(num_actions)]
    policy_counter = scatters = 0
    tick = 0
    metrics = Metrics()
    for _run in range(runs):
        q: dict = {}
        for name in ("steps", "collisions", "greedy_collisions", "task_return"):
            getattr(metrics, name).append([])
        for _episode in range(episodes):
            cell, heading, step = 0, 0, 0
            if period == 0:
                blocked = list(static_obstacles)
            else:
                blocked = scatter(world_key, scatters, 0, size, k) if k else [False] * n
                scatters += 1 if k else 0
            tick += 1
            readings = observe(cell, heading, blocked, tick)
            steps = collisions = greedy_collisions = 0
            task_return = F(0)
            while True:
                position = cell * headings + heading
                if algorithm == "q-learning":
                    state = (position, tuple(readings))
                    values = q.setdefault(state, [F(0)] * num_actions)
                else:
                    state = position
                    values_q = q.setdefault(state, [F(0)] * num_actions)
                    local = [rho[a][pattern(readings, a)] for a in range(num_actions)]
                    g = _normaliser_n(values_q, local, agent.eta, agent.g_min)
                    values = [
                        min(max(values_q[a] + g * local[a], -FMAX), FMAX)
                        for a in range(num_actions)
                    ]
                action, exploratory = _select_n(values, agent.epsilon, policy_key, policy_counter)
                policy_counter += 1
                fired = action
                if world.actuator_noise > 0 and random_bits_int(keys[3], 2 * tick) < slip:
                    other = (random_bits_int(keys[3], 2 * tick + 1) * (num_actions - 1)) >> 32
                    fired = (action + 1 + other) % num_actions
                name = actuators[fired]
                collided = False
                if name in ("turn-left", "turn-right"):
                    heading = (heading + (1 if name == "turn-left" else 3)) % 4
                else:  # a move: north/west/south/east, or forward in the heading's direction
                    direction = ((0 if name == "forward" else TURNS_OF[name]) + heading) % 4
                    row, col = divmod(cell, size)
                    row, col = row + STEP_OF[direction][0], col + STEP_OF[direction][1]
                    inside = 0 <= row < size and 0 <= col < size
                    collided = not inside or blocked[row * size + col]
                    if not collided:
                        cell = row * size + col
                step += 1
                terminated = cell == goal
                truncated = not terminated and step >= world.max_steps
                task_reward = F(-1) + F(terminated)
                local_reward = F(-1) if collided else F(0)
                if period > 0 and k and not terminated and step % period == 0:
                    blocked = scatter(world_key, scatters, cell, size, k)
                    scatters += 1
                tick += 1
                next_readings = observe(cell, heading, blocked, tick)
                next_position = cell * headings + heading
                if algorithm == "q-learning":
                    reward = task_reward + local_reward
                    next_values = q.get((next_position, tuple(next_readings)), [F(0)] * num_actions)
                else:
                    reward = task_reward
                    next_q = q.get(next_position, [F(0)] * num_actions)
                    next_local = [rho[a][pattern(next_readings, a)] for a in range(num_actions)]
                    g_next = _normaliser_n(next_q, next_local, agent.eta, agent.g_min)
                    next_values = [
                        min(max(next_q[a] + g_next * next_local[a], -FMAX), FMAX)
                        for a in range(num_actions)
                    ]
                target = reward if terminated else reward + F(agent.gamma) * max(next_values)
                row = q.setdefault(state, [F(0)] * num_actions)
                row[action] = row[action] + F(agent.alpha) * (target - row[action])
                if algorithm == "factor-q":
                    o = pattern(readings, action)
                    kappa[action][o] += 1
                    rho[action][o] = rho[action][o] + (local_reward - rho[action][o]) / F(
                        kappa[action][o]
                    )
                steps += 1
                collisions += int(collided)
                greedy_collisions += int(collided and not exploratory)
                task_return = task_return + task_reward
                if terminated or truncated:
                    break
                readings = next_readings
            metrics.steps[-1].append(steps)
            metrics.collisions[-1].append(collisions)
            metrics.greedy_collisions[-1].append(greedy_collisions)
            metrics.task_return[-1].append(float(task_return))
    return metrics
