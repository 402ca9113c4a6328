"""Counter-based random streams (base/rng.py): tensor version == Python-int version."""

import pytest
import torch

from factorq_torch.base.rng import (
    MASK64,
    STREAM_POLICY,
    STREAM_WORLD,
    derive_keys,
    probability_threshold,
    randint_from_bits,
    random_bits,
    random_bits_int,
)

INT64_MIN, INT64_MAX = -(1 << 63), (1 << 63) - 1
EDGE_KEYS = [0, 1, -1, INT64_MIN, INT64_MAX, INT64_MIN + 1, 0x5DEECE66D, -0x5DEECE66D]


def many_keys() -> list[int]:
    """Edge values plus derived keys, about half of them negative as int64."""
    derived = derive_keys(12345, STREAM_WORLD, 64).tolist()
    assert any(k < 0 for k in derived) and any(k > 0 for k in derived)
    return EDGE_KEYS + derived


def test_tensor_random_bits_equal_python_int_reference_for_many_keys_and_counters():
    keys = torch.tensor(many_keys())  # [K]
    counters = torch.tensor([0, 1, 2, 3, 17, 999, 123_456, 2**31 - 1, 2**40 + 5])  # [C]
    bits = random_bits(keys.unsqueeze(1), counters.unsqueeze(0))  # [K, C]
    for i, key in enumerate(keys.tolist()):
        for j, counter in enumerate(counters.tolist()):
            expected = random_bits_int(key & MASK64, counter)
            assert bits[i, j].item() == expected, (key, counter)
            # The Python version wraps a negative key the same way as its unsigned pattern.
            assert random_bits_int(key, counter) == expected


def test_random_bits_are_32_bit_values_and_inputs_are_not_modified():
    keys = torch.tensor(many_keys())
    counters = torch.arange(keys.numel())
    keys_before, counters_before = keys.clone(), counters.clone()
    bits = random_bits(keys, counters)
    assert bits.dtype == torch.int64
    assert bool(((bits >= 0) & (bits < 2**32)).all())
    assert torch.equal(keys, keys_before) and torch.equal(counters, counters_before)


def test_random_bits_of_one_key_look_uniform_and_differ_between_counters():
    bits = random_bits(torch.tensor([-7]), torch.arange(20_000))  # [20000]
    assert bits.unique().numel() == bits.numel()  # 32-bit collisions are ~5% likely; none here
    # Mean of uniform [0, 2**32) is 2**31 with sd 2**32 / sqrt(12 n): allow 5 sd.
    sd = 2**32 / (12 * bits.numel()) ** 0.5
    assert abs(bits.double().mean().item() - 2**31) < 5 * sd


def test_derive_keys_of_an_experiment_do_not_depend_on_count_or_offset():
    batch = derive_keys(3, STREAM_WORLD, 8)  # [8]
    for i in range(8):
        assert derive_keys(3, STREAM_WORLD, 1, offset=i).item() == batch[i].item()
    assert torch.equal(derive_keys(3, STREAM_WORLD, 3, offset=5), batch[5:])
    assert torch.equal(derive_keys(3, STREAM_WORLD, 600)[:8], batch)


def test_derive_keys_differ_between_seeds_streams_and_experiments():
    keys = torch.cat(
        [
            derive_keys(0, STREAM_WORLD, 50),
            derive_keys(1, STREAM_WORLD, 50),
            derive_keys(0, STREAM_POLICY, 50),
            derive_keys(-1, STREAM_WORLD, 50),
        ]
    )
    assert keys.dtype == torch.int64
    assert keys.unique().numel() == keys.numel()


def test_derive_keys_are_deterministic():
    assert torch.equal(derive_keys(42, STREAM_WORLD, 16), derive_keys(42, STREAM_WORLD, 16))


@pytest.mark.parametrize("n", [1, 2, 3, 4, 7, 97, 2**31 - 1])
def test_randint_from_bits_stays_in_range_including_extreme_bits(n):
    bits = torch.cat(
        [torch.tensor([0, 1, 2**31, 2**32 - 1]), random_bits(torch.tensor([9]), torch.arange(5000))]
    )
    values = randint_from_bits(bits, n)
    assert bool(((values >= 0) & (values < n)).all())
    assert randint_from_bits(torch.tensor([2**32 - 1]), n).item() == n - 1
    assert randint_from_bits(torch.tensor([0]), n).item() == 0


def test_randint_from_bits_is_uniform_over_a_small_range():
    n, draws = 7, 70_000
    values = randint_from_bits(random_bits(torch.tensor([123]), torch.arange(draws)), n)
    counts = torch.bincount(values, minlength=n).double()
    expected = draws / n
    chi_square = (((counts - expected) ** 2) / expected).sum().item()
    assert chi_square < 40  # 6 degrees of freedom: P(chi2 > 40) ~ 5e-7


def test_randint_from_bits_accepts_a_tensor_of_ranges():
    bits = torch.tensor([2**32 - 1, 2**32 - 1, 2**31])
    assert randint_from_bits(bits, torch.tensor([1, 10, 10])).tolist() == [0, 9, 5]


def test_probability_threshold_is_exact_at_the_ends_and_rounds_in_between():
    assert probability_threshold(0.0) == 0
    assert probability_threshold(1.0) == 2**32  # every 32-bit value is below it
    assert probability_threshold(0.5) == 2**31
    assert probability_threshold(0.01) == round(0.01 * 2**32) == 42_949_673


def test_probability_threshold_gives_the_requested_frequency():
    draws = 200_000
    bits = random_bits(torch.tensor([-99]), torch.arange(draws))
    frequency = (bits < probability_threshold(0.01)).double().mean().item()
    sd = (0.01 * 0.99 / draws) ** 0.5
    assert abs(frequency - 0.01) < 5 * sd


def test_random_bits_accept_a_python_int_counter_including_large_ones():
    keys = torch.tensor(many_keys())
    for counter in (0, 5, 2**40, 2**62):
        bits = random_bits(keys, counter)
        assert bits.tolist() == [random_bits_int(k & MASK64, counter) for k in keys.tolist()]
