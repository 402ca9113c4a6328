"""A short clip of a learned Factor-Q agent: train online (``OnlineCollector``), then record one
greedy episode (torchrl's ``set_exploration_type(DETERMINISTIC)``) through ``RenderPixels`` and
write it as an animated GIF with Pillow (installed with matplotlib; no video codec needed).

Run: ``.venv/bin/python examples/video.py [OUT.gif]`` (a few seconds). The frames are the
gymnasium env's ``rgb_array`` pictures: walls grey, obstacles black, the goal green, the agent
blue, the face that bumped on the last step red. For an MP4 instead, gymnasium's
``RecordVideo`` (with ``moviepy``: the ``video`` extra, ``pip install 'factorq-torch[video]'``)
or torchrl's ``VideoRecorder`` take the same frames.
"""

from __future__ import annotations

import sys

import torch
from PIL import Image
from tensordict.nn import TensorDictSequential
from torchrl.envs import Compose, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

from factorq_envs import FactoredGridEnv, RenderPixels, SplitLocalReward
from factorq_torch.collectors import OnlineCollector
from factorq_torch.objectives import FactorQLoss
from factorq_torch.policy import FactorQPolicy
from factorq_torch.tables import LocalRewardTable, TaskQTable


def record(
    path: str = "factorq.gif",
    *,
    size: int = 6,
    num_obstacles: int = 5,
    obstacle_period: int = 0,
    episodes: int = 200,
    max_frames: int = 60,
    seed: int = 0,
) -> int:
    """Train one agent for ``episodes`` episodes, write a greedy episode to ``path``; return the
    number of frames written."""
    world = dict(size=size, num_obstacles=num_obstacles, obstacle_period=obstacle_period)
    env = TransformedEnv(FactoredGridEnv(**world, batch_size=(1,), seed=seed), SplitLocalReward())
    task, local = TaskQTable(1, num_cells=size * size), LocalRewardTable(1)
    actor = TensorDictSequential(task, local, FactorQPolicy(1, seed=seed))
    OnlineCollector(env, actor, FactorQLoss(task, local), runs=1, episodes=episodes).run()
    viewer = TransformedEnv(
        FactoredGridEnv(**world, batch_size=(1,), seed=seed + 1),
        Compose(SplitLocalReward(), RenderPixels()),
    )
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        rollout = viewer.rollout(max_frames, actor)  # stops at the goal
    frames = [rollout[0, 0]["pixels"], *rollout["next", "pixels"][0]]  # [H, W, 3] uint8 each
    images = [Image.fromarray(frame.numpy()).resize((frame.shape[1] * 2,) * 2) for frame in frames]
    images[0].save(path, save_all=True, append_images=images[1:], duration=250, loop=0)
    return len(images)


if __name__ == "__main__":
    torch.set_num_threads(1)  # small tensors: one thread is fastest (docs: "Speed and threads")
    out = sys.argv[1] if len(sys.argv) > 1 else "factorq.gif"
    print(f"wrote {record(out)} frames to {out}")
