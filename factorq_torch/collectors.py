"""The online collector: act, step, learn after every single step, for ``S`` experiments at once.

The paper's algorithms are online: the tables change after every action and the next action
already uses them, so a batch of frames gathered with a frozen policy would be another algorithm.
``OnlineCollector`` therefore owns the whole loop of SPEC section 4 for a batched env of
``S`` independent experiments:

    policy (no grad) -> env.step (no grad) -> loss -> backward -> optimizer.step -> record
    -> (task-table reset at run boundaries, env reset at episode ends) -> yield the transition

Each experiment has its own run and episode counters. When experiment ``i`` ends the last
episode of a run, the collector calls ``reset_task(mask)`` for ``i`` only (its local tables carry
over, SPEC section 4); when it has finished ``runs x episodes`` it is *finished*: from then on it
is masked everywhere (``("collector", "mask")`` False for the policy and the loss, ``"_step"``
False for the env), so its tables, its policy stream and its world no longer change while the
others go on. The collector stops when every experiment has finished.

It is a torchrl ``BaseCollector``: iterate over it (``for td in collector``) to receive each
step's transition (a TensorDict ``[S]`` with the ``"next"`` entries, after the update was applied,
plus ``("collector", "mask" | "run" | "episode")``, the run and episode each experiment's step
belonged to); or call ``run()`` to go to the end and get the metrics. Stopping an iteration early
and resuming (iterating again, or ``run()``) continues exactly where it stopped.

Per-episode metrics, ``collector.metrics`` (a TensorDict ``[S, runs, episodes]``):
``steps`` (path length), ``collisions``, ``greedy_collisions`` (collisions on actions that were
not exploratory) and ``task_return`` (sum of step + goal rewards, for both algorithms).

Why ``BaseCollector`` and not torchrl's ``Collector``: ``Collector`` gathers ``frames_per_batch``
frames with the policy frozen and leaves learning to the caller; here the update must happen
inside the loop, between two actions, and the end is decided per experiment by run and episode
counters rather than by a frame budget. ``BaseCollector``'s abstract interface (``iterator``,
``shutdown``, ``set_seed``, ``state_dict``, ``load_state_dict``) fits that exactly.
"""

from __future__ import annotations

import warnings
from collections import OrderedDict
from collections.abc import Callable, Iterator

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase
from torchrl.objectives import LossModule

from factorq_torch.base import keys
from factorq_torch.base.indices import row_starts
from factorq_torch.base.validation import check_int
from factorq_torch.objectives import tabular_optimizer
from factorq_torch.policy import MASK_KEY

with warnings.catch_warnings():
    # torchrl 0.14.1 warns about its own deprecated weight updaters when the package is imported.
    warnings.filterwarnings("ignore", "Creating .*WeightUpdater", DeprecationWarning)
    from torchrl.collectors import BaseCollector

#: The module of the forward pre-hook ``torchrl.objectives.LossModule`` puts on every loss.
_TORCHRL_LOSS_HOOKS = LossModule.__init__.__module__

#: ``progress(episodes, experiments)``: episodes and experiments completed since the last call.
ProgressCallback = Callable[[int, int], None]

METRICS = keys.EPISODE_METRICS


def ended_rows(ended: torch.Tensor, count: int, on_host: bool) -> torch.Tensor:
    """The indices ``[count]`` of the ``count`` True entries of ``ended`` ``[S]``, ascending.

    ``on_host`` (the CPU, where reading the flags is a memory read): ``nonzero``. Else without a
    host read: the ``k``-th True entry goes to position ``k`` of a buffer of ``count + 1`` (a
    count the host already holds), the others to the spare position past its end.
    """
    if on_host:
        return ended.nonzero().squeeze(1)
    rows = row_starts(ended.shape[0], 1, ended.device)  # arange(S)
    position = torch.where(ended, ended.cumsum(0) - 1, count)
    return rows.new_empty(count + 1).scatter_(0, position, rows)[:count]


class OnlineCollector(BaseCollector):
    """Runs ``S`` experiments of ``runs x episodes`` episodes, learning after every step.

    Args:
        env: a torchrl env of ``batch_size=(S,)`` (e.g. ``FactoredGridEnv``, with
            ``SplitLocalReward`` for Factor-Q). Its ``("next", "bump")`` ``[S, 4]`` marks
            collisions; the task reward is ``("next", "reward")`` when ``("next",
            "local_reward")`` exists (the reward was split), else ``("next", "reward")`` minus
            the sum of ``("next", "collision")``.
        policy: writes ``action`` and ``exploratory`` from the env's observations, e.g.
            ``TensorDictSequential(task_table, local_table, FactorQPolicy(...))``.
        loss: ``FactorQLoss`` or ``TabularQLoss`` over the same tables; its task provider's
            ``reset_task(mask)`` is called at run boundaries.
        runs, episodes: per experiment (the paper: 10 x 200).
        optimizer: applied to every ``loss_*`` entry that has a gradient; default
            ``tabular_optimizer(loss)`` (SGD, learning rate 1: the exact tabular update).
        progress: ``progress(episodes, experiments)`` with the episodes and experiments completed
            since the previous call, called after each step that completed an episode.

    Example:
        >>> from tensordict.nn import TensorDictSequential
        >>> from factorq_envs import FactoredGridEnv
        >>> from factorq_torch.objectives import TabularQLoss
        >>> from factorq_torch.policy import EpsilonGreedyPolicy
        >>> from factorq_torch.tables import TaskQTable
        >>> env = FactoredGridEnv(size=3, num_obstacles=1, batch_size=(2,))
        >>> table = TaskQTable(2, num_cells=9, with_sensors=True)
        >>> policy = TensorDictSequential(table, EpsilonGreedyPolicy(2, seed=0))
        >>> collector = OnlineCollector(env, policy, TabularQLoss(table), runs=2, episodes=3)
        >>> metrics = collector.run()
        >>> metrics.batch_size, bool((metrics["steps"] >= 4).all())
        (torch.Size([2, 2, 3]), True)
    """

    def __init__(
        self,
        env: EnvBase,
        policy: TensorDictModuleBase,
        loss: LossModule,
        *,
        runs: int,
        episodes: int,
        optimizer: torch.optim.Optimizer | None = None,
        progress: ProgressCallback | None = None,
    ) -> None:
        super().__init__()
        for name, value, kind, what in (
            ("env", env, EnvBase, "a torchrl env (EnvBase)"),
            ("policy", policy, torch.nn.Module, "a TensorDict module"),
            ("loss", loss, LossModule, "a torchrl LossModule"),
        ):
            if not isinstance(value, kind):
                raise TypeError(f"{name} must be {what}, got {type(value).__name__}")
        self.runs = check_int("runs", runs, 1)
        self.episodes = check_int("episodes", episodes, 1)
        if len(env.batch_size) != 1:
            raise ValueError(
                f"env.batch_size={list(env.batch_size)}: OnlineCollector needs one batch "
                f"dimension of independent experiments, batch_size=(S,)"
            )
        self.num_experiments = env.batch_size[0]
        for owner in (policy, loss):
            for module in owner.modules():
                held = getattr(module, "num_experiments", None)
                if held is not None and held != self.num_experiments:
                    raise ValueError(
                        f"env has batch_size [{self.num_experiments}] but {type(module).__name__} "
                        f"holds S={held} experiments: build them with the same S"
                    )
        cells = getattr(
            getattr(env.observation_spec.get(keys.CELL, None), "space", None), "n", None
        )
        for module in (*policy.modules(), *loss.modules()):
            held = getattr(module, "num_cells", None)
            if cells is not None and held is not None and held != cells:
                raise ValueError(
                    f"{type(module).__name__} was built for num_cells={held} but the env has "
                    f"{cells} cells: build it with num_cells={cells} (size**2 of the env)"
                )
        self.env, self.policy, self.loss = env, policy, loss
        # The env takes reset(..., restarts_terminated=True) (FactoredGridEnv): told when every
        # restart follows a terminated episode, it reuses the step's scatter (same numbers).
        self._hints = bool(getattr(env, "accepts_restarts_terminated", False))
        # ... and reset(..., reset_mask=mask): the worlds to restart as a keyword, so that
        # torchrl updates with the env's whole answer instead of merging it under "_reset".
        self._mask_keyword = bool(getattr(env, "accepts_reset_mask", False))
        self._restarts_terminated = False
        #: What a partial reset reads and writes: the env's observation, done and state entries.
        self._env_keys = list(
            dict.fromkeys(
                (
                    *env.full_observation_spec.keys(True, True),
                    *env.full_done_spec.keys(True, True),
                    *env.full_state_spec.keys(True, True),
                )
            )
        )
        self.optimizer = tabular_optimizer(loss) if optimizer is None else optimizer
        # The optimizer is ours and the loss can apply its step directly (a TaskQTable): the
        # same update, bit for bit, without a graph, a sparse gradient or an optimizer call.
        supports = getattr(loss, "supports_tabular_step", None)
        self._tabular = optimizer is None and callable(supports) and bool(supports())
        self.progress = progress
        self._reset_task = getattr(getattr(loss, "task_value_network", None), "reset_task", None)
        if self._reset_task is None and self.runs > 1:
            raise ValueError(
                "runs > 1 needs a task value provider with reset_task(mask) (e.g. TaskQTable) "
                "as loss.task_value_network, to reset it at every run boundary"
            )
        device = env.device
        batch = self.num_experiments
        shape = (batch, self.runs, self.episodes)
        counts = {name: torch.zeros(shape, dtype=torch.int64, device=device) for name in METRICS}
        counts["task_return"] = torch.zeros(shape, dtype=torch.float32, device=device)
        self.metrics = TensorDict(counts, batch_size=shape, device=device)
        zeros = torch.zeros(batch, dtype=torch.int64, device=device)
        self.run_index = zeros.clone()  # [S], the run in progress
        self.episode_index = zeros.clone()  # [S], the episode in progress within the run
        self._episode = {name: zeros.clone() for name in METRICS}  # running sums, this episode
        self._episode["task_return"] = torch.zeros(batch, device=device)
        self.finished = torch.zeros(batch, dtype=torch.bool, device=device)
        self._any_finished = False
        self._finished_count = 0  # = int(self.finished.sum()), kept on the host
        self._td: TensorDictBase | None = None
        self._frames = 0
        self._iter = -1

    @property
    def done(self) -> bool:
        """Whether every experiment has finished its ``runs x episodes`` episodes."""
        return self._finished_count == self.num_experiments

    def iterator(self) -> Iterator[TensorDictBase]:
        """Yield the transition TensorDict ``[S]`` of every step until all experiments finish."""
        while not self.done:
            yield self.step()

    def run(self) -> TensorDictBase:
        """Step until every experiment has finished; return ``metrics`` ``[S, runs, episodes]``."""
        while not self.done:
            self.step()
        return self.metrics

    def step(self) -> TensorDictBase:
        """One step of every running experiment: act, step the env, learn, record."""
        if self.done:
            raise RuntimeError("every experiment has finished: build a new collector to go on")
        active = ~self.finished  # [S]
        finished_before = self._finished_count
        with torch.no_grad():
            td = self.env.reset() if self._td is None else self._td
            td.set(MASK_KEY, active)
            if self._any_finished:  # finished worlds stay as they are
                td.set("_step", active.unsqueeze(-1))
            td = self.env.step(self.policy(td))
        self._learn(td)
        with torch.no_grad():
            td.set(("collector", "run"), self.run_index)
            td.set(("collector", "episode"), self.episode_index)
            next_td = self.env.step_mdp(td)
            restart = self._record(td, active)
            if restart is not None:
                # The env's own entries only: the others (the policy's outputs, the collector's
                # counters) are rewritten before they are read again, and torchrl would merge
                # every entry of the tensordict by the reset mask, one torch.where each.
                env_td = next_td.select(*self._env_keys, strict=False)
                hints: dict[str, object] = {}
                if self._hints and self._restarts_terminated:
                    hints["restarts_terminated"] = True
                if self._mask_keyword:
                    hints["reset_mask"] = restart
                else:
                    env_td.set("_reset", restart.unsqueeze(-1))
                next_td.update(self.env.reset(env_td, **hints))
        self._td = next_td
        self._frames += self.num_experiments - finished_before
        self._iter += 1
        if self.post_collect_hook is not None:
            self.post_collect_hook(td)
        return td

    def _learn(self, td: TensorDictBase) -> None:
        """The loss (eq. 5 inside, in training mode) and one optimizer step on its gradients;
        with the collector's own tabular optimizer, the loss's ``tabular_step`` (the same update
        written directly, see ``factorq_torch.objectives``)."""
        if self._tabular and not self._loss_observed() and self.loss.tabular_step(td):
            return
        losses = self.loss(td)
        total = None
        for key, value in losses.items():
            if key.startswith("loss_") and value.requires_grad:
                total = value if total is None else total + value
        if total is not None:
            total.backward()
            self.optimizer.step()
            self.optimizer.zero_grad(set_to_none=True)

    def _loss_observed(self) -> bool:
        """Whether a hook watches the loss's ``forward`` (e.g. a trainer reading ``td_error``):
        then the loss runs as a module, and the update goes through its gradient."""
        loss = self.loss
        # torchrl's LossModule registers its own pre-hook on every loss (a target-network
        # warning, which reads nothing of the output): it does not count as a watcher.
        pre_hooks = [
            hook
            for hook in loss._forward_pre_hooks.values()
            if getattr(hook, "__module__", None) != _TORCHRL_LOSS_HOOKS
        ]
        return bool(loss._forward_hooks or pre_hooks)

    def _record(self, td: TensorDictBase, active: torch.Tensor) -> torch.Tensor | None:
        """Add the step to the episode sums; file finished episodes; advance the counters.

        Returns the experiments whose env must start a new episode (``None``: none).
        """
        next_td = td.get("next")
        # (until an experiment finishes every one is active: the masking is skipped)
        collided = next_td.get("bump").any(dim=-1)  # [S]
        reward = next_td.get("reward").squeeze(-1)  # [S]
        if next_td.get("local_reward", None) is None:  # conventional reward: remove collisions
            reward = reward - next_td.get("collision").sum(dim=-1)
        ended = next_td.get("done").squeeze(-1)  # [S]
        sums = self._episode
        if self._any_finished:
            collided, ended = collided & active, ended & active
            sums["steps"] = sums["steps"] + active  # int64 + bool: int64, no cast pass
            sums["task_return"] = sums["task_return"] + torch.where(active, reward, 0.0)
        else:
            sums["steps"] = sums["steps"] + 1
            sums["task_return"] = sums["task_return"] + reward
        sums["collisions"] = sums["collisions"] + collided
        greedy = collided & ~td.get("exploratory")
        sums["greedy_collisions"] = sums["greedy_collisions"] + greedy
        # Everything below is computed for every experiment and selected with torch.where, and
        # the host reads one small tensor of counts per step (a GPU waits once, not five times).
        episode = self.episode_index + ended
        run_ended = episode == self.episodes  # only experiments that just ended an episode
        run_index = self.run_index + run_ended
        finishing = run_ended & (run_index == self.runs)
        next_run = run_ended & ~finishing
        # (and how many ended without terminating: a truncated episode's reset draws afresh)
        unterminated = ended & ~next_td.get("terminated").squeeze(-1)
        counts = torch.stack((ended, next_run, finishing, unterminated)).sum(dim=1)  # int64 [4]
        episodes_ended, runs_started, experiments_finishing, truncated = counts.tolist()
        self._restarts_terminated = truncated == 0
        if not episodes_ended:
            return None
        # The experiments that ended an episode, ascending (ended_rows: without a host read on
        # a GPU). Only their slots (run, episode) of the flat [S * runs * episodes] metrics are
        # touched: reading and writing back every experiment's slot, one per S * runs *
        # episodes / S entries, was a cache miss per experiment and metric (a sixth of the
        # README loop's ops time at S = 4096).
        which = ended_rows(ended, episodes_ended, on_host=ended.device.type == "cpu")
        run = self.run_index.index_select(0, which)  # (an ended experiment is not finished)
        episode_in_run = self.episode_index.index_select(0, which)
        slot = (which * self.runs + run) * self.episodes + episode_in_run
        for name, metric in self._flat_metrics().items():
            metric.index_copy_(0, slot, sums[name].index_select(0, which))
            sums[name].masked_fill_(ended, 0)  # (the sums are this collector's own tensors)
        self.episode_index = episode.masked_fill_(run_ended, 0)  # (a new tensor: episode)
        self.run_index = run_index
        if self._reset_task is not None and runs_started:
            self._reset_task(next_run)  # SPEC 4: task table to 0 at every run, local tables kept
        if experiments_finishing:
            self.finished = self.finished | finishing
            self._any_finished = True
            self._finished_count += experiments_finishing
        if self.progress is not None:
            self.progress(episodes_ended, experiments_finishing)
        restart = ended & ~self.finished
        return None if episodes_ended == experiments_finishing else restart

    def _flat_metrics(self) -> dict[str, torch.Tensor]:
        """Each metric of ``self.metrics`` as a flat ``[S * runs * episodes]`` view, built once
        per metrics TensorDict (``load_state_dict`` writes into it in place)."""
        cached = getattr(self, "_flat_views", None)
        if cached is None or cached[0] is not self.metrics:
            views = {name: self.metrics.get(name).view(-1) for name in METRICS}
            cached = self._flat_views = (self.metrics, views)
        return cached[1]

    # -- BaseCollector's interface -------------------------------------------------------------

    def shutdown(
        self, timeout: float | None = None, close_env: bool = True, raise_on_error: bool = True
    ) -> None:
        """Close the env (nothing else runs in the background)."""
        if close_env and not self.env.is_closed:
            self.env.close()

    def set_seed(self, seed: int, static_seed: bool = False) -> int:
        """Reseed the env and every policy stream (before the first step)."""
        if self._td is not None:
            raise RuntimeError("set_seed must be called before the first step")
        self.env.set_seed(seed, static_seed=static_seed)
        for module in self.policy.modules():
            if hasattr(module, "stream_keys"):
                module.set_seed(seed)
        return seed

    def state_dict(self) -> OrderedDict:
        """Counters, metrics, policy and loss state (tables, streams) and the observation the
        next step acts on, as plain tensors and containers (``torch.load(weights_only=True)``
        reads them back). The env's world state is not included: it belongs to the env (for
        ``FactoredGridEnv``, save its ``world_state`` alongside to resume mid-episode)."""
        return OrderedDict(
            policy=self.policy.state_dict(),
            loss=self.loss.state_dict(),
            optimizer=self.optimizer.state_dict(),
            metrics=self.metrics.clone().to_dict(),
            run_index=self.run_index.clone(),
            episode_index=self.episode_index.clone(),
            episode_sums={name: value.clone() for name, value in self._episode.items()},
            finished=self.finished.clone(),
            observation=None if self._td is None else self._td.clone().to_dict(),
        )

    def load_state_dict(self, state_dict: OrderedDict) -> None:
        self.policy.load_state_dict(state_dict["policy"])
        self.loss.load_state_dict(state_dict["loss"])
        self.optimizer.load_state_dict(state_dict["optimizer"])
        self.metrics.update_(state_dict["metrics"])
        self.run_index = state_dict["run_index"].clone()
        self.episode_index = state_dict["episode_index"].clone()
        self._episode = {name: value.clone() for name, value in state_dict["episode_sums"].items()}
        self.finished = state_dict["finished"].clone()
        self._finished_count = int(self.finished.sum())
        self._any_finished = self._finished_count > 0
        observation = state_dict.get("observation")
        self._td = (
            None
            if observation is None
            else TensorDict(observation, batch_size=[self.num_experiments], device=self.env.device)
        )

    def __len__(self) -> int:
        # TypeError (not torchrl's RuntimeError) so that list(collector) works.
        raise TypeError("OnlineCollector stops by episodes, not frames: its length is unknown")

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(experiments={self.num_experiments}, runs={self.runs}, "
            f"episodes={self.episodes}, finished={int(self.finished.sum())})"
        )
