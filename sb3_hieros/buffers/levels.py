"""The replays of a HIEROS hierarchy: one sequence replay per level with a world model (thesis 4.6.1).

Level 0's buffer is the algorithm's ``replay_buffer``; the buffers of levels 1..L-1 live in its ``higher_levels``
attribute, so ``save_replay_buffer`` / ``load_replay_buffer`` carry them. Level i holds ``buffer_size // k**i`` steps
(:func:`make_level_buffers`). Level 0 receives SB3's transitions plus the subgoal in force
(:class:`SubgoalTransitions`).

A row of level i >= 1 (Dreamer view) is ``(o^i_t, a^i_{t-1}, r^i_t, is_first, is_terminal, g^{i+1}_t)`` with
``o^i_t`` the window of world states of level i-1 the level observed, ``a^i_{t-1}`` the subgoal it held before (stored
as indices), ``r^i_t`` the **sum** of the environment rewards since its previous row (thesis 4.3.2: "the summed
observed reward of the k^i environment steps") and ``g^{i+1}_t`` the subgoal code in force from level i+1. Rows are
written (:class:`HigherLevelRows`)

* at every update of level i (``t % k**i == 0`` for all envs, in lock-step, and for env j at its episode start); an
  episode-start row has ``is_first`` and a window with every slot from before the reset zeroed;
* at an episode end of env j: the terminal observation is encoded bottom-up and every level i >= 1 writes a row for
  env j whose window ends with the terminal world state of level i-1, whose reward includes the final reward, and
  whose ``is_terminal`` is ``terminated`` (a time-limit truncation is not terminal). The next row of env j is the
  ``is_first`` row of its next episode.

So the final reward is kept, ``is_first`` and ``is_terminal`` reach every level, one env's episode end never touches
another env's reward sums, a window never straddles an episode border, and a new episode gets fresh subgoals at once.
An episode start costs env j one extra (shorter) window at each level, so rows are written per env with the buffers'
per-stream write heads (``SequenceReplayBuffer.add_step(..., envs=...)``). The summed rewards are those the agent sees
(normalised under ``VecNormalize``), so the higher levels' replays are sampled without normalisation, while level 0's
stores raw rewards and normalises when sampling.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces

from sb3_hieros.buffers.sequence import SequenceReplayBuffer, warn_if_replay_exceeds_memory
from sb3_hieros.buffers.time_balanced import ETBSReplayBuffer
from sb3_hieros.config import HierosConfig
from sb3_hieros.type_aliases import LevelRows

__all__ = ["HigherLevelRows", "SubgoalTransitions", "level_buffer_size", "make_level_buffers"]


def level_buffer_size(config: HierosConfig, buffer_size: int, level: int, n_envs: int) -> int:
    """Capacity of level ``level``'s replay: ``buffer_size // k**level``, at least one chunk per env stream above 0.

    :param config: the configuration (``subgoal_interval``, ``batch_length``)
    :param buffer_size: level 0's capacity
    :param level: the level
    :param n_envs: number of env streams
    :return: capacity in steps over all streams
    """
    size = buffer_size // config.subgoal_interval**level
    return size if level == 0 else max(size, config.batch_length * n_envs)


def make_level_buffers(
    config: HierosConfig,
    level_spaces: Sequence[tuple[spaces.Space, spaces.Space]],
    context_dims: Sequence[int],
    buffer_size: int,
    n_envs: int,
    device: th.device | str,
    buffer_class: type[SequenceReplayBuffer] | None = None,
    buffer_kwargs: dict[str, Any] | None = None,
) -> SequenceReplayBuffer:
    """Level 0's buffer with the buffers of levels 1..L-1 in its ``higher_levels`` attribute.

    One memory warning for all levels together comes before anything is allocated.

    :param config: the configuration (``batch_length``, ``replay``, ``etbs_temperature``, subgoal sizes)
    :param level_spaces: per level with a replay, its (observation space, action space)
    :param context_dims: per level with a replay, the floats of replay context per row (0: none)
    :param buffer_size: level 0's capacity in steps
    :param n_envs: number of env streams
    :param device: device of the sampled tensors
    :param buffer_class: level 0's class, a :class:`SequenceReplayBuffer` subclass; None for :class:`ETBSReplayBuffer`
    :param buffer_kwargs: extra keywords of level 0's buffer
    :return: level 0's buffer
    """
    buffer_class = buffer_class or ETBSReplayBuffer
    if not (isinstance(buffer_class, type) and issubclass(buffer_class, SequenceReplayBuffer)):
        raise ValueError(
            f"replay_buffer_class must be a subclass of sb3_hieros.buffers.SequenceReplayBuffer, got {buffer_class}"
        )
    n_replays = len(level_spaces)
    subgoal_shape = (config.subgoal.n_cat * config.subgoal.n_classes,)
    shapes = [subgoal_shape if i < config.n_levels - 1 else None for i in range(n_replays)]
    sizes = [level_buffer_size(config, buffer_size, i, n_envs) for i in range(n_replays)]
    etbs = {"temperature": config.etbs_temperature, "mode": config.replay}
    kwargs: dict[str, Any] = {"batch_length": config.batch_length, "subgoal_shape": shapes[0]}
    if issubclass(buffer_class, ETBSReplayBuffer):
        kwargs.update(etbs)
    kwargs.update(buffer_kwargs or {})
    estimates = [
        SequenceReplayBuffer.estimate_nbytes(sizes[i], obs, act, n_envs, shapes[i], context_dims[i])
        for i, (obs, act) in enumerate(level_spaces)
    ]
    warned = warn_if_replay_exceeds_memory(estimates, [f"level {i}" for i in range(n_replays)])
    with warnings.catch_warnings():
        if warned:
            warnings.filterwarnings("ignore", message="The replay buffer needs about")
        buffer = buffer_class(
            sizes[0],
            *level_spaces[0],
            device=device,
            n_envs=n_envs,
            optimize_memory_usage=False,
            **({"context_dim": context_dims[0]} if context_dims[0] else {}),  # custom buffer classes may not know it
            **kwargs,
        )
        buffer.higher_levels = [  # type: ignore[attr-defined]
            ETBSReplayBuffer(
                sizes[i],
                *level_spaces[i],
                device=device,
                n_envs=n_envs,
                batch_length=config.batch_length,
                subgoal_shape=shapes[i],
                context_dim=context_dims[i],
                **etbs,
            )
            for i in range(1, n_replays)
        ]
    return buffer


class SubgoalTransitions:
    """Level 0's buffer as ``OffPolicyAlgorithm._store_transition`` sees it: ``add`` also stores the subgoal in force,
    and with ``zero_terminal_reward`` the reward of a step that ends an episode as 0 (reference-compat switch
    ``reference.terminal_reward="zeroed"``).

    :param buffer: level 0's buffer
    :param subgoal: (n_envs, S) the subgoal in force at the transition's first observation, or None
    :param zero_terminal_reward: store the final reward of an episode as 0
    """

    def __init__(
        self, buffer: SequenceReplayBuffer, subgoal: np.ndarray | None, zero_terminal_reward: bool = False
    ) -> None:
        self.buffer = buffer
        self.subgoal = subgoal
        self.zero_terminal_reward = zero_terminal_reward

    def add(self, obs: Any, next_obs: Any, action: Any, reward: Any, done: Any, *args: Any, **kwargs: Any) -> None:
        """:meth:`SequenceReplayBuffer.add` with the subgoal (and the zeroed final reward)."""
        if self.zero_terminal_reward:
            reward = np.where(np.asarray(done, dtype=bool).reshape(-1), 0.0, np.asarray(reward).reshape(-1))
        if self.subgoal is not None:
            kwargs["subgoal"] = self.subgoal
        self.buffer.add(obs, next_obs, action, reward, done, *args, **kwargs)


class HigherLevelRows:
    """The rows of the levels i >= 1 during ``learn``: each env's reward sum since its last row per level, and the
    rows the hierarchy produced (module docstring).

    :param n_replays: number of levels with a replay
    :param n_envs: number of envs
    :param zero_terminal_reward: the reference-compat switch ``reference.terminal_reward="zeroed"``: the pending sums
        of an env are cleared when its episode ends, before its terminal rows are written
    """

    def __init__(self, n_replays: int, n_envs: int, zero_terminal_reward: bool) -> None:
        self.zero_terminal_reward = zero_terminal_reward
        #: per level (index 0 unused), (n_envs,) float64 reward sums since the env's last row of that level
        self.reward_sums = [np.zeros(n_envs, dtype=np.float64) for _ in range(n_replays)]

    def add_rewards(self, reward: np.ndarray, done: np.ndarray) -> None:
        """Add one vec-env step's rewards to every level's sums.

        :param reward: (n_envs,) rewards as the agent sees them
        :param done: (n_envs,) bool episode ends
        """
        for sums in self.reward_sums[1:]:
            sums += np.asarray(reward, dtype=np.float64).reshape(-1)
        if self.zero_terminal_reward:
            for sums in self.reward_sums[1:]:
                sums[done] = 0.0

    def write(
        self, buffer: SequenceReplayBuffer, rows: LevelRows, is_first: np.ndarray | bool, is_terminal: np.ndarray | bool
    ) -> None:
        """One row per env of ``rows`` with the reward summed since that env's previous row (which is reset).

        :param buffer: the replay of level ``rows.level``
        :param rows: the hierarchy's rows of one level
        :param is_first: (m,) or a bool for all
        :param is_terminal: (m,) or a bool for all
        """
        m = rows.envs.size
        reward = self.reward_sums[rows.level][rows.envs].astype(np.float32)
        first = np.broadcast_to(np.asarray(is_first, dtype=bool), (m,))
        terminal = np.broadcast_to(np.asarray(is_terminal, dtype=bool), (m,))
        buffer.add_step(rows.observations, rows.actions, reward, first, terminal, rows.subgoals, envs=rows.envs)
        self.reward_sums[rows.level][rows.envs] = 0.0
