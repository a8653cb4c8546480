import math

import pytest
import torch as th

from sb3_hieros.nn.distributions import (
    BoundedNormal,
    ContinueBernoulli,
    OneHotCategoricalST,
    TwoHotSymlog,
    bins_are_antisymmetric,
    categorical_kl,
    sample_categorical_index,
    symexp,
    symlog,
    symlog_bins,
    symlog_mse,
    two_hot_encode,
    unimix_probs,
)


def test_symlog_symexp_inverse():
    x = th.tensor([-1e6, -100.0, -1.0, -1e-3, 0.0, 1e-3, 0.5, 3.0, 1e4], dtype=th.float64)
    assert th.allclose(symexp(symlog(x)), x, rtol=1e-12, atol=0)
    assert symlog(th.tensor(0.0)) == 0.0
    assert th.allclose(symlog(th.tensor(math.e - 1)), th.tensor(1.0))
    assert th.equal(th.sign(symlog(x)), th.sign(x))


def test_two_hot_round_trip_and_support():
    bins = symlog_bins(255)
    assert bins.shape == (255,) and bins[127] == 0.0 and bins[0] == -20.0 and bins[-1] == 20.0
    x = th.tensor([-1e5, -523.7, -3.3, -0.01, 0.0, 0.01, 0.37, 1.0, 42.0, 1e5, 3e8])
    enc = two_hot_encode(x, bins)
    assert enc.shape == (len(x), 255)
    assert th.allclose(enc.sum(-1), th.ones(len(x)))
    assert ((enc > 0).sum(-1) <= 2).all() and (enc >= 0).all()
    decoded = symexp((enc * bins).sum(-1))
    assert th.allclose(decoded, x, rtol=1e-5, atol=1e-6)
    # logits that put all mass on the encoding decode to the same value
    dist = TwoHotSymlog(th.log(enc.clamp_min(1e-30)), bins)
    assert th.allclose(dist.mean, x, rtol=1e-4, atol=1e-5)
    # out of range is clamped to the end bin
    big = two_hot_encode(th.tensor([1e30]), bins)
    assert big[0, -1] == 1.0


def test_two_hot_log_prob_is_cross_entropy_and_uniform_decodes_to_zero():
    bins = symlog_bins(255)
    logits = th.zeros(4, 255)
    dist = TwoHotSymlog(logits, bins)
    assert th.equal(dist.mean, th.zeros(4))  # exact zero for a zero-initialised head
    target = th.tensor([0.0, 1.5, -7.0, 300.0])
    assert th.allclose(dist.log_prob(target), th.full((4,), -math.log(255)), atol=1e-5)
    # gradient descent on the cross-entropy fits the target
    logits = th.zeros(3, 255, requires_grad=True)
    target = th.tensor([-12.0, 0.5, 1000.0])
    opt = th.optim.Adam([logits], lr=0.5)
    for _ in range(200):
        opt.zero_grad()
        (-TwoHotSymlog(logits, bins).log_prob(target)).sum().backward()
        opt.step()
    assert th.allclose(TwoHotSymlog(logits, bins).mean, target, rtol=0.05)


def test_inverse_cdf_sampler_matches_probabilities():
    gen = th.Generator().manual_seed(0)
    probs = th.tensor([0.05, 0.4, 0.0, 0.25, 0.3])
    n = 200_000
    idx = sample_categorical_index(probs.expand(n, 5), generator=gen)
    counts = th.bincount(idx, minlength=5).double()
    expected = probs.double() * n
    assert counts[2] == 0  # zero-probability class never drawn
    mask = expected > 0
    chi2 = (((counts - expected) ** 2) / expected)[mask].sum().item()
    # 3 degrees of freedom: P(chi2 > 25) < 1e-4
    assert chi2 < 25.0, chi2
    # rounding guard: never returns K even when cumsum < u
    assert sample_categorical_index(th.full((1000, 3), 0.3), generator=gen).max() <= 2


def test_one_hot_st_sample_mode_and_gradients():
    gen = th.Generator().manual_seed(1)
    logits = th.randn(6, 4, 5, requires_grad=True)
    dist = OneHotCategoricalST(logits, unimix=0.01, event_ndims=1)
    sample = dist.sample(generator=gen)
    assert sample.shape == (6, 4, 5)
    assert th.equal(sample.detach().sum(-1), th.ones(6, 4))
    assert set(sample.detach().unique().tolist()) <= {0.0, 1.0}
    # straight-through: the gradient of a sample is the gradient of the probabilities
    weights = th.randn(6, 4, 5)
    expected = th.autograd.grad((dist.probs * weights).sum(), logits, retain_graph=True)[0]
    (sample * weights).sum().backward()
    assert th.allclose(logits.grad, expected)
    assert logits.grad.abs().sum() > 0
    mode = dist.mode()
    assert th.equal(mode.detach().argmax(-1), logits.detach().argmax(-1))
    assert dist.log_prob(mode.detach()).shape == (6,)
    assert dist.entropy().shape == (6,)


def test_unimix_floor_and_entropy():
    logits = th.tensor([[100.0, 0.0, 0.0, 0.0]])
    probs = unimix_probs(logits, 0.01)
    assert th.allclose(probs.sum(-1), th.ones(1))
    assert (probs >= 0.01 / 4 - 1e-7).all()
    uniform = OneHotCategoricalST(th.zeros(2, 8), unimix=0.01)
    assert th.allclose(uniform.entropy(), th.full((2,), math.log(8)))
    no_mix = OneHotCategoricalST(th.tensor([[1000.0, 0.0, 0.0]]), unimix=0.0)
    assert th.isfinite(no_mix.entropy()).all()
    with pytest.raises(ValueError, match="unimix"):
        unimix_probs(logits, 1.0)


def test_categorical_kl():
    p = th.randn(3, 4, 6)
    assert th.allclose(categorical_kl(p, p), th.zeros(3), atol=1e-6)
    q = th.randn(3, 4, 6)
    kl = categorical_kl(p, q)
    assert kl.shape == (3,) and (kl > 0).all()
    # sum over groups of the per-group KL, matching torch.distributions
    ref = th.distributions.kl_divergence(
        th.distributions.Categorical(logits=p), th.distributions.Categorical(logits=q)
    ).sum(-1)
    assert th.allclose(kl, ref, atol=1e-5)
    # uniform prior broadcasts; KL to uniform = log K - entropy
    kl_u = categorical_kl(p, th.zeros(6))
    ent = th.distributions.Categorical(logits=p).entropy().sum(-1)
    assert th.allclose(kl_u, 4 * math.log(6) - ent, atol=1e-5)
    assert categorical_kl(p[:, 0], q[:, 0], group_dims=0).shape == (3,)
    with pytest.raises(ValueError, match="class dims"):
        categorical_kl(p, th.zeros(5))


def test_bounded_normal():
    gen = th.Generator().manual_seed(2)
    mean_raw = (th.randn(512, 3, generator=gen) * 5).requires_grad_()
    std_raw = th.randn(512, 3, generator=gen) * 5
    dist = BoundedNormal(mean_raw, std_raw, min_std=0.1, max_std=1.0)
    assert (dist.std >= 0.1).all() and (dist.std <= 1.0).all()
    x = dist.rsample(generator=gen)
    assert x.shape == (512, 3)
    assert (x >= -1).all() and (x <= 1).all()
    assert (dist.mode().abs() <= 1).all()
    x.sum().backward()  # reparameterised with a straight-through clip: d x / d mean_raw = 1 - tanh^2 >= 0
    assert (mean_raw.grad >= 0).all() and (mean_raw.grad > 0).any()
    # log_prob / entropy against torch's Normal
    a = th.rand(512, 3) * 2 - 1
    ref = th.distributions.Normal(dist.mean, dist.std)
    assert th.allclose(dist.log_prob(a), ref.log_prob(a).sum(-1), atol=1e-5)
    assert th.allclose(dist.entropy(), ref.entropy().sum(-1), atol=1e-5)
    with pytest.raises(ValueError, match="min_std"):
        BoundedNormal(th.zeros(1), th.zeros(1), min_std=1.0, max_std=0.5)


def test_continue_bernoulli():
    logits = th.tensor([-3.0, 0.0, 2.0])
    dist = ContinueBernoulli(logits)
    assert th.allclose(dist.mean, th.sigmoid(logits))
    assert th.equal(dist.mode(), th.tensor([0.0, 0.0, 1.0]))
    target = th.tensor([0.0, 1.0, 1.0])
    ref = th.distributions.Bernoulli(logits=logits)
    assert th.allclose(dist.log_prob(target), ref.log_prob(target))
    assert th.allclose(dist.entropy(), ref.entropy())
    with pytest.raises(ValueError, match="target shape"):
        dist.log_prob(th.zeros(2))


def test_symlog_mse():
    target = th.tensor([[0.0, 10.0], [-3.0, 1.0]])
    assert th.allclose(symlog_mse(symlog(target), target), th.zeros(2))
    loss = symlog_mse(th.zeros(2, 2), target)
    assert th.allclose(loss, symlog(target).pow(2).sum(-1))
    assert symlog_mse(th.zeros(2, 2), target, event_ndims=0).shape == (2, 2)


def test_bad_inputs():
    bins = symlog_bins(255)
    with pytest.raises(ValueError, match="last dim 255"):
        TwoHotSymlog(th.zeros(3, 254), bins)
    with pytest.raises(ValueError, match="target shape"):
        TwoHotSymlog(th.zeros(3, 255), bins).log_prob(th.zeros(4))
    with pytest.raises(ValueError, match="odd"):
        symlog_bins(256)
    with pytest.raises(ValueError, match="one_hot shape"):
        OneHotCategoricalST(th.zeros(3, 4)).log_prob(th.zeros(3, 5))
    with pytest.raises(ValueError, match="event_ndims"):
        OneHotCategoricalST(th.zeros(4), event_ndims=1)
    with pytest.raises(ValueError, match="must match"):
        BoundedNormal(th.zeros(2, 3), th.zeros(2, 2))
    with pytest.raises(ValueError, match="must match"):
        symlog_mse(th.zeros(2, 3), th.zeros(3, 2))


def test_given_bin_symmetry_reads_out_as_the_checked_one():
    bins = symlog_bins(255)
    assert bins_are_antisymmetric(bins)
    assert not bins_are_antisymmetric(th.linspace(-1.0, 2.0, 255))
    assert not bins_are_antisymmetric(th.linspace(-1.0, 1.0, 254))
    logits = th.randn(6, 255)
    checked = TwoHotSymlog(logits, bins).mean
    assert th.equal(TwoHotSymlog(logits, bins, antisymmetric=True).mean, checked)
    assert th.equal(TwoHotSymlog(th.zeros(2, 255), bins, antisymmetric=True).mean, th.zeros(2))
    # the plain sum for bins that are not antisymmetric
    skewed = th.linspace(-1.0, 2.0, 255)
    assert th.allclose(TwoHotSymlog(logits, skewed, antisymmetric=False).mean, TwoHotSymlog(logits, skewed).mean)
