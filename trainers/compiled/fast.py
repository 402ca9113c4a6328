"""The fused fast path: whole experiments (SPEC section 4) advanced by a small compiled C kernel.

The kernel (``_kernel.c``) mirrors ``factorq_envs.grid_world`` and ``factorq_torch.functional``
bit for bit (docs/decisions.md, "The compiled mirror"), one experiment at a time for many steps,
leaving Python once per ``advance`` call. Building and loading are ``loader``'s, the options and
their checks ``batch_options``'s; where the kernel cannot be built ``is_available()`` is False,
``unavailable_reason()`` says why, and callers fall back to the modular torchrl path.

>>> from factorq_envs.grid_world import WorldConfig
>>> from factorq_torch.base.config import AgentConfig
>>> from factorq_torch.base.rng import STREAM_POLICY, STREAM_WORLD, derive_keys
>>> if is_available():
...     metrics = run_experiments(
...         "factor-q", torch.tensor([0, 1]), WorldConfig(size=5, num_obstacles=3), AgentConfig(),
...         runs=2, episodes=3, world_keys=derive_keys(0, STREAM_WORLD, 2),
...         policy_keys=derive_keys(0, STREAM_POLICY, 2))
...     print(tuple(metrics["steps"].shape))
... else:
...     print((2, 2, 3))
(2, 2, 3)
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor, wait
from typing import Any

import torch

from factorq_envs.grid_world import WorldConfig, static_layout
from factorq_torch.base.config import ALGORITHMS, AgentConfig
from factorq_torch.base.keys import EPISODE_METRICS
from factorq_torch.base.rng import probability_threshold
from factorq_torch.base.validation import INT64_MAX, MAX_PARENTS, check_int, check_table_size
from factorq_torch.functional import check_dependency, parent_weights
from factorq_trainers.compiled import batch_options, loader
from factorq_trainers.compiled.batch_options import SensorOrders, StructureOptions, learner_setup
from factorq_trainers.compiled.loader import RANDOM_WALK, unsupported_reason
from factorq_trainers.compiled.loader import is_available as is_available  # callers check here
from factorq_trainers.compiled.loader import unavailable_reason as unavailable_reason

#: The kernel's int64 counters of each experiment.
_COUNTERS = (
    "cell episode_step scatters policy_counter run episode heading ticks episode_collisions "
    "episode_greedy_collisions"
).split()
#: fq_batch's fields that are the world's (``WorldConfig``) and the agent's (``AgentConfig``).
_WORLD_FIELDS = "size num_obstacles max_steps num_actuators num_sensors num_headings".split()
_AGENT_FIELDS = "gamma alpha g_min risk_threshold".split()


@functools.cache
def _pool(workers: int) -> ThreadPoolExecutor:
    """A process-wide pool of ``workers`` helper threads (kept between calls: starting threads on
    every ``advance`` costs more than short chunks of work)."""
    return ThreadPoolExecutor(workers, thread_name_prefix="factorq-fast")


def _wait_uninterrupted(futures: list) -> None:
    """Wait until every future is done, whatever interrupts arrive meanwhile (a second Ctrl-C
    must not skip the wait either); the futures' own errors are left to their callers."""
    pending = list(futures)
    while pending:
        with contextlib.suppress(KeyboardInterrupt):
            wait(pending)
        pending = [future for future in pending if not future.done()]


class ExperimentBatch:
    """S independent experiments of one algorithm, state in tensors, advanced by the C kernel.

    Experiment ``i`` is ``runs`` x ``episodes`` episodes of ``algorithm`` in a world with obstacle
    period ``periods[i]``, drawing from ``world_keys[i]`` and ``policy_keys[i]`` (from
    ``rng.derive_keys``); it gives the same numbers alone or in any batch, whatever the thread
    count and however ``advance`` is chunked. ``algorithm`` is ``"q-learning"``, ``"factor-q"`` or
    ``RANDOM_WALK`` (env only, for benchmarks). ``dependency`` (bool ``[A, K]``) replaces the
    world's in Factor-Q's local tables (e.g. the full joint table); ``structure`` and
    ``sensor_orders``: ``batch_options``'. Not safe to advance from two threads at once.
    """

    def __init__(
        self,
        algorithm: str,
        periods: torch.Tensor,
        world: WorldConfig,
        agent: AgentConfig,
        runs: int,
        episodes: int,
        world_keys: torch.Tensor,
        policy_keys: torch.Tensor,
        threads: int | None = None,
        dependency: torch.Tensor | None = None,
        structure: StructureOptions | None = None,
        sensor_orders: SensorOrders | None = None,
    ) -> None:
        if algorithm not in loader._ALGORITHM_CODES:
            choices = ", ".join((*ALGORITHMS, RANDOM_WALK))
            raise ValueError(f"algorithm={algorithm!r} is unknown: choose one of {choices}")
        if not isinstance(world, WorldConfig):
            raise TypeError(f"world must be a WorldConfig, got {type(world).__name__}")
        if not isinstance(agent, AgentConfig):
            raise TypeError(f"agent must be an AgentConfig, got {type(agent).__name__}")
        unsupported = unsupported_reason(world)
        if unsupported is not None:
            raise ValueError(f"world: the fast path cannot run this world: {unsupported}")
        periods = batch_options._check_vector("periods", periods, None)
        if bool((periods < 0).any()):
            raise ValueError(
                f"periods must be >= 0 (0 static, k > 0 moving), got {periods.min().item()}"
            )
        count = periods.numel()
        self.algorithm, self.world, self.agent = algorithm, world, agent
        self.runs = check_int("runs", runs, 1)
        self.episodes = check_int("episodes", episodes, 1)
        self.threads = (
            torch.get_num_threads() if threads is None else check_int("threads", threads, 1)
        )
        self._library = loader._require()
        world_keys = batch_options._check_vector("world_keys", world_keys, count)
        policy_keys = batch_options._check_vector("policy_keys", policy_keys, count)

        if agent.arbitration:  # the kernel mirrors eqs. 2-3 as the paper writes them
            raise ValueError(
                "agent.arbitration is not on the compiled path: run it on the modular torchrl "
                "path (FactorQPolicy / FactorQLoss, or a command's --path modular)"
            )
        if agent.exploration != "uniform" and algorithm != "factor-q":
            raise ValueError(
                f"agent.exploration={agent.exploration!r} needs a local model to say which "
                f"actuators are risky, and algorithm={algorithm!r} has none: use 'factor-q' or "
                f"exploration='uniform'"
            )
        width = world.size + 2
        pad_of_cell = loader._pad_of_cell(world.size)  # [N]
        static_grid = torch.ones(width * width, dtype=torch.uint8)  # [P], the wall ring is 1
        static = bool((periods == 0).any()) and world.num_obstacles
        static_grid[pad_of_cell.long()] = static_layout(world).to(torch.uint8) if static else 0
        # The paper's body with the paper's options runs the specialised loop; any other body
        # (factorq_envs.body), option or the risk options (AgentConfig) the generic one.
        generic = not world.is_paper_body or agent.risk_gate or agent.exploration != "uniform"
        generic = generic or any(x is not None for x in (dependency, structure, sensor_orders))
        num_actuators, num_sensors = world.num_actuators, world.num_sensors
        num_states = world.num_cells * world.num_headings
        if algorithm == "q-learning":
            num_states <<= num_sensors
            table = num_states * num_actuators
            check_table_size("ExperimentBatch", f"a Q-table of {num_states} states", table)
        if algorithm == RANDOM_WALK:
            num_states = 0
        if dependency is None:
            dependency = world.dependency
        else:
            dependency = check_dependency(dependency, world.num_sensors)
            if dependency.shape[0] != world.num_actuators:
                raise ValueError(
                    f"dependency has {dependency.shape[0]} actuators, the body has "
                    f"{world.num_actuators}"
                )
        parents = int(dependency.sum(dim=1).max())
        check_int("parents of an actuator (dependency)", parents, 0, MAX_PARENTS)
        table_width = 1 << parents
        offsets = world._tables["offsets"]  # [4, L, 2]
        self._body = {  # read-only; kept alive for the kernel's pointers
            "moves": world._tables["moves"].to(torch.int64).contiguous(),
            "turns": world._tables["turns"].to(torch.int64).contiguous(),
            "offsets": (offsets[..., 0] * width + offsets[..., 1]).contiguous(),  # [4, L]
            "permutation": world._tables["permutation"].to(torch.int64).contiguous(),
            "parent_weights": parent_weights(dependency).contiguous(),  # [A, K]
        }
        metric = (count, self.runs, self.episodes)

        # Written in the kernel's inner loop: one cache-line-aligned block per experiment, whose
        # stride is fq_batch's q_stride ... obstacle_stride.
        blocks = {
            "q": ((num_states, num_actuators), torch.float32),  # [S, states, actuator]
            "rho": ((num_actuators, table_width), torch.float32),  # [S, actuator, parents' pattern]
            "kappa": ((num_actuators, table_width), torch.int64),
            "grid": ((width * width,), torch.uint8),  # [S, P]
            "obstacle_pads": ((world.num_obstacles,), torch.int32),  # [S, K]
        }
        padded, strides = {}, {}
        for name, (shape, dtype) in blocks.items():
            padded[name], strides[f"{name.split('_')[0]}_stride"] = batch_options._padded_zeros(
                count, shape, dtype
            )

        # Every tensor the kernel reads or writes, by its fq_batch field name.
        self._tensors: dict[str, torch.Tensor] = {
            "periods": periods,  # [S]
            "world_keys": world_keys,  # [S]
            "policy_keys": policy_keys,  # [S]
            "static_grid": static_grid,  # [P]
            "pad_of_cell": pad_of_cell,  # [N]
            **padded,
            **{name: torch.zeros(count, dtype=torch.int64) for name in _COUNTERS},  # [S] each
            "bump": torch.zeros(count, num_actuators, dtype=torch.uint8),
            "episode_task_return": torch.zeros(count, dtype=torch.float32),
            # the per-episode metrics [S, runs, episodes]: int64 counts, the float32 return
            **{name: torch.zeros(metric, dtype=torch.int64) for name in EPISODE_METRICS[:3]},
            "task_return": torch.zeros(metric, dtype=torch.float32),
        }
        self.structure = structure
        learner_fields, self._learner_tables, state, self._candidate_sets = learner_setup(
            structure, sensor_orders, algorithm, world, count, self.runs, self.episodes
        )
        self._tensors.update(state)
        self._learner_state = tuple(state)
        pointers = {
            name: tensor.data_ptr()
            for tensors in (self._tensors, self._body, self._learner_tables)
            for name, tensor in tensors.items()
        }
        self._batch = loader._Batch(
            algorithm=loader._ALGORITHM_CODES[algorithm],
            num_experiments=count,
            runs=self.runs,
            episodes=self.episodes,
            explore_threshold=probability_threshold(agent.epsilon),
            eta_factor=1 + agent.eta,
            generic=int(generic),
            num_layout=world.layout.num_sensors,
            table_width=table_width,
            sensor_noise_threshold=probability_threshold(world.sensor_noise),
            actuator_noise_threshold=probability_threshold(world.actuator_noise),
            **strides,
            risk_gate=int(agent.risk_gate),
            risk_explore=int(agent.exploration == "risk-aware"),
            **{name: getattr(world, name) for name in _WORLD_FIELDS},
            **{name: getattr(agent, name) for name in _AGENT_FIELDS},
            **learner_fields,
            **pointers,
        )
        self._library.fq_start(ctypes.byref(self._batch))

    def learner_state(self) -> dict[str, torch.Tensor]:
        """The structure learner's state and bookkeeping (copies): ``committed``, ``samples``,
        ``block_samples``, ``reopened``, ``map_cache``, ``right_since``, ``samples_at_change``
        ``[S, A]``; ``wrong_commitments``, ``change_tick`` ``[S]``; ``curve`` ``[S, points]``;
        the counts as ``count``, ``successes``, ``reward_sum``, ``log_marginal`` and their
        ``block_`` twins ``[S, A, C, P]``; ``truth`` ``[S, 2, A]`` (candidate indices)."""
        if self.structure is None:
            raise RuntimeError("this batch runs no structure learner")
        names = ("count", "successes", "reward_sum", "log_marginal")
        state = {
            name: self._tensors[name].clone() for name in self._learner_state if name != "counts"
        }
        # the kernel's layout [S, A, C, 8, P]: one candidate's eight arrays side by side
        shape = (self.num_experiments, self.world.num_actuators, self._batch.num_candidates, 8)
        counts = self._tensors["counts"].reshape(*shape, self._batch.learner_patterns)
        for index, name in enumerate((*names, *("block_" + name for name in names))):
            state[name] = counts[:, :, :, index].clone()
        state["truth"] = self._learner_tables["truth"].clone()
        return state

    @property
    def num_experiments(self) -> int:
        return self._batch.num_experiments

    @property
    def done(self) -> bool:
        """All experiments have finished their runs x episodes."""
        return bool((self._tensors["run"] >= self.runs).all())

    @property
    def total_steps(self) -> int:
        """Env steps taken so far, summed over the experiments (one policy decision per step)."""
        return int(self._tensors["policy_counter"].sum())

    def advance(self, max_steps: int) -> int:
        """Run each unfinished experiment for up to ``max_steps`` more env steps (stopping early
        at its end); return the number of episodes completed in this call (all experiments)."""
        check_int("max_steps", max_steps, 0, INT64_MAX)  # the kernel's int64 (2**64 + 5 wrapped)
        if max_steps == 0 or self.done:
            return 0
        next_experiment = ctypes.c_int64(0)
        arguments = (ctypes.byref(self._batch), max_steps, ctypes.byref(next_experiment))
        threads = min(self.threads, self.num_experiments)
        if threads == 1:
            return self._checked([self._library.fq_advance(*arguments)])
        # ctypes releases the GIL during the call: each thread takes whole experiments from the
        # shared counter until none is left (results never depend on who ran what).
        pool = _pool(threads - 1)
        helpers = [pool.submit(self._library.fq_advance, *arguments) for _ in range(threads - 1)]
        try:
            completed = self._library.fq_advance(*arguments)
            results = [completed, *(helper.result() for helper in helpers)]
        except BaseException:
            # An interrupt (Ctrl-C) or an error here must not unwind while a helper still runs
            # the kernel on this batch: leaving would free the batch (and the shared counter)
            # under it, a crash. Wait for them (each finishes its current chunk), then raise.
            _wait_uninterrupted(helpers)
            raise
        return self._checked(results)

    def _checked(self, results: list[int]) -> int:
        """The episodes completed, or the kernel's refusal of a state out of range (ValueError)."""
        refused = [result for result in results if result < 0]
        if refused:
            experiment, code = divmod(-refused[0] - 1, loader._CHECK_CODES)
            names = loader._STATE_FIELDS
            field = names[code - 1] if 0 < code <= len(names) else f"code {code}"
            raise ValueError(
                f"the fast kernel refused experiment {experiment}: its {field} is out of range "
                f"(the state was loaded from a bad checkpoint or edited)"
            )
        return sum(results)

    def run(self, progress: Callable[[int], object] | None = None) -> dict[str, torch.Tensor]:
        """Advance every experiment to its end and return ``metrics()``; ``progress(n)`` is
        called with the number of episodes completed since its last call."""
        # Chunks only matter for progress reports (results do not depend on them).
        chunk = 20_000 if progress is not None else 1 << 62
        while not self.done:
            completed = self.advance(chunk)
            if progress is not None and completed:
                progress(completed)
        return self.metrics()

    def metrics(self) -> dict[str, torch.Tensor]:
        """Per-episode ``steps``, ``collisions``, ``greedy_collisions`` (int64) and
        ``task_return`` (float32), each ``[S, runs, episodes]``; zeros where not yet played."""
        return {name: self._tensors[name].clone() for name in EPISODE_METRICS}

    def tables(self) -> dict[str, torch.Tensor]:
        """The learned tables: ``q`` ``[S, states, 4]``, ``rho`` ``[S, 4, 2]`` (float32) and
        ``kappa`` ``[S, 4, 2]`` (int64; indexed by actuator, then sensor value)."""
        return {name: self._tensors[name].clone() for name in ("q", "rho", "kappa")}

    def state_dict(self) -> dict[str, torch.Tensor]:
        """Everything needed to resume exactly: tables, world state, stream positions, counters,
        partial metrics, and the batch's identity (periods and keys, checked on load)."""
        state = {
            name: tensor.clone()
            for name, tensor in self._tensors.items()
            if name not in ("static_grid", "pad_of_cell", "grid", "obstacle_pads", "bump")
        }
        pads = self._tensors["pad_of_cell"].long()
        state["obstacles"] = self._tensors["grid"][:, pads].bool()  # [S, N]
        state["bump"] = self._tensors["bump"].bool()  # [S, 4]
        return state

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        """Restore a ``state_dict`` of a batch built with the same arguments."""
        expected = self.state_dict()
        missing = sorted(set(expected) - set(state))
        unexpected = sorted(set(state) - set(expected))
        if missing or unexpected:
            raise KeyError(f"state_dict mismatch: missing {missing}, unexpected {unexpected}")
        for name, reference in expected.items():
            value = state[name]
            if not isinstance(value, torch.Tensor):
                raise TypeError(f"state[{name!r}] must be a tensor, got {type(value).__name__}")
            if value.shape != reference.shape or value.dtype != reference.dtype:
                raise ValueError(
                    f"state[{name!r}] has shape {tuple(value.shape)} and dtype {value.dtype}, "
                    f"expected {tuple(reference.shape)} and {reference.dtype}"
                )
            # tables, metrics: no NaN or infinity into the kernel
            if value.is_floating_point() and not bool(torch.isfinite(value).all()):
                raise ValueError(f"state[{name!r}] holds NaN or infinite values")
        for name in ("periods", "world_keys", "policy_keys"):
            if not torch.equal(state[name], expected[name]):
                raise ValueError(f"state[{name!r}] belongs to a different batch")
        obstacles = state["obstacles"]  # [S, N]
        if bool((obstacles.sum(dim=1) != self.world.num_obstacles).any()):
            raise ValueError(
                f"state['obstacles'] must hold num_obstacles={self.world.num_obstacles} per world"
            )
        if bool((state["cell"] < 0).any()) or bool((state["cell"] >= self.world.num_cells).any()):
            raise ValueError(f"state['cell'] must be in [0, {self.world.num_cells})")
        # In place: the kernel holds these tensors' data pointers.
        for name, tensor in self._tensors.items():
            if name in state:
                tensor.copy_(state[name])  # bump: bool to uint8
        pads = self._tensors["pad_of_cell"].long()
        grid = self._tensors["grid"]
        grid[:, pads] = obstacles.to(torch.uint8)
        cells = obstacles.nonzero()[:, 1].view(self.num_experiments, self.world.num_obstacles)
        self._tensors["obstacle_pads"].copy_(pads[cells])


def run_experiments(
    *batch: Any, progress: Callable[[int], object] | None = None, **options: Any
) -> dict[str, torch.Tensor]:
    """Run S experiments to the end and return their ``metrics()``: ``ExperimentBatch(*batch,
    **options)`` (its arguments, the same names and order) advanced until done.

    ``progress(n)`` is called with the number of episodes completed since its last call.
    """
    return ExperimentBatch(*batch, **options).run(progress)
