"""Sequence replay buffers for HIEROS: chunks of consecutive steps in the Dreamer row convention.

Storage convention
------------------
Each env has its own **stream** of rows (a ring of ``buffer_size // n_envs`` rows) and its own write head.
Row t of a stream is one step in the Dreamer view:

========================  ==================================================================
``observations[t]``       o_t (the observation dtype is kept: uint8 images stay uint8)
``actions[t]``            a_{t-1}, the action that led to o_t (0 where ``is_first``)
``rewards[t]``            r_t, the reward received on arriving at o_t (0 where ``is_first``), float32
``is_first[t]``           o_t is the first observation of an episode (bool)
``is_terminal[t]``        o_t is a terminal observation (bool; a time-limit truncation is not terminal)
``subgoals[t]``           g_t, the subgoal in force at o_t (float32, only if ``subgoal_shape`` is given)
``context[t]``            the world model's packed state after o_t when row t was last trained on (float32,
                          only if ``context_dim > 0``; see *Replay context*)
========================  ==================================================================

:meth:`SequenceReplayBuffer.add_step` writes such a row directly (for HIEROS's higher levels).
:meth:`SequenceReplayBuffer.add` takes SB3's transition ``(o_t, o_{t+1}, a_t, r_{t+1}, done_{t+1}, infos)`` from
``OffPolicyAlgorithm._store_transition`` and turns it into rows:

* if the stream starts a new episode (first call, ``done`` in the previous call, or ``obs`` differs from the
  stream's last stored observation, e.g. after ``learn()`` reset the env), it first writes the row
  ``(o_t, 0, 0, is_first=True, is_terminal=False, g_t)``; otherwise it writes ``g_t`` into the stream's last row,
  which already holds o_t;
* it then writes ``(o_{t+1}, a_t, r_{t+1}, is_first=False, is_terminal=done and not truncated, g_t)``; the
  subgoal there is provisional and is replaced by the next call's ``g_{t+1}``.

So every observation is stored exactly once (no separate next-observation array), and an episode of L
transitions takes L + 1 rows: the reset observation and the terminal observation each get a row of their own,
the terminal one with its reward and ``is_terminal``. SB3's ``_store_transition`` already puts the true
terminal observation (``infos[i]["terminal_observation"]``, unnormalised under VecNormalize) into ``next_obs``
at ``done``, and that is what is stored. Because episode starts cost an extra row, streams drift apart; each
has its own write head (``stream_pos``). ``pos`` and ``full`` mirror stream 0 and are kept only for SB3 code
that reads them.

Sampling
--------
``sample(batch_size)`` returns :class:`SequenceSamples` of ``batch_size`` chunks of ``batch_length``
consecutive rows, each from one stream, shaped ``(B, T, ...)``. A chunk never crosses a stream's write head
(so never joins the newest and the oldest rows) but may cross episode borders: ``is_first`` marks them, and is
**not** forced to True at ``t = 0`` (the world model starts every chunk from its initial state anyway, or from
the replay context below).
The stream of a chunk is drawn in proportion to its number of valid chunk starts, so every valid
``(stream, start)`` pair is equally likely with uniform selection. Random numbers come from numpy's
**global** state (``np.random.random_sample``), as SB3's buffers draw from ``np.random``, so
``stable_baselines3.common.utils.set_random_seed`` makes sampling reproducible and the buffer holds no
generator: its state is plain arrays and numbers (``HIEROS.save_replay_buffer`` stores them without pickle,
:mod:`sb3_hieros.replay_io`).

:class:`ETBSReplayBuffer` selects the chunk start by insertion age with efficient time-balanced sampling
(:mod:`sb3_hieros.etbs`, thesis section 4.5) instead of uniformly.

Replay context
--------------
With ``context_dim > 0`` each row can hold an opaque float vector, the learner's state after that step (HIEROS
stores :meth:`~sb3_hieros.agent.world_model.WorldModel.pack_context` of the posterior). :meth:`store_context`
writes it for the rows of a sampled batch (:attr:`SequenceSamples.index`); a later chunk starting at row s gets the
vector of row s - 1 as :attr:`SequenceSamples.context` if that row holds one and precedes s in the same stream
(zeros otherwise: the chunk starts at the stream's oldest row, or row s - 1 was never trained on). Writing a new
step into a row drops its vector. This is DreamerV3's replay context: the sequence model is trained from states
of the same length of history as in acting instead of from zeros at every chunk start.
"""

from sb3_hieros.buffers.sequence import (
    DictSequenceReplayBuffer,
    SequenceReplayBuffer,
    available_memory,
    warn_if_replay_exceeds_memory,
)
from sb3_hieros.buffers.time_balanced import ETBS_BUFFER_MODES, ETBSReplayBuffer
from sb3_hieros.type_aliases import SequenceSamples

# The classes carry their public path: saved replays (sb3_hieros.replay_io) and safe loads name them by it.
for _cls in (SequenceReplayBuffer, DictSequenceReplayBuffer, ETBSReplayBuffer):
    _cls.__module__ = __name__
del _cls

__all__ = [
    "ETBS_BUFFER_MODES",
    "DictSequenceReplayBuffer",
    "ETBSReplayBuffer",
    "SequenceReplayBuffer",
    "SequenceSamples",
    "available_memory",
    "warn_if_replay_exceeds_memory",
]
