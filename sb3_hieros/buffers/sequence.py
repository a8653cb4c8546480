"""The sequence replay buffer: per-env streams of rows in the Dreamer view, sampled as chunks (see
:mod:`sb3_hieros.buffers` for the row convention)."""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import BaseBuffer, ReplayBuffer
from stable_baselines3.common.preprocessing import get_action_dim, get_obs_shape
from stable_baselines3.common.type_aliases import DictReplayBufferSamples, ReplayBufferSamples
from stable_baselines3.common.vec_env import VecNormalize

from sb3_hieros.type_aliases import SequenceSamples

__all__ = ["DictSequenceReplayBuffer", "SequenceReplayBuffer", "available_memory", "warn_if_replay_exceeds_memory"]


def _global_uniform(n: int) -> np.ndarray:
    """``n`` uniform numbers in [0, 1) from numpy's global state, which SB3's ``set_random_seed`` seeds."""
    return np.random.random_sample(n)  # noqa: NPY002 (deliberate: reproducible under SB3 seeding, picklable)


def available_memory() -> int | None:
    """Bytes of memory available for new allocations: ``psutil.virtual_memory().available`` if psutil is installed,
    else ``MemAvailable`` of ``/proc/meminfo``; None when neither can be read.

    :return: bytes, or None
    """
    try:
        import psutil

        return int(psutil.virtual_memory().available)
    except ImportError:
        pass
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def warn_if_replay_exceeds_memory(nbytes: Sequence[int], names: Sequence[str] | None = None) -> bool:
    """Warn (``UserWarning``, before anything is allocated) when replay arrays of ``sum(nbytes)`` bytes will not fit
    into the available memory (SB3's ``ReplayBuffer`` check, done before allocation and for all levels together).

    :param nbytes: estimated bytes of each buffer (:meth:`SequenceReplayBuffer.estimate_nbytes`)
    :param names: a name per buffer for the message (e.g. ``"level 1"``)
    :return: whether the warning was issued
    """
    available = available_memory()
    total = int(sum(nbytes))
    if available is None or total <= available:
        return False
    parts = ""
    if names is not None and len(nbytes) > 1:
        parts = " (" + ", ".join(f"{name}: {n / 1e9:.2f} GB" for name, n in zip(names, nbytes, strict=True)) + ")"
    warnings.warn(
        f"The replay buffer needs about {total / 1e9:.2f} GB{parts}, but only {available / 1e9:.2f} GB of memory "
        "is available: the system may start swapping or kill the process once the buffer fills; reduce buffer_size",
        stacklevel=3,
    )
    return True


def _check_shape(
    value: Any, expected: tuple[int, ...], name: str, also: tuple[tuple[int, ...], ...] = ()
) -> np.ndarray:
    """``value`` as an array of shape ``expected``; shapes listed in ``also`` are reshaped to it, others refused."""
    array = np.asarray(value)
    if array.shape == expected:
        return array
    if array.shape in also:
        return array.reshape(expected)
    accepted = " or ".join(str(s) for s in (expected, *also))
    raise ValueError(f"{name} has shape {array.shape}, expected {accepted}")


class SequenceReplayBuffer(ReplayBuffer):
    """Replay buffer of per-env step streams, sampled as chunks of consecutive steps (Dreamer view).

    See the module docstring for the row convention. Box, Discrete, MultiDiscrete, MultiBinary and Dict
    observation spaces are supported (:class:`DictSequenceReplayBuffer` is the Dict-only name).

    :param buffer_size: max number of stored steps over all envs; each env stream holds ``buffer_size // n_envs``
    :param observation_space: observation space
    :param action_space: action space
    :param device: torch device of the sampled tensors
    :param n_envs: number of parallel environments (streams)
    :param optimize_memory_usage: must be False: each observation is already stored only once
    :param handle_timeout_termination: if True, a done with ``infos[i]["TimeLimit.truncated"]`` is not terminal
    :param batch_length: number of consecutive steps T per sampled chunk
    :param subgoal_shape: shape of the subgoal stored with each step (higher HIEROS levels), or None
    :param context_dim: floats of replay context per row (module docstring), 0 for none
    """

    observations: np.ndarray | dict[str, np.ndarray]  # type: ignore[assignment]

    def __init__(
        self,
        buffer_size: int,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        device: th.device | str = "auto",
        n_envs: int = 1,
        optimize_memory_usage: bool = False,
        handle_timeout_termination: bool = True,
        batch_length: int = 64,
        subgoal_shape: tuple[int, ...] | None = None,
        context_dim: int = 0,
    ):
        # BaseBuffer directly, as DictReplayBuffer does: ReplayBuffer.__init__ would allocate next_observations
        BaseBuffer.__init__(self, buffer_size, observation_space, action_space, device, n_envs=n_envs)
        if int(n_envs) != n_envs or n_envs < 1:
            raise ValueError(f"n_envs must be an integer >= 1, got {n_envs!r}")
        if optimize_memory_usage:
            raise ValueError(
                "optimize_memory_usage=True is not supported by SequenceReplayBuffer: it never stores a separate "
                "next observation, so its memory is already that of the optimised variant; pass False"
            )
        if int(batch_length) != batch_length or batch_length < 1:
            raise ValueError(f"batch_length must be an integer >= 1, got {batch_length!r}")
        self.buffer_size = max(buffer_size // n_envs, 1)  # rows per stream
        if batch_length > self.buffer_size:
            raise ValueError(
                f"batch_length={batch_length} exceeds the rows per env stream (buffer_size // n_envs = "
                f"{buffer_size} // {n_envs} = {self.buffer_size})"
            )
        if subgoal_shape is not None:
            subgoal_shape = tuple(subgoal_shape)
            if not all(int(d) == d and d >= 1 for d in subgoal_shape):
                raise ValueError(f"subgoal_shape must be a tuple of positive integers or None, got {subgoal_shape!r}")
        if isinstance(context_dim, bool) or int(context_dim) != context_dim or context_dim < 0:
            raise ValueError(f"context_dim must be an integer >= 0 (0: no replay context), got {context_dim!r}")
        self.optimize_memory_usage = False
        self.handle_timeout_termination = handle_timeout_termination
        self.batch_length = int(batch_length)
        self.subgoal_shape = subgoal_shape
        self.context_dim = int(context_dim)
        # before allocating: the arrays below are lazily committed, so the failure would come much later
        warn_if_replay_exceeds_memory(
            [self.estimate_nbytes(buffer_size, observation_space, action_space, n_envs, subgoal_shape, context_dim)]
        )

        rows, n = self.buffer_size, self.n_envs
        self._dict_obs = isinstance(observation_space, spaces.Dict)
        if self._dict_obs:
            self.observations = {
                key: np.zeros((rows, n, *shape), dtype=observation_space[key].dtype)
                for key, shape in self.obs_shape.items()  # type: ignore[attr-defined]
            }
        else:
            self.observations = np.zeros((rows, n, *self.obs_shape), dtype=observation_space.dtype)
        self.actions = np.zeros((rows, n, self.action_dim), dtype=self._maybe_cast_dtype(action_space.dtype))
        self.rewards = np.zeros((rows, n), dtype=np.float32)
        self.is_first = np.zeros((rows, n), dtype=bool)
        self.is_terminal = np.zeros((rows, n), dtype=bool)
        self.subgoals = None if subgoal_shape is None else np.zeros((rows, n, *subgoal_shape), dtype=np.float32)
        self.context = np.zeros((rows, n, self.context_dim), dtype=np.float32) if self.context_dim else None
        self.has_context = np.zeros((rows, n), dtype=bool)
        # per-stream write heads; a stream expects an episode start until add() has seen its first step
        self.stream_pos = np.zeros(n, dtype=np.int64)
        self.stream_full = np.zeros(n, dtype=bool)
        self._expect_first = np.ones(n, dtype=bool)

    @staticmethod
    def estimate_nbytes(
        buffer_size: int,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        n_envs: int = 1,
        subgoal_shape: tuple[int, ...] | None = None,
        context_dim: int = 0,
    ) -> int:
        """Bytes the arrays of a buffer built with these arguments take once filled (computed without allocating).

        :param buffer_size: as for the constructor (steps over all envs)
        :param observation_space: observation space
        :param action_space: action space
        :param n_envs: number of envs
        :param subgoal_shape: subgoal shape or None
        :param context_dim: floats of replay context per row
        :return: bytes of observations, actions, rewards, is_first, is_terminal, subgoals and context
        """
        rows = max(int(buffer_size) // int(n_envs), 1) * int(n_envs)
        subspaces = (
            observation_space.spaces.values() if isinstance(observation_space, spaces.Dict) else [observation_space]
        )
        obs = sum(int(np.prod(get_obs_shape(sub))) * np.dtype(sub.dtype).itemsize for sub in subspaces)  # type: ignore[arg-type]
        action_dtype = np.dtype(ReplayBuffer._maybe_cast_dtype(action_space.dtype))
        action = get_action_dim(action_space) * action_dtype.itemsize
        subgoal = 0 if subgoal_shape is None else int(np.prod(subgoal_shape)) * 4
        context = int(context_dim) * 4 + 1 if context_dim else 1
        return rows * (obs + action + 4 + 1 + 1 + subgoal + context)

    def __setstate__(self, state: dict[str, Any]) -> None:
        # buffers pickled before replay context existed (``save_replay_buffer`` files) load without one
        self.__dict__.update(state)
        if "context_dim" not in state:
            self.context_dim, self.context = 0, None
            self.has_context = np.zeros((self.buffer_size, self.n_envs), dtype=bool)

    # ----------------------------------------------------------------------------------------------------
    # bookkeeping

    def _obs_arrays(self) -> dict[str, np.ndarray]:
        return self.observations if self._dict_obs else {"": self.observations}  # type: ignore[return-value]

    def stored_steps(self) -> np.ndarray:
        """:return: number of rows (steps) stored in each env stream, int64 ``(n_envs,)``"""
        return np.where(self.stream_full, self.buffer_size, self.stream_pos)

    def size(self) -> int:
        """Rows stored over all env streams. SB3's buffers count the rows of one env, as all their streams have the
        same length; here streams differ (see the module docstring).

        :return: number of steps (rows) stored over all env streams
        """
        return int(self.stored_steps().sum())

    def valid_starts(self) -> np.ndarray:
        """:return: number of chunk starts per stream that give ``batch_length`` steps behind the write head"""
        return np.maximum(self.stored_steps() - self.batch_length + 1, 0)

    def can_sample(self) -> bool:
        """:return: whether at least one stream holds ``batch_length`` steps, so ``sample`` will not raise"""
        return bool(self.valid_starts().sum() > 0)

    def oldest_rows(self) -> np.ndarray:
        """:return: the row of the oldest stored step of each env stream, int64 ``(n_envs,)``"""
        return np.where(self.stream_full, self.stream_pos, 0)

    def _stored_rows(self) -> np.ndarray:
        """(rows, n_envs) bool: the row holds a stored step."""
        return self.stream_full[None, :] | (np.arange(self.buffer_size)[:, None] < self.stream_pos[None, :])

    @property
    def dones(self) -> np.ndarray:
        """SB3's ``dones`` in the row convention: (rows, n_envs) float32, 1 where row t's observation ends its episode
        (terminal, truncated by a time limit, or followed by the first row of a new episode; the newest row of a
        stream when the stream's next :meth:`add` starts a new episode). Computed from ``is_terminal``, ``is_first``
        and the write heads, not stored.

        Row t holds ``a_{t-1}``, ``r_t`` and ``done_t`` of the step that arrived at ``o_t`` (module docstring), so
        the SB3 transition of row t is ``(observations[t-1], actions[t], rewards[t], observations[t], dones[t])`` for
        rows that are not ``is_first`` (:meth:`sample_transitions` draws them).
        """
        stored = self._stored_rows()
        ended = self.is_terminal | (np.roll(self.is_first, -1, axis=0) & np.roll(stored, -1, axis=0))
        streams = np.flatnonzero(stored.any(axis=0))
        newest = (self.stream_pos[streams] - 1) % self.buffer_size
        ended[newest, streams] = self.is_terminal[newest, streams] | self._expect_first[streams]
        return (ended & stored).astype(np.float32)

    @property
    def timeouts(self) -> np.ndarray:
        """SB3's ``timeouts`` in the row convention: (rows, n_envs) float32, 1 where row t ends its episode without
        being terminal (a time-limit truncation, or an episode cut off by a reset); all zero with
        ``handle_timeout_termination=False``, as in SB3. Computed, not stored.
        """
        if not self.handle_timeout_termination:
            return np.zeros((self.buffer_size, self.n_envs), dtype=np.float32)
        return self.dones * (~self.is_terminal)

    def sample_transitions(
        self, batch_size: int, env: VecNormalize | None = None
    ) -> ReplayBufferSamples | DictReplayBufferSamples:
        """SB3's transitions ``(o_t, a_t, o_{t+1}, done, r_{t+1})``, drawn uniformly from the stored ones, as
        ``ReplayBuffer.sample`` returns them (for SB3 code; HIEROS itself samples chunks with :meth:`sample`).

        :param batch_size: number of transitions
        :param env: VecNormalize to normalise observations and rewards with, as in SB3
        :return: ``ReplayBufferSamples`` (``DictReplayBufferSamples`` for Dict spaces): observations, actions as
            stored (Box actions scaled to [-1, 1], Discrete indices), next observations, ``dones`` (terminal only,
            as SB3 samples them) and rewards, each with the batch on axis 0
        """
        if int(batch_size) != batch_size or batch_size < 1:
            raise ValueError(f"batch_size must be an integer >= 1, got {batch_size!r}")
        valid = self._stored_rows() & ~self.is_first  # the row was reached by a step from the row before it
        full = np.flatnonzero(self.stream_full)
        valid[self.stream_pos[full], full] = False  # the oldest row of a full stream: its predecessor is gone
        rows, envs = np.nonzero(valid)
        if rows.size == 0:
            raise ValueError("the buffer holds no transition yet (every stored row starts an episode)")
        chosen = np.minimum((_global_uniform(int(batch_size)) * rows.size).astype(np.int64), rows.size - 1)
        rows, envs = rows[chosen], envs[chosen]
        before = (rows - 1) % self.buffer_size

        def observations(at: np.ndarray) -> th.Tensor | dict[str, th.Tensor]:
            obs = {key: array[at, envs] for key, array in self._obs_arrays().items()}
            normalized = self._normalize_obs(obs if self._dict_obs else obs[""], env)  # type: ignore[arg-type]
            if isinstance(normalized, dict):
                return {key: self.to_torch(value) for key, value in normalized.items()}
            return self.to_torch(normalized)

        samples = DictReplayBufferSamples if self._dict_obs else ReplayBufferSamples
        return samples(  # type: ignore[return-value]
            observations(before),
            self.to_torch(self.actions[rows, envs]),
            observations(rows),
            self.to_torch(self.is_terminal[rows, envs].astype(np.float32).reshape(-1, 1)),
            self.to_torch(self._normalize_reward(self.rewards[rows, envs].reshape(-1, 1), env)),
        )

    def reset(self) -> None:
        """Forget all stored steps (the arrays are not cleared, as in SB3)."""
        super().reset()
        self.stream_pos[:] = 0
        self.stream_full[:] = False
        self._expect_first[:] = True
        self.has_context[:] = False

    # ----------------------------------------------------------------------------------------------------
    # writing

    def _check_obs(
        self, obs: np.ndarray | Mapping[str, np.ndarray], name: str, n: int | None = None
    ) -> dict[str, np.ndarray]:
        n = self.n_envs if n is None else n
        if self._dict_obs:
            if not isinstance(obs, Mapping) or set(obs.keys()) != set(self.observations.keys()):  # type: ignore[union-attr]
                got = sorted(obs.keys()) if isinstance(obs, Mapping) else type(obs).__name__
                raise ValueError(f"{name} must be a dict with keys {sorted(self.observations)}, got {got}")
            items = {key: (obs[key], self.observation_space[key]) for key in self.observations}  # type: ignore[index]
        else:
            items = {"": (obs, self.observation_space)}
        checked = {}
        for key, (value, space) in items.items():
            shape = (n, *space.shape) if not isinstance(space, spaces.Discrete) else (n, 1)
            also = ((n,),) if isinstance(space, spaces.Discrete) else ()
            checked[key] = _check_shape(value, shape, f"{name}[{key!r}]" if key else name, also)
        return checked

    def _check_action(self, action: np.ndarray, n: int | None = None) -> np.ndarray:
        n, dim = (self.n_envs if n is None else n), self.action_dim
        # SB3 passes (n_envs, *action_space.shape); one-dimensional actions may come as (n_envs,)
        also = [(n, *self.action_space.shape)] + ([(n,)] if dim == 1 else [])
        return _check_shape(action, (n, dim), "action", tuple(s for s in dict.fromkeys(also) if s != (n, dim)))

    def _check_subgoal(
        self, subgoal: np.ndarray | None, n: int | None = None, required: bool = True
    ) -> np.ndarray | None:
        if self.subgoal_shape is None:
            if subgoal is not None:
                raise ValueError(
                    f"subgoal given with shape {np.shape(subgoal)}, but this buffer has subgoal_shape=None; "
                    "construct it with subgoal_shape=... to store subgoals"
                )
            return None
        n = self.n_envs if n is None else n
        if subgoal is None:
            if required:
                raise ValueError(f"subgoal is required: this buffer stores subgoals of shape {self.subgoal_shape}")
            return np.zeros((n, *self.subgoal_shape), dtype=np.float32)
        return _check_shape(subgoal, (n, *self.subgoal_shape), "subgoal")

    def _on_rows_written(self, rows: np.ndarray, envs: np.ndarray) -> None:
        """Hook called after rows ``rows`` of streams ``envs`` received new steps (before the heads advance)."""

    def _write_rows(
        self,
        envs: np.ndarray,
        obs: dict[str, np.ndarray],
        actions: np.ndarray | int,
        rewards: np.ndarray | float,
        is_first: np.ndarray | bool,
        is_terminal: np.ndarray | bool,
        subgoals: np.ndarray | None,
    ) -> None:
        """Write one row at the head of each stream in ``envs`` (values already sliced to ``envs``) and advance."""
        rows = self.stream_pos[envs]
        for key, array in self._obs_arrays().items():
            array[rows, envs] = obs[key]
        self.actions[rows, envs] = actions
        self.rewards[rows, envs] = rewards
        self.is_first[rows, envs] = is_first
        self.is_terminal[rows, envs] = is_terminal
        if self.subgoals is not None:
            self.subgoals[rows, envs] = subgoals
        self.has_context[rows, envs] = False  # a new step: the stored state belonged to the old one
        self._on_rows_written(rows, envs)
        heads = rows + 1
        wrapped = heads >= self.buffer_size
        self.stream_full[envs[wrapped]] = True
        self.stream_pos[envs] = np.where(wrapped, 0, heads)
        self.pos, self.full = int(self.stream_pos[0]), bool(self.stream_full[0])

    def _differs_from_last(self, obs: dict[str, np.ndarray], envs: np.ndarray) -> np.ndarray:
        """Bitwise comparison of ``obs[envs]`` with the last stored observation of those streams."""
        differs = np.zeros(len(envs), dtype=bool)
        last_rows = (self.stream_pos[envs] - 1) % self.buffer_size
        for key, array in self._obs_arrays().items():
            stored = array[last_rows, envs].reshape(len(envs), -1)
            new = np.ascontiguousarray(obs[key][envs], dtype=array.dtype).reshape(len(envs), -1)
            differs |= (stored.view(np.uint8) != new.view(np.uint8)).any(axis=1)
        return differs

    def add(  # type: ignore[override]
        self,
        obs: np.ndarray | dict[str, np.ndarray],
        next_obs: np.ndarray | dict[str, np.ndarray],
        action: np.ndarray,
        reward: np.ndarray,
        done: np.ndarray,
        infos: list[dict[str, Any]],
        subgoal: np.ndarray | None = None,
    ) -> None:
        """Store one SB3 transition per env (signature of ``ReplayBuffer.add``, as called by ``_store_transition``).

        ``next_obs`` must hold the true terminal observation where ``done`` (SB3 substitutes it). It becomes the
        stream's new row; ``obs`` is stored only when a new episode starts (see the module docstring).

        :param obs: o_t, ``(n_envs, *obs_shape)`` (or a dict of such arrays)
        :param next_obs: o_{t+1}, same shape
        :param action: a_t, ``(n_envs, action_dim)`` (``(n_envs,)`` for one-dimensional actions)
        :param reward: r_{t+1}, ``(n_envs,)``
        :param done: ``(n_envs,)``, the episode ended with o_{t+1}
        :param infos: ``n_envs`` info dicts; ``"TimeLimit.truncated"`` marks a time-limit end (not terminal)
        :param subgoal: g_t, the subgoal in force at o_t, ``(n_envs, *subgoal_shape)``, only for a buffer with a
            ``subgoal_shape`` (level 0 below a level that sets subgoals); without it such a buffer stores an all-zero
            code (no subgoal: SB3 code such as ``extend`` can fill it; the subgoal reward of those rows compares
            with the autoencoder's decoding of the zero code)
        """
        n = self.n_envs
        obs_d = self._check_obs(obs, "obs")
        next_d = self._check_obs(next_obs, "next_obs")
        action = self._check_action(action)
        reward = _check_shape(reward, (n,), "reward")
        done = _check_shape(done, (n,), "done").astype(bool)
        if len(infos) != n:
            raise ValueError(f"infos has length {len(infos)}, expected n_envs={n}")
        subgoal = self._check_subgoal(subgoal, required=False)
        truncated = np.zeros(n, dtype=bool)
        if self.handle_timeout_termination:
            truncated = np.array([bool(info.get("TimeLimit.truncated", False)) for info in infos])

        first = self._expect_first.copy()
        continuing = np.flatnonzero(~first)
        if continuing.size:
            first[continuing] = self._differs_from_last(obs_d, continuing)
        starts = np.flatnonzero(first)
        if starts.size:
            self._write_rows(
                starts,
                {key: value[starts] for key, value in obs_d.items()},
                actions=0,
                rewards=0.0,
                is_first=True,
                is_terminal=False,
                subgoals=None if subgoal is None else subgoal[starts],
            )
        continuing = np.flatnonzero(~first)
        if subgoal is not None and continuing.size:
            last_rows = (self.stream_pos[continuing] - 1) % self.buffer_size
            self.subgoals[last_rows, continuing] = subgoal[continuing]  # type: ignore[index]
        self._write_rows(np.arange(n), next_d, action, reward, False, done & ~truncated, subgoal)
        self._expect_first = done.copy()

    def add_step(
        self,
        obs: np.ndarray | dict[str, np.ndarray],
        action: np.ndarray,
        reward: np.ndarray,
        is_first: np.ndarray,
        is_terminal: np.ndarray,
        subgoal: np.ndarray | None = None,
        envs: np.ndarray | Sequence[int] | None = None,
    ) -> None:
        """Store one step per env directly in the row convention (for HIEROS's higher levels).

        With ``envs`` only those streams get a row (each keeps its own write head), e.g. at one env's episode end;
        every array then has ``m = len(envs)`` rows instead of ``n_envs``.

        :param obs: o_t, ``(m, *obs_shape)`` (or a dict of such arrays)
        :param action: a_{t-1}, the action that led to o_t, ``(m, action_dim)``; ignored where ``is_first``
        :param reward: r_t, received on arriving at o_t, ``(m,)``; ignored where ``is_first``
        :param is_first: ``(m,)`` bool, o_t starts an episode
        :param is_terminal: ``(m,)`` bool, o_t is terminal
        :param subgoal: g_t, the subgoal in force at o_t, ``(m, *subgoal_shape)``; required iff the buffer
            has a ``subgoal_shape``
        :param envs: distinct stream indices in ``[0, n_envs)``, or None for all streams (``m = n_envs``)
        """
        if envs is None:
            envs = np.arange(self.n_envs)
        else:
            envs = np.asarray(envs)
            if (
                envs.ndim != 1
                or envs.size == 0
                or not np.issubdtype(envs.dtype, np.integer)
                or envs.min() < 0
                or envs.max() >= self.n_envs
                or np.unique(envs).size != envs.size
            ):
                raise ValueError(
                    f"envs must be a non-empty 1-d array of distinct integer stream indices in [0, {self.n_envs}), "
                    f"got {envs.tolist()}"
                )
        n = int(envs.size)
        obs_d = self._check_obs(obs, "obs", n)
        action = self._check_action(action, n)
        reward = _check_shape(reward, (n,), "reward")
        is_first = _check_shape(is_first, (n,), "is_first").astype(bool)
        is_terminal = _check_shape(is_terminal, (n,), "is_terminal").astype(bool)
        subgoal = self._check_subgoal(subgoal, n)
        self._write_rows(envs, obs_d, action, reward, is_first, is_terminal, subgoal)

    # ----------------------------------------------------------------------------------------------------
    # sampling

    def _draw_ages(self, n_valid: np.ndarray) -> np.ndarray:
        """Chunk-start ages (0 = oldest valid start) for streams with ``n_valid`` valid starts; uniform here."""
        ages = (_global_uniform(len(n_valid)) * n_valid).astype(np.int64)
        return np.minimum(ages, n_valid - 1)

    def _sample_starts(self, batch_size: int) -> tuple[np.ndarray, np.ndarray]:
        """Draw ``(stream, start age)`` pairs: the stream in proportion to its valid starts, then the age."""
        n_valid = self.valid_starts()
        cumulative = np.cumsum(n_valid)
        envs = np.searchsorted(cumulative, _global_uniform(batch_size) * cumulative[-1], side="right")
        envs = np.minimum(envs, self.n_envs - 1)
        return envs, self._draw_ages(n_valid[envs])

    def sample(self, batch_size: int, env: VecNormalize | None = None) -> SequenceSamples:  # type: ignore[override]
        """Sample ``batch_size`` chunks of ``batch_length`` consecutive steps (see :class:`SequenceSamples`).

        :param batch_size: number of chunks B
        :param env: VecNormalize to normalise observations and rewards with, as in SB3
        :return: the chunks as torch tensors on ``self.device``, shaped ``(B, T, ...)``
        """
        if int(batch_size) != batch_size or batch_size < 1:
            raise ValueError(f"batch_size must be an integer >= 1, got {batch_size!r}")
        if not self.can_sample():
            stored = self.stored_steps()
            raise ValueError(
                f"cannot sample chunks of batch_length={self.batch_length}: need at least {self.batch_length} "
                f"steps in one env stream, but the streams hold {stored.tolist()} steps"
            )
        envs, ages = self._sample_starts(int(batch_size))
        return self._get_chunks(envs, ages, env)

    def _get_chunks(self, envs: np.ndarray, ages: np.ndarray, env: VecNormalize | None = None) -> SequenceSamples:
        """Gather the chunks that start ``ages`` rows after the oldest row of streams ``envs``."""
        starts = self.oldest_rows()[envs] + ages
        rows = (starts[:, None] + np.arange(self.batch_length)) % self.buffer_size  # (B, T)
        context = None
        if self.context is not None:
            before = (starts - 1) % self.buffer_size
            usable = (ages > 0) & self.has_context[before, envs]  # (B,): row s - 1 is older data of the same stream
            context = self.to_torch(np.where(usable[:, None], self.context[before, envs], 0.0).astype(np.float32))
        return self._gather(rows, envs, env)._replace(context=context)

    def _gather(self, rows: np.ndarray, envs: np.ndarray, env: VecNormalize | None) -> SequenceSamples:
        """Rows ``rows`` (B, T) of streams ``envs`` (B,) as a batch, normalised and with placeholders zeroed."""
        cols = envs[:, None]  # (B, 1)
        obs = {key: array[rows, cols] for key, array in self._obs_arrays().items()}  # (B, T, *shape)
        obs = self._normalize_obs(obs if self._dict_obs else obs[""], env)
        is_first = self.is_first[rows, cols]
        actions = self.actions[rows, cols]  # (B, T, action_dim)
        actions[is_first] = 0
        rewards = self.rewards[rows, cols]
        rewards[is_first] = 0.0
        rewards = self._normalize_reward(rewards, env)
        if isinstance(obs, dict):
            observations: th.Tensor | dict[str, th.Tensor] = {k: self.to_torch(v, copy=False) for k, v in obs.items()}
        else:
            observations = self.to_torch(obs, copy=False)
        return SequenceSamples(
            observations=observations,
            actions=self.to_torch(actions, copy=False),
            rewards=self.to_torch(rewards, copy=False),
            is_first=self.to_torch(is_first, copy=False),
            is_terminal=self.to_torch(self.is_terminal[rows, cols], copy=False),
            subgoals=None if self.subgoals is None else self.to_torch(self.subgoals[rows, cols], copy=False),
            index=(rows, envs.copy()),
        )

    def chunk(self, stream: int, rows: np.ndarray, env: VecNormalize | None = None) -> SequenceSamples:
        """Given rows of one env stream as a batch of one chunk, as :meth:`sample` returns them (normalised with
        ``env``, actions and rewards zero at episode starts, no context). Draws no random numbers.

        :param stream: the env stream
        :param rows: (T,) row indices, e.g. from :func:`sb3_hieros.callbacks.recent_window`
        :param env: VecNormalize to normalise observations and rewards with, or None
        :return: the chunk, shaped (1, T, ...)
        """
        if not 0 <= stream < self.n_envs:
            raise ValueError(f"stream must lie in [0, {self.n_envs}), got {stream}")
        return self._gather(np.asarray(rows)[None], np.array([stream]), env)

    def store_context(self, index: tuple[np.ndarray, np.ndarray], context: np.ndarray | th.Tensor) -> None:
        """Keep the learner's state after each step of a sampled batch (module docstring, *Replay context*).

        Call it before new steps are added (as HIEROS does, right after the update on that batch): a row written
        since the draw would keep the state of the step it held before.

        :param index: :attr:`SequenceSamples.index` of the batch, ``(rows (B, T), streams (B,))``
        :param context: ``(B, T, context_dim)`` the packed states after each step of the batch
        """
        if self.context is None:
            raise ValueError("this buffer keeps no replay context (context_dim=0); build it with context_dim > 0")
        rows, envs = index
        values = context.detach().cpu().numpy() if isinstance(context, th.Tensor) else np.asarray(context)
        values = _check_shape(values, (*rows.shape, self.context_dim), "context")
        cols = np.broadcast_to(envs[:, None], rows.shape)
        self.context[rows, cols] = values
        self.has_context[rows, cols] = True

    def _get_samples(self, batch_inds: np.ndarray, env: VecNormalize | None = None):  # type: ignore[override]
        raise NotImplementedError(
            "SequenceReplayBuffer returns chunks: use sample(batch_size), or sample_transitions(batch_size) for SB3's "
            "ReplayBufferSamples"
        )


class DictSequenceReplayBuffer(SequenceReplayBuffer):
    """:class:`SequenceReplayBuffer` for Dict observation spaces (same code; observations are dicts of arrays).

    :param buffer_size: max number of stored steps over all envs
    :param observation_space: a ``spaces.Dict``
    :param action_space: action space
    :param kwargs: the other arguments of :class:`SequenceReplayBuffer`
    """

    def __init__(self, buffer_size: int, observation_space: spaces.Dict, action_space: spaces.Space, **kwargs: Any):
        if not isinstance(observation_space, spaces.Dict):
            raise ValueError(
                "DictSequenceReplayBuffer needs a spaces.Dict observation space, "
                f"got {type(observation_space).__name__}"
            )
        super().__init__(buffer_size, observation_space, action_space, **kwargs)
