"""An independent numba implementation of the paper's experiment: issue 17's speed anchor.

The same work as the fast path (``factorq_trainers.compiled.fast``) does for the paper's default
workload (SPEC section 4: 100 seeds x 3 worlds x 2 algorithms x 10 runs x 200 episodes, 10x10 worlds
with 10 obstacles, static / semi-dynamic (period 10) / dynamic (period 1)): the world (move or
collide, the obstacle scatter by Floyd's algorithm, the proximity sensors), epsilon-greedy with
random tie-breaking, Q-learning (eq. 1 on cell x proximity pattern) and Factor-Q (eqs. 2-5), written
plainly in numba: ``@njit(parallel=True)``, ``prange`` over experiments, float32 tables, the same
counter-based random streams (SplitMix64, ``factorq_torch.base.rng``) so that it draws the same
numbers. It shares no code with the C kernel (``trainers/compiled/_kernel.c``); it reuses only the
project's key derivation, configuration defaults and static layout. As a check that it does the same
work it prints its total env steps beside the fast path's: equal when both follow the SPEC to the
bit (it does not try to be bit-identical in every corner, e.g. NaN handling).

numba is not a dependency of the project (``pip install numba``, or the ``bench`` extra); without
it this script says so in one line and exits 0. Run from the repository root:

    .venv/bin/python benchmarks/bench_numba_anchor.py            # 1 and 2 threads
    .venv/bin/python benchmarks/bench_numba_anchor.py --threads 2 --repeats 5

``benchmarks/bench_speed.py`` imports ``workload`` and ``paper_workload`` from here to print the
measured ratio beside the quoted anchor when numba is importable. Each experiment runs from start
to end in one go with its tables freshly allocated (they stay in cache); the fast path keeps every
experiment's state in the batch between calls (checkpoints, progress), which costs it memory
traffic on large batches advanced in chunks. Timings are printed, never asserted.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(ROOT))

try:
    import numba
    from numba import njit, prange
except ImportError:  # optional: the caller says so in one line
    numba = None

PAPER_PERIODS = (0, 10, 1)  # static, semi-dynamic, dynamic
Q_LEARNING, FACTOR_Q = 1, 2


def available() -> bool:
    return numba is not None


if numba is not None:
    _GOLDEN = np.uint64(0x9E3779B97F4A7C15)
    _MIX1 = np.uint64(0xBF58476D1CE4E5B9)
    _MIX2 = np.uint64(0x94D049BB133111EB)
    _U1, _U3 = np.uint64(1), np.uint64(3)
    _S27, _S30, _S31, _S32 = np.uint64(27), np.uint64(30), np.uint64(31), np.uint64(32)
    _FLT_MAX = np.float32(3.4028234663852886e38)
    _ZERO, _ONE, _THREE = np.float32(0.0), np.float32(1.0), np.float32(3.0)
    _LOWEST = np.array([0, 0, 1, 0, 2, 0, 1, 0, 3, 0, 1, 0, 2, 0, 1, 0])  # lowest set bit

    @njit(inline="always")
    def _bits(key, counter):
        """rng.random_bits: the top 32 bits of mix64(key + (counter + 1) * GOLDEN)."""
        z = key + (counter + _U1) * _GOLDEN
        z = (z ^ (z >> _S30)) * _MIX1
        z = (z ^ (z >> _S27)) * _MIX2
        z = z ^ (z >> _S31)
        return z >> _S32

    @njit(inline="always")
    def _proximity(grid, pos, width):
        return (
            np.int64(grid[pos - width])
            | np.int64(grid[pos - 1]) << 1
            | np.int64(grid[pos + width]) << 2
            | np.int64(grid[pos + 1]) << 3
        )

    @njit(inline="always")
    def _scatter(grid, pads, pad_of_cell, num_cells, count, key, index, agent):
        """Floyd's algorithm over the cells other than start, goal and agent."""
        goal = num_cells - 1
        agent_free = 1 if (agent != 0 and agent != goal) else 0
        skip = agent if agent_free else num_cells
        allowed = num_cells - 2 - agent_free
        for k in range(count):
            grid[pads[k]] = 0
        for k in range(count):
            j = allowed - count + k
            t = np.int64((_bits(key, np.uint64(index * count + k)) * np.uint64(j + 1)) >> _S32)
            cell_t = t + 1
            if cell_t >= skip:
                cell_t += 1
            cell_j = j + 1
            if cell_j >= skip:
                cell_j += 1
            pad = pad_of_cell[cell_t]
            if grid[pad]:
                pad = pad_of_cell[cell_j]
            grid[pad] = 1
            pads[k] = pad

    @njit(inline="always")
    def _choose(v0, v1, v2, v3, key, counter, threshold):
        """Epsilon-greedy with the policy stream's three draws per step: explore?, the random
        action, the tie-break among the maxima (drawn only when there is a tie)."""
        base = counter * _U3
        if _bits(key, base) < threshold:
            return np.int64(_bits(key, base + _U1) >> _S30), True
        best = max(max(max(v0, v1), v2), v3)
        mask = (v0 == best) | (v1 == best) << 1 | (v2 == best) << 2 | (v3 == best) << 3
        count = (mask & 1) + (mask >> 1 & 1) + (mask >> 2 & 1) + (mask >> 3 & 1)
        if count <= 1:
            return np.int64(0 if count == 0 else _LOWEST[mask]), False
        k = np.int64((_bits(key, base + np.uint64(2)) * np.uint64(count)) >> _S32)
        for _ in range(k):
            mask &= mask - 1
        return np.int64(_LOWEST[mask]), False

    @njit(inline="always")
    def _combined(q, base, local, o, spread, eta_factor, g_min):
        """Eqs. 2-3: C = Q + G rho(o), G the normaliser of eq. 3 (g_min when not defined);
        local[o] = rho(o) and spread its denominator, for proximity pattern o."""
        q0, q1, q2, q3 = q[base], q[base + 1], q[base + 2], q[base + 3]
        g = g_min
        if spread > _ZERO:
            a_hat, best = 0, q0  # the first maximum
            if q1 > best:
                a_hat, best = 1, q1
            if q2 > best:
                a_hat, best = 2, q2
            if q3 > best:
                a_hat, best = 3, q3
            q_sum = _ZERO  # the other three, left to right
            if a_hat != 0:
                q_sum = q_sum + q0
            if a_hat != 1:
                q_sum = q_sum + q1
            if a_hat != 2:
                q_sum = q_sum + q2
            if a_hat != 3:
                q_sum = q_sum + q3
            ratio = (best - q_sum / _THREE) / spread * eta_factor
            if ratio >= g_min:
                g = min(ratio, _FLT_MAX)
        return (
            min(max(q0 + g * local[o, 0], -_FLT_MAX), _FLT_MAX),
            min(max(q1 + g * local[o, 1], -_FLT_MAX), _FLT_MAX),
            min(max(q2 + g * local[o, 2], -_FLT_MAX), _FLT_MAX),
            min(max(q3 + g * local[o, 3], -_FLT_MAX), _FLT_MAX),
        )

    @njit(inline="always")
    def _patterns(rho, local, spread):
        """rho(o) and eq. 3's denominator for the 16 proximity patterns o (when rho changes)."""
        for o in range(16):
            a_check = 0
            for a in range(4):
                local[o, a] = rho[a * 2 + ((o >> a) & 1)]
                if local[o, a] < local[o, a_check]:
                    a_check = a
            rho_sum = _ZERO
            for a in range(4):
                if a != a_check:
                    rho_sum = rho_sum + local[o, a]
            spread[o] = rho_sum / _THREE - local[o, a_check]

    @njit(parallel=True)
    def _run(algorithm, periods, world_keys, policy_keys, static_grid, pad_of_cell, size,
             num_obstacles, max_steps, runs, episodes, threshold, gamma, alpha, eta_factor,
             g_min, order, counts_out, return_out):  # fmt: skip
        """Every experiment to the end, with the fast path's metrics per episode: counts_out
        [S, runs, episodes, 3] steps, collisions, greedy collisions; return_out the return.
        prange's n-th iteration runs experiment order[n]."""
        width = size + 2
        num_cells = size * size
        goal = num_cells - 1
        move_pad = np.array([-width, -1, width, 1])
        move_cell = np.array([-size, -1, size, 1])
        states = num_cells * 16 if algorithm == Q_LEARNING else num_cells
        for n in prange(periods.shape[0]):
            i = order[n]
            period = periods[i]
            world_key = np.uint64(world_keys[i])
            policy_key = np.uint64(policy_keys[i])
            moving = period > 0 and num_obstacles > 0
            grid = static_grid.copy()
            pads = np.full(max(num_obstacles, 1), pad_of_cell[0], np.int64)
            if period > 0:
                for c in range(num_cells):
                    grid[pad_of_cell[c]] = 0
            q = np.zeros(states * 4, np.float32)
            rho = np.zeros(8, np.float32)
            kappa = np.zeros(8, np.int64)
            local = np.empty((16, 4), np.float32)
            spread = np.empty(16, np.float32)
            _patterns(rho, local, spread)
            scatters = 0
            counter = np.uint64(0)
            for run in range(runs):
                q[:] = _ZERO
                for episode in range(episodes):
                    if moving:
                        _scatter(grid, pads, pad_of_cell, num_cells, num_obstacles, world_key,
                                 scatters, 0)  # fmt: skip
                        scatters += 1
                    cell = 0
                    pos = pad_of_cell[0]
                    prox = _proximity(grid, pos, width)
                    step = 0
                    collisions = 0
                    greedy_collisions = 0
                    task_return = _ZERO
                    while True:
                        if algorithm == Q_LEARNING:
                            state = cell * 16 + prox
                            b = state * 4
                            v0, v1, v2, v3 = q[b], q[b + 1], q[b + 2], q[b + 3]
                        else:
                            state = cell
                            v0, v1, v2, v3 = _combined(
                                q, state * 4, local, prox, spread[prox], eta_factor, g_min
                            )
                        action, exploratory = _choose(
                            v0, v1, v2, v3, policy_key, counter, threshold
                        )
                        counter += _U1
                        collided = (prox >> action) & 1
                        if collided == 0:
                            pos += move_pad[action]
                            cell += move_cell[action]
                        step += 1
                        terminated = cell == goal
                        task_reward = np.float32(-1.0) + (_ONE if terminated else _ZERO)
                        local_reward = np.float32(-1.0) if collided else _ZERO
                        if moving and not terminated and step % period == 0:
                            _scatter(grid, pads, pad_of_cell, num_cells, num_obstacles,
                                     world_key, scatters, cell)  # fmt: skip
                            scatters += 1
                        next_prox = _proximity(grid, pos, width)
                        entry = state * 4 + action
                        if algorithm == Q_LEARNING:
                            reward = task_reward + local_reward
                            target = reward
                            if not terminated:
                                b = (cell * 16 + next_prox) * 4
                                best = max(max(max(q[b], q[b + 1]), q[b + 2]), q[b + 3])
                                target = reward + gamma * best
                        else:
                            target = task_reward
                            if not terminated:
                                n0, n1, n2, n3 = _combined(
                                    q,
                                    cell * 4,
                                    local,
                                    next_prox,
                                    spread[next_prox],
                                    eta_factor,
                                    g_min,
                                )
                                best = max(max(max(n0, n1), n2), n3)
                                target = task_reward + gamma * best
                        q[entry] = q[entry] + alpha * (target - q[entry])
                        if algorithm == FACTOR_Q:  # eq. 5 on the sensor read before acting
                            local_entry = action * 2 + collided
                            kappa[local_entry] += 1
                            old = rho[local_entry]
                            rho[local_entry] = old + (local_reward - old) / np.float32(
                                kappa[local_entry]
                            )
                            if rho[local_entry] != old:
                                _patterns(rho, local, spread)
                        collisions += collided
                        if not exploratory:
                            greedy_collisions += collided
                        task_return = task_return + task_reward
                        prox = next_prox
                        if terminated or step >= max_steps:
                            break
                    counts_out[i, run, episode, 0] = step
                    counts_out[i, run, episode, 1] = collisions
                    counts_out[i, run, episode, 2] = greedy_collisions
                    return_out[i, run, episode] = task_return


def _inputs(periods, seed: int) -> dict:
    """A batch of experiments with obstacle ``periods`` [S] (0 static, k > 0 scatter every k-th
    step) and ``seed``'s keys: the static layout padded, the cells' padded indices, the config."""
    from factorq_envs.grid_world import WorldConfig, static_layout
    from factorq_torch.base.config import AgentConfig
    from factorq_torch.base.rng import (
        STREAM_POLICY,
        STREAM_WORLD,
        derive_keys,
        probability_threshold,
    )

    world, agent = WorldConfig(), AgentConfig()
    size, width = world.size, world.size + 2
    cells = np.arange(size * size)
    pad_of_cell = (cells // size + 1) * width + cells % size + 1
    static_grid = np.ones(width * width, np.uint8)
    static_grid[pad_of_cell] = static_layout(world).numpy().astype(np.uint8)
    f32 = np.float32
    return dict(
        periods=np.asarray(periods, dtype=np.int64),
        world_keys=derive_keys(seed, STREAM_WORLD, len(periods)).numpy().view(np.uint64),
        policy_keys=derive_keys(seed, STREAM_POLICY, len(periods)).numpy().view(np.uint64),
        static_grid=static_grid,
        pad_of_cell=pad_of_cell.astype(np.int64),
        size=size,
        num_obstacles=world.num_obstacles,
        max_steps=world.max_steps,
        threshold=np.uint64(probability_threshold(agent.epsilon)),
        gamma=f32(agent.gamma),
        alpha=f32(agent.alpha),
        eta_factor=f32(1 + agent.eta),
        g_min=f32(agent.g_min),
    )


def workload(
    algorithm: str, periods, threads: int, runs: int, episodes: int, seed: int = 0
) -> tuple[float, int]:
    """(seconds, env steps) of ``algorithm`` ("q-learning" or "factor-q") on one experiment per
    entry of ``periods``, every experiment to its end, on ``threads`` numba threads (compiled
    beforehand on a tiny batch, so no compile time is included)."""
    code = {"q-learning": Q_LEARNING, "factor-q": FACTOR_Q}[algorithm]
    inputs = _inputs(periods, seed)
    numba.set_num_threads(threads)
    # Experiments differ in length (static, semi-dynamic, dynamic worlds) and prange gives each
    # thread one contiguous block of iterations (measured: set_parallel_chunksize(1) did not
    # balance the paper's static/semi/dynamic blocks, 1.38x on 2 threads): deal the experiments
    # out cyclically, thread r's block holding experiments r, r + T, r + 2T, ... (1.7x-1.9x).
    count = len(periods)
    order = np.concatenate([np.arange(r, count, threads) for r in range(threads)])
    for shape in ((1, 1), (runs, episodes)):  # compile and warm up, then the timed run
        counts = np.zeros((len(periods), *shape, 3), np.int64)
        returns = np.zeros((len(periods), *shape), np.float32)
        start = time.perf_counter()
        _run(
            code,
            runs=shape[0],
            episodes=shape[1],
            order=order,
            counts_out=counts,
            return_out=returns,
            **inputs,
        )
    return time.perf_counter() - start, int(counts[..., 0].sum())


def paper_workload(threads: int, seeds: int = 100) -> dict[str, tuple[float, int]]:
    """{algorithm: (seconds, env steps)} of the paper workload (``bench_speed.paper_workload``'s
    batch: ``seeds`` experiments per world, seed 0's keys, 10 runs x 200 episodes)."""
    periods = np.repeat(PAPER_PERIODS, seeds)
    return {name: workload(name, periods, threads, 10, 200) for name in ("q-learning", "factor-q")}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--repeats", type=int, default=3, help="runs per thread count")
    parser.add_argument("--no-fast", action="store_true", help="skip the fast path's figure")
    args = parser.parse_args()
    if numba is None:
        print("numba is not installed: skipping the numba anchor (pip install numba)")
        return
    print(f"numba {numba.__version__}, threading layer after the first run below")
    print(f"{'threads':>7}{'q-learning':>14}{'factor-q':>14}{'env steps':>14}{'steps/s':>12}")
    for threads in args.threads:
        for _ in range(args.repeats):
            results = paper_workload(threads)
            seconds = sum(value[0] for value in results.values())
            steps = sum(value[1] for value in results.values())
            times = results["q-learning"][0], results["factor-q"][0]
            print(f"{threads:>7}{times[0]:>12.2f} s{times[1]:>12.2f} s{steps:>14,}"
                  f"{steps / seconds / 1e6:>10.1f} M")  # fmt: skip
    print(f"threading layer: {numba.threading_layer()}")
    if not args.no_fast:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from bench_speed import paper_workload as fast_paper

        for threads in args.threads:
            results = fast_paper(threads)
            seconds = sum(value[0] for value in results.values())
            steps = sum(value[1] for value in results.values())
            print(f"fast path, {threads} thread(s): {steps:,} env steps, "
                  f"{steps / seconds / 1e6:.1f} M steps/s")  # fmt: skip


if __name__ == "__main__":
    main()
