"""benchmarks/structure_evidence.py's body flip model (issue 39, item 5): hand-computed cases of
its likelihood (nothing timed here; the comparison itself is in docs/decisions.md)."""

from __future__ import annotations

import math

import pytest
import torch

from factorq_torch.functional import candidate_sets, mixture_log_marginal


@pytest.fixture(scope="module")
def evidence(script):
    return script("benchmarks/structure_evidence.py")


def test_one_firing_cannot_tell_a_sensor_from_no_sensor(evidence):
    # one collision with sensor 0 reading an obstacle and sensor 1 free: "no sensor" is E[q] = 1/2
    # (the rate grid and Beta(1/4, 1/4) are symmetric); a single is E[p1] or E[p0] under its two
    # labellings, and p0(1 - q) = 1 - p1(q), so (E[p1] + 1 - E[p1]) / 2 = 1/2 at every flip rate
    sets = candidate_sets(2)
    scores = evidence.flip_scores(torch.tensor([[1, 0]]), torch.tensor([1.0]), sets)
    assert scores.shape == (1, len(sets), len(evidence.FLIP_GRID))
    for index in (sets.index(()), sets.index((0,)), sets.index((1,))):
        torch.testing.assert_close(
            scores[0, index], torch.full_like(scores[0, index], -math.log(2))
        )
    # the pair keeps the mixture: one visited pattern with n = s = 1, the same at every rate
    pair = mixture_log_marginal(torch.tensor([1.0]), torch.tensor([1.0]))
    torch.testing.assert_close(scores[0, sets.index((0, 1))], pair.expand(len(evidence.FLIP_GRID)))


def test_a_single_is_the_flip_model_summed_over_the_rate_grid(evidence):
    # three firings, written out: (reading, collided) = (1, 1), (0, 0), (1, 0); under the
    # labelling "obstacle = collides" the single's likelihood at (q, eps) is p1 (1 - p0) (1 - p1),
    # under the other one p0 (1 - p1) (1 - p0); each summed over the rate grid with its weights
    bits = torch.tensor([[1], [0], [1]])
    collided = torch.tensor([1.0, 0.0, 0.0])
    sets = candidate_sets(1)
    scores = evidence.flip_scores(bits, collided, sets)[-1]
    weights = evidence.LOG_RATE_PRIOR.exp().tolist()
    for k, eps in enumerate(evidence.FLIP_GRID.tolist()):
        direct = inverse = none = 0.0
        for w, q in zip(weights, evidence.RATE_GRID.tolist(), strict=True):
            p1 = (1 - eps) * q / ((1 - eps) * q + eps * (1 - q))
            p0 = eps * q / (eps * q + (1 - eps) * (1 - q))
            direct += w * p1 * (1 - p0) * (1 - p1)
            inverse += w * p0 * (1 - p1) * (1 - p0)
            none += w * q * (1 - q) * (1 - q)
        single = float(scores[sets.index((0,)), k])
        assert single == pytest.approx(math.log((direct + inverse) / 2), rel=1e-9), k
        assert float(scores[sets.index(()), k]) == pytest.approx(math.log(none), rel=1e-9)
    # the disagreement costs the single against "no sensor" at the smallest flip rate, and less
    # at the largest (where a reading says almost nothing: within 0.01 nats of "no sensor")
    single, nothing = scores[sets.index((0,))], scores[sets.index(())]
    assert float(single[0]) < float(nothing[0]) - 2
    assert float(single[-1]) == pytest.approx(float(nothing[-1]), abs=0.01)
