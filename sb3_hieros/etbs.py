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

Beyond the thesis, :class:`MeanFieldCountSampler` reproduces the count-based sampler's draw-count profile in
O(1) per draw, from a mean-field analysis of the count process (:func:`meanfield_beta`,
:func:`meanfield_weight`): the closed form of eq. 4.20 does not reach that profile.
"""

from __future__ import annotations

import math

import numpy as np

ETBS_MODES = ("etbs", "uniform", "reference")
_LOG_2 = math.log(2.0)


def etbs_cdf(x: np.ndarray | float, n_eq: np.ndarray | float) -> np.ndarray:
    """Closed-form CDF of the skewed sampling density, thesis eq. 4.20.

    ``CDF_s(x) = [x (ln x - ln n - 1) + 2 (ln n - ln 2 + 1)] / (2 ln n - n - 2 ln 2 + 2)`` for ``2 <= x <= n``.
    It is the integral from 2 to x of ``p_s(t) ∝ ln n - ln t`` (eq. 4.17-4.19): 0 at ``x = 2`` and 1 at ``x = n``.

    :param x: evaluation points in ``[2, n_eq]``
    :param n_eq: the ``n`` of eq. 4.20; ETBS uses ``n_eq = size + 2`` (must be > 2, elementwise)
    :return: ``CDF_s(x)`` as float64, broadcast over ``x`` and ``n_eq``
    """
    x = np.asarray(x, dtype=np.float64)
    if isinstance(n_eq, (int, float, np.integer, np.floating)):
        # scalar n (the per-draw hot path): its terms once in Python, then in-place array operations
        n = float(n_eq)
        log_n = math.log(n)
        cdf = np.log(x)
        cdf -= log_n + 1.0
        cdf *= x
        cdf += 2.0 * (log_n - _LOG_2 + 1.0)
        cdf /= 2.0 * log_n - n - 2.0 * _LOG_2 + 2.0
        return cdf
    n = np.asarray(n_eq, dtype=np.float64)
    log_n = np.log(n)
    numerator = x * (np.log(x) - log_n - 1.0) + 2.0 * (log_n - _LOG_2 + 1.0)
    denominator = 2.0 * log_n - n - 2.0 * _LOG_2 + 2.0
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
    scalar = isinstance(size, (int, np.integer))
    size_f = float(size) if scalar else np.asarray(size, dtype=np.float64)
    offset = np.asarray(u, dtype=np.float64) * size_f  # x - 2, in [0, size)
    if mode == "uniform" or temperature == 0.0:
        index = offset
    else:
        # sizes of 1 give n_eq = 3, where eq. 4.20 is still finite; their index is clamped to 0 below
        index = etbs_cdf(offset + 2.0, size_f + 2.0)
        if mode == "reference":
            index *= np.asarray(capacity, dtype=np.float64)
            index = np.minimum(index, size_f - 1.0)
            index *= temperature
        else:
            index *= temperature * size_f
        offset *= 1.0 - temperature
        index += offset
    # index >= 0 up to rounding, so truncation is the floor (and a rounding error of -1e-16 gives 0)
    last = int(size) - 1 if scalar else np.asarray(size, dtype=np.int64) - 1
    return np.minimum(index.astype(np.int64), last)


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
        positions = self._draw(u, self.counts[candidates])
        np.add.at(self.counts, candidates[positions], 1)
        return positions

    def _draw(self, u: np.ndarray, counts: np.ndarray) -> np.ndarray:
        """Inverse-CDF draws from ``softmax(-counts / temperature)`` (O(n)); positions into ``counts``."""
        cumulative = np.cumsum(np.exp((counts.min() - counts) / self.temperature))
        positions = np.searchsorted(cumulative, np.asarray(u) * cumulative[-1], side="right")
        return np.minimum(positions, len(counts) - 1).astype(np.int64)

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
        ids = self._draw(rng.random(int(n)), self.counts[: int(size)])  # item id = position here
        np.add.at(self.counts, ids, 1)
        return ids


def _birth_rates(temperature: float, theta_max: float) -> np.ndarray:
    """Draw rates ``exp(-c / temperature)`` of an item with count c, up to where ``rate * theta_max < 1e-6``."""
    n_states = math.ceil(temperature * math.log(max(theta_max, 1.0) * 1e6)) + 2
    return np.exp(-np.arange(n_states) / temperature)


def meanfield_beta(temperature: float, draws_per_insert: float = 1.0) -> float:
    """Time-scale ``beta`` of the scale-free mean-field solution of the count-based sampler.

    With ``q_j = r_j / (r_j + 1 / beta)`` and ``r_j = exp(-j / temperature)``, ``beta`` solves
    ``sum_{c >= 0} prod_{j <= c} q_j = draws_per_insert`` (the Laplace transform of the expected sampling weight
    at ``1 / beta``, see :class:`MeanFieldCountSampler`). Uniform sampling (temperature -> inf, one draw per
    insert) gives ``beta = 1``.

    :param temperature: softmax temperature of the count-based sampler (> 0)
    :param draws_per_insert: draws per inserted item (> 0)
    :return: beta (> 0)
    """
    if not temperature > 0.0:
        raise ValueError(f"temperature must be > 0, got {temperature!r}")
    if not draws_per_insert > 0.0:
        raise ValueError(f"draws_per_insert must be > 0, got {draws_per_insert!r}")

    def laplace(log_lam: float) -> float:  # sum_c prod_{j <= c} q_j, decreasing in lambda
        # past c0 = T ln(1 / lambda) the log-products fall quadratically; 40 sqrt(T) more terms reach e^-800
        n_terms = math.ceil(temperature * max(0.0, -log_lam) + 40.0 * math.sqrt(temperature)) + 64
        log_q = -np.logaddexp(0.0, log_lam + np.arange(n_terms) / temperature)  # log(r_j / (r_j + lambda))
        return float(np.exp(np.cumsum(log_q)).sum())

    lo, hi, step = -1.0, 1.0, 1.0  # bracket of log(1 / beta), widened until it holds the root
    while laplace(lo) <= draws_per_insert and lo > -700.0:
        lo, step = lo - step, 2.0 * step
    step = 1.0
    while laplace(hi) > draws_per_insert and hi < 700.0:
        hi, step = hi + step, 2.0 * step
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if laplace(mid) > draws_per_insert:
            lo = mid
        else:
            hi = mid
    return math.exp(-0.5 * (lo + hi))


def meanfield_weight(theta: np.ndarray, temperature: float) -> np.ndarray:
    """Expected sampling weight ``E[exp(-count / temperature)]`` of an item after operational time ``theta``.

    The count of one item is a pure-birth process with rates ``r_c = exp(-c / temperature)`` in operational time;
    its state probabilities follow ``P_c' = r_{c-1} P_{c-1} - r_c P_c`` from ``P = (1, 0, ...)``. They are
    integrated along the increasing grid ``theta`` (starting at 0) with an exponential integrator (each state's
    decay exact, its inflow linear over a step, predictor-corrector), vectorised over the states. The weight is
    ``sum_c r_c P_c``, which is also the rate at which the expected count grows.

    :param theta: increasing grid of operational times, ``theta[0] == 0``
    :param temperature: softmax temperature of the count-based sampler
    :return: weights on the grid, shape of ``theta``
    """
    theta = np.asarray(theta, dtype=np.float64)
    rates = _birth_rates(temperature, float(theta[-1]))
    probs = np.zeros_like(rates)
    probs[0] = 1.0
    weights = np.empty_like(theta)
    weights[0] = 1.0
    for k, h in enumerate(np.diff(theta)):
        rh = rates * h
        small = rh < 1e-4
        safe_r = np.where(small, 1.0, rates)
        phi1 = np.where(small, h * (1.0 - rh / 2.0), -np.expm1(-rh) / safe_r)  # int_0^h e^{-r (h - u)} du
        phi2 = np.where(small, h * (0.5 - rh / 6.0), (h - phi1) / np.where(small, 1.0, rh))  # ... * u / h du
        decay = np.exp(-rh)
        inflow = np.concatenate([[0.0], rates[:-1] * probs[:-1]])
        predicted = decay * probs + phi1 * inflow
        inflow_new = np.concatenate([[0.0], rates[:-1] * predicted[:-1]])
        probs = decay * probs + phi1 * inflow + phi2 * (inflow_new - inflow)
        weights[k + 1] = rates @ probs
    return weights


class MeanFieldCountSampler:
    """O(1)-per-draw sampler with the draw-count profile of :class:`CountBalancedSampler` (beyond the thesis).

    Mean-field analysis of the count-based sampler (``p_i ∝ exp(-count_i / T)``, ``d`` draws per insert): in the
    operational time ``theta(s) = d * sum_{t <= s} 1 / Z(t)`` (Z the softmax normaliser) the count of every item
    is the same pure-birth process, so item i's expected weight at step s is ``w(theta(s) - theta(i))``
    (:func:`meanfield_weight`). The ansatz ``theta(s) = beta * ln(s)`` is self-consistent for the ``beta`` of
    :func:`meanfield_beta`, and then a draw's relative position ``v = i / s`` (``0 = oldest, 1 = newest``) has the
    density ``∝ w(-beta ln v)``, the same at every buffer size. That density is tabulated once (in
    ``t = -ln v``) and sampled by inverse CDF: O(log K) per draw for a fixed table of K points, independent of
    the buffer size and with no per-item counters. It is asymptotic (large buffers) and replaces Z by its mean.

    :param temperature: softmax temperature T of the count-based sampler to imitate (> 0)
    :param draws_per_insert: draws per inserted item d (> 0)
    :param grid_points: points of the tabulated inverse CDF
    """

    def __init__(self, temperature: float, draws_per_insert: float = 1.0, grid_points: int = 4000):
        if int(grid_points) != grid_points or grid_points < 2:
            raise ValueError(f"grid_points must be an integer >= 2, got {grid_points!r}")
        self.temperature = float(temperature)
        self.draws_per_insert = float(draws_per_insert)
        self.beta = meanfield_beta(self.temperature, self.draws_per_insert)
        t = np.concatenate([[0.0], np.geomspace(1e-8, 40.0, int(grid_points))])  # t = -ln v
        density = meanfield_weight(self.beta * t, self.temperature) * np.exp(-t)
        cdf = np.concatenate([[0.0], np.cumsum((density[1:] + density[:-1]) / 2.0 * np.diff(t))])
        # the exact normaliser is d / beta; the ratio checks the tabulation
        self.normaliser_error = float(cdf[-1] * self.beta / self.draws_per_insert - 1.0)
        self.t_grid = t
        self.cdf = cdf / cdf[-1]

    def index_from_uniform(self, u: np.ndarray, size: np.ndarray | int) -> np.ndarray:
        """Indices (0 = oldest) for uniform numbers ``u`` in buffers of ``size`` items, O(1) per draw.

        :param u: uniform numbers in ``[0, 1)``
        :param size: number of stored items (>= 1), scalar or broadcastable to ``u``
        :return: int64 indices in ``[0, size)``
        """
        v = np.exp(-np.interp(u, self.cdf, self.t_grid))  # relative position, 1 = newest
        last = np.asarray(size, dtype=np.int64) - 1
        return np.minimum((v * np.asarray(size, dtype=np.float64)).astype(np.int64), last)

    def sample(self, size: int, n: int, rng: np.random.Generator) -> np.ndarray:
        """Draw ``n`` indices over ``size`` stored items (0 = oldest).

        :param size: number of stored items (>= 1)
        :param n: number of draws (>= 0)
        :param rng: numpy random generator
        :return: int64 indices in ``[0, size)``, shape ``(n,)``
        """
        if int(size) != size or size < 1:
            raise ValueError(f"size must be an integer >= 1, got {size!r}")
        if int(n) != n or n < 0:
            raise ValueError(f"n must be an integer >= 0, got {n!r}")
        return self.index_from_uniform(rng.random(int(n)), int(size))
