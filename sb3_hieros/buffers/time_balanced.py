"""Sequence replay whose chunk starts are drawn by insertion age with efficient time-balanced sampling (ETBS,
thesis 4.5), or one of its baselines."""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import spaces

from sb3_hieros.buffers.sequence import SequenceReplayBuffer, _global_uniform
from sb3_hieros.etbs import CountBalancedSampler, MeanFieldCountSampler, etbs_index_from_uniform

__all__ = ["ETBS_BUFFER_MODES", "ETBSReplayBuffer"]

ETBS_BUFFER_MODES = ("etbs", "uniform", "reference", "count", "meanfield")


class ETBSReplayBuffer(SequenceReplayBuffer):
    """:class:`SequenceReplayBuffer` whose chunk starts are picked by insertion age with ETBS (thesis section 4.5).

    Within the drawn stream, the start age (0 = oldest valid chunk start) comes from
    :func:`sb3_hieros.etbs.etbs_index_from_uniform` over the stream's valid starts, O(1) per chunk.

    :param buffer_size: max number of stored steps over all envs
    :param observation_space: observation space (Dict included)
    :param action_space: action space
    :param temperature: tau of eq. 4.21 (thesis default 0.3); used by "etbs" and "reference"
    :param mode: "etbs" (thesis), "uniform", "reference" (the public code's capacity scaling, capacity being
        the valid starts of a full stream), "count" (O(n) count-based baseline,
        :class:`sb3_hieros.etbs.CountBalancedSampler`, one counter per chunk start over all streams) or
        "meanfield" (beyond the thesis: O(1) sampler with the count-based profile,
        :class:`sb3_hieros.etbs.MeanFieldCountSampler`)
    :param count_temperature: softmax temperature of the "count" and "meanfield" modes, in draws per chunk start
    :param draws_per_insert: "meanfield" only (required there): chunks drawn per step added to a stream, e.g.
        ``batch_size * gradient_steps / (train_freq * n_envs)`` for SB3's training loop
    :param kwargs: the other keywords of :class:`SequenceReplayBuffer` (``device``, ``n_envs``, ``batch_length``,
        ``subgoal_shape``, ``context_dim``, ...)
    """

    def __init__(
        self,
        buffer_size: int,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        temperature: float = 0.3,
        mode: str = "etbs",
        count_temperature: float = 1.0,
        draws_per_insert: float | None = None,
        **kwargs: Any,
    ):
        if mode not in ETBS_BUFFER_MODES:
            raise ValueError(f"mode must be one of {ETBS_BUFFER_MODES}, got {mode!r}")
        if not 0.0 <= temperature <= 1.0:  # also rejects NaN
            raise ValueError(f"temperature must lie in [0, 1], got {temperature!r}")
        if mode == "meanfield" and draws_per_insert is None:
            raise ValueError("mode='meanfield' needs draws_per_insert (chunks drawn per step added to a stream)")
        super().__init__(buffer_size, observation_space, action_space, **kwargs)
        self.temperature = float(temperature)
        self.mode = mode
        self.counter = (
            CountBalancedSampler(self.buffer_size * self.n_envs, count_temperature) if mode == "count" else None
        )
        self.meanfield = (
            MeanFieldCountSampler(count_temperature, draws_per_insert) if mode == "meanfield" else None  # type: ignore[arg-type]
        )

    def _on_rows_written(self, rows: np.ndarray, envs: np.ndarray) -> None:
        if self.counter is not None:
            self.counter.clear(rows * self.n_envs + envs)

    def _draw_ages(self, n_valid: np.ndarray) -> np.ndarray:
        u = _global_uniform(len(n_valid))
        if self.meanfield is not None:
            return self.meanfield.index_from_uniform(u, n_valid)
        capacity = self.buffer_size - self.batch_length + 1
        return etbs_index_from_uniform(u, n_valid, self.temperature, self.mode, capacity=capacity)

    def _sample_starts(self, batch_size: int) -> tuple[np.ndarray, np.ndarray]:
        if self.counter is None:
            return super()._sample_starts(batch_size)
        # O(n): every valid (stream, start) pair is a candidate with its own draw counter
        n_valid = self.valid_starts()
        envs = np.repeat(np.arange(self.n_envs), n_valid)
        ages = np.arange(len(envs)) - np.repeat(np.cumsum(n_valid) - n_valid, n_valid)
        rows = (self.oldest_rows()[envs] + ages) % self.buffer_size
        chosen = self.counter.draw_from_uniform(_global_uniform(batch_size), rows * self.n_envs + envs)
        return envs[chosen], ages[chosen]
