"""torchrl's DQN + local risk on the dynamic grid, with the layer's explanations in the frames.

Trains torchrl's DQN recipe (``QValueActor``, ``EGreedyModule``, ``DQNLoss``, ``SoftUpdate``,
``Collector``, ``ReplayBuffer``) with the local-risk layer over the oracle ``LocalRewardTable``
(``factorq_torch.risk``), printing one ``RiskSummary`` line per training episode; then records one
greedy episode through ``RenderPixels``, draws an orange mark on the side of every actuator the
layer penalised in each frame (``factorq_envs.render.mark_risk``), prints the layer's line of
text per step (``"north: -1.10, north blocked"``) and writes the frames as an animated GIF.

Run: ``.venv/bin/python examples/risk_video.py [OUT.gif]`` (about a minute on one core).
"""

from __future__ import annotations

import sys
import warnings

import torch
from PIL import Image
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs import Compose, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import MLP, EGreedyModule, QValueActor
from torchrl.objectives import DQNLoss, SoftUpdate

from factorq_envs import FactoredGridEnv, RenderPixels, SplitLocalReward
from factorq_envs.render import mark_risk, risky_faces
from factorq_torch.risk import (
    RISK_MASK,
    LocalRiskLoss,
    RiskSummary,
    find_local_risk,
    with_local_risk,
)
from factorq_torch.tables import LocalRewardTable

with warnings.catch_warnings():
    warnings.filterwarnings("ignore", category=DeprecationWarning)
    from torchrl.collectors import Collector


class Features(torch.nn.Module):
    """The cell one-hot and the sensor bits (what Q-learning's state holds)."""

    def __init__(self, cells: int) -> None:
        super().__init__()
        self.cells = cells

    def forward(self, cell, sensors):
        one_hot = torch.nn.functional.one_hot(cell, self.cells).to(torch.float32)
        return torch.cat([one_hot, sensors.to(torch.float32)], dim=-1)


def record(path: str = "risk.gif", *, size: int = 6, steps: int = 3000, seed: int = 0) -> int:
    """Train, then write a greedy episode with the risk marks to ``path``; returns the frames."""
    torch.manual_seed(seed)
    world = dict(size=size, num_obstacles=6, obstacle_period=1, batch_size=(1,))
    env = TransformedEnv(FactoredGridEnv(**world, seed=seed), SplitLocalReward(keep_reward=True))
    spec = env.action_spec_unbatched
    features = TensorDictModule(Features(size * size), ["cell", "sensors"], ["q_input"])
    network = MLP(in_features=size * size + 4, out_features=4, num_cells=[64, 64])
    head = TensorDictModule(network, ["q_input"], ["action_value"])
    actor = QValueActor(TensorDictSequential(features, head), in_keys=["cell"], spec=spec)
    provider = LocalRewardTable(1, dependency=env.base_env.dependency)
    acting = with_local_risk(actor, provider, env=env)  # the layer: line 1
    local_loss = LocalRiskLoss(provider)  # the layer: line 2
    explore = EGreedyModule(spec, annealing_num_steps=steps // 3, action_mask_key=RISK_MASK)
    loss = DQNLoss(actor, action_space=spec, delay_value=True)
    loss.make_value_estimator(gamma=0.9)
    target, optimizer = SoftUpdate(loss, tau=0.02), torch.optim.Adam(loss.parameters(), lr=1e-3)
    buffer = ReplayBuffer(storage=LazyTensorStorage(10_000), batch_size=64)
    policy = TensorDictSequential(acting, explore)
    collector = Collector(env, policy, frames_per_batch=2, total_frames=steps)
    risk = find_local_risk(acting)  # the layer, found by type
    summary, episode = RiskSummary.for_env(env), 0  # named by the env's actuators
    for batches, data in enumerate(collector):
        data = data.reshape(-1)
        local_loss(data)  # eq. 5 on each transition once
        buffer.extend(data)
        explore.step(data.shape[0])
        for t in range(data.shape[0]):
            summary.update(data[t : t + 1])
            if bool(data[t]["next", "done"].any()):
                episode += 1
                if episode % 25 == 0:
                    print(f"episode {episode}: {RiskSummary.line(summary.episode())}")
                else:
                    summary.episode()
        if batches * 2 >= 200:  # learning starts
            value = loss(buffer.sample())["loss"]
            optimizer.zero_grad()
            value.backward()
            optimizer.step()
            target.step()
    collector.shutdown()
    viewer = TransformedEnv(
        FactoredGridEnv(**world, seed=seed + 1),
        Compose(SplitLocalReward(keep_reward=True), RenderPixels()),
    )
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        rollout = viewer.rollout(4 * size * size, acting)[0]  # [T]: stops at the goal
    body = viewer.base_env.config.body_spec
    frames = [rollout[0]["pixels"], *rollout["next", "pixels"][:-1]]  # the state acted in
    images = []
    for t, (frame, text) in enumerate(zip(frames, risk.explain_text(rollout), strict=True)):
        penalties = rollout[t]["risk_normaliser"] * rollout[t]["local_value"]  # [A]
        image = mark_risk(
            frame.numpy().copy(), int(rollout[t]["cell"]), size, risky_faces(penalties, 0, body)
        )
        print(f"step {t}: {text or '-'}")
        images.append(Image.fromarray(image).resize((image.shape[1] * 2,) * 2))
    images[0].save(path, save_all=True, append_images=images[1:], duration=300, loop=0)
    return len(images)


if __name__ == "__main__":
    out = sys.argv[1] if len(sys.argv) > 1 else "risk.gif"
    print(f"wrote {record(out)} frames to {out}")
