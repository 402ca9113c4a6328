"""The local-risk layer for Stable-Baselines3's DQN (the ``sb3`` extra: ``pip install
'factorq-torch[sb3]'``).

SB3's DQN takes its greedy action from its policy's ``_predict`` and its exploratory one from
``DQN.predict`` (``action_space.sample()``, and a uniform warm-up before ``learning_starts``).
So the layer comes in three parts that SB3 supports as such:

- ``LocalRiskPolicy``: SB3's ``MultiInputPolicy`` whose greedy action maximises ``C(s) = Q(s) +
  G rho(o)`` (eqs. 2-3 through ``factorq_torch.risk.LocalRisk``) instead of ``Q(s)``; its
  ``q_net`` and target network, their optimiser and SB3's TD loss are SB3's own, unchanged;
- ``LocalRiskCallback``: trains the provider after every env step from the sensors before
  acting, the action and ``info["local_reward"]`` (the gymnasium FactoredGrid env writes it;
  ``LocalRiskLoss`` does the work, eq. 5 for tables and ``StructureLearner``);
- ``LocalRiskDQN``: SB3's ``DQN`` with both, whose random actions (epsilon and warm-up) are
  drawn among the actions the layer does not call risky (as torchrl's ``EGreedyModule`` with
  ``action_mask_key="risk_mask"``).

Example (``FactoredGrid-v0``, registered by ``import factorq_envs``)::

    env = gymnasium.make("FactoredGrid-v0", size=5, num_obstacles=3, obstacle_period=1)
    provider = LocalRewardTable(1, dependency=env.unwrapped.config.dependency)
    model = LocalRiskDQN("MultiInputPolicy", env, provider=provider, learning_starts=100)
    model.learn(2_000)

The observation must be a ``Dict`` holding ``sensors`` (``MultiBinary(K)``); the reward SB3
reads is the env's own (the conventional reward, collisions included). Without the extra the
module still imports; building any of its classes raises an ImportError naming the extra.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Self

import gymnasium
import numpy as np
import torch
from tensordict import TensorDict

from factorq_torch.base import keys as names
from factorq_torch.risk import RISK_MASK, LocalRisk, LocalRiskLoss

if TYPE_CHECKING:
    from stable_baselines3.common.noise import ActionNoise
    from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, PyTorchObs
    from stable_baselines3.dqn.policies import DQNPolicy
    from tensordict.nn import TensorDictModuleBase

try:
    from stable_baselines3 import DQN
    from stable_baselines3.common.callbacks import BaseCallback, CallbackList, ConvertCallback
    from stable_baselines3.dqn.policies import MultiInputPolicy

    _MISSING: ImportError | None = None
except ImportError as error:  # the optional extra: the module imports (docs, doctest
    # collection), its classes refuse to be built
    _MISSING = error
    if not TYPE_CHECKING:  # mypy checks against SB3's own types
        DQN = BaseCallback = CallbackList = ConvertCallback = MultiInputPolicy = object


def _require() -> None:
    """A clear error naming the extra when Stable-Baselines3 is not installed."""
    if _MISSING is not None:
        raise ImportError(
            "factorq_torch.integrations.sb3 needs Stable-Baselines3: pip install "
            "'factorq-torch[sb3]' (stable-baselines3==2.9.2)"
        ) from _MISSING


class LocalRiskPolicy(MultiInputPolicy):
    """SB3's ``MultiInputPolicy`` acting greedily on ``C(s) = Q(s) + G rho(o)`` (eqs. 2-3).

    Extra keyword arguments (``policy_kwargs``): ``provider`` (a local value provider with
    ``S = 1``: one agent), ``sensors_key`` (the observation entry holding the sensor bits,
    default ``"sensors"``) and ``risk_options`` (given to ``LocalRisk``: ``eta``, ``g_min``,
    ``mask_threshold``, names).
    """

    def __init__(
        self,
        *args: Any,
        provider: TensorDictModuleBase | None = None,
        sensors_key: str = names.SENSORS,
        risk_options: dict[str, Any] | None = None,
        **kwargs: Any,
    ) -> None:
        _require()
        super().__init__(*args, **kwargs)
        if provider is None:
            raise ValueError("LocalRiskPolicy needs policy_kwargs={'provider': ...}")
        space, action_space = self.observation_space, self.action_space
        if not isinstance(space, gymnasium.spaces.Dict):
            raise TypeError(f"LocalRiskPolicy needs a Dict observation space, got {space}")
        if not isinstance(action_space, gymnasium.spaces.Discrete):
            raise TypeError(f"LocalRiskPolicy needs a Discrete action space, got {action_space}")
        if sensors_key not in space.spaces:
            raise ValueError(
                f"LocalRiskPolicy reads the sensors from the observation entry {sensors_key!r}; "
                f"the observation space has {list(space.spaces)}"
            )
        shape = space.spaces[sensors_key].shape
        if not shape:
            raise ValueError(
                f"the observation entry {sensors_key!r} must hold an array of sensor bits, got "
                f"{space.spaces[sensors_key]}"
            )
        sensors = shape[-1]
        actions = int(action_space.n)
        self.risk = LocalRisk(provider, num_actions=actions, **(risk_options or {}))
        declared = self.risk.num_sensors
        if declared is not None and declared != sensors:
            raise ValueError(
                f"the observation {sensors_key!r} has {sensors} sensors but the local value "
                f"provider {type(provider).__name__} has {declared}"
            )
        if self.risk.num_experiments != 1:
            raise ValueError(
                f"the local value provider holds S={self.risk.num_experiments} experiments: an "
                f"SB3 model is one agent, give it a provider of S=1"
            )
        self.sensors_key = sensors_key

    def risk_values(self, obs: dict[str, torch.Tensor]) -> TensorDict:
        """The layer's output for a batch of observations (dict of tensors ``[n, ...]``):
        ``action_value`` (``C(s)``), ``task_value``, ``local_value``, ``risk_mask``."""
        with torch.no_grad():
            q = self.q_net(obs)  # [n, A]
            sensors = obs[self.sensors_key].to(torch.bool)
            td = TensorDict({names.ACTION_VALUE: q, names.SENSORS: sensors}, batch_size=q.shape[:1])
            return self.risk(td)

    def _predict(self, obs: PyTorchObs, deterministic: bool = True) -> torch.Tensor:
        assert isinstance(obs, dict)  # __init__ checked the Dict observation space
        return self.risk_values(obs).get(names.ACTION_VALUE).argmax(dim=-1)


class LocalRiskCallback(BaseCallback):
    """Trains the policy's provider from every env step (``info["local_reward"]``)."""

    def __init__(self, verbose: int = 0) -> None:
        _require()
        super().__init__(verbose)
        self.loss: LocalRiskLoss | None = None

    def _init_callback(self) -> None:
        policy = self.model.policy
        if not isinstance(policy, LocalRiskPolicy):
            raise TypeError(f"LocalRiskCallback needs a LocalRiskPolicy, got {type(policy)}")
        self.loss = LocalRiskLoss(policy.risk.provider)
        self.optimizer = None
        parameters = [p for p in policy.risk.provider.parameters() if p.requires_grad]
        if parameters:  # a network provider: its own Adam on loss_local
            self.optimizer = torch.optim.Adam(parameters, lr=1e-2)

    def _on_step(self) -> bool:
        sensors = getattr(self.model, "_risk_sensors", None)
        infos = self.locals.get("infos")
        actions = self.locals.get("actions")
        if sensors is None or infos is None or actions is None:
            return True
        assert self.loss is not None  # SB3 calls _init_callback before the first step
        if any("local_reward" not in info for info in infos):
            raise KeyError(
                "LocalRiskCallback reads info['local_reward'] (the collision vector) from every "
                "step; the env's info has " + str(sorted(infos[0]))
            )
        local_reward = torch.as_tensor(np.stack([info["local_reward"] for info in infos]))
        td = TensorDict(
            {
                names.SENSORS: sensors,
                names.ACTION: torch.as_tensor(np.asarray(actions)).reshape(-1).to(torch.int64),
                ("next", names.LOCAL_REWARD): local_reward.to(torch.float32),
            },
            batch_size=[len(infos)],
        )
        loss = self.loss(td)["loss_local"]
        if self.optimizer is not None:
            self.optimizer.zero_grad()
            loss.backward()
            self.optimizer.step()
        return True


class LocalRiskDQN(DQN):
    """SB3's ``DQN`` with the local-risk layer (module docstring): ``provider`` is required,
    ``policy`` defaults to ``LocalRiskPolicy`` (``"MultiInputPolicy"`` is taken as it), and
    ``learn`` adds ``LocalRiskCallback`` to the given callbacks."""

    policy: LocalRiskPolicy  # what __init__ makes it (DQN's is any DQNPolicy)

    def __init__(
        self,
        policy: str | type[DQNPolicy] = "MultiInputPolicy",
        env: GymEnv | str | None = None,
        *,
        provider: TensorDictModuleBase | None = None,
        **kwargs: Any,
    ) -> None:
        _require()
        # DQN.load builds the model with _init_setup_model=False, then restores the saved
        # policy_kwargs (the provider included) and the policy's state
        loading = kwargs.get("_init_setup_model", True) is False
        if provider is None and not loading:
            raise ValueError("LocalRiskDQN needs provider= (a local value provider of S=1)")
        if policy in ("MultiInputPolicy", MultiInputPolicy):
            policy = LocalRiskPolicy
        if not (isinstance(policy, type) and issubclass(policy, LocalRiskPolicy)):
            raise TypeError(f"LocalRiskDQN needs a LocalRiskPolicy, got {policy!r}")
        policy_kwargs = dict(kwargs.pop("policy_kwargs", None) or {})
        if provider is not None:
            policy_kwargs["provider"] = provider
        # env=None is how DQN.load builds the model, as SB3 does itself; its annotation omits it
        super().__init__(policy, env, policy_kwargs=policy_kwargs, **kwargs)  # type: ignore[arg-type]

    def _risk_step(
        self, observation: np.ndarray | dict[str, np.ndarray], exploration_rate: float
    ) -> np.ndarray:
        """Epsilon-greedy on ``C(s)``, the random actions among the allowed ones."""
        obs, vectorized = self.policy.obs_to_tensor(observation)
        assert isinstance(obs, dict)  # LocalRiskPolicy checked its Dict observation space
        out = self.policy.risk_values(obs)
        greedy = out.get(names.ACTION_VALUE).argmax(dim=-1)
        allowed = out.get(RISK_MASK)  # [n, A]
        random = torch.multinomial(allowed.to(torch.float32), 1).squeeze(-1)
        explore = torch.rand(greedy.shape) < exploration_rate
        self._risk_sensors = obs[self.policy.sensors_key].to(torch.bool).cpu()
        action = torch.where(explore, random, greedy).cpu().numpy()
        return action if vectorized else action[0]

    def predict(
        self,
        observation: np.ndarray | dict[str, np.ndarray],
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = False,
    ) -> tuple[np.ndarray, tuple[np.ndarray, ...] | None]:
        rate = 0.0 if deterministic else self.exploration_rate
        return self._risk_step(observation, rate), state

    def _sample_action(
        self, learning_starts: int, action_noise: ActionNoise | None = None, n_envs: int = 1
    ) -> tuple[np.ndarray, np.ndarray]:
        # SB3's warm-up (uniform before learning_starts) and epsilon branch, both masked
        warm = self.num_timesteps < learning_starts
        assert self._last_obs is not None  # learn() reset the env before the first step
        action = self._risk_step(self._last_obs, 1.0 if warm else self.exploration_rate)
        return action, action

    def learn(
        self,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "DQN",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> Self:
        """SB3's ``DQN.learn`` with ``LocalRiskCallback`` first among the callbacks (SB3's
        forms: one callback, a list, or a function ``(locals, globals) -> bool``)."""
        given = [] if callback is None else callback if isinstance(callback, list) else [callback]
        callbacks: list[BaseCallback] = [LocalRiskCallback()]
        for item in given:
            callbacks.append(item if isinstance(item, BaseCallback) else ConvertCallback(item))
        return super().learn(
            total_timesteps,
            callback=CallbackList(callbacks),
            log_interval=log_interval,
            tb_log_name=tb_log_name,
            reset_num_timesteps=reset_num_timesteps,
            progress_bar=progress_bar,
        )
