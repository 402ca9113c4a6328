"""Env transforms for the FactoredGrid world.

``SplitLocalReward`` turns the conventional reward of ``FactoredGridEnv`` into what Factor-Q
learns from (SPEC section 2): the task reward (step + goal) under ``"reward"`` and the local
reward vector (the collision vector) under ``"local_reward"``. Q-learning and DQN use the env
without it.
"""

from __future__ import annotations

from tensordict import TensorDictBase
from torchrl.data import Composite
from torchrl.envs.transforms import Transform


class SplitLocalReward(Transform):
    """Split the conventional reward into the task reward and the local reward vector.

    On every step it reads ``("next", reward_key)`` ``[*B, 1]`` (step + goal + sum(collision))
    and ``("next", collision_key)`` ``[*B, 4]`` (written by ``FactoredGridEnv``), then writes

    - ``("next", reward_key)`` ``[*B, 1]``: the task reward step + goal, i.e. the conventional
      reward minus sum(collision) (exact: all terms are small integers);
    - ``("next", local_reward_key)`` ``[*B, 4]`` float32: the collision vector, declared as a
      second reward (so pass reward keys explicitly: ``env.reward_key`` is ambiguous).

    Example:
        >>> import torch
        >>> from torchrl.envs import TransformedEnv
        >>> from envs.grid import FactoredGridEnv
        >>> env = TransformedEnv(FactoredGridEnv(size=3, num_obstacles=0), SplitLocalReward())
        >>> td = env.reset()
        >>> td["action"] = torch.tensor(0)  # north: into the wall
        >>> td = env.step(td)
        >>> td["next", "reward"], td["next", "local_reward"]
        (tensor([-1.]), tensor([-1.,  0.,  0.,  0.]))
    """

    def __init__(
        self,
        reward_key: str = "reward",
        collision_key: str = "collision",
        local_reward_key: str = "local_reward",
    ) -> None:
        super().__init__(
            in_keys=[reward_key, collision_key], out_keys=[reward_key, local_reward_key]
        )
        self.reward_key = reward_key
        self.collision_key = collision_key
        self.local_reward_key = local_reward_key

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        reward = next_tensordict.get(self.reward_key, None)  # [*B, 1]
        if reward is None:  # a reset carries no reward: nothing to split
            return next_tensordict
        collision = next_tensordict.get(self.collision_key)  # [*B, 4]
        next_tensordict.set(self.reward_key, reward - collision.sum(dim=-1, keepdim=True))
        # A copy, so that editing one entry in place never changes the other.
        next_tensordict.set(self.local_reward_key, collision.clone())
        return next_tensordict

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Split a TensorDict offline (e.g. in a replay buffer) holding the root-level keys."""
        return self._call(tensordict)

    def transform_output_spec(self, output_spec: Composite) -> Composite:
        """Add ``local_reward`` to the reward specs, with the collision entry's spec."""
        output_spec = output_spec.clone()
        observation_spec = output_spec["full_observation_spec"]
        if self.collision_key not in observation_spec.keys():
            raise KeyError(
                f"SplitLocalReward needs the observation {self.collision_key!r} (the collision "
                f"vector written by FactoredGridEnv); the env has {list(observation_spec.keys())}"
            )
        output_spec["full_reward_spec"][self.local_reward_key] = observation_spec[
            self.collision_key
        ].clone()
        return super().transform_output_spec(output_spec)
