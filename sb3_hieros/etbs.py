"""Efficient time-balanced sampling (ETBS, thesis section 4.5) and its O(n) count-based baseline.

When one item is inserted into a replay buffer and the buffer is then sampled uniformly, again and again,
old items end up drawn far more often than new ones: the item inserted at step i is drawn about
``H_n - H_i ≈ ln(n / i)`` times after n steps (eq. 4.14-4.15). ETBS undoes that skew in O(1) per draw:
a draw ``x ~ U[2, n)`` is pushed through the closed-form CDF of the skewed density (eq. 4.20), which
favours recently inserted items, and mixed with the plain uniform draw by a temperature (eq. 4.21).

Indices returned here count **insertion age**: 0 is the oldest stored item, ``size - 1`` the newest.

Three index modes share one code path (:func:`etbs_indices`):

* ``"etbs"``: the thesis, with the CDF index scaled by ``size``, the number of items stored now;
* ``"reference"``: the public HIEROS code, which scales the CDF index by the buffer **capacity** and clamps
  it to ``size - 1``; while ``size << capacity`` the oldest ``temperature`` share of the buffer is then
  almost never drawn. Kept only to compare against;
* ``"uniform"``: the plain uniform index (the same as ``"etbs"`` with temperature 0).

:class:`CountBalancedSampler` is the O(n) sampler in the spirit of Robine et al. (2023) that ETBS
approximates: it keeps a draw counter per item and recomputes ``p ∝ exp(-count / temperature)`` over all
candidates at every call.
"""

from __future__ import annotations

import numpy as np

ETBS_MODES = ("etbs", "uniform", "reference")


def etbs_cdf(x: np.ndarray | float, n_eq: np.ndarray | float) -> np.ndarray:
    """Closed-form CDF of the skewed sampling density, thesis eq. 4.20.

    ``CDF_s(x) = [x (ln x - ln n - 1) + 2 (ln n - ln 2 + 1)] / (2 ln n - n - 2 ln 2 + 2)`` for ``2 <= x <= n``.
    It is the integral from 2 to x of ``p_s(t) ∝ ln n - ln t`` (eq. 4.17-4.19): 0 at ``x = 2`` and 1 at ``x = n``.

    :param x: evaluation points in ``[2, n_eq]``
    :param n_eq: the ``n`` of eq. 4.20; ETBS uses ``n_eq = size + 2`` (must be > 2, elementwise)
    :return: ``CDF_s(x)`` as float64, broadcast over ``x`` and ``n_eq``
    """
    x = np.asarray(x, dtype=np.float64)
    n = np.asarray(n_eq, dtype=np.float64)
    log_n = np.log(n)
    numerator = x * (np.log(x) - log_n - 1.0) + 2.0 * (log_n - np.log(2.0) + 1.0)
    denominator = 2.0 * log_n - n - 2.0 * np.log(2.0) + 2.0
    return numerator / denominator


def _check_temperature(temperature: float) -> None:
    if not 0.0 <= temperature <= 1.0:  # also rejects NaN
        raise ValueError(f"temperature must lie in [0, 1], got {temperature!r}")


def _check_mode(mode: str, allowed: tuple[str, ...] = ETBS_MODES) -> None:
    if mode not in allowed:
        raise ValueError(f"mode must be one of {allowed}, got {mode!r}")


def etbs_index_from_uniform(
    u: np.ndarray,
    size: np.ndarray | int,
    temperature: float,
    mode: str = "etbs",
    capacity: np.ndarray | int | None = None,
) -> np.ndarray:
    """ETBS index (thesis eq. 4.21) from given uniform numbers; the vectorised core of :func:`etbs_indices`.

    With ``x = 2 + size * u`` (so ``x ~ U[2, size + 2)``) and ``n_eq = size + 2``:
    ``index = floor(temperature * size * CDF_s(x) + (1 - temperature) * (x - 2))``, clamped to ``[0, size - 1]``
    (the clamp only guards against rounding). In ``"reference"`` mode the CDF term is
    ``min(CDF_s(x) * capacity, size - 1)`` instead, as in the public code. Arguments are not validated here.

    :param u: uniform numbers in ``[0, 1)``, any shape
    :param size: number of stored items (scalar or broadcastable to ``u``), each >= 1
    :param temperature: tau of eq. 4.21, in ``[0, 1]``
    :param mode: ``"etbs"``, ``"uniform"`` or ``"reference"``
    :param capacity: buffer capacity, only used (and required) by ``"reference"``
    :return: int64 indices, 0 = oldest, shape of ``u`` broadcast with ``size``
    """
    size_f = np.asarray(size, dtype=np.float64)
    offset = size_f * np.asarray(u, dtype=np.float64)  # x - 2, in [0, size)
    if mode == "uniform" or temperature == 0.0:
        index = offset
    else:
        # sizes of 1 give n_eq = 3, where eq. 4.20 is still finite; their index is clamped to 0 below
        cdf = etbs_cdf(offset + 2.0, size_f + 2.0)
        if mode == "reference":
            cdf_index = np.minimum(cdf * np.asarray(capacity, dtype=np.float64), size_f - 1.0)
        else:
            cdf_index = cdf * size_f
        index = temperature * cdf_index + (1.0 - temperature) * offset
    return np.clip(np.floor(index), 0.0, size_f - 1.0).astype(np.int64)


def etbs_indices(
    size: int,
    n: int,
    temperature: float,
    rng: np.random.Generator,
    mode: str = "etbs",
    capacity: int | None = None,
) -> np.ndarray:
    """Draw ``n`` time-balanced indices over ``size`` stored items, thesis eq. 4.20-4.21, O(1) per draw.

    Draws ``x ~ U[2, size + 2)``, maps it through the closed-form CDF of eq. 4.20 (:func:`etbs_cdf`, with
    ``n_eq = size + 2``), scales that by ``size`` and mixes with the uniform index by the temperature:
    ``index = tau * size * CDF_s(x) + (1 - tau) * (x - 2)`` (eq. 4.21). No per-item state is kept.

    :param size: number of stored items (>= 1)
    :param n: number of indices to draw (>= 0)
    :param temperature: tau of eq. 4.21 in ``[0, 1]``; 0 gives uniform indices, the thesis uses 0.3
    :param rng: numpy random generator to draw from
    :param mode: ``"etbs"`` (the thesis), ``"uniform"`` or ``"reference"`` (the public code's capacity scaling)
    :param capacity: buffer capacity (>= size); required by ``"reference"``, unused otherwise
    :return: int64 array of shape ``(n,)`` with values in ``[0, size)``, 0 = oldest item
    """
    _check_mode(mode)
    if int(size) != size or size < 1:
        raise ValueError(f"size must be an integer >= 1, got {size!r}")
    if int(n) != n or n < 0:
        raise ValueError(f"n must be an integer >= 0, got {n!r}")
    _check_temperature(temperature)
    if mode == "reference" and (capacity is None or capacity < size):
        raise ValueError(f"mode='reference' needs capacity >= size={size}, got capacity={capacity!r}")
    u = rng.random(int(n))
    if size == 1:
        return np.zeros(int(n), dtype=np.int64)
    return etbs_index_from_uniform(u, int(size), temperature, mode, capacity)


class CountBalancedSampler:
    """O(n) count-based time-balanced sampler in the spirit of Robine et al. (2023), thesis sections 4.1.3 and 4.5.

    Every item slot has a draw counter. A call recomputes ``p_i ∝ exp(-(count_i - min count) / temperature)``
    over all candidate items (O(n)), draws from it by inverse CDF, then adds the draws to the counters. Items
    that have been drawn less (usually the new ones) are therefore preferred; a small temperature pushes
    towards equal draw counts for all items, the "true uniform" replay that ETBS approximates in O(1).
    Probabilities are computed once per call, so the draws of one call are independent given the counters.

    The temperature is in units of draws per item. Robine et al. use a value of 20 in a setting where each
    item is drawn many times (every step of every sampled sequence is counted); with one draw per insert
    (thesis Fig. 4.9) values well below 1 are needed for a visible effect.

    :param capacity: number of item slots (ids ``0 .. capacity - 1``); a slot's counter is cleared with
        :meth:`clear` when a new item is written into it
    :param temperature: softmax temperature (> 0)
    """

    def __init__(self, capacity: int, temperature: float = 0.1):
        if int(capacity) != capacity or capacity < 1:
            raise ValueError(f"capacity must be an integer >= 1, got {capacity!r}")
        if not temperature > 0.0:
            raise ValueError(f"temperature must be > 0, got {temperature!r}")
        self.capacity = int(capacity)
        self.temperature = float(temperature)
        self.counts = np.zeros(self.capacity, dtype=np.int64)

    def clear(self, ids: np.ndarray | int) -> None:
        """Set the draw counters of the given item slots to zero (a new item was written there).

        :param ids: item slot ids
        """
        self.counts[ids] = 0

    def probabilities(self, candidates: np.ndarray) -> np.ndarray:
        """Sampling probabilities over the candidates, ``softmax(-counts / temperature)`` (O(n)).

        :param candidates: item slot ids, shape ``(n,)``
        :return: float64 probabilities, shape ``(n,)``, summing to 1
        """
        counts = self.counts[candidates]
        weights = np.exp(-(counts - counts.min()) / self.temperature)
        return weights / weights.sum()

    def draw_from_uniform(self, u: np.ndarray, candidates: np.ndarray) -> np.ndarray:
        """Draw one candidate per uniform number and count the draws.

        :param u: uniform numbers in ``[0, 1)``, shape ``(k,)``
        :param candidates: item slot ids to draw from, shape ``(n,)``, n >= 1
        :return: positions into ``candidates`` (int64, shape ``(k,)``)
        """
        if len(candidates) < 1:
            raise ValueError("candidates must hold at least one item id, got an empty array")
        counts = self.counts[candidates]
        cumulative = np.cumsum(np.exp(-(counts - counts.min()) / self.temperature))
        positions = np.searchsorted(cumulative, np.asarray(u) * cumulative[-1], side="right")
        positions = np.minimum(positions, len(candidates) - 1).astype(np.int64)
        np.add.at(self.counts, candidates[positions], 1)
        return positions

    def sample(self, size: int, n: int, rng: np.random.Generator) -> np.ndarray:
        """Draw ``n`` items from the growing list of items ``0 .. size - 1`` (item id = insertion order).

        :param size: number of stored items, ``1 <= size <= capacity``
        :param n: number of draws (>= 0)
        :param rng: numpy random generator
        :return: int64 item ids in ``[0, size)``, shape ``(n,)``
        """
        if int(size) != size or not 1 <= size <= self.capacity:
            raise ValueError(f"size must be an integer in [1, capacity={self.capacity}], got {size!r}")
        if int(n) != n or n < 0:
            raise ValueError(f"n must be an integer >= 0, got {n!r}")
        return self.draw_from_uniform(rng.random(int(n)), np.arange(int(size)))
