"""Tabular Factor-Q trained off-policy from a torchrl ``ReplayBuffer`` filled by torchrl's
``Collector``: the ordinary torchrl loop (collect a batch, extend the buffer, sample minibatches,
step the loss), with ``S`` independent experiments in one env.

Every transition carries its experiment index (``ExperimentIndex``), so a minibatch mixes the
experiments freely; a minibatch update moves each table entry by ``alpha`` times the mean TD error
of its transitions (``factorq_torch.objectives``). Evaluation is the greedy policy under torchrl's
``set_exploration_type(ExplorationType.DETERMINISTIC)``.

Run: ``.venv/bin/python examples/offpolicy_replay.py`` (about 10 s on one core); it prints, per
collected batch, the mean steps of the episodes that ended in it and the collisions per step.
"""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictSequential
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs import Compose, InitTracker, RewardSum, StepCounter, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

from factorq_envs import ExperimentIndex, FactoredGridEnv, SplitLocalReward
from factorq_torch.objectives import FactorQLoss, tabular_optimizer
from factorq_torch.policy import FactorQPolicy
from factorq_torch.tables import LocalRewardTable, TaskQTable


def train(
    *,
    experiments: int = 4,
    size: int = 5,
    batches: int = 20,
    frames_per_experiment: int = 100,
    updates_per_batch: int = 20,
    minibatch: int = 64,
    epsilon: float = 0.1,
    seed: int = 0,
) -> dict[str, list[float]]:
    """Train and return, per collected batch, ``steps`` (mean steps of the episodes that ended in
    it, NaN if none) and ``collisions`` (collisions per step), plus ``greedy_steps``: the
    greedy policy's episode lengths after training (one per experiment)."""
    torch.manual_seed(seed)  # the replay buffer samples from torch's global stream
    S = experiments
    transforms = Compose(
        SplitLocalReward(),  # "reward": task reward, "local_reward": the collision vector
        ExperimentIndex(),  # "experiment": which experiment (table) a transition belongs to
        StepCounter(),
        InitTracker(),
        RewardSum(in_keys=["reward", "local_reward"]),
    )
    world = dict(size=size, num_obstacles=3, max_steps=200)
    env = TransformedEnv(FactoredGridEnv(**world, batch_size=(S,), seed=seed), transforms)
    task, local = TaskQTable(S, num_cells=size * size), LocalRewardTable(S)
    actor = TensorDictSequential(task, local, FactorQPolicy(S, seed=seed, epsilon=epsilon))
    loss = FactorQLoss(task, local)
    optimizer = tabular_optimizer(loss)
    collector = Collector(
        env,
        actor,
        frames_per_batch=S * frames_per_experiment,
        total_frames=S * frames_per_experiment * batches,
    )
    buffer = ReplayBuffer(storage=LazyTensorStorage(20_000), batch_size=minibatch)
    history: dict[str, list[float]] = {"steps": [], "collisions": []}
    for data in collector:  # [S, T]
        done = data["next", "done"].squeeze(-1)
        ended = data["next", "step_count"].squeeze(-1)[done].float()
        history["steps"].append(float(ended.mean()) if ended.numel() else float("nan"))
        history["collisions"].append(float(data["next", "bump"].any(-1).float().mean()))
        buffer.extend(data.reshape(-1))  # the experiment index travels with each transition
        for _ in range(updates_per_batch):
            losses = loss(buffer.sample())  # eq. 4 as a loss; eq. 5 applied inside (training)
            losses["loss_task"].backward()
            optimizer.step()
            optimizer.zero_grad()
    collector.shutdown()
    # Evaluation: greedy on C(s), ties still broken at random; "exploratory" is all False.
    eval_env = TransformedEnv(
        FactoredGridEnv(**world, batch_size=(S,), seed=seed + 1),
        Compose(SplitLocalReward(), StepCounter()),
    )
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        rollout = eval_env.rollout(200, actor, break_when_any_done=False)
    assert not rollout["exploratory"].any()
    done = rollout["next", "done"].squeeze(-1)  # [S, T]
    first = done.float().argmax(dim=-1)  # the first episode's end
    history["greedy_steps"] = [
        float(rollout["next", "step_count"][i, first[i]]) if done[i].any() else float("nan")
        for i in range(S)
    ]
    return history


if __name__ == "__main__":
    # One torch thread: the tensors here are a few hundred numbers, and on a busy 2-core machine
    # torch's default threads made this script 3-8x slower (issue 28: 18.7-47.5 s against
    # 6.1-6.5 s with one; docs: how-to "Speed and threads").
    torch.set_num_threads(1)
    result = train()
    for index, (steps, collisions) in enumerate(
        zip(result["steps"], result["collisions"], strict=True)
    ):
        print(
            f"batch {index:2d}: steps per episode {steps:6.1f}, collisions per step "
            f"{collisions:.3f}"
        )
    print("greedy episode lengths after training:", result["greedy_steps"])
