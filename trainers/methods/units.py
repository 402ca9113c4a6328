"""What several commands' units share around their methods, torch loaded only when a unit runs:
``torch_threads`` (a unit's torch threads, restored after), ``tick`` (progress every 100 env
steps), ``seed_stat`` (a measure's mean over seeds with its 95% interval), ``Tally`` (one
experiment's training record: ``gym``, ``risk``, ``minigrid``) and ``record`` (a collected step
into tallies), and for the commands on declared
worlds their extras (``require_extras``) and processes (``world_processes``)."""

from __future__ import annotations

import contextlib
import functools
import sys
from collections.abc import Callable, Iterable, Iterator
from typing import Any

from factorq_trainers.analysis.stats import bootstrap_mean_ci, interval, scalar_ci, wilson_ci


@contextlib.contextmanager
def torch_threads(count: int) -> Iterator[None]:
    """torch's intra-op threads set to ``count`` while the block runs (tiny tensors: more
    threads only wait on each other), the caller's number restored after."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def require_extras(worlds: Iterable[Any], sb3: bool = False) -> None:
    """The extras the declared ``worlds`` (``factorq_envs.worlds.DeclaredWorld``) need, and with
    ``sb3`` Stable-Baselines3's, installed; else one ModuleNotFoundError naming the extra."""
    from factorq_envs.gymnasium_adapter import require_extra

    for world in worlds:
        for module, extra in world.requires:
            require_extra(module, f"factorq-torch[{extra}]")
    if sb3:
        require_extra("stable_baselines3", "factorq-torch[sb3]")


def world_processes(worlds: Iterable[Any], steps: int, units: int) -> tuple[int, str]:
    """How many processes ``units`` units of ``steps`` env steps take by default
    (``runner.cluster.default_workers``): one per core where the slowest of the declared
    ``worlds`` steps slowly (highway-env), else 1 (in-process); and why."""
    from factorq_trainers.runner.cluster import default_workers

    slowest, why = 0.0, ""
    for world in worlds:
        step_s = world.step_seconds()
        if step_s > slowest:
            slowest, why = step_s, f"{world.label} takes {1e3 * step_s:.1f} ms an env step"
    return default_workers(slowest, steps, units), why


def tick(progress: Callable[[int], None], step: int, total: int, every: int = 100) -> None:
    """Report env steps to ``progress`` every ``every`` steps of ``total``, and the rest at the
    end."""
    if step % every == 0 or step == total:
        progress(every if step % every == 0 else step % every)


def seed_stat(values: list[float | None], seed: int, proportion: bool = False) -> dict[str, Any]:
    """Mean over the seeds that have a value, its 95% interval (Wilson's for a proportion, the
    BCa bootstrap's otherwise: neither leaves the possible range) and how many seeds have one."""
    present = [v for v in values if v is not None]
    if not present:
        return {"mean": None, "ci95": None, "n": 0}
    method = wilson_ci if proportion else functools.partial(bootstrap_mean_ci, seed=seed)
    mean, low, high = scalar_ci(present, method)
    return {"mean": mean, "ci95": interval(low, high), "n": len(present)}


class Tally:
    """One experiment's training, fed one env step at a time: its collisions (all, and on greedy
    actions), its finished episodes (``episodes``: end step, return, success, length each),
    ``reached``: the env step at which the mean score of the last ``window`` episodes first
    reached ``threshold`` (their successes, or with ``by_return`` their returns; None before),
    and with ``curve_every`` the curves of ``factorq gym``: at every ``curve_every``-th step and
    at step ``steps``, the step, the collisions so far and the mean return of the last ``window``
    episodes (None before the first)."""

    def __init__(
        self,
        window: int,
        threshold: float,
        *,
        by_return: bool = False,
        curve_every: int = 0,
        steps: int = 0,
    ) -> None:
        self.window, self.threshold, self.by_return = window, threshold, by_return
        self.curve_every, self.steps = curve_every, steps
        self.step = self.collisions = self.greedy_collisions = self.length = 0
        self.episode_return = 0.0
        self.episodes: list[tuple[int, float, bool, int]] = []
        self.reached: int | None = None
        names = ("curve_steps", "curve_crashes", "curve_return")
        self.curves: dict[str, list[Any]] = {name: [] for name in names}

    def update(
        self, reward: float, collided: bool, done: bool, success: bool = False, greedy: bool = True
    ) -> None:
        """Count one env step: its conventional reward, whether it collided, ended the episode,
        reached the goal (or survived), and whether its action was greedy (not exploratory)."""
        self.step += 1
        self.length += 1
        self.collisions += int(collided)
        self.greedy_collisions += int(collided and greedy)
        self.episode_return += reward
        window = self.window
        if done:
            self.episodes.append((self.step, self.episode_return, success, self.length))
            self.episode_return, self.length = 0.0, 0
            recent = [episode[1 if self.by_return else 2] for episode in self.episodes[-window:]]
            if self.reached is None and len(recent) == window and _mean(recent) >= self.threshold:
                self.reached = self.step
        if self.curve_every and (self.step % self.curve_every == 0 or self.step == self.steps):
            self.curves["curve_steps"].append(self.step)
            self.curves["curve_crashes"].append(self.collisions)
            recent = [episode[1] for episode in self.episodes[-window:]]
            self.curves["curve_return"].append(_mean(recent) if recent else None)


def _mean(values: list[Any]) -> float:
    return float(sum(values) / len(values))


def record(tallies: list[Tally], td: Any) -> None:
    """One collected step of the ``S`` experiments ``td`` into their tallies: ``td``'s
    ``exploratory`` and ``("next", reward | bump | done)``, the reward the world's conventional
    one (a split one with its collisions put back, in float64; a success: a positive one that
    ends the episode)."""
    nxt = td.get("next")
    rewards = nxt.get("reward").reshape(-1).tolist()
    local = nxt.get("local_reward", None)
    if local is not None:  # the reward was split: put the collisions back
        collisions = local.sum(dim=-1).reshape(-1).tolist()
        rewards = [reward + back for reward, back in zip(rewards, collisions, strict=True)]
    bumps = nxt.get("bump").any(dim=-1).reshape(-1).tolist()
    exploratory = td.get("exploratory").reshape(-1).tolist()
    done = nxt.get("done").reshape(-1).tolist()
    for i, r in enumerate(rewards):
        tallies[i].update(r, bumps[i], done[i], r > 0, not exploratory[i])


def greedy_rollouts(policy: Any, envs: Iterable[Any], limit: int | None = None) -> list[Any]:
    """One episode of ``policy`` in each torchrl env of ``envs``, greedy (exploration
    ``DETERMINISTIC``, no gradients), at most ``limit`` steps (None: until it ends): the
    rollouts ``[*B, T]``."""
    import torch
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    steps = sys.maxsize if limit is None else limit
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        return [env.rollout(steps, policy, break_when_any_done=True) for env in envs]


#: Stable-Baselines3 ``DQN``'s argument for each of ``methods.dqn.DQNConfig``'s names.
SB3_DQN_NAMES = {
    "lr": "learning_rate",
    "train_every": "train_freq",
    "eps_start": "exploration_initial_eps",
    "eps_end": "exploration_final_eps",
    **{name: name for name in ("buffer_size", "learning_starts", "batch_size", "gamma", "tau")},
    **{name: name for name in ("target_update_interval", "exploration_fraction")},
}


def sb3_dqn(
    settings: dict[str, Any], env: Any, policy: str, model: Any = None, **extra: Any
) -> Any:
    """SB3's ``DQN`` (or ``model``, a subclass) on ``env`` with ``settings`` in ``DQNConfig``'s
    names (``hidden``: the widths of ``policy``'s hidden layers) and SB3's own ``extra``. Its
    logger writes nowhere: SB3's default makes a ``SB3-<time>`` folder in the temp dir per run."""
    from stable_baselines3 import DQN
    from stable_baselines3.common.logger import Logger

    arguments = {SB3_DQN_NAMES[name]: value for name, value in settings.items() if name != "hidden"}
    net = {"net_arch": list(settings["hidden"])}
    built = (model or DQN)(policy, env, policy_kwargs=net, **arguments, **extra)
    built.set_logger(Logger(folder=None, output_formats=[]))
    return built


def sb3_greedy(
    model: Any, envs: Iterable[Any], collided: Callable[[dict], bool], limit: int | None = None
) -> list[tuple[float, int, bool]]:
    """One greedy episode (``predict(deterministic=True)``) of SB3 ``model`` in each gymnasium
    env of ``envs`` (reset first), at most ``limit`` steps (None: until it ends): its return,
    its collisions (``collided(info)`` of each step) and whether it terminated on a step without
    one (the goal reached)."""
    episodes = []
    for env in envs:
        observation, _ = env.reset()
        total, collisions, success = 0.0, 0, False
        for _ in range(sys.maxsize if limit is None else limit):
            action, _ = model.predict(observation, deterministic=True)
            observation, reward, terminated, truncated, info = env.step(int(action))
            hit = collided(info)
            total, collisions = total + float(reward), collisions + int(hit)
            if terminated or truncated:
                success = bool(terminated) and not hit
                break
        episodes.append((total, collisions, success))
    return episodes


def stat_cell(stat: dict[str, Any], digits: int = 2, seeds: int | None = None) -> str:
    """A report's cell of a ``seed_stat``: the mean with its interval, and with ``seeds`` the
    seeds that had a value where not all did (``(n/seeds)``); ``-`` for none."""
    if stat["mean"] is None:
        return "-"
    text = f"{stat['mean']:.{digits}f}"
    if stat["ci95"] is not None and stat["ci95"][0] is not None:
        text += f" [{stat['ci95'][0]:.{digits}f}, {stat['ci95'][1]:.{digits}f}]"
    if seeds is not None and stat["n"] < seeds:
        text += f" ({stat['n']}/{seeds})"
    return text


def sweep_cell(
    world: str, algorithm: str, stats: dict[str, Any], measures: tuple[str, ...]
) -> dict[str, Any]:
    """A ``factorq sweep`` cell: ``world``, ``algorithm`` and the mean and 95% interval of each
    of ``measures`` in ``stats`` (``seed_stat``'s, or a bare mean: no interval)."""
    cells: dict[str, Any] = {"world": world, "algorithm": algorithm}
    for name in measures:
        stat = stats[name]
        bare = not isinstance(stat, dict)
        cells[name] = (
            {"mean": stat, "ci95": None} if bare else {k: stat[k] for k in ("mean", "ci95")}
        )
    return cells
