"""Env transforms for the FactoredGrid world.

``SplitLocalReward`` turns the conventional reward of ``FactoredGridEnv`` into what Factor-Q
learns from (SPEC section 2): the task reward (step + goal) under ``"reward"`` and the local
reward vector (the collision vector) under ``"local_reward"``. Q-learning and DQN use the env
without it, or with ``SplitLocalReward(keep_reward=True)`` (a DQN with the local-risk layer,
``factorq_torch.risk``): ``"reward"`` stays the conventional reward and ``"local_reward"`` is
added beside it.

**Which reward each part reads** (the trap: a DQN recipe on the default split never sees a
collision, since its ``"reward"`` is then the task reward alone, and its greedy policy keeps
colliding; nothing in torchrl can tell):

- the plain env: ``reward`` = step + goal + collisions, read by Q-learning and DQN;
- ``SplitLocalReward()``: ``reward`` = step + goal, read by ``FactorQLoss`` with ``local_reward``;
- ``SplitLocalReward(keep_reward=True)``: ``reward`` = step + goal + collisions, read by
  ``DQNLoss`` or any recipe; ``local_reward`` read by ``LocalRiskLoss``.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs.transforms import Transform

from factorq_torch.base import keys


class SplitLocalReward(Transform):
    """Split the conventional reward into the task reward and the local reward vector.

    On every step it reads ``("next", reward_key)`` ``[*B, 1]`` (step + goal + sum(collision))
    and ``("next", collision_key)`` ``[*B, 4]`` (written by ``FactoredGridEnv``), then writes

    - ``("next", reward_key)`` ``[*B, 1]``: the task reward step + goal, i.e. the conventional
      reward minus sum(collision) (exact: all terms are small integers);
    - ``("next", local_reward_key)`` ``[*B, 4]`` float32: the collision vector, declared as a
      second reward (so pass reward keys explicitly: ``env.reward_key`` is ambiguous).

    With ``keep_reward=True`` (torchrl recipes, the local-risk layer) ``("next", reward_key)``
    is left as the conventional reward, what a DQN recipe expects, and ``local_reward`` is
    declared as an observation entry, not a second reward: ``env.reward_key`` stays
    ``reward_key`` (torchrl's ``RewardSum`` then sums the conventional reward only).

    Args:
        reward_key: the env's reward, read as the conventional reward and rewritten as the task
            reward.
        collision_key: the collision vector ``[*B, actuators]`` the env writes.
        local_reward_key: where the local reward vector is written.
        keep_reward: leave the conventional reward under ``reward_key`` and declare
            ``local_reward`` as an observation (see above).

    Example:
        >>> import torch
        >>> from torchrl.envs import TransformedEnv
        >>> from factorq_envs.torchrl_env import FactoredGridEnv
        >>> env = TransformedEnv(FactoredGridEnv(size=3, num_obstacles=0), SplitLocalReward())
        >>> td = env.reset()
        >>> td["action"] = torch.tensor(0)  # north: into the wall
        >>> td = env.step(td)
        >>> td["next", "reward"], td["next", "local_reward"]
        (tensor([-1.]), tensor([-1.,  0.,  0.,  0.]))
        >>> kept = TransformedEnv(FactoredGridEnv(size=3, num_obstacles=0),
        ...                       SplitLocalReward(keep_reward=True))
        >>> td = kept.step(kept.reset().set("action", torch.tensor(0)))
        >>> kept.reward_key, td["next", "reward"], td["next", "local_reward"]
        ('reward', tensor([-2.]), tensor([-1.,  0.,  0.,  0.]))
    """

    def __init__(
        self,
        reward_key: str = "reward",
        collision_key: str = "collision",
        local_reward_key: str = "local_reward",
        *,
        keep_reward: bool = False,
    ) -> None:
        if not isinstance(keep_reward, bool):
            raise TypeError(f"keep_reward must be a bool, got {keep_reward!r}")
        out_keys = [local_reward_key] if keep_reward else [reward_key, local_reward_key]
        super().__init__(in_keys=[reward_key, collision_key], out_keys=out_keys)
        self.reward_key = reward_key
        self.collision_key = collision_key
        self.local_reward_key = local_reward_key
        self.keep_reward = keep_reward

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        reward = next_tensordict.get(self.reward_key, None)  # [*B, 1]
        if reward is None:  # a reset carries no reward: nothing to split
            return next_tensordict
        if self.local_reward_key in next_tensordict.keys():
            raise ValueError(
                f"SplitLocalReward: {self.local_reward_key!r} is already there, so the reward "
                f"was already split (by the env's SplitLocalReward); splitting again would "
                f"subtract the collisions twice"
            )
        collision = next_tensordict.get(self.collision_key)  # [*B, 4]
        if not self.keep_reward:
            next_tensordict.set(self.reward_key, reward - collision.sum(dim=-1, keepdim=True))
        # A copy, so that editing one entry in place never changes the other.
        next_tensordict.set(self.local_reward_key, collision.clone())
        return next_tensordict

    def _reset(
        self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase
    ) -> TensorDictBase:
        # kept reward: local_reward is an observation, present from the reset on (the
        # collision vector of a reset: zeros)
        if self.keep_reward:
            collision = tensordict_reset.get(self.collision_key, None)
            if collision is not None:
                tensordict_reset.set(self.local_reward_key, collision.clone())
        return tensordict_reset

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Split transitions offline, e.g. as a replay buffer's transform
        (``ReplayBuffer(..., transform=SplitLocalReward())``, applied to every sample): the
        ``"next"`` entries of a transition of the plain env (or root-level keys) are split.
        Transitions already split (``local_reward`` present) are refused with a ValueError."""
        next_tensordict = tensordict.get("next", None)
        if isinstance(next_tensordict, TensorDictBase):
            if self.reward_key not in next_tensordict.keys():
                raise KeyError(
                    f"SplitLocalReward needs ('next', {self.reward_key!r}) and ('next', "
                    f"{self.collision_key!r}) in the transitions; they have "
                    f"{list(next_tensordict.keys())}"
                )
            self._call(next_tensordict)
            return tensordict
        if self.reward_key not in tensordict.keys():
            raise KeyError(
                f"SplitLocalReward needs {self.reward_key!r} and {self.collision_key!r} (root "
                f"level) or a 'next' entry holding them; the tensordict has "
                f"{list(tensordict.keys())}"
            )
        return self._call(tensordict)

    def transform_output_spec(self, output_spec: Composite) -> Composite:
        """Add ``local_reward`` to the reward specs: float32, unbounded (a sum of local rewards,
        e.g. torchrl's ``RewardSum`` over an episode, goes below -1)."""
        output_spec = output_spec.clone()
        observation_spec = output_spec["full_observation_spec"]
        if self.collision_key not in observation_spec.keys():
            raise KeyError(
                f"SplitLocalReward needs the observation {self.collision_key!r} (the collision "
                f"vector written by FactoredGridEnv); the env has {list(observation_spec.keys())}"
            )
        collision = observation_spec[self.collision_key]
        # kept reward: an observation entry, so that env.reward_key stays the one reward key
        where = "full_observation_spec" if self.keep_reward else "full_reward_spec"
        output_spec[where][self.local_reward_key] = Unbounded(
            shape=collision.shape, dtype=collision.dtype, device=collision.device
        )
        return super().transform_output_spec(output_spec)


class ExperimentIndex(Transform):
    """Write each world's experiment index ``keys.EXPERIMENT`` (``[*B]`` int64, ``0 .. S-1`` in
    the env's flattened batch order), so transitions keep their experiment through a replay
    buffer (``rb.extend(data.reshape(-1))``) and the tables, policies and losses can take any
    minibatch of them.

    Args:
        key: where the index is written (``keys.EXPERIMENT``, ``"experiment"``, which the tables,
            policies and losses read).

    Example:
        >>> from torchrl.envs import TransformedEnv
        >>> from factorq_envs.torchrl_env import FactoredGridEnv
        >>> world = FactoredGridEnv(size=3, num_obstacles=1, batch_size=(2, 2))
        >>> env = TransformedEnv(world, ExperimentIndex())
        >>> env.reset()["experiment"]
        tensor([[0, 1],
                [2, 3]])
    """

    def __init__(self, key: str = keys.EXPERIMENT) -> None:
        super().__init__(in_keys=[], out_keys=[key])
        self.key = key

    def _index(self, tensordict: TensorDictBase) -> torch.Tensor:
        batch = tensordict.batch_size
        return torch.arange(math.prod(batch), device=tensordict.device).reshape(batch)

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        next_tensordict.set(self.key, self._index(next_tensordict))
        return next_tensordict

    def _reset(
        self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase
    ) -> TensorDictBase:
        return self._call(tensordict_reset)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        return self._call(tensordict)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        shape = observation_spec.shape
        observation_spec[self.key] = Categorical(
            max(1, math.prod(shape)), shape=shape, dtype=torch.int64, device=observation_spec.device
        )
        return observation_spec


class RenderPixels(Transform):
    """Write every world's picture as ``pixels`` ``[*B, H, W, 3]`` uint8 on reset and step
    (``FactoredGridEnv.render_rgb``: the gymnasium env's ``rgb_array`` frames), for torchrl's
    ``VideoRecorder`` or any frame consumer. Costs a picture per world per step: for
    evaluation and videos, not for training.

    Args:
        key: where the frames are written.

    Example:
        >>> from torchrl.envs import TransformedEnv
        >>> from factorq_envs.torchrl_env import FactoredGridEnv
        >>> env = TransformedEnv(FactoredGridEnv(size=3, num_obstacles=1), RenderPixels())
        >>> env.reset()["pixels"].shape
        torch.Size([80, 80, 3])
    """

    def __init__(self, key: str = "pixels") -> None:
        super().__init__(in_keys=[], out_keys=[key])
        self.key = key

    def _base(self) -> Any:  # the env with render_rgb (torchrl: untyped)
        env = self.parent
        base = getattr(env, "base_env", env)
        if not hasattr(base, "render_rgb"):
            raise TypeError(
                f"RenderPixels needs an env with render_rgb(index) (FactoredGridEnv), got "
                f"{type(base).__name__}"
            )
        return base

    def _frames(self, tensordict: TensorDictBase) -> torch.Tensor:
        base = self._base()
        frames = [torch.from_numpy(base.render_rgb(i)) for i in range(base.num_worlds)]
        stacked = torch.stack(frames).to(tensordict.device or "cpu")
        return stacked.reshape(*tensordict.batch_size, *stacked.shape[1:])

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        next_tensordict.set(self.key, self._frames(next_tensordict))
        return next_tensordict

    def _reset(
        self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase
    ) -> TensorDictBase:
        return self._call(tensordict_reset)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        base = self._base()
        frame = base.render_rgb(0).shape  # [H, W, 3], whatever the world draws
        observation_spec[self.key] = Bounded(
            low=0,
            high=255,
            shape=(*observation_spec.shape, *frame),
            dtype=torch.uint8,
            device=observation_spec.device,
        )
        return observation_spec
