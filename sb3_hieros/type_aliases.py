"""Types shared by the replay layer (:mod:`sb3_hieros.buffers`) and the agent layer (:mod:`sb3_hieros.agent`), as
SB3's ``common/type_aliases.py`` does for its buffers and algorithms."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch as th

__all__ = ["LevelRows", "LevelUpdate", "Observation", "SequenceSamples"]

#: A batch of observations as tensors: one tensor, or a dict of them for Dict observation spaces.
Observation = th.Tensor | dict[str, th.Tensor]


class SequenceSamples(NamedTuple):
    """A batch of chunks in the Dreamer view, torch tensors on the buffer's device.

    :param observations: o_t, ``(B, T, *obs_shape)`` in the observation dtype (uint8 images stay uint8);
        a dict of such tensors for Dict observation spaces
    :param actions: a_{t-1}, the action that led to ``observations[:, t]``, ``(B, T, action_dim)``; 0 at ``is_first``
    :param rewards: r_t, the reward received with ``observations[:, t]``, ``(B, T)`` float32; 0 at ``is_first``
    :param is_first: ``(B, T)`` bool, episode starts
    :param is_terminal: ``(B, T)`` bool, terminal observations (continue target = ``~is_terminal``)
    :param subgoals: ``(B, T, *subgoal_shape)`` float32, the subgoal in force at each step, or None
    :param context: ``(B, context_dim)`` float32, the stored context of the row before each chunk (zeros where there
        is none), or None if the buffer keeps no context
    :param index: where the chunks lie, ``(rows (B, T), streams (B,))`` numpy int64 arrays, for
        :meth:`~sb3_hieros.buffers.SequenceReplayBuffer.store_context`; None for batches not drawn from a buffer
    """

    observations: Observation
    actions: th.Tensor
    rewards: th.Tensor
    is_first: th.Tensor
    is_terminal: th.Tensor
    subgoals: th.Tensor | None
    context: th.Tensor | None = None
    index: tuple[np.ndarray, np.ndarray] | None = None


class LevelUpdate(NamedTuple):
    """What one training iteration of a level (Algorithm 2) returns.

    :param metrics: name -> value (see :meth:`~sb3_hieros.agent.hierarchy.Hierarchy.train`)
    :param context: ``(B, T, C)`` packed posterior states of the batch, for the replay context
        (:meth:`~sb3_hieros.buffers.SequenceReplayBuffer.store_context`); None when the batch had no context
    """

    metrics: dict[str, float]
    context: th.Tensor | None


class LevelRows(NamedTuple):
    """Replay rows of a level i >= 1 for some env streams, as the hierarchy produced them (numpy, on the host).

    :param level: the level i
    :param envs: ``(m,)`` env stream indices
    :param observations: ``(m, obs_dim)`` what level i observes: its window of world states of level i-1
    :param actions: ``(m, n_cat)`` int64 indices of the subgoal level i held before (a_{t-1} in the row convention)
    :param subgoals: ``(m, n_cat * n_classes)`` subgoal code in force from level i+1, or None at the top
    """

    level: int
    envs: np.ndarray
    observations: np.ndarray
    actions: np.ndarray
    subgoals: np.ndarray | None
