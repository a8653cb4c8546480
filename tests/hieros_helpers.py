"""Shared tiny configurations and small environments for the HIEROS algorithm tests (not a test module)."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from benchmarks._equivalence_cases import TINY_NETWORKS

#: Tiny world model shared by the world-model and subactor tests (two S5 layers, widths of 16).
TINY_WORLD_MODEL: dict[str, Any] = dict(
    s5_layers=2,
    s5_model_dim=16,
    s5_state_dim=8,
    s5_hippo_blocks=2,
    dropout=0.0,
    deter_dim=16,
    stoch_groups=4,
    stoch_classes=4,
    hidden=16,
    cnn_depth=2,
    mlp_units=16,
    mlp_layers=1,
    head_units=16,
    head_layers=1,
)

#: Tiny networks: every code path of the small preset, a fraction of the cost.
TINY_OVERRIDES: dict[str, Any] = TINY_NETWORKS


#: HierosConfig fields that :func:`tiny_kwargs` takes as keywords and puts into ``config_overrides``
CONFIG_KEYWORDS = ("batch_length", "imag_horizon", "n_levels", "subgoal_interval", "train_ratio", "etbs_temperature")


def tiny_kwargs(**changes: Any) -> dict[str, Any]:
    """Constructor keywords of a tiny HIEROS (0.25 level-0 updates per env step after 20 random steps).

    ``config_overrides`` replaces :data:`TINY_OVERRIDES`; the fields of :data:`CONFIG_KEYWORDS` given as keywords
    (default: the tiny run's batch_length 8, imag_horizon 3, n_levels 2, subgoal_interval 2, train_ratio 4) are put
    into it and win over it, None leaves the field to ``config_overrides`` and the preset.

    :param changes: keywords to replace or add
    :return: keywords for ``HIEROS(policy, env, **kwargs)``
    """
    fields: dict[str, Any] = dict(batch_length=8, imag_horizon=3, n_levels=2, subgoal_interval=2, train_ratio=4.0)
    fields.update({name: changes.pop(name) for name in CONFIG_KEYWORDS if name in changes})
    overrides = dict(changes.pop("config_overrides", TINY_OVERRIDES))
    overrides.update({name: value for name, value in fields.items() if value is not None})
    kwargs: dict[str, Any] = dict(
        preset="small",
        config_overrides=overrides,
        batch_size=2,
        learning_starts=20,
        buffer_size=500,
        seed=0,
    )
    kwargs.update(changes)
    return kwargs


class CountingEnv(gym.Env):
    """Scripted episodes for the replay bookkeeping tests.

    The observation is ``[step in episode, episode index]``; every step pays reward 1, the step that ends the episode
    pays ``final_reward``. The episode terminates after ``length`` steps (or never, with ``length=None``; wrap it in
    ``TimeLimit`` to truncate).

    :param length: steps per episode, or None
    :param final_reward: reward of the terminal step
    :param action_space: action space (``Discrete(2)`` by default)
    """

    def __init__(self, length: int | None = 5, final_reward: float = 10.0, action_space: spaces.Space | None = None):
        self.length = length
        self.final_reward = final_reward
        self.observation_space = spaces.Box(-1e6, 1e6, (2,), np.float32)
        self.action_space = action_space if action_space is not None else spaces.Discrete(2)
        self.t = 0
        self.episode = -1

    def _obs(self) -> np.ndarray:
        return np.array([self.t, self.episode], dtype=np.float32)

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        self.t = 0
        self.episode += 1
        return self._obs(), {}

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        self.t += 1
        terminated = self.length is not None and self.t >= self.length
        reward = self.final_reward if terminated else 1.0
        return self._obs(), reward, terminated, False, {}


class SmallDictEnv(gym.Env):
    """Dict observations (a 16x16x1 uint8 image, channel-last, and a float vector), 12-step episodes.

    :param discrete: Discrete(3) actions, else Box(-2, 2, (2,))
    """

    def __init__(self, discrete: bool = True):
        self.observation_space = spaces.Dict(
            {
                "img": spaces.Box(0, 255, (16, 16, 1), np.uint8),
                "vec": spaces.Box(-1.0, 1.0, (3,), np.float32),
            }
        )
        self.action_space = spaces.Discrete(3) if discrete else spaces.Box(-2.0, 2.0, (2,), np.float32)
        self.t = 0

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        super().reset(seed=seed)
        self.t = 0
        return self.observation_space.sample(), {}

    def step(self, action: Any) -> tuple[dict, float, bool, bool, dict]:
        self.t += 1
        return self.observation_space.sample(), float(self.t % 3 == 0), self.t >= 12, False, {}
