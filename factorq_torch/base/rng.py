"""Counter-based random numbers: one independent stream per experiment, identical everywhere.

Every random decision of the project (the obstacle scatter of the world, exploration and
tie-breaking of the policies) is a pure function of a 64-bit *key* and a *counter*:

    bits = mix64(key + (counter + 1) * GOLDEN) >> 32        (SplitMix64, Steele et al. 2014)

Each experiment of a batch owns its keys (derived from the seed and its index in the batch) and its
counters, so

- nothing is shared across the batch: experiment ``i`` draws the same numbers whatever the batch
  size, the thread count or the order in which experiments are computed;
- the state of a stream is one integer, which makes checkpoints and exact resumes trivial;
- the compiled fast path (``trainers/compiled/_kernel.c``) draws bit-identical numbers, so it can be
  tested for equality with the pure-torch path, not merely for closeness.

Tensors hold the unsigned 64-bit arithmetic in ``int64``: additions and products wrap modulo
2**64 exactly as unsigned ones do, and right shifts are made logical by masking.
"""

from __future__ import annotations

import torch

MASK64 = (1 << 64) - 1
GOLDEN = 0x9E3779B97F4A7C15
_MIX1 = 0xBF58476D1CE4E5B9
_MIX2 = 0x94D049BB133111EB

# Streams: one constant per consumer, so that e.g. the world and the policy of one experiment
# never draw the same numbers.
STREAM_WORLD = 1
STREAM_POLICY = 2
STREAM_LAYOUT = 3
STREAM_EXPERIMENT = 4
STREAM_TASK_NETWORK = 5  # initial weights of a task Q-network
STREAM_LOCAL_NETWORK = 6  # initial weights of a local reward network

#: Draws the policy makes per step: explore?, random action, tie-break.
POLICY_DRAWS_PER_STEP = 3


def as_int64(value: int) -> int:
    """The int64 with the same low 64 bits as ``value`` (the streams' arithmetic wraps modulo
    2**64: an int64 tensor takes it)."""
    value &= MASK64
    return value - (1 << 64) if value >= 1 << 63 else value


def _shr(z: torch.Tensor, k: int) -> torch.Tensor:
    """Logical right shift of int64 bit patterns."""
    return (z >> k) & ((1 << (64 - k)) - 1)


def _xor_shr_(z: torch.Tensor, k: int) -> torch.Tensor:
    """``z ^= z >>> k`` (logical shift) in place on ``z``, through one temporary."""
    shifted = z >> k
    shifted &= (1 << (64 - k)) - 1
    return z.bitwise_xor_(shifted)


def mix64(z: torch.Tensor) -> torch.Tensor:
    """SplitMix64's finaliser on int64 bit patterns (a bijection of 64-bit words).

    The input is not modified: the first step writes a new tensor, the others work in place on
    it (the same values; half the allocations, which at ``[4096, 10]`` also cost page faults).
    """
    z = z ^ _shr(z, 30)
    z *= as_int64(_MIX1)
    _xor_shr_(z, 27)
    z *= as_int64(_MIX2)
    return _xor_shr_(z, 31)


def mix64_int(z: int) -> int:
    """``mix64`` on a Python int (unsigned 64-bit), the reference for tests and key derivation."""
    z &= MASK64
    z = ((z ^ (z >> 30)) * _MIX1) & MASK64
    z = ((z ^ (z >> 27)) * _MIX2) & MASK64
    return z ^ (z >> 31)


def random_bits(key: torch.Tensor, counter: torch.Tensor | int) -> torch.Tensor:
    """32 uniformly random bits, as int64 in ``[0, 2**32)``, for each ``(key, counter)`` pair.

    ``key`` and ``counter`` broadcast against each other. Inputs are not modified.
    """
    if isinstance(counter, int):  # a Python int would overflow int64 before wrapping
        z = key + as_int64((counter + 1) * GOLDEN)
    else:
        z = key + (counter + 1) * as_int64(GOLDEN)
    z = mix64(z)  # (a new tensor: the top half shifted down in place)
    z >>= 32
    return z.bitwise_and_(0xFFFFFFFF)


def random_bits_int(key: int, counter: int) -> int:
    """``random_bits`` on Python ints: the slow reference the tensor version is tested against."""
    return mix64_int(key + (counter + 1) * GOLDEN) >> 32


def randint_from_bits(
    bits: torch.Tensor, n: torch.Tensor | int, *, in_place: bool = False
) -> torch.Tensor:
    """An integer in ``[0, n)`` from 32 random bits (multiply-shift; ``n < 2**31``).

    ``in_place``: written over ``bits`` (a tensor nothing reads again) instead of a new one.
    """
    product = bits.mul_(n) if in_place else bits * n
    product >>= 32
    return product


def probability_threshold(probability: float) -> int:
    """``bits < threshold`` happens with ``probability`` (to 2**-32) for 32 random bits.

    Comparing integers keeps the decision identical in every implementation.
    """
    if not 0.0 <= probability <= 1.0:  # False for NaN too
        raise ValueError(f"probability={probability!r} is out of range: must be in [0, 1]")
    return round(probability * (1 << 32))


def derive_keys(seed: int, stream: int, count: int, offset: int = 0) -> torch.Tensor:
    """Keys ``[count]`` (int64) of ``stream`` for experiments ``offset .. offset + count - 1``.

    A key depends on ``(seed, stream, index)`` only, so experiment ``i`` of a batch of 600 draws
    exactly what it draws in a batch of one that starts at ``offset=i``.
    """
    for name, value in (("count", count), ("offset", offset)):
        if value < 0:
            raise ValueError(f"{name}={value} is out of range: must be >= 0")
    base = mix64_int(mix64_int(seed * GOLDEN + stream) + stream * _MIX1)
    keys = [as_int64(mix64_int(base + (offset + i + 1) * GOLDEN)) for i in range(count)]
    return torch.tensor(keys, dtype=torch.int64)


# Sub-streams of a world key (``substream_key``): the sensors' and actuators' randomness of a
# world never overlaps its obstacle scatter, and the paper's world (which draws none of them)
# keeps its stream positions exactly.
SUBSTREAM_DISTRACTOR = 1
SUBSTREAM_SENSOR_NOISE = 2
SUBSTREAM_ACTUATOR_NOISE = 3
SUBSTREAM_PERMUTATION = 4


def substream_key(key: torch.Tensor, substream: int) -> torch.Tensor:
    """The key of ``substream`` of each key ``[...]`` int64: ``mix64(key + substream * MIX1)``."""
    return mix64(key + as_int64(substream * _MIX1))


def substream_key_int(key: int, substream: int) -> int:
    """``substream_key`` on a Python int (unsigned 64-bit result)."""
    return mix64_int(key + substream * _MIX1)
