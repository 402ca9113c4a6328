"""Factor-Q on MiniGrid Dynamic-Obstacles against Q-learning and DQN: ``factorq minigrid``.

On each size of ``MiniGrid-Dynamic-Obstacles-{5x5,6x6,8x8,16x16}-v0``
(``factorq_envs.minigrid_adapter``: MiniGrid's real env, read through the adapter), every method
trains ``seeds`` independent experiments for the same env-step budget, all seeds of a method in
one batch:

- ``factor-q-learned``: Factor-Q with ``StructureLearner`` as its local value provider, told only
  ``A = 3`` actuators and ``K`` sensors (no pairing): it must find that only forward has a local
  reward and that the front sensor decides it;
- ``factor-q-oracle``: Factor-Q with ``LocalRewardTable`` on the true pairing (forward <- front);
- ``q-learning``: tabular Q-learning on (cell, heading, all sensors);
- ``dqn``: ``experiments.dqn``'s torchrl DQN (DQNLoss, target network, replay, annealed
  epsilon) on the same information (``TaskQNetwork``: one-hot (cell, heading) and the sensor bits);
- ``dqn-image``: the same DQN on MiniGrid's own 7x7x3 ``image`` observation (the standard track).

The tabular agents run on the modular torchrl path (``OnlineCollector``, learning after every
step): the compiled kernel (``trainers/compiled/fast.py``) cannot step MiniGrid.

**Budget.** ``steps * size / 5`` env steps per seed at each size (rounded), the same for every
method. **Measures**, per seed: collisions during training (all, and on greedy actions); over the
episodes that end in the last ``final_fraction`` of the budget: success rate (the goal reached),
MiniGrid return (its own reward summed: goal reward, -1 per collision) and steps to goal (length
of the successful episodes); env steps until the success rate over the last ``window`` finished
episodes first reaches 90%; for ``factor-q-learned``, the env step at which the learner first
committed to "forward <- front" (and nothing else for forward). Wall time per method and size
(all seeds together). Means with 95% intervals across seeds that stay in the possible range:
Wilson's for the success rate, the BCa bootstrap for the rest (``factorq_trainers.analysis.stats``).
"""

from __future__ import annotations

import functools
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from factorq_torch.base.validation import check_int
from factorq_trainers.analysis.stats import DESCRIPTION as DESCRIPTION_OF_STATISTICS
from factorq_trainers.analysis.stats import bootstrap_mean_ci, interval, scalar_ci, wilson_ci
from factorq_trainers.reports.minigrid import FOUND_TARGET_STEPS
from factorq_trainers.runner import resources
from factorq_trainers.runner.options import option

if TYPE_CHECKING:
    import torch

    from factorq_envs.declared_env import DeclaredEnv

NAME = "minigrid"
HELP = (
    "Factor-Q against Q-learning and DQN on MiniGrid Dynamic-Obstacles (needs the minigrid extra)"
)
EXTRA = "factorq-torch[minigrid]"
DESCRIPTION = (
    "Train Factor-Q (learned dependencies and oracle pairing), Q-learning and DQN (same "
    "information, and MiniGrid's image) on MiniGrid-Dynamic-Obstacles-{5x5,6x6,8x8,16x16}-v0 with "
    "equal env-step budgets; write minigrid.json, minigrid.png and minigrid.md to --out. Needs "
    f"pip install '{EXTRA}'."
)
HINT = resources.MINIGRID_HINT
REPORT = "factorq_trainers.reports.minigrid"
WORK_UNIT = "step"
METHODS = (
    "factor-q-learned",
    "factor-q-posterior",
    "factor-q-oracle",
    "q-learning",
    "dqn",
    "dqn-image",
)
#: factor-q-posterior (StructureLearner's own open prediction) is an ablation, run on request.
DEFAULT_METHODS = tuple(m for m in METHODS if m != "factor-q-posterior")
METHOD_LABELS = {
    "factor-q-learned": "Factor-Q, learned dependencies",
    "factor-q-posterior": "Factor-Q, learned, posterior prediction",
    "factor-q-oracle": "Factor-Q, oracle pairing",
    "q-learning": "Q-learning (cell, heading, sensors)",
    "dqn": "DQN (cell, heading, sensors)",
    "dqn-image": "DQN (MiniGrid image)",
}
SIZE_NAMES = ("5", "6", "8", "16")
SEMANTICS_NAMES = ("minigrid", "nodeath")
LAYOUT_NAMES = ("front3", "ahead6")
SUCCESS_THRESHOLD = 0.9
NOTICE = (
    "factorq minigrid: the tabular agents run on the modular torchrl path (the compiled kernel "
    "cannot step MiniGrid)"
)


@dataclass(frozen=True)
class MiniGridConfig:
    """The MiniGrid experiment; the defaults run in a few minutes on 2 cores
    (``docs/tutorials/minigrid.md``).

    Args:
        seed, seeds: the master seed and the experiments per size and method.
        sizes, methods: what runs (``SIZE_NAMES``, ``METHODS``).
        steps: env steps per seed at 5x5 (size ``n`` gets ``steps * n / 5``).
        semantics, layout: the collision semantics and the sensors
            (``factorq_envs.minigrid_adapter``).
        window: finished episodes in the success rate behind "steps to 90%".
        final_fraction: the share of the budget, at its end, of the final measures.
        out: the output directory.
    """

    seed: int = option(0, "Master seed: worlds, policies and networks derive from it.")
    seeds: int = option(10, "Independent experiments per size and method.")
    sizes: tuple[str, ...] = option(SIZE_NAMES, "Sizes to run: 5, 6, 8, 16 (comma-separated).")
    methods: tuple[str, ...] = option(
        DEFAULT_METHODS,
        "Methods to run (comma-separated): " + ", ".join(METHODS) + ".",
    )
    steps: int = option(
        1_000, "Env steps per seed at 5x5; size n gets steps * n / 5, the same for every method."
    )
    semantics: str = option(
        "minigrid",
        "Collision semantics: minigrid (a collision ends the episode) or nodeath (it goes on).",
        choices=SEMANTICS_NAMES,
    )
    layout: str = option(
        "front3",
        "Sensors read from the view: front3 or ahead6 (factorq_envs.minigrid_adapter).",
        choices=LAYOUT_NAMES,
    )
    window: int = option(10, "Finished episodes in the success rate behind 'steps to 90%'.")
    final_fraction: float = option(
        0.2, "Fraction of the budget, at its end, whose episodes give the final measures."
    )
    out: str = option("results/minigrid", "Directory for the json, figure and report.")

    def __post_init__(self) -> None:
        from factorq_torch.base.validation import check_float, check_names

        check_int("seed", self.seed, 0, 2**31 - 1)
        check_int("seeds", self.seeds, 1, 10_000)
        object.__setattr__(self, "sizes", check_names("sizes", self.sizes, SIZE_NAMES))
        object.__setattr__(self, "methods", check_names("methods", self.methods, METHODS))
        check_int("steps", self.steps, 10, 10**8)
        if self.semantics not in SEMANTICS_NAMES:
            raise ValueError(f"semantics={self.semantics!r}: choose one of {SEMANTICS_NAMES}")
        if self.layout not in LAYOUT_NAMES:
            raise ValueError(f"layout={self.layout!r}: choose one of {LAYOUT_NAMES}")
        check_int("window", self.window, 1, 10_000)
        check_float("final_fraction", self.final_fraction, 0.0, 1.0, low_open=True)

    def budget(self, size: int) -> int:
        """Env steps per seed at ``size``.

        Args:
            size: the grid's side.
        """
        return max(1, round(self.steps * size / 5))


CONFIG = MiniGridConfig


# --------------------------------------------------------------------------------------------
# Keys: common random numbers (every method meets the same worlds at a size)


def world_seeds(config: MiniGridConfig, size: int) -> list[int]:
    """MiniGrid's reset seed of each experiment at ``size`` (the same for every method).

    Args:
        config: the experiment.
        size: the grid's side.
    """
    from factorq_torch.base.rng import STREAM_WORLD, derive_keys

    offset = SIZE_NAMES.index(str(size)) * config.seeds
    keys = derive_keys(config.seed, STREAM_WORLD, config.seeds, offset)
    return [int(key) & 0x7FFFFFFF for key in keys.tolist()]


def method_keys(config: MiniGridConfig, size: int, method: str, stream: int) -> torch.Tensor:
    """Keys ``[S]`` of ``stream`` for ``method``'s experiments at ``size``.

    Args:
        config: the experiment.
        size: the grid's side.
        method: one of ``METHODS``.
        stream: a stream of ``factorq_torch.base.rng``.
    """
    from factorq_torch.base.rng import derive_keys

    slot = SIZE_NAMES.index(str(size)) * len(METHODS) + METHODS.index(method)
    return derive_keys(config.seed, stream, config.seeds, slot * config.seeds)


# --------------------------------------------------------------------------------------------
# Recording


class Recorder:
    """Per-step collisions and per-episode outcomes of ``S`` experiments stepped in lockstep.

    Args:
        count: ``S``, the experiments.
    """

    def __init__(self, count: int) -> None:
        self.count = count
        self.step = 0
        self.collisions = np.zeros(count, dtype=np.int64)
        self.greedy_collisions = np.zeros(count, dtype=np.int64)
        self.returns = np.zeros(count)
        self.lengths = np.zeros(count, dtype=np.int64)
        # per experiment: (end step, success, return, length) of every finished episode
        self.episodes: list[list[tuple[int, bool, float, int]]] = [[] for _ in range(count)]

    def update(self, td: Any, conventional_reward: torch.Tensor) -> None:
        """Record one step.

        Args:
            td: the step's tensordict: ``exploratory`` and ``("next", bump | done)``.
            conventional_reward: ``[S]``, MiniGrid's own reward of the step.
        """
        self.step += 1
        nxt = td.get("next")
        bump = nxt.get("bump").any(dim=-1).numpy()
        exploratory = td.get("exploratory").reshape(-1).numpy()
        reward = conventional_reward.reshape(-1).numpy().astype(np.float64)
        done = nxt.get("done").reshape(-1).numpy()
        self.collisions += bump
        self.greedy_collisions += bump & ~exploratory
        self.returns += reward
        self.lengths += 1
        for i in np.flatnonzero(done):
            success = bool(reward[i] > 0)
            self.episodes[i].append(
                (self.step, success, float(self.returns[i]), int(self.lengths[i]))
            )
            self.returns[i], self.lengths[i] = 0.0, 0

    def summary(self, budget: int, window: int, final_fraction: float) -> dict[str, list[Any]]:
        """Per-seed measures (module docstring); ``None`` where there is nothing to measure.

        Args:
            budget: the env steps each seed ran.
            window: finished episodes in the success rate behind ``steps_to_90``.
            final_fraction: the share of the budget, at its end, of the final measures.
        """
        start = budget - final_fraction * budget
        out: dict[str, list[Any]] = {
            "success_rate": [],
            "return": [],
            "steps_to_goal": [],
            "episodes": [],
            "steps_to_90": [],
        }
        for episodes in self.episodes:
            final = [e for e in episodes if e[0] > start]
            out["episodes"].append(len(episodes))
            out["success_rate"].append(float(np.mean([e[1] for e in final])) if final else None)
            out["return"].append(float(np.mean([e[2] for e in final])) if final else None)
            lengths = [e[3] for e in final if e[1]]
            out["steps_to_goal"].append(float(np.mean(lengths)) if lengths else None)
            reached = None
            for k in range(window, len(episodes) + 1):
                recent = episodes[k - window : k]
                if np.mean([e[1] for e in recent]) >= SUCCESS_THRESHOLD:
                    reached = recent[-1][0]
                    break
            out["steps_to_90"].append(reached)
        out["collisions"] = self.collisions.tolist()
        out["greedy_collisions"] = self.greedy_collisions.tolist()
        return out


# --------------------------------------------------------------------------------------------
# The methods


def _env(config: MiniGridConfig, size: int, *, with_image: bool = False) -> DeclaredEnv:
    from factorq_envs.minigrid_torchrl import MiniGridEnv

    return MiniGridEnv(
        size,
        config.semantics,
        layout=config.layout,
        with_image=with_image,
        seeds=world_seeds(config, size),
    )


def run_tabular(
    config: MiniGridConfig, size: int, method: str, tick: Callable[[int], None]
) -> dict[str, Any]:
    """Factor-Q (learned or oracle) or Q-learning through ``OnlineCollector``.

    Args:
        config: the experiment.
        size: the grid's side.
        method: a tabular one of ``METHODS``.
        tick: called with env steps done, every 100.
    """
    import torch

    from factorq_envs.body import HEADING
    from factorq_envs.minigrid_adapter import FORWARD
    from factorq_torch.base.config import AgentConfig
    from factorq_torch.base.rng import STREAM_POLICY
    from factorq_torch.collectors import OnlineCollector
    from factorq_torch.structure import StructureLearner
    from factorq_torch.tables import LocalRewardTable, TaskQTable
    from factorq_trainers.experiments.experiment import online_agent

    count, budget = config.seeds, config.budget(size)
    base = _env(config, size)
    agent = AgentConfig()
    cells, sensors, actions = base.num_cells, base.num_sensors, base.num_actions
    learner = None
    if method == "q-learning":
        task = TaskQTable(
            count,
            cells,
            with_sensors=True,
            num_sensors=sensors,
            num_headings=HEADING.num_headings,
            num_actions=actions,
        )
        local = None
    else:
        task = TaskQTable(count, cells, num_headings=HEADING.num_headings, num_actions=actions)
        if method == "factor-q-oracle":
            local = LocalRewardTable(count, dependency=base.dependency)
        elif method == "factor-q-posterior":
            local = learner = StructureLearner(
                count, num_actions=actions, num_sensors=sensors, prediction="posterior"
            )
        else:  # an open actuator predicts no local reward (docs/decisions.md, MiniGrid)
            local = learner = StructureLearner(
                count, num_actions=actions, num_sensors=sensors, prediction="committed"
            )
    keys = method_keys(config, size, method, STREAM_POLICY)
    env, policy, loss = online_agent(base, task, local, agent, keys)
    # one run of as many episodes as the budget could hold: the loop below stops at the budget
    collector = OnlineCollector(env, policy, loss, runs=1, episodes=budget)
    recorder = Recorder(count)
    assert base.dependency is not None  # MiniGrid's declaration states its oracle
    truth = base.dependency[FORWARD]  # [K]
    found: list[int | None] = [None] * count
    started = time.perf_counter()
    for step, td in enumerate(collector, start=1):
        nxt = td.get("next")
        reward = nxt.get("reward").squeeze(-1)
        if local is not None:  # the reward was split: put the collisions back
            reward = reward + nxt.get("local_reward").sum(dim=-1)
        recorder.update(td, reward)
        if learner is not None:
            right = (learner.structure()[:, FORWARD] == truth).all(dim=-1).tolist()
            for i, ok in enumerate(right):
                if ok and found[i] is None:
                    found[i] = step
        if step % 100 == 0 or step == budget:
            tick(min(100, step - 100 * ((step - 1) // 100)))
        if step >= budget:
            break
    wall = time.perf_counter() - started
    collector.shutdown()
    result: dict[str, Any] = recorder.summary(budget, config.window, config.final_fraction)
    result["wall_s"] = wall
    if learner is not None:
        result["found_forward_front"] = found
        result["structure_at_end"] = learner.structure().to(torch.int64).tolist()
    return result


def _image_network(count: int, hidden: tuple[int, ...], keys: torch.Tensor, actions: int) -> Any:
    """``S`` MLPs on MiniGrid's image: ``image`` ``[..., S, 7, 7, 3]`` uint8 -> ``action_value``
    ``[..., S, A]``; the input is the image flattened and divided by 10 (object, colour and
    state indices are below 11)."""
    import torch
    from tensordict.nn import TensorDictModuleBase

    from factorq_torch.neural import BatchedMLP

    class _ImageQNetwork(TensorDictModuleBase):
        def __init__(self) -> None:
            super().__init__()
            self.in_keys, self.out_keys = ["image"], ["action_value"]
            self.mlp = BatchedMLP((count,), 7 * 7 * 3, actions, hidden=hidden, keys=keys)

        def forward(self, tensordict: Any) -> Any:
            image = tensordict.get("image")
            x = image.reshape(*image.shape[:-3], -1).to(torch.float32) / 10.0
            tensordict.set("action_value", self.mlp(x))
            return tensordict

    return _ImageQNetwork()


def run_dqn(
    config: MiniGridConfig, size: int, method: str, tick: Callable[[int], None]
) -> dict[str, Any]:
    """``factorq_trainers.experiments.dqn``'s DQN (its defaults) on the cell/heading/sensors or on
    the image.

    Args:
        config: the experiment.
        size: the grid's side.
        method: ``"dqn"`` or ``"dqn-image"``.
        tick: called with env steps done, every 100.
    """
    import torch

    from factorq_envs.body import HEADING
    from factorq_torch.base.rng import STREAM_POLICY, STREAM_TASK_NETWORK
    from factorq_torch.neural import TaskQNetwork
    from factorq_trainers.experiments.dqn import DQNConfig, _gradient_step, dqn_agent

    dqn = DQNConfig()
    count, budget = config.seeds, config.budget(size)
    image = method == "dqn-image"
    env = _env(config, size, with_image=image)
    actions = env.num_actions
    init_keys = method_keys(config, size, method, STREAM_TASK_NETWORK)
    if image:
        q_network = _image_network(count, dqn.hidden, init_keys, actions)
        stored = ["image", ("next", "image")]
    else:
        q_network = TaskQNetwork(
            count,
            env.num_cells,
            with_proximity=True,
            num_sensors=env.num_sensors,
            num_headings=HEADING.num_headings,
            num_actions=actions,
            hidden=dqn.hidden,
            keys=init_keys,
            zero_output=False,
        )
        stored = [
            "cell",
            "heading",
            "sensors",
            ("next", "cell"),
            ("next", "heading"),
            ("next", "sensors"),
        ]
    stored += ["action", ("next", "reward"), ("next", "done"), ("next", "terminated")]
    torch.manual_seed(int(method_keys(config, size, method, STREAM_POLICY)[0]) & 0x7FFFFFFF)
    agent = dqn_agent(q_network, actions, dqn, budget)
    policy, buffer = agent.policy, agent.buffer
    recorder = Recorder(count)
    started = time.perf_counter()
    td = env.reset()
    for step in range(1, budget + 1):
        with torch.no_grad():
            td = env.step(policy(td))
        recorder.update(td, td.get(("next", "reward")).squeeze(-1))
        buffer.extend(td.select(*stored).unsqueeze(0))
        if step >= dqn.learning_starts and step % dqn.train_every == 0:
            _gradient_step(agent, dqn.batch_size)
        td = env.step_mdp(td)
        done = td.get("done")
        if bool(done.any()):
            td.set("_reset", done)
            td = env.reset(td)
        if step % 100 == 0 or step == budget:
            tick(min(100, step - 100 * ((step - 1) // 100)))
    wall = time.perf_counter() - started
    env.close()
    result: dict[str, Any] = recorder.summary(budget, config.window, config.final_fraction)
    result["wall_s"] = wall
    return result


RUNNERS = {
    "factor-q-learned": run_tabular,
    "factor-q-posterior": run_tabular,
    "factor-q-oracle": run_tabular,
    "q-learning": run_tabular,
    "dqn": run_dqn,
    "dqn-image": run_dqn,
}


# --------------------------------------------------------------------------------------------
# The experiment


def _stat(values: list[float | None], seed: int, proportion: bool = False) -> dict[str, Any]:
    """Mean and 95% interval of the seeds that have a value (Wilson's for a proportion, the
    bootstrap's otherwise: both stay inside the possible range, stats), and how many have one."""
    present = [v for v in values if v is not None]
    if not present:
        return {"mean": None, "ci95": None, "n": 0}
    method = wilson_ci if proportion else functools.partial(bootstrap_mean_ci, seed=seed)
    mean, low, high = scalar_ci(present, method)
    return {"mean": mean, "ci95": interval(low, high), "n": len(present)}


MEASURES = (
    "success_rate",
    "return",
    "steps_to_goal",
    "collisions",
    "greedy_collisions",
    "steps_to_90",
    "episodes",
)


def summarise_method(result: dict[str, Any], budget: int, seed: int = 0) -> dict[str, Any]:
    """Each measure's mean over seeds and 95% interval (Wilson for the success rate, the BCa
    bootstrap otherwise), and how often the learner found forward <- front.

    Args:
        result: a method's per-seed measures (``Recorder.summary`` and ``wall_s``).
        budget: the env steps each seed ran.
        seed: the master seed (the bootstrap's resamples).
    """
    summary: dict[str, Any] = {
        name: _stat(result[name], seed, name == "success_rate") for name in MEASURES
    }
    found = result.get("found_forward_front")
    if found is not None:
        within = [f is not None and f <= FOUND_TARGET_STEPS for f in found]
        summary["found_forward_front"] = _stat(found, seed)
        summary["found_within_target"] = float(np.mean(within))
        summary["found_at_all"] = float(np.mean([f is not None for f in found]))
    summary["wall_s"] = result["wall_s"]
    summary["env_steps_per_seed"] = budget
    return summary


def estimate(config: MiniGridConfig) -> resources.Estimate:
    """``resources.minigrid_estimate`` for the body of ``config``'s sensor layout.

    Args:
        config: the experiment.
    """
    from factorq_envs.body import HEADING
    from factorq_envs.minigrid_adapter import sensor_names

    return resources.minigrid_estimate(
        config, len(sensor_names(config.layout)), HEADING.num_headings, len(HEADING.actuators)
    )


def units(config: MiniGridConfig) -> list[dict[str, Any]]:
    """One unit per size and method (a method's seeds run as one batch).

    Args:
        config: the experiment.
    """
    return [
        {"id": f"{size}/{method}", "size": int(size), "method": method}
        for size in config.sizes
        for method in config.methods
    ]


def work(config: MiniGridConfig, unit: dict[str, Any]) -> int:
    """A unit's env steps per seed (what ``run_unit`` reports to ``progress``).

    Args:
        config: the experiment.
        unit: one of ``units(config)``.
    """
    return config.budget(unit["size"])


def prepare(config: MiniGridConfig) -> None:
    """``factorq_envs.minigrid_adapter.require_minigrid`` (a ModuleNotFoundError naming the extra).

    Args:
        config: the experiment.
    """
    from factorq_envs.minigrid_adapter import require_minigrid

    require_minigrid()


def run_unit(
    config: MiniGridConfig, unit: dict[str, Any], progress: Callable[[int], None] | None = None
) -> dict[str, Any]:
    """One method at one size, all seeds; ``progress(env_steps)`` after each 100 steps.

    Args:
        config: the experiment.
        unit: one of ``units(config)``.
        progress: called with env steps done.
    """
    import torch

    size, method = unit["size"], unit["method"]
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny tensors: more threads only wait on each other
    try:
        raw = RUNNERS[method](config, size, method, progress or (lambda steps: None))
    finally:
        torch.set_num_threads(threads)
    return {"seeds": raw, "summary": summarise_method(raw, config.budget(size), config.seed)}


def summarise(config: MiniGridConfig, outcomes: list[dict[str, Any]]) -> dict[str, Any]:
    """``minigrid.json``'s entries from the units (in ``units`` order).

    Args:
        config: the experiment.
        outcomes: ``run_unit``'s results.
    """
    from factorq_envs.minigrid_adapter import sensor_names

    results: dict[str, Any] = {}
    for unit, outcome in zip(units(config), outcomes, strict=True):
        results.setdefault(str(unit["size"]), {})[unit["method"]] = outcome
    return {
        "sensors": list(sensor_names(config.layout)),
        "budgets": {size: config.budget(int(size)) for size in config.sizes},
        "results": results,
        "statistics": DESCRIPTION_OF_STATISTICS,
        "notice": NOTICE,
        "methods": dict(METHOD_LABELS),
    }


def run(config: MiniGridConfig, progress: Callable[[int], None] | None = None) -> dict[str, Any]:
    """Every method on every size, here; the results (what ``minigrid.json`` holds).

    Args:
        config: the experiment.
        progress: called with env steps done.
    """
    from factorq_trainers.runner import frame

    return frame.run_in_process(sys.modules[__name__], config, progress)
