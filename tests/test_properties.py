"""Property tests (hypothesis): the equations and the world hold their invariants for any input."""

from __future__ import annotations

import kernel_probes  # tests/kernel_probes.py: pytest puts tests/ on sys.path
import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from factorq_envs.grid_world import (
    NUM_ACTIONS,
    WorldConfig,
    empty_state,
    proximity,
    reset_worlds,
    static_layout,
    step_worlds,
)
from factorq_torch.base.rng import STREAM_WORLD, derive_keys
from factorq_torch.functional import combined_values, normaliser, running_mean_update
from factorq_trainers.compiled import fast

FLOAT32_MAX = float(np.finfo(np.float32).max)
finite32 = st.floats(
    min_value=-FLOAT32_MAX, max_value=FLOAT32_MAX, allow_nan=False, width=32, allow_subnormal=True
)
# Values a table can hold in practice: bounded by the reward scale over the horizon, with some
# slack, so that the property about the local term's reach is not about float overflow.
moderate = st.floats(min_value=-1e4, max_value=1e4, allow_nan=False, width=32)
vectors = st.lists(finite32, min_size=NUM_ACTIONS, max_size=NUM_ACTIONS)
equal_vectors = finite32.map(lambda v: [v] * NUM_ACTIONS)


@settings(max_examples=300, deadline=None)
@given(q=st.one_of(vectors, equal_vectors), rho=st.one_of(vectors, equal_vectors))
def test_normaliser_and_combined_values_are_finite_and_floored_for_any_finite_input(q, rho):
    q_t, rho_t = torch.tensor([q]), torch.tensor([rho])
    g = normaliser(q_t, rho_t, eta=0.1, g_min=0.01)
    c = combined_values(q_t, rho_t, g)
    assert torch.isfinite(g).all() and torch.isfinite(c).all()
    assert float(g) >= np.float32(0.01)


@settings(max_examples=300, deadline=None)
@given(
    q=st.lists(moderate, min_size=NUM_ACTIONS, max_size=NUM_ACTIONS),
    rho=st.lists(moderate, min_size=NUM_ACTIONS, max_size=NUM_ACTIONS),
    eta=st.sampled_from([0.1, 0.5, 1.0]),
)
def test_greedy_action_under_combined_values_avoids_a_strictly_worst_local_action(q, rho, eta):
    # In exact arithmetic, whenever rho singles out one worst action, C's mean over the other
    # actions exceeds C at the worst one by at least eta * (Q(a_hat) - Q_bar) (and by the local
    # spread when Q is flat), so the worst action is never greedy. Float rounding can only eat a
    # margin that is tiny against the values, so require a margin the float32 sums can resolve.
    worst = int(np.argmin(rho))
    others = [r for a, r in enumerate(rho) if a != worst]
    assume(min(others) > rho[worst])
    spread = float(np.mean(others)) - rho[worst]
    task_spread = max(q) - float(np.mean([v for a, v in enumerate(q) if a != int(np.argmax(q))]))
    scale = max(1.0, *map(abs, q), *map(abs, rho))
    assume(spread > 1e-3 * scale and (task_spread == 0 or task_spread * eta > 1e-3 * scale))
    q_t, rho_t = torch.tensor([q]), torch.tensor([rho])
    c = combined_values(q_t, rho_t, normaliser(q_t, rho_t, eta=eta, g_min=0.01))
    assert int(c.argmax()) != worst or bool((c[0] == c[0, worst]).sum() > 1)


@settings(max_examples=200, deadline=None)
@given(rewards=st.lists(st.sampled_from([-1.0, 0.0]), min_size=1, max_size=300))
def test_running_mean_update_equals_the_arithmetic_mean_of_the_rewards_seen(rewards):
    rho, kappa = torch.zeros(1), torch.zeros(1, dtype=torch.int64)
    for reward in rewards:
        rho, kappa = running_mean_update(rho, kappa, torch.tensor([reward]))
    assert int(kappa) == len(rewards)
    assert float(rho) == pytest.approx(sum(rewards) / len(rewards), abs=1e-6)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    size=st.integers(2, 7),
    obstacle_fraction=st.floats(0.0, 1.0),
    periods=st.lists(st.sampled_from([0, 1, 2, 3, 10]), min_size=1, max_size=6),
    max_steps=st.integers(1, 30),
    seed=st.integers(0, 2**31),
    actions=st.lists(st.integers(0, NUM_ACTIONS - 1), min_size=1, max_size=60),
)
def test_random_worlds_and_actions_keep_every_invariant_of_the_world(
    size, obstacle_fraction, periods, max_steps, seed, actions
):
    # A crowded static layout is rarely reachable (redrawn up to 10,000 times): keep it sparse.
    most = (size - 1) ** 2 // 2 if 0 in periods else size * size - 3
    num_obstacles = round(obstacle_fraction * most)
    config = WorldConfig(size=size, num_obstacles=num_obstacles, max_steps=max_steps)
    batch = len(periods)
    period = torch.tensor(periods)
    key = derive_keys(seed, STREAM_WORLD, batch)
    layout = static_layout(config) if 0 in periods else torch.zeros(size * size, dtype=torch.bool)
    everyone = torch.ones(batch, dtype=torch.bool)
    state = reset_worlds(empty_state(batch, size), everyone, key, period, layout, config)
    goal = size * size - 1
    for step, action in enumerate(actions):
        before = state
        state, outcome = step_worlds(state, torch.full((batch,), action), key, period, config)
        # obstacles: the right count, never on start, goal or agent
        assert (state.obstacles.sum(1) == num_obstacles).all()
        assert not state.obstacles[:, 0].any() and not state.obstacles[:, goal].any()
        assert not state.obstacles.gather(1, state.cell.unsqueeze(1)).any()
        # a collision leaves the agent in place and sets exactly that face's bump bit
        collided = outcome.collision.sum(1) < 0
        assert torch.equal(state.cell[collided], before.cell[collided])
        assert torch.equal(state.bump.sum(1), collided.to(torch.int64))
        assert torch.equal(collided, proximity(before.cell, before.obstacles, size)[:, action])
        # rewards and episode end
        assert torch.equal(outcome.terminated, state.cell == goal)
        assert not (outcome.terminated & outcome.truncated).any()
        assert torch.equal(
            outcome.truncated, ~outcome.terminated & (state.episode_step >= max_steps)
        )
        # static worlds never change
        static = period == 0
        assert torch.equal(state.obstacles[static], layout.expand(int(static.sum()), -1))
        done = outcome.terminated | outcome.truncated
        if done.any():
            state = reset_worlds(state, done, key, period, layout, config)
        assert step < len(actions)


@pytest.mark.skipif(not fast.is_available(), reason="no C compiler for the fast path")
@settings(max_examples=300, deadline=None)
@given(q=st.one_of(vectors, equal_vectors), rho=st.one_of(vectors, equal_vectors))
def test_compiled_kernel_equals_the_equations_bit_for_bit_on_any_finite_input(q, rho):
    q_t, rho_t = torch.tensor([q]), torch.tensor([rho])
    g = normaliser(q_t, rho_t, eta=0.1, g_min=0.01)
    kernel_g, kernel_c = kernel_probes.kernel_combined_values(q_t, rho_t, 0.1, 0.01)
    assert torch.equal(kernel_g, g)
    assert torch.equal(kernel_c, combined_values(q_t, rho_t, g))
