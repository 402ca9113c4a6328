"""The paper's equations (factorq_torch.functional) against numbers worked out by hand."""

from __future__ import annotations

import math

import pytest
import torch

from factorq_torch.functional import (
    combined_values,
    epsilon_greedy,
    epsilon_greedy_from_bits,
    factorq_target,
    greedy_action_from_bits,
    local_risk_rows,
    normaliser,
    q_learning_target,
    q_update,
    risk_mask,
    running_mean_update,
    safe_exploration_from_bits,
    significant_local,
)

TWO_32 = 1 << 32


# -- eq. 3, the normaliser ---------------------------------------------------------------------


def test_normaliser_scales_local_spread_to_task_spread():
    q = torch.tensor([[2.0, 0.0, 0.0, 1.0]])  # a_hat = 0, Q_bar = 1/3, x = 5/3
    rho = torch.tensor([[-1.0, 0.0, 0.0, 0.0]])  # a_check = 0, P_bar = 0,  y = 1
    assert torch.allclose(normaliser(q, rho, eta=0.1, g_min=0.01), torch.tensor([5 / 3 * 1.1]))


def test_normaliser_without_margin_equals_the_spread_ratio():
    q = torch.tensor([2.0, 0.0, 0.0, 1.0])  # x = 2 - 1/3 = 5/3
    rho = torch.tensor([-1.0, 0.0, -0.5, 0.0])  # a_check = 0, P_bar = -1/6, y = 5/6
    # G = (5/3) / (5/6) * (1 + 0) = 2
    assert torch.allclose(normaliser(q, rho, eta=0.0, g_min=0.01), torch.tensor(2.0))


def test_normaliser_falls_to_g_min_in_an_unvisited_state_where_all_q_are_equal():
    q = torch.zeros(1, 4)  # x = 0 - 0 = 0, so G = 0 < g_min
    rho = torch.tensor([[-1.0, 0.0, 0.0, 0.0]])  # y = 1
    assert torch.equal(normaliser(q, rho, eta=0.1, g_min=0.01), torch.tensor([0.01]))


def test_normaliser_falls_to_g_min_when_all_rho_are_equal():
    q = torch.tensor([[5.0, 0.0, 0.0, 0.0]])  # x = 5, a large task spread
    rho = torch.full((1, 4), -0.5)  # P_bar = -0.5 = rho[a_check]: y = 0, no local spread
    assert torch.equal(normaliser(q, rho, eta=0.1, g_min=0.01), torch.tensor([0.01]))


def test_normaliser_applies_the_g_min_floor_only_below_it():
    q = torch.tensor([[0.05, 0.0, 0.0, 0.0], [0.1, 0.0, 0.0, 0.0]])  # x = 0.05 and 0.1
    rho = torch.tensor([[-10.0, 0.0, 0.0, 0.0]] * 2)  # y = 10
    # G = 0.05 / 10 * 1.1 = 0.0055 < 0.01 -> 0.01;  0.1 / 10 * 1.1 = 0.011 >= 0.01 -> kept
    assert torch.allclose(normaliser(q, rho, 0.1, 0.01), torch.tensor([0.01, 0.011]))
    # with a lower floor the first one is kept too
    assert torch.allclose(normaliser(q, rho, 0.1, 0.001), torch.tensor([0.0055, 0.011]))


def test_normaliser_is_the_same_whichever_tied_maximum_or_minimum_is_taken():
    q = torch.tensor([[1.0, 1.0, 0.0, 0.0]])  # a_hat 0 or 1: Q_bar = 1/3 either way, x = 2/3
    rho = torch.tensor([[-1.0, -1.0, 0.0, 0.0]])  # a_check 0 or 1: P_bar = -1/3, y = 2/3
    # G = (2/3) / (2/3) * 1.1 = 1.1
    assert torch.allclose(normaliser(q, rho, 0.1, 0.01), torch.tensor([1.1]))


def test_normaliser_keeps_leading_batch_dimensions_and_does_not_mutate_inputs():
    q = torch.randn(2, 3, 4)
    rho = -torch.rand(2, 3, 4)
    q_before, rho_before = q.clone(), rho.clone()
    assert normaliser(q, rho).shape == (2, 3)
    assert torch.equal(q, q_before) and torch.equal(rho, rho_before)


# -- eq. 2, combined values --------------------------------------------------------------------


def test_combined_values_add_the_scaled_local_values_to_the_task_values():
    q = torch.tensor([[1.0, 2.0, 3.0, 4.0], [0.0, 0.0, 0.0, 0.0]])
    rho = torch.tensor([[-1.0, 0.0, -0.5, 0.0], [-1.0, 0.0, 0.0, 0.0]])
    g = torch.tensor([2.0, 0.01])
    # row 0: [1 - 2, 2, 3 - 1, 4];  row 1: [-0.01, 0, 0, 0]
    expected = torch.tensor([[-1.0, 2.0, 2.0, 4.0], [-0.01, 0.0, 0.0, 0.0]])
    assert torch.allclose(combined_values(q, rho, g), expected)


def _risk_reference(q, rho, eta=0.1, g_min=0.01, threshold=0.5):
    g = normaliser(q, rho, eta=eta, g_min=g_min)
    return combined_values(q, rho, g), g, risk_mask(rho, threshold)


def _risk_cases():
    """Random rows and the corner cases of eqs. 2-3: ties, signed zeros, overflow, A = 1."""
    generator = torch.Generator().manual_seed(26)
    cases = [
        (torch.zeros(1, 4), torch.zeros(1, 4)),  # unvisited: G = g_min
        (torch.tensor([[1.0, 1.0, 0.0, 1.0]]), torch.tensor([[-1.0, 0.0, -1.0, 0.0]])),  # ties
        (torch.tensor([[-0.0, 0.0, -0.0, 0.0]]), torch.tensor([[0.0, -0.0, -0.0, 0.0]])),
        (torch.tensor([[3e38, -3e38, 3e38, 0.0]]), torch.tensor([[-3e38, 3e38, 0.0, -1.0]])),
        (torch.tensor([[1e30, 0.0, 0.0, 0.0]]), torch.tensor([[-1e-30, 0.0, 0.0, 0.0]])),  # inf G
        (torch.tensor([[2.0]]), torch.tensor([[-1.0]])),  # one action: 0 / 0 spreads
        (torch.tensor([2.0, 1.0, 0.5]), torch.tensor([-1.0, 0.0, -0.25])),  # no batch
        (torch.randn(2, 1, 3, generator=generator), -torch.rand(2, 1, 3, generator=generator)),
        (torch.full((1, 4), -1.0), torch.full((1, 4), -1.0)),  # every action risky: all kept
    ]
    for index in range(600):
        rows, actions = 1 + index % 3, 1 + index % 7
        q = torch.randn(rows, actions, generator=generator) * 10 ** (index % 5 - 2)
        rho = -torch.rand(rows, actions, generator=generator)
        if index % 2:  # the tables' values: 0, -1 and running means of them
            rho = (rho * 4).round() / 4
            q = q.round()
        cases.append((q, rho))
    return cases


def test_the_fused_rows_are_eqs_2_3_and_the_mask_bit_for_bit():
    for q, rho in _risk_cases():
        for eta, g_min, threshold in ((0.1, 0.01, 0.5), (0.0, 0.3, 0.25)):
            fused = local_risk_rows(q, rho, eta, g_min, threshold)
            assert fused is not None
            for got, expected in zip(
                fused, _risk_reference(q, rho, eta, g_min, threshold), strict=True
            ):
                assert got.shape == expected.shape and got.dtype == expected.dtype
                if got.dtype == torch.bool:
                    assert torch.equal(got, expected), (q, rho)
                else:  # the same bits (a signed zero or a NaN would show)
                    assert torch.equal(got.view(torch.int32), expected.view(torch.int32)), (q, rho)


def test_the_fused_rows_leave_what_they_do_not_mirror_to_the_tensor_ops():
    q, rho = torch.zeros(1, 4), torch.zeros(1, 4)
    assert local_risk_rows(q.double(), rho.double()) is None  # another dtype
    assert local_risk_rows(torch.zeros(9, 4), torch.zeros(9, 4)) is None  # a large batch
    assert local_risk_rows(q, torch.zeros(2, 4)) is None  # two shapes: broadcasting
    for bad in (math.nan, math.inf):  # finiteness is checked (and reported) by the caller
        assert local_risk_rows(torch.tensor([[bad, 0.0]]), torch.zeros(1, 2)) is None
        assert local_risk_rows(torch.zeros(1, 2), torch.tensor([[0.0, bad]])) is None
    infinities = torch.tensor([[math.inf, -math.inf]])  # (checked on their sum: NaN)
    assert local_risk_rows(infinities, torch.zeros(1, 2)) is None
    assert local_risk_rows(torch.zeros(1, 2), infinities) is None
    grad = torch.ones(1, 4, requires_grad=True)  # read without its graph
    assert torch.equal(local_risk_rows(grad, rho)[0], grad.detach() + 0.01 * rho)


# -- eqs. 1 and 4, targets and update ----------------------------------------------------------


def test_q_learning_target_bootstraps_unless_terminated():
    reward = torch.tensor([-1.0, -2.0, 0.0])
    q_next = torch.tensor([[1.0, 2.0, 3.0, 4.0], [0.0, 0.0, 0.0, 0.0], [5.0, 5.0, 5.0, 5.0]])
    terminated = torch.tensor([False, False, True])
    # -1 + 0.9 * 4 = 2.6;  -2 + 0.9 * 0 = -2;  terminated: the reward alone, 0
    expected = torch.tensor([2.6, -2.0, 0.0])
    target = q_learning_target(reward, q_next, terminated, gamma=0.9)
    assert torch.allclose(target, expected)


def test_a_truncated_transition_still_bootstraps():
    # truncation is not termination: only `terminated` is passed, and it is False here
    reward, q_next = torch.tensor([-1.0]), torch.tensor([[0.0, 2.0, 0.0, 0.0]])
    target = q_learning_target(reward, q_next, torch.tensor([False]), gamma=0.5)
    assert torch.allclose(target, torch.tensor([0.0]))  # -1 + 0.5 * 2


def test_factorq_target_bootstraps_on_the_combined_values_of_the_next_state():
    task_reward = torch.tensor([-1.0, 0.0])
    q_next = torch.tensor([[2.0, 0.0, 1.5, 0.0], [1.0, 1.0, 1.0, 1.0]])
    rho_next = torch.tensor([[-1.0, 0.0, -0.5, 0.0], [0.0, 0.0, 0.0, 0.0]])
    # row 0: Q_bar = 1.5/3 = 0.5, x = 1.5; P_bar = -0.5/3 = -1/6, y = -1/6 + 1 = 5/6;
    #   G = 1.5 / (5/6) * 1.1 = 1.98
    #   C = [2 - 1.98, 0, 1.5 - 0.99, 0] = [0.02, 0, 0.51, 0]: target -1 + 0.9 * 0.51 = -0.541
    # row 1 ends at the goal: the task reward alone, 0
    g = normaliser(q_next, rho_next)
    c_next = combined_values(q_next, rho_next, g)
    target = factorq_target(task_reward, c_next, torch.tensor([False, True]), gamma=0.9)
    assert torch.allclose(target, torch.tensor([-0.541, 0.0]))


def test_q_update_moves_q_a_fraction_alpha_towards_the_target():
    q = torch.tensor([1.0, 0.5, -1.0])
    target = torch.tensor([2.0, -0.541, -1.0])
    # 1 + 0.2 * (2 - 1) = 1.2;  0.5 + 0.2 * (-1.041) = 0.2918;  already there: unchanged
    assert torch.allclose(q_update(q, target, alpha=0.2), torch.tensor([1.2, 0.2918, -1.0]))
    # the paper's form (1 - alpha) Q + alpha target, in exact arithmetic the same
    assert torch.allclose(q_update(q, target, 0.2), 0.8 * q + 0.2 * target)


# -- eq. 5, the running mean -------------------------------------------------------------------


def test_running_mean_update_keeps_rho_the_mean_of_the_rewards_seen():
    rho, kappa = torch.tensor(0.0), torch.tensor(0)
    rho, kappa = running_mean_update(rho, kappa, torch.tensor(-1.0))  # 0 + (-1 - 0) / 1 = -1
    assert (rho.item(), kappa.item()) == (-1.0, 1)
    rho, kappa = running_mean_update(rho, kappa, torch.tensor(0.0))  # -1 + (0 + 1) / 2 = -0.5
    assert (rho.item(), kappa.item()) == (-0.5, 2)
    rho, kappa = running_mean_update(rho, kappa, torch.tensor(-1.0))  # -0.5 - 0.5 / 3 = -2/3
    assert kappa.item() == 3 and rho.item() == pytest.approx(-2 / 3)


def test_running_mean_update_does_not_mutate_its_inputs():
    rho, kappa, reward = torch.tensor([0.5]), torch.tensor([3]), torch.tensor([-1.0])
    running_mean_update(rho, kappa, reward)
    assert rho.item() == 0.5 and kappa.item() == 3 and reward.item() == -1.0


# -- epsilon-greedy with random tie-breaking ---------------------------------------------------


def test_greedy_action_takes_the_unique_maximum_whatever_the_bits():
    values = torch.tensor([[0.0, 0.0, 5.0, 0.0]] * 3)
    bits = torch.tensor([0, 1 << 31, TWO_32 - 1])
    assert torch.equal(greedy_action_from_bits(values, bits), torch.tensor([2, 2, 2]))


def test_greedy_action_breaks_ties_by_the_random_bits():
    values = torch.tensor([[0.0, 3.0, 3.0, 1.0]] * 3 + [[0.0] * 4])
    # two maxima (1, 2): k = bits * 2 >> 32 -> 0, 1, 1;  all four tied: k = 3 * 2**30 * 4 >> 32 = 3
    bits = torch.tensor([0, 1 << 31, TWO_32 - 1, 3 << 30])
    assert torch.equal(greedy_action_from_bits(values, bits), torch.tensor([1, 2, 2, 3]))


def test_epsilon_greedy_explores_below_the_threshold_and_flags_it_even_when_greedy():
    values = torch.tensor([[0.0, 0.0, 5.0, 0.0]] * 3)
    # epsilon = 0.25: explore when explore_bits < 2**30
    explore = torch.tensor([(1 << 30) - 1, (1 << 30) - 1, 1 << 30])
    # random action = bits * 4 >> 32: 2**30 -> 1;  2**31 -> 2 (the greedy one, still flagged)
    random_action = torch.tensor([1 << 30, 1 << 31, 0])
    action, exploratory = epsilon_greedy_from_bits(
        values, 0.25, explore, random_action, torch.zeros(3, dtype=torch.int64)
    )
    assert torch.equal(action, torch.tensor([1, 2, 2]))
    assert torch.equal(exploratory, torch.tensor([True, True, False]))


def test_epsilon_greedy_breaks_all_zero_ties_uniformly():
    generator = torch.Generator().manual_seed(0)
    action, exploratory = epsilon_greedy(torch.zeros(40_000, 4), 0.0, generator)
    counts = torch.bincount(action, minlength=4)
    # each count ~ Binomial(40000, 1/4): mean 10000, sd sqrt(40000 * 3/16) = 86.6; 5 sd = 433
    assert ((counts - 10_000).abs() < 433).all(), counts
    assert not exploratory.any()


def test_epsilon_greedy_explores_a_fraction_epsilon_and_is_greedy_otherwise():
    values = torch.tensor([[0.0, 0.0, 0.0, 1.0]]).expand(40_000, 4)
    generator = torch.Generator().manual_seed(1)
    action, exploratory = epsilon_greedy(values, 0.1, generator)
    # fraction ~ 0.1 with sd sqrt(0.09 / 40000) = 0.0015; 5 sd = 0.0075
    assert abs(exploratory.float().mean().item() - 0.1) < 0.0075
    assert (action[~exploratory] == 3).all()
    # exploratory actions are uniform over the 4 actions: ~1000 each of 4000, sd 27
    counts = torch.bincount(action[exploratory], minlength=4)
    assert ((counts - exploratory.sum() / 4).abs() < 140).all(), counts


def test_epsilon_greedy_with_the_same_generator_seed_repeats_and_does_not_mutate_values():
    values = torch.randn(100, 4)
    before = values.clone()
    first = epsilon_greedy(values, 0.5, torch.Generator().manual_seed(7))
    second = epsilon_greedy(values, 0.5, torch.Generator().manual_seed(7))
    assert torch.equal(first[0], second[0]) and torch.equal(first[1], second[1])
    assert torch.equal(values, before)


# -- the risk gate and risk-aware exploration (issue 39) -----------------------------------------


def test_eq_3_never_lets_the_least_rewarded_actuator_be_greedy_however_small_its_risk():
    # the heading body under sensor noise: forward (0) is the task's choice, a 2% risk
    q = torch.tensor([[1.0, 0.0, 0.0]])  # a_hat = 0, Q_bar = 0, x = 1
    rho = torch.tensor([[-0.02, 0.0, 0.0]])  # a_check = 0, P_bar = 0, y = 0.02
    g = normaliser(q, rho)  # 1 / 0.02 * 1.1 = 55
    assert torch.allclose(g, torch.tensor([55.0]))
    # C = [1 - 55 * 0.02, 0, 0] = [-0.1, 0, 0]: forward loses to both turns
    assert torch.allclose(combined_values(q, rho, g), torch.tensor([[-0.1, 0.0, 0.0]]))


def test_significant_local_keeps_only_values_beyond_the_threshold():
    rho = torch.tensor([[-0.02, 0.0, -0.5, -0.51, 0.6, 0.4]])
    # |rho| > 0.5 kept; -0.5 itself (a collision exactly one time in two) is not significant
    expected = torch.tensor([[0.0, 0.0, 0.0, -0.51, 0.6, 0.0]])
    assert torch.equal(significant_local(rho, 0.5), expected)
    assert torch.equal(rho, torch.tensor([[-0.02, 0.0, -0.5, -0.51, 0.6, 0.4]]))  # not mutated


def test_the_gated_combination_lets_the_task_choose_under_small_risks_and_vetoes_large_ones():
    q = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    rho = torch.tensor([[-0.02, 0.0, 0.0], [-0.9, 0.0, 0.0]])
    gated = significant_local(rho)  # [[0, 0, 0], [-0.9, 0, 0]]
    g = normaliser(q, gated)
    # row 0: y = 0, G = g_min = 0.01, C = Q; row 1: x = 1, y = 0.9, G = 1 / 0.9 * 1.1
    assert torch.allclose(g, torch.tensor([0.01, 1.1 / 0.9]))
    combined = combined_values(q, gated, g)
    # row 1: C_forward = 1 - 1.1 / 0.9 * 0.9 = -0.1 (vetoed, as without the gate)
    assert torch.allclose(combined, torch.tensor([[1.0, 0.0, 0.0], [-0.1, 0.0, 0.0]]))


def test_an_all_zero_or_all_minus_one_table_is_unchanged_by_the_gate():
    rho = torch.tensor([[0.0, -1.0, 0.0, -1.0], [0.0, 0.0, 0.0, 0.0]])
    assert torch.equal(significant_local(rho), rho)


def test_safe_exploration_draws_the_kth_allowed_actuator():
    allowed = torch.tensor([[True, False, True, True]] * 3 + [[False] * 3 + [True]])
    # n = 3 allowed: k = bits * 3 >> 32; 0 -> 0 (actuator 0), 2**31 -> 1 (actuator 2),
    # 2**32 - 1 -> 2 (actuator 3); one allowed: always it
    bits = torch.tensor([0, 1 << 31, TWO_32 - 1, 1 << 31])
    assert torch.equal(safe_exploration_from_bits(allowed, bits), torch.tensor([0, 2, 3, 3]))


def test_risk_aware_epsilon_greedy_explores_only_among_the_actuators_not_risky():
    values = torch.tensor([[0.0, 0.0, 5.0, 0.0]] * 2)
    rho = torch.tensor([[-1.0, 0.0, -0.6, 0.0], [-1.0, -1.0, -1.0, -1.0]])
    allowed = risk_mask(rho)  # [[F, T, F, T], all True: none left]
    explore = torch.zeros(2, dtype=torch.int64)  # both explore
    # row 0: n = 2, bits 2**31 -> k = 1 -> actuator 3; row 1: n = 4, 2**31 -> k = 2
    bits = torch.tensor([1 << 31, 1 << 31])
    action, exploratory = epsilon_greedy_from_bits(
        values, 0.5, explore, bits, torch.zeros(2, dtype=torch.int64), allowed
    )
    assert torch.equal(action, torch.tensor([3, 2]))
    assert bool(exploratory.all())
    # with every actuator allowed it is the paper's uniform draw from the same bits
    uniform, _ = epsilon_greedy_from_bits(values, 0.5, explore, bits, explore)
    everywhere, _ = epsilon_greedy_from_bits(
        values, 0.5, explore, bits, explore, torch.ones(2, 4, dtype=torch.bool)
    )
    assert torch.equal(uniform, everywhere)


# -- eqs. 2-3 with local rewards of either sign (issue 40, item 2) -----------------------------


@pytest.mark.parametrize("shift", [-2.0, -1.0, 0.5, 1.0, 3.0])
def test_eqs_2_and_3_do_not_see_the_sign_of_the_local_rewards(shift):
    """``G`` depends on ``rho`` only through ``P_bar - rho[a_check]``, a difference, and eq. 2
    adds ``G * shift`` to every action alike: adding a constant to ``rho`` changes neither ``G``
    (up to the rounding of the mean) nor the greedy action (where no two actions tie within
    that rounding)."""
    generator = torch.Generator().manual_seed(0)
    q = torch.randint(-8, 9, (256, 4), generator=generator).double() / 4
    rho = torch.randint(-4, 1, (256, 4), generator=generator).double() / 2  # collisions: <= 0
    shifted = rho + shift  # rewards of the other sign, or of both
    g, g_shifted = normaliser(q, rho), normaliser(q, shifted)
    assert torch.allclose(g, g_shifted, rtol=1e-12, atol=0)
    combined = combined_values(q, rho, g)
    top2 = combined.topk(2, dim=-1).values
    clear = (top2[:, 0] - top2[:, 1]) > 1e-9  # a tie within rounding may break either way
    assert int(clear.sum()) > 128
    greedy = combined.argmax(-1)
    assert torch.equal(greedy[clear], combined_values(q, shifted, g_shifted).argmax(-1)[clear])


def test_a_paying_actuator_is_always_greedy_as_a_colliding_one_never_is():
    # q: the task prefers action 0 (x = Q(a_hat) - Q_bar = 3 - 1 = 2)
    q = torch.tensor([3.0, 0.0, 1.0, 2.0])
    # one actuator pays (rho = +1, a charger under the body), the others nothing:
    # a_check = 0 (the first minimum, 0), P_bar = (1 + 0 + 0) / 3, y = 1/3, G = 2 / (1/3) * 1.1
    paying = torch.tensor([0.0, 1.0, 0.0, 0.0])
    g = normaliser(q, paying, eta=0.1, g_min=0.01)
    assert torch.allclose(g, torch.tensor(6.6))
    assert combined_values(q, paying, g).argmax().item() == 1  # 0 + 6.6 against 3
    # the same with a collision: a_check = 1, P_bar = 0, y = 1, G = 2.2; action 1 is never chosen
    colliding = -paying
    g = normaliser(q, colliding, eta=0.1, g_min=0.01)
    assert torch.allclose(g, torch.tensor(2.2))
    assert combined_values(q, colliding, g).argmax().item() == 0
    # the bound behind it (docs/decisions.md): Q(a_hat) - Q(a) <= (A - 1) x for every a, and
    # a lone paying actuator gets G rho = (1 + eta) (A - 1) x: more than any task preference
    assert (q.max() - q).max() <= 3 * 2.0
