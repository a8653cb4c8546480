import itertools

import numpy as np
import pytest

from sb3_hieros.etbs import (
    CountBalancedSampler,
    MeanFieldCountSampler,
    etbs_cdf,
    etbs_index_from_uniform,
    etbs_indices,
    meanfield_beta,
)

# 99.9% quantile of the chi-square distribution with 9 degrees of freedom (10 deciles)
CHI2_9_999 = 27.877


def chi_square(observed: np.ndarray, probabilities: np.ndarray) -> float:
    expected = observed.sum() * probabilities
    return float(((observed - expected) ** 2 / expected).sum())


def decile_counts(indices: np.ndarray, size: int) -> np.ndarray:
    return np.bincount(indices * 10 // size, minlength=10)


def analytic_decile_probabilities(size: int, temperature: float) -> np.ndarray:
    """P(index in decile k) from eq. 4.21: index = floor(g(x)), g increasing, x = 2 + size * u."""

    def g(x):
        return temperature * size * etbs_cdf(x, size + 2) + (1 - temperature) * (x - 2)

    edges = np.arange(11) * size // 10
    lo, hi = np.full(11, 2.0), np.full(11, size + 2.0)
    for _ in range(100):  # bisection for g(x) = edge
        mid = (lo + hi) / 2
        below = g(mid) < edges
        lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
    cdf_at_edges = (lo - 2) / size  # P(g(x) < edge) = P(index < edge)
    return np.diff(cdf_at_edges)


def old_new_ratio(counts: np.ndarray) -> float:
    tenth = len(counts) // 10
    return counts[:tenth].mean() / counts[-tenth:].mean()


def test_cdf_matches_integral_of_skewed_density():
    n = 500.0
    x = np.linspace(2, n, 20001)
    density = (np.log(n) - np.log(x)) / (-2 * np.log(n) + n + 2 * np.log(2) - 2)  # eq. 4.17
    integral = np.concatenate([[0.0], np.cumsum((density[1:] + density[:-1]) / 2 * np.diff(x))])
    np.testing.assert_allclose(etbs_cdf(x, n), integral, atol=1e-6)
    assert etbs_cdf(2.0, n) == pytest.approx(0.0, abs=1e-12)
    assert etbs_cdf(n, n) == pytest.approx(1.0)


@pytest.mark.parametrize("mode", ["etbs", "uniform", "reference"])
@pytest.mark.parametrize("size", [1, 2, 7, 1000])
@pytest.mark.parametrize("temperature", [0.0, 0.3, 1.0])
def test_index_range_and_dtype(mode, size, temperature):
    rng = np.random.default_rng(0)
    idx = etbs_indices(size, 5000, temperature, rng, mode=mode, capacity=10 * size)
    assert idx.dtype == np.int64
    assert idx.shape == (5000,)
    assert idx.min() >= 0
    assert idx.max() < size
    if size == 1:
        assert not idx.any()
    assert etbs_indices(size, 0, temperature, rng, mode=mode, capacity=size).shape == (0,)


def test_reproducible_with_same_generator_seed():
    a = etbs_indices(1000, 64, 0.3, np.random.default_rng(3))
    b = etbs_indices(1000, 64, 0.3, np.random.default_rng(3))
    np.testing.assert_array_equal(a, b)


def test_vectorised_core_accepts_per_draw_sizes():
    u = np.random.default_rng(1).random(100)
    sizes = np.arange(1, 101)
    together = etbs_index_from_uniform(u, sizes, 0.3)
    one_by_one = [etbs_index_from_uniform(u[i : i + 1], int(sizes[i]), 0.3)[0] for i in range(100)]
    np.testing.assert_array_equal(together, one_by_one)
    assert (together < sizes).all()


@pytest.mark.parametrize("mode", ["etbs", "uniform"])
def test_temperature_zero_and_uniform_mode_are_uniform(mode):
    size, n = 1000, 200_000
    idx = etbs_indices(size, n, 0.0 if mode == "etbs" else 0.7, np.random.default_rng(4), mode=mode)
    assert chi_square(decile_counts(idx, size), np.full(10, 0.1)) < CHI2_9_999
    # the index itself is uniform, not only its deciles
    assert chi_square(np.bincount(idx % 10, minlength=10), np.full(10, 0.1)) < CHI2_9_999


@pytest.mark.parametrize("temperature", [1.0, 0.3])
def test_deciles_match_closed_form(temperature):
    size, n = 1000, 200_000
    probabilities = analytic_decile_probabilities(size, temperature)
    assert probabilities.sum() == pytest.approx(1.0)
    idx = etbs_indices(size, n, temperature, np.random.default_rng(5))
    assert chi_square(decile_counts(idx, size), probabilities) < CHI2_9_999
    # and the distribution is not uniform: newer items are preferred
    assert chi_square(decile_counts(idx, size), np.full(10, 0.1)) > 10 * CHI2_9_999
    assert probabilities[-1] > probabilities[0]


def test_closed_form_at_temperature_one_favours_the_newest_decile():
    # the reference's N-scaling gives P(index >= 0.9 N) = 0.412 at tau = 1
    assert analytic_decile_probabilities(10_000, 1.0)[-1] == pytest.approx(0.412, abs=0.01)


def test_growing_buffer_balances_old_and_new_items():
    inserts, draws_per_insert = 3000, 4
    ratios = {}
    for name, temperature in [("uniform", 0.0), ("etbs", 0.3), ("etbs1", 1.0)]:
        rng = np.random.default_rng(6)
        counts = np.zeros(inserts, dtype=np.int64)
        for size in range(1, inserts + 1):
            np.add.at(counts, etbs_indices(size, draws_per_insert, temperature, rng), 1)
        assert counts.sum() == inserts * draws_per_insert
        ratios[name] = old_new_ratio(counts)
    assert ratios["uniform"] > 20  # ln-shaped oversampling of old items
    assert ratios["etbs"] < 0.6 * ratios["uniform"]
    assert ratios["etbs1"] < 0.2 * ratios["uniform"]


def test_reference_mode_rarely_draws_the_oldest_items_when_far_from_capacity():
    size, n = 1000, 50_000
    rng = np.random.default_rng(7)
    reference = etbs_indices(size, n, 0.3, rng, mode="reference", capacity=1_000_000)
    thesis = etbs_indices(size, n, 0.3, rng, mode="etbs")
    assert (reference < 0.3 * size).mean() < 0.01
    assert (thesis < 0.3 * size).mean() > 0.15
    # at capacity the two scalings agree, up to the reference's clamp of the CDF index to size - 1
    same_u = np.random.default_rng(8).random(1000)
    difference = etbs_index_from_uniform(same_u, size, 0.3, "etbs") - etbs_index_from_uniform(
        same_u, size, 0.3, "reference", capacity=size
    )
    assert set(np.unique(difference)) <= {0, 1}
    assert (difference == 0).mean() > 0.9


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(size=0), "size"),
        (dict(size=-3), "size"),
        (dict(size=2.5), "size"),
        (dict(n=-1), "n must"),
        (dict(temperature=-0.1), "temperature"),
        (dict(temperature=1.5), "temperature"),
        (dict(temperature=float("nan")), "temperature"),
        (dict(mode="greedy"), "mode"),
        (dict(mode="reference"), "capacity"),
        (dict(mode="reference", capacity=5), "capacity"),
    ],
)
def test_bad_input_raises(kwargs, match):
    args = dict(size=10, n=4, temperature=0.3, rng=np.random.default_rng(0)) | kwargs
    with pytest.raises(ValueError, match=match):
        etbs_indices(**args)


def test_count_sampler_prefers_rarely_drawn_items():
    sampler = CountBalancedSampler(capacity=4, temperature=1.0)
    sampler.counts[:] = [3, 0, 1, 0]
    p = sampler.probabilities(np.arange(4))
    assert p.sum() == pytest.approx(1.0)
    np.testing.assert_allclose(p / p[1], np.exp([-3.0, 0.0, -1.0, 0.0]))
    positions = sampler.draw_from_uniform(np.array([0.0, 0.999]), np.array([2, 3]))
    np.testing.assert_array_equal(positions, [0, 1])
    np.testing.assert_array_equal(sampler.counts, [3, 0, 2, 1])
    sampler.clear(np.array([0, 2]))
    np.testing.assert_array_equal(sampler.counts, [0, 0, 0, 1])


def test_count_sampler_balances_a_growing_buffer():
    inserts = 2000
    sampler = CountBalancedSampler(capacity=inserts, temperature=0.1)
    rng = np.random.default_rng(9)
    for size in range(1, inserts + 1):
        idx = sampler.sample(size, 1, rng)
        assert 0 <= idx[0] < size
    assert sampler.counts.sum() == inserts
    uniform = np.zeros(inserts)
    for size in range(1, inserts + 1):
        uniform[rng.integers(size)] += 1
    assert old_new_ratio(sampler.counts) < 1.5 < 20 < old_new_ratio(uniform)


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda: CountBalancedSampler(0), "capacity"),
        (lambda: CountBalancedSampler(5, temperature=0.0), "temperature"),
        (lambda: CountBalancedSampler(5).sample(6, 1, np.random.default_rng(0)), "size"),
        (lambda: CountBalancedSampler(5).sample(3, -1, np.random.default_rng(0)), "n must"),
        (lambda: CountBalancedSampler(5).draw_from_uniform(np.zeros(1), np.array([], dtype=np.int64)), "candidates"),
    ],
)
def test_count_sampler_bad_input(call, match):
    with pytest.raises(ValueError, match=match):
        call()


def test_meanfield_beta_limits_and_monotonicity():
    assert meanfield_beta(1e4) == pytest.approx(1.0, abs=1e-3)  # uniform sampling: theta = ln(s)
    assert meanfield_beta(1e4, draws_per_insert=4.0) == pytest.approx(4.0, rel=1e-3)
    betas = [meanfield_beta(t) for t in (3.0, 1.0, 0.3, 0.1)]
    assert all(a < b for a, b in itertools.pairwise(betas))
    assert meanfield_beta(1.0, 4.0) > meanfield_beta(1.0, 1.0)


@pytest.mark.parametrize("temperature, draws", [(1.0, 1.0), (0.3, 4.0)])
def test_meanfield_sampler_range_and_tabulation(temperature, draws):
    sampler = MeanFieldCountSampler(temperature, draws)
    assert abs(sampler.normaliser_error) < 1e-3  # the tabulated density integrates to the exact d / beta
    rng = np.random.default_rng(0)
    for size in (1, 2, 1000):
        idx = sampler.sample(size, 4000, rng)
        assert idx.dtype == np.int64 and idx.shape == (4000,)
        assert 0 <= idx.min() and idx.max() < size
    assert (sampler.sample(1000, 4000, rng) >= 500).mean() > 0.5  # newer half preferred


def test_meanfield_sampler_matches_count_based_profile():
    inserts, seeds, temperature = 2000, 4, 0.3
    count_profile, meanfield_profile = np.zeros(10), np.zeros(10)
    meanfield = MeanFieldCountSampler(temperature)
    for seed in range(seeds):
        rng = np.random.default_rng(seed)
        counter = CountBalancedSampler(inserts, temperature)
        counts = np.zeros(inserts)
        for size in range(1, inserts + 1):
            counter.sample(size, 1, rng)
            counts[meanfield.sample(size, 1, rng)] += 1
        count_profile += counter.counts.reshape(10, -1).mean(axis=1)
        meanfield_profile += counts.reshape(10, -1).mean(axis=1)
    np.testing.assert_allclose(meanfield_profile, count_profile, rtol=0.1)
    uniform_like = np.log(10.0)  # roughly the oldest decile of uniform sampling
    assert count_profile[0] / seeds < uniform_like


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda: meanfield_beta(0.0), "temperature"),
        (lambda: meanfield_beta(1.0, 0.0), "draws_per_insert"),
        (lambda: MeanFieldCountSampler(1.0, grid_points=1), "grid_points"),
        (lambda: MeanFieldCountSampler(1.0).sample(0, 1, np.random.default_rng(0)), "size"),
    ],
)
def test_meanfield_bad_input(call, match):
    with pytest.raises(ValueError, match=match):
        call()
