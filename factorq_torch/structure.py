"""Learned sensor-actuator dependencies: Factor-Q that finds its own pairing.

The paper hand-pairs each actuator with its sensor (section 5.2, footnote 2) and names learning
that pairing as future work. ``StructureLearner`` is a local value provider (it writes
``local_value`` ``[S, A]`` like ``LocalRewardTable`` and owns an ``update_running_mean`` that
``FactorQLoss`` applies as eq. 5), told nothing about the body but ``A`` and ``K``.

**Candidates.** For every actuator ``a`` the candidate parent sets are "no sensor", every single
sensor ``j`` and, with ``max_parents=2`` (the default and the cap), every pair ``{j, k}``:
``C = 1 + K + K (K - 1) / 2`` candidates (529 for 32 sensors). Larger sets are refused
(``MAX_CANDIDATE_PARENTS``): triples would be ``O(K**3)`` tables per actuator and experiment.

**Counts.** Per (experiment, actuator, candidate, pattern of the candidate's sensors read
*before* acting): the times the actuator fired ``n``, the sum of its "successes" ``y`` and the sum
of its local rewards ``r``. Every firing updates one pattern of every candidate of the fired
actuator.

**Likelihood.** The local reward of the collision world is 0 or -1: ``y = -r`` is a Bernoulli
outcome. A local reward outside ``{0, -1}`` is read as the fractional success ``y = clip(-r, 0,
1)`` (a Beta-Bernoulli likelihood with fractional counts, still a proper conjugate update:
``lgamma`` takes real arguments); rewards above 0 count as 0 and below -1 as -1 for the structure
only, while the prediction uses the real rewards (their running mean). Each pattern of a
candidate has its own rate with a ``Beta(prior_a, prior_b)`` prior (default ``Beta(1/4, 1/4)``:
the collisions of a body are near-deterministic given the right sensors, so a rate near 0 or 1 is
likely a priori and one counterexample counts against a candidate), so the marginal likelihood
of candidate ``c`` is

    log p(D | c) = sum_patterns [ lgamma(a + s) + lgamma(b + n - s) - lgamma(a + b + n)
                                  - lgamma(a) - lgamma(b) + lgamma(a + b) ]

in float64 (``beta_bernoulli_log_marginal``; ``likelihood="pattern"``). By default
(``likelihood="mixture"``) each pattern's rate comes from a clean population (that
``Beta(prior_a, prior_b)``) or a noisy one (``functional.NOISY_PRIOR``, a sensor that reads wrong
leaves the rate anywhere in between), at the more probable of the two
(``functional.mixture_log_marginal``); ``likelihood="flip"`` gives each candidate one flip rate
between its patterns' labels and the outcomes (``functional.flip_log_marginal``). Derivations and
measurements: docs/decisions.md, "Learned dependencies with noisy sensors". The prior
over candidates (``candidate_log_prior``,
``prior``) is by default ``"sparse"``: "no sensor" and the single sensors (together) the same
mass, all pairs together 1/100 of it, uniform within a size (``"size"``: every size the same
mass; ``"uniform"``: every candidate the same).

**Pair pruning.** With ``pairs="pruned"`` (``factorq dependencies``' default) a pair ``{j, k}`` is
counted and scored only while it is *active* (``functional.pair_activity``). No pair is active while
"no sensor" or a single explains every firing (no outcome against one of its patterns' majority,
``functional.single_explains``: a pair that explains them as well splits that candidate's patterns,
which lowers the marginal, and one with a mixed pattern pays for it, so no pair is needed); before
any data, so, none is. Otherwise a pair is active while one of its singles is plausible (log
posterior within ``log(bayes_factor)`` of the best active candidate: the evidence has not ruled out
that ``j`` matters), while it is plausible itself, or while it is committed to. An inactive pair has
no log posterior (``-inf``: no commitment, prediction or change-point test reads it). When it
enters, its counts are rebuilt from the experiment's stored firings since the actuator's last reset
(``functional.rebuild_pair_counts``), in firing order: the integer counts, and the sums of a
collision world's rewards, are exactly those that counting it at every firing would have left, so a
pair's evidence is never lost, only not looked at while its sensors are ruled out. After the first
firings, a firing costs ``O(K + active pairs)`` instead of ``O(K**2)``; the history costs one entry
per firing. ``pairs="all"`` counts every pair always.

**Commitment.** Until it commits, actuator ``a``'s local value is, by ``prediction``:
``"optimistic"`` (the default) the largest running mean ``rho_c[o_c]`` among the *plausible*
candidates, those whose log posterior is within ``log(bayes_factor)`` of the best (a firing is
avoided only when every structure not yet ruled out predicts a loss); ``"map"`` the running mean
of the maximum a posteriori candidate; ``"posterior"`` the posterior-weighted running mean
``sum_c p(c | D) rho_c[o_c]``; ``"committed"`` 0. An unvisited pattern predicts 0, as an
unvisited table entry does. (Why optimistic: ``docs/decisions.md``, "Learned dependencies".)
It commits to the maximum a posteriori candidate ``c*`` when ``c*`` beats every
*competitor* by the Bayes factor ``bayes_factor`` (default 300; posterior odds, the prior
included). The competitors of ``c*`` are all candidates but its strict supersets; the competitors
of "no sensor" are the single sensors. Why supersets are left out: a superset ``c* + {x}`` with
an irrelevant ``x`` predicts what ``c*`` predicts, and its Occam penalty grows only like
``log n`` (about ``n0 n1 / 16`` for a deterministic single sensor seen ``n0`` and ``n1`` times per
reading with ``Beta(1, 1)``; more slowly with a sharper prior), so requiring it would delay
every commitment to hundreds of samples; a superset whose extra sensor matters overtakes ``c*``
at a rate linear in ``n`` and becomes the MAP itself. Once committed, the actuator's local value
is the committed candidate's running mean.

**Reopening.** Alongside the counts, the learner keeps the same counts over a *block* of the last at
most ``window`` firings of each actuator (restarted every ``window`` firings). A Bayesian
change-point test compares "nothing changed": the committed candidate ``c*`` predicting the block
from the data before it, ``p(block | c*, earlier) = p(all | c*) / p(earlier | c*)``, against "a
change before the block": the best candidate (``c*`` included) fitted afresh to the block alone,
both with their prior. When the change wins by ``reopen_factor`` (default ``bayes_factor``), the
actuator reopens: it forgets all its counts (``reopen="body"``, the default: every actuator of the
experiment does, a body changes as a whole) (the block's too: the block may straddle the change, and
restarting from it recommitted to the old structure in most experiments of the ``change`` setting)
and commits again by the rule above. Comparing only fresh fits on the block would not do: an agent
that keeps repeating one action in one place (into a wall its stale table calls safe) produces data
every candidate fits equally well, while the stale prediction is refuted after a few collisions.

**The noise gate.** With sensors that read wrong a fraction ``eps`` of the time, a pattern's
collision rate is ``(1 - eps) q / ((1 - eps) q + eps (1 - q))`` for the pattern that reads an
obstacle, where ``q`` is how often the actuator fires towards one: it drifts as the policy learns,
so the block test raises alarms that are no change of structure; with clean sensors the rates
are 0 and 1 whatever ``q``. A clean pairing is deterministic, so a commitment whose data hold an
outcome against one of its patterns' majority (``functional.has_minority``, read at the moment
of commitment, when the data are of one structure) shows that the sensors read wrong:
``noise_seen`` is set for the experiment (kept through reopenings, cleared by ``reset``) and the
test asks for ``noisy_reopen_factor`` instead (``docs/decisions.md``, "The noise gate").

The float64 operations run in a fixed order (``functional.log_posterior_of``: left-to-right sums
over patterns; ``argmax``: the first maximum), which the compiled path (``trainers/_kernel.c``)
repeats bit for bit for every prediction but ``"posterior"`` (its ``exp``).

Keys: reads ``sensors`` ``[S, K]`` bool, writes ``local_value`` ``[S, A]`` float32.
"""

from __future__ import annotations

import math
import operator
from functools import reduce
from itertools import islice

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch.autograd.graph import increment_version

from factorq_torch.base import keys
from factorq_torch.base.indices import row_starts, scalar
from factorq_torch.base.validation import check_float, check_int
from factorq_torch.functional import (
    LIKELIHOODS,
    MAX_CANDIDATE_PARENTS,
    MAX_SENSORS,
    NOISY_ODDS,
    NOISY_PRIOR,
    PAIR_MODES,
    PREDICTIONS,
    REOPENINGS,
    ROW_KERNEL_VALUES,
    beta_bernoulli_log_marginal,
    candidate_log_prior,
    candidate_sets,
    competitor_mask,
    flip_log_marginal,
    has_minority,
    initial_activity,
    log_posterior_of,
    mixture_log_marginal,
    pair_activity,
    pair_members,
    posterior_weights,
    rebuild_pair_counts,
    single_explains,
)
from factorq_torch.tables import _check_entry, check_batch, check_firing, check_mask

#: The read update (``StructureLearner._update_read``) looks ``lgamma`` up in tables for counts
#: below this (a few MiB of tables at most); larger counts go through ``torch.lgamma``.
_LGAMMA_TABLE_COUNTS = 8192
#: The read path's memo by reading is cleared when it reaches this many entries.
_MEMO_SIZE = 1 << 16


class StructureLearner(TensorDictModuleBase):
    """A local value provider that learns each actuator's parent sensors (module docstring).

    Args:
        num_experiments: ``S``.
        num_actions: ``A``, the actuators.
        num_sensors: ``K``, the sensors the agent receives.
        max_parents: the largest candidate parent set, 0..2 (default 2: pairs).
        bayes_factor: the posterior odds at which the best candidate is committed to (and at
            which evidence on the recent block reopens it, unless ``reopen_factor`` is given);
            must be > 1.
        reopen_factor: the posterior odds of the change-point test at which a commitment is
            reopened (``None``: ``bayes_factor``); must be > 1. A higher one ignores more false
            alarms under sensor noise and notices a changed body later.
        noisy_reopen_factor: the change-point test's odds once the experiment's sensors are
            known to read wrong (``noise_seen``: a commitment rested on data with an outcome
            against its pattern's majority, ``functional.has_minority``; ``None``:
            ``reopen_factor``). Under noise a pattern's collision rate drifts with the policy, so
            the block test raises false alarms that a clean body does not (module docstring);
            ``factorq dependencies`` uses 10,000.
        window: firings per actuator in the block the reopening test reads.
        prior_a, prior_b: the Beta prior of every pattern's rate (``likelihood="pattern"``;
            ``"mixture"``: of the clean population) or of every candidate's flip rate
            (``"flip"``).
        pairs: ``"all"`` (the default here: every pair at every firing, as every experiment
            built on the learner has measured it) or ``"pruned"`` (a pair is counted and scored
            only while it is active, ``functional.pair_activity``; module docstring: the same
            counts where a pair is counted, a fraction of the work with many sensors; the
            default of ``factorq dependencies`` and of the compiled path's
            ``StructureOptions``).
        likelihood: ``"mixture"`` (the default: each pattern's rate from a clean or a noisy
            population, sensors may read wrong), ``"pattern"`` (each pattern its own rate under
            ``Beta(prior_a, prior_b)``) or ``"flip"`` (one flip rate per candidate between its
            patterns' labels and the outcomes); module docstring.
        prior: the prior over candidates, ``"size"``, ``"sparse"`` or ``"uniform"``
            (``candidate_log_prior``).
        prediction: what an open actuator predicts: ``"optimistic"``, ``"map"``, ``"posterior"``
            or ``"committed"`` (module docstring).
        reopen: what a reopening forgets: ``"body"`` (every actuator) or ``"actuator"``.
        sensors_key: where the sensors are read.
        device: where the counts live.

    Buffers: ``count``, ``successes``, ``reward_sum`` ``[S, A, C, 4]`` float64 (and their
    ``block_*`` twins), ``committed`` ``[S, A]`` int64 (candidate index, -1 while open),
    ``samples`` ``[S, A]`` int64 (firings so far), ``reopened`` ``[S, A]`` int64 (how often),
    ``noise_seen`` ``[S]`` bool (the experiment's sensors read wrong: ``noisy_reopen_factor``).

    Example:
        >>> learner = StructureLearner(1, num_actions=1, num_sensors=3)
        >>> generator = torch.Generator().manual_seed(0)
        >>> for step in range(60):  # sensor 1 decides the collision
        ...     sensors = torch.rand(1, 3, generator=generator) < 0.5
        ...     reward = -sensors[:, 1:2].float()
        ...     learner.update_running_mean(sensors, torch.tensor([0]), reward)
        >>> learner.structure()[0].nonzero().tolist()
        [[0, 1]]
    """

    def __init__(
        self,
        num_experiments: int,
        *,
        num_actions: int,
        num_sensors: int,
        max_parents: int = MAX_CANDIDATE_PARENTS,
        bayes_factor: float = 300.0,
        window: int = 100,
        prior_a: float = 0.25,
        prior_b: float = 0.25,
        prior: str = "sparse",
        prediction: str = "optimistic",
        reopen: str = "body",
        reopen_factor: float | None = None,
        noisy_reopen_factor: float | None = None,
        likelihood: str = "mixture",
        pairs: str = "all",
        sensors_key: str = keys.SENSORS,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__()
        self.num_experiments = check_int("num_experiments", num_experiments, 1)
        self.num_actions = check_int("num_actions", num_actions, 1)
        self.num_sensors = check_int("num_sensors", num_sensors, 1, MAX_SENSORS)
        self.sets = candidate_sets(num_sensors, max_parents)
        self.max_parents = max_parents
        if not isinstance(bayes_factor, (int, float)) or not bayes_factor > 1:
            raise ValueError(
                f"bayes_factor={bayes_factor!r} must be > 1: a commitment needs evidence for the "
                f"best candidate over the runner-up"
            )
        if not math.isfinite(bayes_factor):
            raise ValueError(f"bayes_factor={bayes_factor!r} must be finite")
        for name, value in (("prior_a", prior_a), ("prior_b", prior_b)):
            if not isinstance(value, (int, float)) or not value > 0 or not math.isfinite(value):
                raise ValueError(f"{name}={value!r} must be a finite number > 0")
        self.bayes_factor = float(bayes_factor)
        self.log_bayes_factor = math.log(self.bayes_factor)
        for name, factor in (
            ("reopen_factor", reopen_factor),
            ("noisy_reopen_factor", noisy_reopen_factor),
        ):
            if factor is not None:
                check_float(name, factor, 1.0, math.inf, low_open=True, high_open=True)
        self.reopen_factor = self.bayes_factor if reopen_factor is None else float(reopen_factor)
        self.log_reopen_factor = math.log(self.reopen_factor)
        self.noisy_reopen_factor = (
            self.reopen_factor if noisy_reopen_factor is None else float(noisy_reopen_factor)
        )
        self.log_noisy_reopen_factor = math.log(self.noisy_reopen_factor)
        self.window = check_int("window", window, 1)
        if prediction not in PREDICTIONS:
            raise ValueError(f"prediction={prediction!r} is unknown: choose one of {PREDICTIONS}")
        self.prediction = prediction
        if reopen not in REOPENINGS:
            raise ValueError(f"reopen={reopen!r} is unknown: choose one of {REOPENINGS}")
        self.reopen = reopen
        if likelihood not in LIKELIHOODS:
            raise ValueError(f"likelihood={likelihood!r} is unknown: choose one of {LIKELIHOODS}")
        self.likelihood = likelihood
        if pairs not in PAIR_MODES:
            raise ValueError(f"pairs={pairs!r} is unknown: choose one of {PAIR_MODES}")
        self.pairs = pairs
        self.pruned = pairs == "pruned" and max_parents >= 2 and num_sensors >= 2
        self.prior = prior
        self.prior_a, self.prior_b = float(prior_a), float(prior_b)
        self.sensors_key = sensors_key
        self.in_keys = [sensors_key]
        self.out_keys = [keys.LOCAL_VALUE]
        num_candidates = len(self.sets)
        self.num_candidates = num_candidates
        patterns = 1 << min(max_parents, num_sensors)
        self._pattern_count = patterns  # P, the last dimension of the counts (read paths)
        # Weights [C, K]: 2**r where sensor k is the r-th member of candidate c (parent_weights).
        weights = torch.zeros(num_candidates, num_sensors, dtype=torch.int64)
        members = torch.zeros(num_candidates, num_sensors, dtype=torch.bool)
        for index, parents in enumerate(self.sets):
            for rank, sensor in enumerate(parents):
                weights[index, sensor] = 1 << rank
                members[index, sensor] = True
        self.register_buffer("weights", weights.to(device))
        self.register_buffer("members", members.to(device))
        self.register_buffer("log_prior", candidate_log_prior(self.sets, prior).to(device))
        self.register_buffer("competitors", competitor_mask(self.sets).to(device))
        # pair pruning (pairs="pruned"): which candidates are counted, and the firings since the
        # last reset of each experiment (every actuator's, in order) to rebuild an entering pair
        self.register_buffer("pair_members", pair_members(self.sets).to(device))
        small = torch.tensor([len(parents) < 2 for parents in self.sets])
        self.register_buffer("small", small.to(device))
        self.register_buffer(  # derived: not in the state dict
            "small_index", small.nonzero().flatten().to(device), persistent=False
        )
        initial = initial_activity(self.sets)
        if not self.pruned:
            initial = torch.ones_like(initial)
        self.register_buffer("initial_active", initial.to(device))
        self.register_buffer(
            "active", initial.to(device).expand(num_experiments, num_actions, -1).clone()
        )
        for name in ("history_start", "block_start"):
            self.register_buffer(
                name, torch.zeros(num_experiments, num_actions, dtype=torch.int64, device=device)
            )
        self.register_buffer(
            "history_length", torch.zeros(num_experiments, dtype=torch.int64, device=device)
        )
        capacity = 64 if self.pruned else 0
        for name, dtype in (
            ("history_readings", torch.int64),
            ("history_action", torch.int64),
            ("history_reward", torch.float64),
        ):
            self.register_buffer(
                name, torch.zeros(num_experiments, capacity, dtype=dtype, device=device)
            )
        shape = (num_experiments, num_actions, num_candidates, patterns)
        for prefix in ("", "block_"):
            for name in ("count", "successes", "reward_sum", "log_marginal"):
                self.register_buffer(
                    prefix + name, torch.zeros(shape, dtype=torch.float64, device=device)
                )
        # caches: the running mean of every pattern, the posterior of every candidate
        self.register_buffer("mean", torch.zeros(shape, dtype=torch.float64, device=device))
        self.register_buffer(
            "weights_cache",
            torch.full(shape[:3], 1.0 / num_candidates, dtype=torch.float64, device=device),
        )
        self.register_buffer("map_cache", torch.zeros(shape[:2], dtype=torch.int64, device=device))
        self.register_buffer(
            "plausible_cache", torch.zeros(shape[:3], dtype=torch.bool, device=device)
        )
        self._refresh_cache(slice(None), slice(None))
        self.register_buffer(
            "committed", torch.full((num_experiments, num_actions), -1, device=device)
        )
        for name in ("samples", "block_samples", "reopened"):
            self.register_buffer(
                name, torch.zeros(num_experiments, num_actions, dtype=torch.int64, device=device)
            )
        self.register_buffer(
            "noise_seen", torch.zeros(num_experiments, dtype=torch.bool, device=device)
        )

    # -- what it holds -----------------------------------------------------------------------

    def log_posterior(self, block: bool = False) -> torch.Tensor:
        """``[S, A, C]`` float64: ``log p(c) + log p(D | c)`` (up to a constant per actuator)."""
        return self._log_posterior_at(slice(None), slice(None), block)

    def _log_posterior_at(
        self, rows: torch.Tensor | slice, action: torch.Tensor | slice, block: bool = False
    ) -> torch.Tensor:
        """``[R, C]`` (or ``[S, A, C]``): the log posterior of the candidates of the given (rows,
        actuators) from all their counts or (``block``) the block's."""
        prefix = "block_" if block else ""
        if self.likelihood != "flip":  # a sum over the patterns
            log_marginal = getattr(self, prefix + "log_marginal")[rows, action]
            return self._masked(
                log_posterior_of(self.log_prior, log_marginal), self.active[rows, action]
            )
        count = getattr(self, prefix + "count")[rows, action]
        successes = getattr(self, prefix + "successes")[rows, action]
        return self._masked(
            self.log_prior + self._flip(count, successes), self.active[rows, action]
        )

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs) -> None:  # type: ignore[no-untyped-def]
        # a state saved before noise_seen existed: that learner had one reopening threshold,
        # which noise_seen False reproduces (a copy: the caller's dict is left as it was)
        if prefix + "noise_seen" not in state_dict and prefix + "committed" in state_dict:
            state_dict[prefix + "noise_seen"] = torch.zeros_like(self.noise_seen)
        # the history buffers grow (``_record``): take the saved capacity before loading
        for name in ("history_readings", "history_action", "history_reward"):
            saved = state_dict.get(prefix + name)
            buffer = getattr(self, name)
            if isinstance(saved, torch.Tensor) and saved.dim() == 2 and saved.shape != buffer.shape:
                setattr(self, name, buffer.new_zeros(buffer.shape[0], saved.shape[1]))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def _masked(self, log_posterior: torch.Tensor, active: torch.Tensor) -> torch.Tensor:
        """``log_posterior`` with ``-inf`` at the inactive candidates (``pairs="pruned"``)."""
        if not self.pruned:
            return log_posterior
        return torch.where(active, log_posterior, scalar(-math.inf, log_posterior))

    def _pattern_log_marginal(self, count: torch.Tensor, successes: torch.Tensor) -> torch.Tensor:
        """Each pattern's log marginal (``"pattern"`` and ``"flip"``: Beta-Bernoulli; the flip
        likelihood reads the counts instead, the patterns' are kept alike)."""
        if self.likelihood == "mixture":
            return mixture_log_marginal(count, successes, self.prior_a, self.prior_b)
        return beta_bernoulli_log_marginal(count, successes, self.prior_a, self.prior_b)

    def _flip(self, count: torch.Tensor, successes: torch.Tensor) -> torch.Tensor:
        return flip_log_marginal(count, successes, self.prior_a, self.prior_b)

    def posterior(self) -> torch.Tensor:
        """``[S, A, C]`` float64: ``p(c | D)`` over the candidates of each actuator."""
        return posterior_weights(self.log_posterior())

    def structure(self) -> torch.Tensor:
        """``[S, A, K]`` bool: the committed parents of each actuator (none while open)."""
        committed = self.committed.clamp(min=0)
        parents = self.members[committed]  # [S, A, K]
        return parents & (self.committed >= 0).unsqueeze(-1)

    def is_committed(self) -> torch.Tensor:
        """``[S, A]`` bool: the actuator has committed to a candidate."""
        return self.committed >= 0

    def patterns(self, readings: torch.Tensor) -> torch.Tensor:
        """``[S, C]`` int64: the pattern of each candidate's sensors in ``readings`` ``[S, K]``."""
        return readings.to(torch.int64) @ self.weights.T

    # -- the provider --------------------------------------------------------------------------

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        owner = type(self).__name__
        check_batch(tensordict, self.num_experiments, owner)
        readings = _check_entry(
            tensordict,
            self.sensors_key,
            (self.num_experiments, self.num_sensors),
            (torch.bool,),
            owner,
        )
        tensordict.set(keys.LOCAL_VALUE, self.local_values(readings))
        return tensordict

    def local_values(self, readings: torch.Tensor) -> torch.Tensor:
        """``[S, A]`` float32: each actuator's predicted local reward under ``readings``."""
        if (
            self.prediction in ("optimistic", "committed")
            and readings.is_cpu  # (and the caches: else the tensor ops, below)
            and readings.shape[0] * self.num_actions <= ROW_KERNEL_VALUES
        ):
            return self._local_values_read(readings)
        return self._local_values_tensor(readings)

    def _local_values_tensor(self, readings: torch.Tensor) -> torch.Tensor:
        """``local_values`` by tensor ops (any batch, device and prediction)."""
        pattern = self.patterns(readings)  # [S, C]
        index = pattern.unsqueeze(1).unsqueeze(-1).expand(-1, self.num_actions, -1, 1)
        mean = self.mean.gather(-1, index).squeeze(-1)  # [S, A, C]
        if self.prediction == "optimistic":
            unseen = scalar(-math.inf, mean)
            before = torch.where(self.plausible_cache, mean, unseen).max(dim=-1).values
        elif self.prediction == "posterior":
            before = (self.weights_cache * mean).sum(dim=-1)  # [S, A]
        elif self.prediction == "map":
            before = mean.gather(-1, self.map_cache.unsqueeze(-1)).squeeze(-1)
        else:  # "committed": an open actuator predicts nothing
            before = torch.zeros_like(mean[..., 0])
        none = scalar(0, self.committed)
        chosen = mean.gather(-1, self.committed.clamp_min(none).unsqueeze(-1)).squeeze(-1)
        return torch.where(self.committed >= none, chosen, before).to(torch.float32)

    def _local_values_read(self, readings: torch.Tensor) -> torch.Tensor:
        """``local_values`` of a few experiments on the CPU read from the caches as Python
        numbers (``"optimistic"`` and ``"committed"`` predictions: a maximum and a lookup, no
        arithmetic; a dozen tensor ops otherwise): each candidate's pattern (its sensors' bits,
        ``patterns``), the committed candidate's running mean, else the largest among the
        plausible candidates (``-inf`` if none, as ``max`` over ``where`` gives), rounded to
        float32 as ``.to(torch.float32)`` does. The entries are read through memoryviews of the
        buffers (``_numpy_views``): what they hold now, whoever wrote it."""
        memory = self._read_memory()
        if memory is None:  # (a buffer of another dtype or layout: the tensor ops)
            return self._local_values_tensor(readings)
        means, plausibles = memory["mean"], memory["plausible_cache"]
        committed = memory["committed"]
        optimistic = self.prediction == "optimistic"
        actions, candidates = self.num_actions, self.num_candidates
        block = candidates * self._pattern_count  # one actuator's [C, P]
        rows = []
        for row, reading in enumerate(readings.tolist()):
            offsets = self._reading_entries(reading)[1]  # c * P + pattern
            values = []
            for flat in range(row * actions, (row + 1) * actions):
                held, start = committed[flat], flat * block
                if held >= 0:
                    value = means[start + offsets[held]]
                elif optimistic:
                    value = -math.inf
                    first = flat * candidates
                    for candidate, offset in enumerate(offsets):
                        if plausibles[first + candidate] and means[start + offset] > value:
                            value = means[start + offset]
                else:
                    value = 0.0
                values.append(value)
            rows.append(values)
        # (float64 -> float32 rounded to nearest, as .to(torch.float32) does)
        out = np.array(rows, dtype=np.float32)
        return torch.from_numpy(out if rows else out.reshape(0, actions))

    def update_running_mean(
        self,
        readings: torch.Tensor,
        action: torch.Tensor,
        local_reward: torch.Tensor,
        mask: torch.Tensor | None = None,
    ) -> None:
        """Count the firing of ``action`` under ``readings`` (before acting) with its local reward
        (for every candidate), then commit or reopen (module docstring). Same arguments as
        ``LocalRewardTable.update_running_mean``."""
        batch = self.num_experiments
        if mask is not None:
            mask = check_mask(mask, batch, "StructureLearner.update_running_mean")
        shapes = self.__dict__.get("_update_shapes")
        if shapes is None:  # (fixed at construction)
            shapes = (batch, self.num_sensors), (batch,), (batch, self.num_actions)
            self.__dict__["_update_shapes"] = shapes
        given = (readings.shape, action.shape, local_reward.shape)
        if given != shapes:
            for name, value, shape in zip(
                ("readings", "action", "local_reward"), given, shapes, strict=True
            ):
                if value != shape:
                    raise ValueError(
                        f"StructureLearner.update_running_mean: {name} has shape "
                        f"{list(value)}, expected {list(shape)}"
                    )
        if mask is None and self._update_read(readings, action, local_reward):
            return  # (numbers through numpy: no autograd to turn off)
        with torch.no_grad():
            self._update_tensor(readings, action, local_reward, mask)

    def _update_tensor(
        self,
        readings: torch.Tensor,
        action: torch.Tensor,
        local_reward: torch.Tensor,
        mask: torch.Tensor | None,
    ) -> None:
        """``update_running_mean`` by tensor ops (any batch, mask and device)."""
        batch = self.num_experiments
        owner, device = "StructureLearner.update_running_mean", self.count.device
        check_firing(owner, readings, action, local_reward, self.num_actions, device)
        rows = row_starts(batch, 1, action.device)  # arange(S), cached
        if mask is not None:
            rows, action = rows[mask], action[mask]
            readings, local_reward = readings[mask], local_reward[mask]
        if rows.numel() == 0:
            return
        # (Python numbers as cached 0-d tensors and flat index_select / index_copy_ for
        # advanced indexing: the same values, in about half the time of a step's small ops)
        reward = local_reward.gather(1, action.unsqueeze(1)).squeeze(1).to(torch.float64)  # [R]
        fired_reward = reward
        success = (-reward).clamp(scalar(0.0, reward), scalar(1.0, reward))  # [R], fractional
        pattern = self.patterns(readings)  # [R, C]
        candidates, width = self.num_candidates, self.count.shape[-1]
        fired = rows * scalar(self.num_actions, rows) + action  # [R], into [S A]
        # one flat index per (row, candidate) into [S, A, C, P]: no entry appears twice
        offsets = row_starts(candidates, width, action.device)  # c * P
        where = (
            (fired * scalar(candidates * width, fired)).unsqueeze(1) + offsets + pattern
        ).reshape(-1)  # [R C]
        success = success.unsqueeze(1).expand(-1, candidates).reshape(-1)
        reward = reward.unsqueeze(1).expand(-1, candidates).reshape(-1)
        # both count sets ("" and "block_") at once: [2, R C]
        names = ("count", "successes", "reward_sum", "log_marginal")
        flat = {
            prefix + name: getattr(self, prefix + name).view(-1)
            for prefix in ("", "block_")
            for name in names
        }

        def read(name: str) -> torch.Tensor:
            return torch.stack(
                (flat[name].index_select(0, where), flat["block_" + name].index_select(0, where))
            )

        old = {name: read(name) for name in names}
        new_count = old["count"] + scalar(1.0, reward)
        new_successes = old["successes"] + success
        new_reward_sum = old["reward_sum"] + reward
        new_log_marginal = self._pattern_log_marginal(new_count, new_successes)
        new: tuple[torch.Tensor, ...] = (new_count, new_successes, new_reward_sum, new_log_marginal)
        if self.pruned:  # an inactive pair is not counted: it keeps what it held
            active = self._rows_of("active", fired).reshape(-1)  # [R C]
            new = tuple(
                torch.where(active, value, old[name])
                for name, value in zip(names, new, strict=True)
            )
        for name, values in zip(names, new, strict=True):
            whole, block = values.unbind(0)
            flat[name].index_copy_(0, where, whole)
            flat["block_" + name].index_copy_(0, where, block)
        one = scalar(1, self.samples)
        self.samples.view(-1).index_add_(0, fired, one.expand(fired.shape))
        self.block_samples.view(-1).index_add_(0, fired, one.expand(fired.shape))
        if self.pruned:
            self._record(rows, readings, action, fired_reward)
            log_posterior = self._enter(rows, action, fired)
        else:
            log_posterior = self._log_posterior_rows(fired)
        kept = self._decide(rows, action, fired, log_posterior)
        self._refresh_cache(rows, action, fired, kept)

    #: The buffers the read update (``_update_read``) reads or writes, as flat numpy views.
    _READ_BUFFERS = (
        "count",
        "successes",
        "reward_sum",
        "log_marginal",
        "block_count",
        "block_successes",
        "block_reward_sum",
        "block_log_marginal",
        "samples",
        "block_samples",
        "committed",
        "noise_seen",
        "block_start",
        "history_length",
        "mean",
        "weights_cache",
        "map_cache",
        "plausible_cache",
        "log_prior",
        "competitors",
    )

    def _numpy_views(self) -> tuple[dict, list[torch.Tensor], dict, tuple] | None:
        """``({name: flat numpy view}, the tensors written, {name: memoryview of that view}, the
        posterior weights' rows and input)`` of ``_READ_BUFFERS`` (None if one is not a
        contiguous CPU tensor), cached while the buffers are the same tensors on the same memory
        (a module moved, copied or given new buffers builds them again)."""
        tensors = tuple(map(self._buffers.__getitem__, self._READ_BUFFERS))
        cached = self.__dict__.get("_views")
        if (
            cached is not None
            and all(map(operator.is_, cached[0], tensors))
            and cached[1] == tuple(map(torch.Tensor.data_ptr, tensors))
        ):
            return cached[2]
        if not all(
            tensor is not None
            and tensor.device.type == "cpu"
            and tensor.is_contiguous()
            and (tensor.dtype == torch.float64 or not tensor.is_floating_point())
            for tensor in tensors
        ):
            return None  # (float buffers of another dtype: the tensor path's arithmetic)
        arrays = {
            name: tensor.view(-1).numpy()
            for name, tensor in zip(self._READ_BUFFERS, tensors, strict=True)
        }
        # the same memory as memoryviews: an entry read is a Python number, a write stores one
        # (float64 'd', int64 'l', bool '?'), without a numpy call
        memory = {name: memoryview(array) for name, array in arrays.items()}
        # _update_one's posterior weights: each actuator's [1, C] row of weights_cache (softmax
        # writes it), and the [1, C] tensor it reads (written through its memoryview)
        candidates = self.num_candidates
        weights = self._buffers["weights_cache"].view(-1, candidates)
        weight_rows = [weights[flat : flat + 1] for flat in range(weights.shape[0])]
        posterior = torch.zeros(1, candidates, dtype=torch.float64)
        softmax = (weight_rows, posterior, posterior.numpy().data.cast("B").cast("d"))
        pointers = tuple(map(torch.Tensor.data_ptr, tensors))
        # (log_prior, competitors: only read)
        views = (arrays, list(tensors[:-2]), memory, softmax)
        taken = [  # (for _read_memory)
            (name, tensor, pointer)
            for name, tensor, pointer in zip(self._READ_BUFFERS, tensors, pointers, strict=True)
            if name in self._VALUE_BUFFERS
        ]
        self.__dict__["_views"] = (tensors, pointers, views, taken)
        return views

    #: The buffers ``_local_values_read`` reads (through ``_numpy_views``' memoryviews).
    _VALUE_BUFFERS = ("mean", "plausible_cache", "committed")

    def _read_memory(self) -> dict | None:
        """``_numpy_views``' memoryviews for ``_local_values_read``, checked on the three buffers
        it reads only (the same tensors on the same memory; else all of them, again)."""
        cached = self.__dict__.get("_views")
        if cached is not None:
            buffers, taken = self._buffers, cached[3]
            if all(
                buffers[name] is tensor and tensor.data_ptr() == pointer
                for name, tensor, pointer in taken
            ):
                return cached[2][2]
        views = self._numpy_views()
        return None if views is None else views[2]

    def _reading_entries(self, reading: list[bool]) -> tuple[list[int], list[int]]:
        """``(patterns, offsets)`` of one reading ``[K]``: each candidate's pattern (its sensors'
        bits, ``patterns``) and its entry in one actuator's ``[C, P]`` (``c * P + pattern``),
        cached by reading (a few thousand at most)."""
        key = tuple(reading)
        memo = self.__dict__.setdefault("_entries", {})
        found = memo.get(key)
        if found is None:
            width = self.count.shape[-1]
            patterns = [
                sum(1 << rank for rank, sensor in enumerate(parents) if reading[sensor])
                for parents in self.sets
            ]
            found = (patterns, [c * width + p for c, p in enumerate(patterns)])
            if len(memo) >= _MEMO_SIZE:
                memo.clear()
            memo[key] = found
        return found

    def _update_read(
        self, readings: torch.Tensor, action: torch.Tensor, local_reward: torch.Tensor
    ) -> bool:
        """``update_running_mean`` of one firing per experiment (the online step, no mask) on a
        small CPU learner, its few entries read and written through numpy as Python numbers:
        bit for bit the tensor ops (every sum, difference, quotient and comparison is the same
        IEEE double operation in the same order; the log marginals and the posterior weights are
        computed by the same torch functions on tensors of the same shapes), in a fraction of the
        time of the tensor path's ~200 small ops (the local-risk layer of one agent learns on
        every env step). A reopening's forgetting is left to the tensor code.

        Returns False (nothing written) where it does not apply: pair pruning, the flip
        likelihood, another device, a large batch, or inputs the tensor path refuses (it then
        runs, and names what is wrong).
        """
        num_actions = self.num_actions
        if (
            self.pruned
            or self.likelihood == "flip"
            or self.num_experiments * num_actions > ROW_KERNEL_VALUES
            or readings.dtype != torch.bool
            or action.dtype not in (torch.int64, torch.int32)
            or local_reward.dtype not in (torch.float32, torch.float64)
            or local_reward.requires_grad
            or not (readings.is_cpu and action.is_cpu and local_reward.is_cpu)
        ):
            return False
        fired_actions = action.tolist()  # [S]
        rewards = local_reward.tolist()  # [S][A]
        if not all(0 <= fired < num_actions for fired in fired_actions) or not all(
            math.isfinite(value) for row in rewards for value in row
        ):
            return False
        views = self._numpy_views()  # (None off the CPU)
        if views is None:
            return False
        arrays, written = views[:2]
        if len(fired_actions) == 1:  # one experiment (one agent's step)
            reading = readings.tolist()[0]
            return self._update_one(views, fired_actions[0], rewards[0], reading)
        candidates, width = self.num_candidates, self._pattern_count
        block_size = candidates * width  # one actuator's [C, P]
        log_prior = arrays["log_prior"].tolist()  # [C]
        # one firing per experiment: the entry of every candidate (its sensors' pattern)
        fired_rows: list[int] = []
        wheres: list[int] = []
        rewards_fired: list[float] = []
        successes_fired: list[float] = []
        for row, (fired, reading) in enumerate(zip(fired_actions, readings.tolist(), strict=True)):
            reward = float(rewards[row][fired])  # exact: float32 -> float64
            rewards_fired.append(reward)
            successes_fired.append(min(max(-reward, 0.0), 1.0))  # clamp(-r, 0, 1)
            flat = row * num_actions + fired
            fired_rows.append(flat)
            start = flat * block_size
            wheres.extend([start + offset for offset in self._reading_entries(reading)[1]])
        where_index = np.array(wheres, dtype=np.intp)  # (a list index is converted at every use)
        new: dict[str, list[list[float]]] = {"count": [], "successes": [], "reward_sum": []}
        for prefix in ("", "block_"):
            count = arrays[prefix + "count"][where_index].tolist()
            successes = arrays[prefix + "successes"][where_index].tolist()
            reward_sum = arrays[prefix + "reward_sum"][where_index].tolist()
            new["count"].append([value + 1.0 for value in count])
            if len(fired_rows) == 1:  # (the online step of one agent: one reward for all)
                success, reward = successes_fired[0], rewards_fired[0]
                new["successes"].append([value + success for value in successes])
                new["reward_sum"].append([value + reward for value in reward_sum])
                continue
            per_row = [index // candidates for index in range(len(wheres))]
            new["successes"].append(
                [
                    value + successes_fired[row]
                    for value, row in zip(successes, per_row, strict=True)
                ]
            )
            new["reward_sum"].append(
                [value + rewards_fired[row] for value, row in zip(reward_sum, per_row, strict=True)]
            )
        marginal = self._read_log_marginal(
            new["count"][0] + new["count"][1], new["successes"][0] + new["successes"][1]
        )
        new["log_marginal"] = [marginal[: len(wheres)], marginal[len(wheres) :]]
        for name, (whole, block) in new.items():
            arrays[name][where_index] = whole
            arrays["block_" + name][where_index] = block
        samples, block_samples = arrays["samples"], arrays["block_samples"]
        for flat in fired_rows:  # (one firing per experiment: no index twice)
            samples[flat] += 1
            block_samples[flat] += 1
        log_posteriors = [
            self._read_log_posterior(arrays, "", flat, log_prior) for flat in fired_rows
        ]
        reopened = self._decide_read(arrays, fired_rows, log_posteriors, log_prior)
        if reopened is not None:  # the tensor code forgets, closes the blocks and refreshes
            increment_version(written)
            rows = row_starts(self.num_experiments, 1, action.device)  # arange(S), cached
            fired_tensor = torch.tensor(fired_rows, dtype=torch.int64)
            action = action.to(torch.int64)
            with torch.no_grad():
                self._forget(rows, action, torch.tensor(reopened))
                self._close_blocks(rows, action, fired_tensor, None)
                self._refresh_cache(rows, action, fired_tensor, None)
            return True
        for row, flat in enumerate(fired_rows):  # _close_blocks
            if block_samples[flat] >= self.window:
                for name in ("count", "successes", "reward_sum", "log_marginal"):
                    arrays["block_" + name][flat * block_size : (flat + 1) * block_size] = 0.0
                block_samples[flat] = 0
                arrays["block_start"][flat] = arrays["history_length"][row]
        # _refresh_cache of the fired actuators, with their log posterior: the running means of
        # the entries counted (the others' counts are as they were, so are their means)
        means = [
            t / max(n, 1.0) if n > 0.0 else 0.0
            for n, t in zip(new["count"][0], new["reward_sum"][0], strict=True)
        ]
        arrays["mean"][where_index] = means
        stacked = torch.from_numpy(np.array(log_posteriors, dtype=np.float64))  # [R, C]
        weights = posterior_weights(stacked).tolist()
        threshold = self.log_bayes_factor
        for flat, log_posterior, weight in zip(fired_rows, log_posteriors, weights, strict=True):
            span = slice(flat * candidates, (flat + 1) * candidates)
            arrays["weights_cache"][span] = weight
            best = max(log_posterior)
            arrays["map_cache"][flat] = log_posterior.index(best)  # the first maximum (argmax)
            plausible = [value >= best - threshold for value in log_posterior]
            arrays["plausible_cache"][span] = plausible
        increment_version(written)  # in place, as by index_copy_: seen by autograd
        return True

    def _update_one(
        self,
        views: tuple[dict, list[torch.Tensor], dict, tuple],
        fired: int,
        rewards: list[float],
        reading: list[bool],
    ) -> bool:
        """``_update_read`` of one experiment's firing (``S = 1``): the same entries, the same
        numbers and the same writes, without the lists over experiments (a reopening goes to the
        tensor code as there). Every entry is read and written through the buffers' memoryviews
        (``_numpy_views``) as a Python number: the same double operations, entry by entry, and
        no numpy call but the posterior weights' (one agent's step reaches it at every env step,
        where each numpy or torch call costs microseconds of dispatch)."""
        arrays, written, memory, (weight_rows, posterior, posterior_input) = views
        candidates, width = self.num_candidates, self._pattern_count
        reward = float(rewards[fired])  # exact: float32 -> float64
        success = min(max(-reward, 0.0), 1.0)  # clamp(-r, 0, 1)
        start = fired * candidates * width  # the actuator's [C, P] in [S A C P]
        where = [start + offset for offset in self._reading_entries(reading)[1]]
        count, block_count = memory["count"], memory["block_count"]
        successes, block_successes = memory["successes"], memory["block_successes"]
        reward_sum, block_reward_sum = memory["reward_sum"], memory["block_reward_sum"]
        counts, block_counts, sums, block_sums = [], [], [], []  # the entries' new counts
        for entry in where:
            counts.append(count[entry] + 1.0)
            block_counts.append(block_count[entry] + 1.0)
            sums.append(successes[entry] + success)
            block_sums.append(block_successes[entry] + success)
        marginal = self._read_log_marginal(counts + block_counts, sums + block_sums)
        log_marginal, block_log_marginal = memory["log_marginal"], memory["block_log_marginal"]
        mean, totals = memory["mean"], []
        for index, entry in enumerate(where):
            count[entry], block_count[entry] = counts[index], block_counts[index]
            successes[entry], block_successes[entry] = sums[index], block_sums[index]
            total = reward_sum[entry] + reward
            reward_sum[entry] = total
            totals.append(total)
            block_reward_sum[entry] = block_reward_sum[entry] + reward
            log_marginal[entry] = marginal[index]
            block_log_marginal[entry] = marginal[candidates + index]
        block_samples = memory["block_samples"]
        memory["samples"][fired] += 1
        block_samples[fired] += 1
        log_prior = memory["log_prior"].tolist()  # [C]
        log_posterior = self._read_log_posterior(memory, "", fired, log_prior)
        held = memory["committed"][fired]
        if held >= 0:  # committed: _decide_read's change-point test of this one actuator
            reopened = self._change_read(memory, fired, held, log_prior)
        else:
            reopened = self._decide_read(arrays, [fired], [log_posterior], log_prior)
        if reopened is not None:
            # a reopening: the tensor code forgets, closes the blocks and refreshes
            increment_version(written)
            rows = row_starts(1, 1, self.committed.device)  # arange(1), cached
            fired_tensor = torch.tensor([fired], dtype=torch.int64)
            with torch.no_grad():
                self._forget(rows, fired_tensor, torch.tensor([True]))
                self._close_blocks(rows, fired_tensor, fired_tensor, None)
                self._refresh_cache(rows, fired_tensor, fired_tensor, None)
            return True
        if block_samples[fired] >= self.window:  # _close_blocks
            span = slice(start, start + candidates * width)
            for name in ("count", "successes", "reward_sum", "log_marginal"):
                arrays["block_" + name][span] = 0.0
            block_samples[fired] = 0
            arrays["block_start"][fired] = arrays["history_length"][0]
        # _refresh_cache of the fired actuator with its log posterior (module docstring)
        for n, total, entry in zip(counts, totals, where, strict=True):
            mean[entry] = total / max(n, 1.0) if n > 0.0 else 0.0
        # posterior_weights (softmax) of the same [1, C] float64 tensor as torch.tensor's, written
        # into the actuator's row of weights_cache (out=: the same kernel)
        for candidate, value in enumerate(log_posterior):
            posterior_input[candidate] = value
        posterior_weights(posterior, out=weight_rows[fired])
        first = fired * candidates
        best = max(log_posterior)
        memory["map_cache"][fired] = log_posterior.index(best)  # the first maximum (argmax)
        threshold = best - self.log_bayes_factor
        plausible = memory["plausible_cache"]
        for candidate, value in enumerate(log_posterior, first):
            plausible[candidate] = value >= threshold
        increment_version(written)  # in place, as by index_copy_: seen by autograd
        return True

    def _read_log_marginal(self, count: list[float], successes: list[float]) -> list[float]:
        """``_pattern_log_marginal`` of Python numbers (``_read_log_marginal_of``): entry by entry
        from the ``lgamma`` tables where they hold every entry (integral counts below their size,
        ``_tabled_log_marginals``), else all of them by ``_read_log_marginal_of`` (which builds
        or grows the tables). Each entry's value is a function of its own ``n`` and ``s`` (the
        tables hold ``torch.lgamma`` of the same arguments): the same values either way."""
        tabled = self.__dict__.get("_tabled")
        if tabled is not None:
            marginal = self._tabled_log_marginals(tabled, count, successes)
            if marginal is not None:
                return marginal
        return self._read_log_marginal_of(count, successes)[0]

    @staticmethod
    def _tabled_log_marginals(
        tabled: tuple, count: list[float], successes: list[float]
    ) -> list[float] | None:
        """``_read_log_marginal_of`` of the entries ``(n, s)`` where the ``lgamma`` tables built
        by ``_read_lgamma`` hold every one (integral ``0 <= s <= n`` below their size; else
        None): the same table values and the same double operations in the same order, one
        entry at a time (a firing's entries are new ``(n, s)`` mostly: the counts grow)."""
        size, levels, mixture = tabled
        first, second, third, log_beta_prior, mass = levels[0]
        if mixture:
            noisy_first, noisy_second, noisy_third, noisy_log_beta_prior, noisy_mass = levels[1]
        marginal = []
        for n, s in zip(count, successes, strict=True):
            if not (0.0 <= s <= n < size and n.is_integer() and s.is_integer()):
                return None
            hits, misses, total = int(s), int(n - s), int(n)
            value = first[hits] + second[misses] - third[total] - log_beta_prior
            if mixture:  # the clean level's and the noisy level's, the more probable
                clean = value + mass
                noisy = (
                    noisy_first[hits]
                    + noisy_second[misses]
                    - noisy_third[total]
                    - noisy_log_beta_prior
                    + noisy_mass
                )
                value = (clean if clean > noisy else noisy) if n > 0 else 0.0
            marginal.append(value)
        return marginal

    def _read_log_marginal_of(
        self, count: list[float], successes: list[float]
    ) -> tuple[list[float], bool]:
        """``_pattern_log_marginal`` of Python numbers (``"mixture"`` or ``"pattern"``): the same
        double operations in the same order as ``functional.mixture_log_marginal`` /
        ``beta_bernoulli_log_marginal``, with the same constants (Python floats there too), and
        their ``lgamma`` values from one ``torch.lgamma`` call (elementwise, the values torch's
        gives there); and whether the ``lgamma`` tables gave them (``_read_lgamma``)."""
        levels = self.__dict__.get("_marginal_levels")
        if levels is None:  # (a, b, a + b, log B(a, b), the level's log prior mass) per level
            a, b = self.prior_a, self.prior_b
            levels = [(a, b, a + b, math.lgamma(a) + math.lgamma(b) - math.lgamma(a + b), 0.0)]
            if self.likelihood == "mixture":
                log_total = math.log1p(NOISY_ODDS)
                noisy_a, noisy_b = (float(value) for value in NOISY_PRIOR)
                levels = [
                    (*levels[0][:4], -log_total),
                    (
                        noisy_a,
                        noisy_b,
                        noisy_a + noisy_b,
                        math.lgamma(noisy_a)
                        + math.lgamma(noisy_b)
                        - math.lgamma(noisy_a + noisy_b),
                        math.log(NOISY_ODDS) - log_total,
                    ),
                ]
            self.__dict__["_marginal_levels"] = levels
        values, tabled = self._read_lgamma(levels, count, successes)
        logs = iter(values)
        size = len(count)
        by_level = []
        for _, _, _, log_beta_prior, _ in levels:
            by_level.append(
                [
                    first + second - third - log_beta_prior
                    for first, second, third in islice(zip(logs, logs, logs, strict=False), size)
                ]
            )
        if len(levels) == 1:  # "pattern"
            return by_level[0], tabled
        clean_level, noisy_level = levels[0][4], levels[1][4]
        marginal = []
        for n, clean, noisy in zip(count, by_level[0], by_level[1], strict=True):
            clean, noisy = clean + clean_level, noisy + noisy_level
            marginal.append((clean if clean > noisy else noisy) if n > 0 else 0.0)
        return marginal, tabled

    def _read_lgamma(
        self, levels: list[tuple[float, ...]], count: list[float], successes: list[float]
    ) -> tuple[list[float], bool]:
        """``lgamma`` of ``(a + s, b + n - s, a + b + n)`` for every level and entry, in that
        order, as ``torch.lgamma`` computes them: integral counts (every firing of a collision
        world: ``s`` and ``n`` whole numbers) are looked up in tables of ``torch.lgamma(base +
        arange(M))`` per base (the same doubles in, the same function: the compiled kernel's
        tables too; then True), anything else in one ``torch.lgamma`` call (False)."""
        largest = max(count, default=0.0)
        bases, dyadic = self.__dict__.get("_lgamma_bases") or (None, None)
        if bases is None:  # (the levels are fixed at construction)
            bases = {value for level in levels for value in level[:3]}
            dyadic = all((base * 1024.0).is_integer() for base in bases)
            self.__dict__["_lgamma_bases"] = (bases, dyadic)
        if (
            largest < _LGAMMA_TABLE_COUNTS
            # dyadic bases: b + n - s is then exactly b + (n - s), the table's argument
            and dyadic
            and all(value.is_integer() for value in successes)
            and all(value.is_integer() for value in count)
        ):
            tables = self.__dict__.setdefault("_lgamma_tables", {})
            size = tables.get("size", 0)
            if largest >= size:  # (re)build the tables past the largest count
                size = min(max(2 * int(largest) + 2, 256), _LGAMMA_TABLE_COUNTS + 1)
                steps = torch.arange(size, dtype=torch.float64)
                for base in bases:
                    tables[base] = torch.lgamma(base + steps).tolist()
                tables["size"] = size
                # (for _tabled_log_marginals: the counts the tables take, each level's tables)
                tabled_levels = [
                    (tables[level[0]], tables[level[1]], tables[level[2]], level[3], level[4])
                    for level in levels
                ]
                limit = min(size, _LGAMMA_TABLE_COUNTS)
                self.__dict__["_tabled"] = (float(limit), tabled_levels, len(levels) == 2)
            out: list[float] = []
            for level_a, level_b, level_ab, _, _ in levels:
                first, second, third = tables[level_a], tables[level_b], tables[level_ab]
                for n, s in zip(count, successes, strict=True):
                    out += (first[int(s)], second[int(n - s)], third[int(n)])
            return out, True
        arguments: list[float] = []
        for level_a, level_b, level_ab, _, _ in levels:
            for n, s in zip(count, successes, strict=True):
                arguments += (level_a + s, level_b + n - s, level_ab + n)
        return torch.lgamma(torch.tensor(arguments, dtype=torch.float64)).tolist(), False

    def _read_log_posterior(
        self, arrays: dict, prefix: str, flat: int, log_prior: list[float]
    ) -> list[float]:
        """``log_posterior_of`` of the actuator at flat index ``flat`` (``row * A + action``) from
        the numpy views (``_update_read``): ``log_prior + (((m_0 + m_1) + m_2) + m_3)``."""
        width = self._pattern_count
        values = iter(
            arrays[prefix + "log_marginal"][
                flat * self.num_candidates * width : (flat + 1) * self.num_candidates * width
            ].tolist()
        )
        # each candidate's patterns in turn, summed left to right (reduce: ((m_0 + m_1) + ...))
        if width == 4:  # (two parents at most: the default, written out)
            return [
                prior + (((m_0 + m_1) + m_2) + m_3)
                for prior, m_0, m_1, m_2, m_3 in zip(
                    log_prior, values, values, values, values, strict=True
                )
            ]
        patterns = zip(*(values,) * width, strict=True)
        return [
            prior + reduce(operator.add, row)
            for prior, row in zip(log_prior, patterns, strict=True)
        ]

    def _decide_read(
        self,
        arrays: dict,
        fired_rows: list[int],
        log_posteriors: list[list[float]],
        log_prior: list[float],
    ) -> list[bool] | None:
        """``_decide`` on the numpy views (``_update_read``): commit open actuators, test the
        committed ones for a change; writes ``committed`` and ``noise_seen``. Returns the
        reopening flags ``[R]`` where some actuator reopened (the caller forgets), else None."""
        candidates, width = self.num_candidates, self._pattern_count
        committed = arrays["committed"][fired_rows].tolist()
        new = list(committed)
        if not all(held >= 0 for held in committed):
            competitors = arrays["competitors"]  # [C C] bool
            for row, (held, log_posterior) in enumerate(
                zip(committed, log_posteriors, strict=True)
            ):
                if held >= 0:
                    continue
                lead = max(log_posterior)
                best = log_posterior.index(lead)  # the first maximum (argmax)
                rivals = competitors[best * candidates : (best + 1) * candidates].tolist()
                rival = max(
                    (value for value, rival in zip(log_posterior, rivals, strict=True) if rival),
                    default=-math.inf,
                )
                if lead - rival >= self.log_bayes_factor:
                    new[row] = best
                    cell = (fired_rows[row] * candidates + best) * width
                    count = arrays["count"][cell : cell + width].tolist()
                    successes = arrays["successes"][cell : cell + width].tolist()
                    if any(min(s, n - s) > 0 for n, s in zip(count, successes, strict=True)):
                        arrays["noise_seen"][row] = True  # has_minority
        if not any(held >= 0 for held in committed):
            arrays["committed"][fired_rows] = new
            return None
        if len(committed) == 1:  # one committed actuator (one agent's step): the test below
            return self._change_read(arrays, fired_rows[0], committed[0], log_prior)
        # the change-point test (every row, as the tensor path computes it, shape [R, P])
        cells = [(flat * candidates + max(held, 0)) * width for flat, held in
                 zip(fired_rows, committed, strict=True)]  # fmt: skip

        def at(name: str) -> list[list[float]]:
            return [arrays[name][cell : cell + width].tolist() for cell in cells]

        count, successes = at("count"), at("successes")
        block_count, block_successes = at("block_count"), at("block_successes")
        earlier_count = [[n - b for n, b in zip(*pair, strict=True)] for pair in
                         zip(count, block_count, strict=True)]  # fmt: skip
        earlier_successes = [[s - b for s, b in zip(*pair, strict=True)] for pair in
                             zip(successes, block_successes, strict=True)]  # fmt: skip
        marginals = self._read_log_marginal(sum(earlier_count, []), sum(earlier_successes, []))
        earlier = [marginals[row * width : (row + 1) * width] for row in range(len(cells))]
        reopen = []
        for row, (flat, held) in enumerate(zip(fired_rows, committed, strict=True)):
            if held < 0:
                reopen.append(False)
                continue
            marginal = arrays["log_marginal"][cells[row] : cells[row] + width].tolist()
            differences = [m - e for m, e in zip(marginal, earlier[row], strict=True)]
            total = differences[0]
            for value in differences[1:]:
                total = total + value
            lead = log_prior[held] + (0.0 + total)  # log_posterior_of(0.0, ...)
            reopen.append(self._reopens_read(arrays, flat, lead, log_prior))
        arrays["committed"][fired_rows] = [-1 if gone else held for gone, held in
                                           zip(reopen, new, strict=True)]  # fmt: skip
        return reopen if any(reopen) else None

    def _reopens_read(self, arrays: dict, flat: int, lead: float, log_prior: list[float]) -> bool:
        """Whether the block's best log posterior beats the committed set's ``lead`` by the
        reopening factor (the noisy one once the body's sensors read wrong)."""
        rival = max(self._read_log_posterior(arrays, "block_", flat, log_prior))
        threshold = (
            self.log_noisy_reopen_factor
            if arrays["noise_seen"][flat // self.num_actions]
            else self.log_reopen_factor
        )
        return rival - lead >= threshold

    def _change_read(
        self, arrays: dict, flat: int, held: int, log_prior: list[float]
    ) -> list[bool] | None:
        """``_decide_read``'s change-point test of one committed actuator (flat index ``flat``,
        committed to ``held``): the same numbers in the same order as its loop over rows (the
        differences ``m - e`` summed left to right, ``log_prior + (0.0 + total)`` against the
        block's best log posterior); writes ``committed`` -1 and returns ``[True]`` where it
        reopens, else None (nothing written: the actuator stays committed to ``held``)."""
        width = self._pattern_count
        cell = (flat * self.num_candidates + held) * width
        end = cell + width
        count = arrays["count"][cell:end].tolist()
        successes = arrays["successes"][cell:end].tolist()
        block_count = arrays["block_count"][cell:end].tolist()
        block_successes = arrays["block_successes"][cell:end].tolist()
        earlier = self._read_log_marginal(
            [n - b for n, b in zip(count, block_count, strict=True)],
            [s - b for s, b in zip(successes, block_successes, strict=True)],
        )
        marginal = arrays["log_marginal"][cell:end].tolist()
        total = marginal[0] - earlier[0]
        for m, e in zip(marginal[1:], earlier[1:], strict=True):
            total = total + (m - e)
        lead = log_prior[held] + (0.0 + total)  # log_posterior_of(0.0, ...)
        if self._reopens_read(arrays, flat, lead, log_prior):
            arrays["committed"][flat] = -1
            return [True]
        return None

    def _refresh_cache(
        self,
        rows: torch.Tensor | slice,
        action: torch.Tensor | slice,
        fired: torch.Tensor | None = None,
        log_posterior: torch.Tensor | None = None,
    ) -> None:
        """Recompute the running means and posterior weights of the given (rows, actuators); with
        ``fired`` (``rows * A + action`` ``[R]``) by flat index, reusing ``log_posterior``
        ``[R, C]`` when the caller has it."""
        if fired is None:
            count, total = self.count[rows, action], self.reward_sum[rows, action]
            self.mean[rows, action] = torch.where(count > 0, total / count.clamp(min=1.0), 0.0)
            log_posterior = self._log_posterior_at(rows, action)
            self.weights_cache[rows, action] = posterior_weights(log_posterior)
            self.map_cache[rows, action] = log_posterior.argmax(dim=-1)
            best = log_posterior.max(dim=-1, keepdim=True).values
            self.plausible_cache[rows, action] = log_posterior >= best - self.log_bayes_factor
            return
        count, total = self._rows_of("count", fired), self._rows_of("reward_sum", fired)
        zero = scalar(0.0, count)
        mean = torch.where(count > zero, total / count.clamp_min(scalar(1.0, count)), zero)
        self._flat_rows("mean").index_copy_(0, fired, mean)
        if log_posterior is None:
            log_posterior = self._log_posterior_rows(fired)
        self._flat_rows("weights_cache").index_copy_(0, fired, posterior_weights(log_posterior))
        self.map_cache.view(-1).index_copy_(0, fired, log_posterior.argmax(dim=-1))
        best = log_posterior.max(dim=-1, keepdim=True).values
        plausible = log_posterior >= best - scalar(self.log_bayes_factor, best)
        self._flat_rows("plausible_cache").index_copy_(0, fired, plausible)

    def _flat_rows(self, name: str) -> torch.Tensor:
        """Buffer ``name`` ``[S, A, ...]`` viewed as ``[S A, ...]`` (a view: writes land)."""
        buffer = getattr(self, name)
        return buffer.view(-1, *buffer.shape[2:])

    def _rows_of(self, name: str, fired: torch.Tensor) -> torch.Tensor:
        """``getattr(self, name)[rows, action]`` by the flat index ``fired`` ``[R]``."""
        return self._flat_rows(name).index_select(0, fired)

    def _log_posterior_rows(self, fired: torch.Tensor, block: bool = False) -> torch.Tensor:
        """``_log_posterior_at(rows, action, block)`` by the flat index ``fired``: ``[R, C]``."""
        prefix = "block_" if block else ""
        active = self._rows_of("active", fired) if self.pruned else None
        if self.likelihood != "flip":  # a sum over the patterns
            log_posterior = log_posterior_of(
                self.log_prior, self._rows_of(prefix + "log_marginal", fired)
            )
            return log_posterior if active is None else self._masked(log_posterior, active)
        count = self._rows_of(prefix + "count", fired)
        successes = self._rows_of(prefix + "successes", fired)
        log_posterior = self.log_prior + self._flip(count, successes)
        return log_posterior if active is None else self._masked(log_posterior, active)

    def _record(
        self, rows: torch.Tensor, readings: torch.Tensor, action: torch.Tensor, reward: torch.Tensor
    ) -> None:
        """Append the firings (``readings`` ``[R, K]``, ``action`` ``[R]``, the fired actuator's
        local reward ``[R]`` float64) to the experiments' histories (``pairs="pruned"``)."""
        at = self.history_length.index_select(0, rows)  # [R]
        capacity = self.history_readings.shape[1]
        if int(at.max()) >= capacity:  # double the capacity
            for name in ("history_readings", "history_action", "history_reward"):
                buffer = getattr(self, name)
                setattr(self, name, torch.cat((buffer, torch.zeros_like(buffer)), dim=1))
            capacity *= 2
        weights = row_starts(self.num_sensors, 1, readings.device)  # arange(K)
        packed = (readings.to(torch.int64) << weights).sum(dim=-1)  # [R]
        where = rows * scalar(capacity, rows) + at
        self.history_readings.view(-1).index_copy_(0, where, packed)
        self.history_action.view(-1).index_copy_(0, where, action)
        self.history_reward.view(-1).index_copy_(0, where, reward)
        self.history_length.index_add_(0, rows, scalar(1, at).expand(at.shape))

    def _enter(self, rows: torch.Tensor, action: torch.Tensor, fired: torch.Tensor) -> torch.Tensor:
        """``pairs="pruned"``: the candidates active after the firing (``pair_activity``), the
        counts of the entering pairs rebuilt from the history (``rebuild_pair_counts``); returns
        the log posterior ``[R, C]`` of the given actuators over the new active set."""
        log_posterior = self._log_posterior_rows(fired)  # over the old active set
        committed = self.committed.view(-1).index_select(0, fired)
        active = self._rows_of("active", fired)
        width = self.count.shape[-1]
        shape = (-1, self.num_candidates, width)
        explained = single_explains(
            self.count.view(shape).index_select(0, fired),
            self.successes.view(shape).index_select(0, fired),
            self.small_index,
        )
        new = pair_activity(
            log_posterior,
            committed,
            self.pair_members,
            self.small,
            self.log_bayes_factor,
            explained,
        )
        entering = new & ~active  # [R, C]
        self._flat_rows("active").index_copy_(0, fired, new)
        if not bool(entering.any()):
            return self._masked(log_posterior, new)
        names = ("count", "successes", "reward_sum")
        for index in entering.any(dim=-1).nonzero().flatten().tolist():
            row, actuator, flat = int(rows[index]), int(action[index]), int(fired[index])
            start, length = int(self.history_start[row, actuator]), int(self.history_length[row])
            firings = torch.arange(start, length, device=rows.device)
            firings = firings[self.history_action[row, start:length] == actuator]
            readings = self.history_readings[row].index_select(0, firings)
            reward = self.history_reward[row].index_select(0, firings)
            block = firings >= self.block_start[row, actuator]
            candidates = entering[index].nonzero().flatten()
            first = self.pair_members[0].index_select(0, candidates) - 1  # the singles' sensors
            second = self.pair_members[1].index_select(0, candidates) - 1
            sums = rebuild_pair_counts(readings, reward, block, first, second)
            for prefix, values in (("", sums[:3]), ("block_", sums[3:])):
                for name, value in zip(names, values, strict=True):
                    getattr(self, prefix + name).view(-1, self.num_candidates, width)[
                        flat, candidates
                    ] = value
                count, successes = values[0], values[1]
                marginal = self._pattern_log_marginal(count, successes)
                marginal = torch.where(count > scalar(0.0, count), marginal, scalar(0.0, count))
                getattr(self, prefix + "log_marginal").view(-1, self.num_candidates, width)[
                    flat, candidates
                ] = marginal
        return self._log_posterior_rows(fired)

    def _decide(
        self,
        rows: torch.Tensor,
        action: torch.Tensor,
        fired: torch.Tensor,
        log_posterior: torch.Tensor,
    ) -> torch.Tensor | None:
        """Commit open actuators that have the evidence; reopen committed ones that lost it.
        ``log_posterior`` ``[R, C]``: that of the given actuators (``_log_posterior_rows``).
        Returns it when none reopened (their counts are then as they were), else None."""
        committed = self.committed.view(-1).index_select(0, fired)  # [R]
        none = scalar(0, committed)
        # Each test only where it can change something: commitment for the open actuators,
        # reopening for the committed ones (the other's result would be masked out: skipping it
        # leaves every value as it is, and saves ~55 of a step's ~200 small ops while the
        # actuator is open, ~13 once it committed)
        held_rows = committed >= none
        states = held_rows.tolist()
        new = committed
        if not all(states):  # an open actuator: commit where the evidence is enough
            best = log_posterior.argmax(dim=-1)  # [R]
            margin = self._margin(log_posterior, best)
            commit = (committed < none) & (margin >= scalar(self.log_bayes_factor, margin))
            new = torch.where(commit, best, committed)
            if bool(commit.any()):  # a commitment on data against a pattern's majority
                cell = fired * scalar(self.num_candidates, fired) + best  # into [S A C]
                width = self.count.shape[-1]
                minority = has_minority(
                    self.count.view(-1, width).index_select(0, cell),
                    self.successes.view(-1, width).index_select(0, cell),
                )
                self.noise_seen[rows[commit & minority]] = True
        if not any(states):
            self.committed.view(-1).index_copy_(0, fired, new)
            return self._close_blocks(rows, action, fired, log_posterior)
        # reopening, a change-point test on the block: the commitment's prediction of the block
        # from the data before it, p(block | c*, earlier) = p(all | c*) / p(earlier | c*), against
        # any candidate (c* too) fitted afresh to the block alone
        held = committed.clamp_min(none)
        width = self.count.shape[-1]
        cell = fired * scalar(self.num_candidates, fired) + held  # into [S A C]

        def at(name: str) -> torch.Tensor:  # [R, P]: the held candidate's patterns
            return getattr(self, name).view(-1, width).index_select(0, cell)

        count, successes = at("count"), at("successes")  # [R, P]
        earlier_count = count - at("block_count")
        earlier_successes = successes - at("block_successes")
        if self.likelihood != "flip":
            earlier = self._pattern_log_marginal(earlier_count, earlier_successes)
            predicted = log_posterior_of(0.0, at("log_marginal") - earlier)  # [R]
        else:  # the flip likelihood does not split over patterns: the ratio of the whole
            predicted = self._flip(count[:, None], successes[:, None]) - self._flip(
                earlier_count[:, None], earlier_successes[:, None]
            )
            predicted = predicted.squeeze(1)
        lead = self.log_prior.index_select(0, held) + predicted
        block_posterior = self._log_posterior_rows(fired, block=True)
        rival = block_posterior.max(dim=-1).values  # [R]
        threshold = torch.where(
            self.noise_seen.index_select(0, rows),
            scalar(self.log_noisy_reopen_factor, lead),
            scalar(self.log_reopen_factor, lead),
        )
        reopen = held_rows & (rival - lead >= threshold)
        new = torch.where(reopen, scalar(-1, new), new)
        self.committed.view(-1).index_copy_(0, fired, new)
        reopened = bool(reopen.any())
        if reopened:
            self._forget(rows, action, reopen)
        return self._close_blocks(rows, action, fired, None if reopened else log_posterior)

    def _forget(self, rows: torch.Tensor, action: torch.Tensor, reopen: torch.Tensor) -> None:
        """``_decide``'s reopening of the actuators where ``reopen`` ``[R]``: forget everything
        (the block may straddle the change)."""
        lost_rows, lost_actions = rows[reopen], action[reopen]
        # "body": every actuator of the experiment forgets (a body changes as a whole)
        lost = slice(None) if self.reopen == "body" else lost_actions
        for prefix in ("", "block_"):
            for name in ("count", "successes", "reward_sum", "log_marginal"):
                getattr(self, prefix + name)[lost_rows, lost] = 0.0
        self.block_samples[lost_rows, lost] = 0
        self.committed[lost_rows, lost] = -1
        self.active[lost_rows, lost] = self.initial_active
        # the history restarts after this firing (the counts forget it too)
        length = self.history_length[lost_rows]
        if self.reopen == "body":
            length = length.unsqueeze(1).expand(-1, self.num_actions)
        self.history_start[lost_rows, lost] = length
        self.block_start[lost_rows, lost] = length
        self.reopened[lost_rows, lost_actions] += 1
        if self.reopen == "body":
            self._refresh_cache(lost_rows, slice(None))

    def _close_blocks(
        self,
        rows: torch.Tensor,
        action: torch.Tensor,
        fired: torch.Tensor,
        log_posterior: torch.Tensor | None,
    ) -> torch.Tensor | None:
        """``_decide``'s end: clear the block of the actuators whose block is full (``window``
        firings); returns ``log_posterior``."""
        full = self.block_samples.view(-1).index_select(0, fired) >= scalar(
            self.window, self.block_samples
        )
        if bool(full.any()):
            full_rows, full_actions = rows[full], action[full]
            for name in ("count", "successes", "reward_sum", "log_marginal"):
                getattr(self, "block_" + name)[full_rows, full_actions] = 0.0
            self.block_samples[full_rows, full_actions] = 0
            self.block_start[full_rows, full_actions] = self.history_length[full_rows]
        return log_posterior

    def _margin(self, log_posterior: torch.Tensor, best: torch.Tensor) -> torch.Tensor:
        """``[R]``: log posterior odds of ``best`` over its strongest competitor."""
        rivals = self.competitors.index_select(0, best)  # [R, C]
        lead = log_posterior.gather(1, best.unsqueeze(1)).squeeze(1)
        unseen = scalar(-math.inf, log_posterior)
        return lead - torch.where(rivals, log_posterior, unseen).max(dim=-1).values

    @torch.no_grad()
    def reset(self, mask: torch.Tensor | None = None) -> None:
        """Forget everything (of every experiment, or only where ``mask`` ``[S]``)."""
        mask = check_mask(mask, self.num_experiments, "StructureLearner.reset")
        rows = slice(None) if mask is None else mask
        for prefix in ("", "block_"):
            for name in ("count", "successes", "reward_sum", "log_marginal"):
                getattr(self, prefix + name)[rows] = 0.0
        self.committed[rows] = -1
        for name in ("samples", "block_samples", "reopened"):
            getattr(self, name)[rows] = 0
        self.noise_seen[rows] = False
        self.active[rows] = self.initial_active
        for name in ("history_start", "block_start", "history_length"):
            getattr(self, name)[rows] = 0
        self._refresh_cache(rows, slice(None))
