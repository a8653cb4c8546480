import math

import pytest
import torch as th

from sb3_hieros.agent.subgoal import SubgoalAutoencoder, max_cosine_subgoal_reward, novelty_reward


def test_encode_decode_shapes_and_modes():
    ae = SubgoalAutoencoder(16, hidden=32, layers=1)
    h = th.randn(5, 3, 16)
    g = ae.encode(h)
    assert g.shape == (5, 3, 8, 8) and ae.subgoal_shape == (8, 8) and ae.subgoal_dim == 64
    assert th.equal(g.detach().sum(-1), th.ones(5, 3, 8))
    assert ae.decode(g).shape == (5, 3, 16)
    assert th.allclose(ae.decode(g), ae.decode(g.reshape(5, 3, 64)))
    ae.eval()
    assert th.equal(ae.encode(h), ae.encode(h))  # mode in eval mode
    assert th.equal(ae.encode(h).argmax(-1), ae.dist(h).probs.argmax(-1))
    ae.train()
    samples = th.stack([ae.encode(h).detach() for _ in range(20)])
    assert not (samples == samples[0]).all()  # sampled in training mode
    assert th.equal(ae.encode(h, sample=False), ae.encode(h, sample=False))


def test_loss_is_reconstruction_plus_beta_kl():
    th.manual_seed(0)
    ae = SubgoalAutoencoder(12, n_cat=4, n_classes=5, hidden=16, layers=1, beta=0.5).eval()
    h = th.randn(7, 12)
    loss, metrics = ae.loss(h)
    rec = (ae(h) - h).pow(2).mean(-1)
    probs = ae.dist(h).probs
    kl = (probs * (probs.log() - math.log(1 / 5))).sum(-1).mean(-1)  # averaged over the 4 categoricals
    assert th.isclose(loss, (rec + 0.5 * kl).mean(), rtol=1e-5)
    assert th.isclose(metrics["subgoal_ae/reconstruction"], rec.mean(), rtol=1e-5)
    # the loss does not reach h
    hg = h.clone().requires_grad_(True)
    ae.loss(hg)[0].backward()
    assert hg.grad is None
    assert all(p.grad is not None for p in ae.parameters())


def test_autoencoder_learns_and_novelty_flags_outliers():
    th.manual_seed(0)
    ae = SubgoalAutoencoder(8, hidden=32, layers=1, beta=0.05)
    centre = th.randn(8)
    data = centre + 0.1 * th.randn(256, 8)
    opt = th.optim.Adam(ae.parameters(), lr=3e-3)
    first = None
    for _ in range(80):
        loss, _ = ae.loss(data)
        first = first if first is not None else loss.item()
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert loss.item() < 0.2 * first
    ae.eval()
    with th.no_grad():
        familiar = novelty_reward(centre + 0.1 * th.randn(32, 8), ae)
        outlier = novelty_reward(-3.0 * centre + th.randn(32, 8), ae)
    assert familiar.shape == (32,) and (familiar >= 0).all()
    assert outlier.min() > familiar.max()


def test_max_cosine_reward():
    gen = th.Generator().manual_seed(0)
    h = th.randn(5, 4, 16, generator=gen)  # (H+1, N, D)
    goal = th.randn(4, 16, generator=gen)  # (N, D), constant over the horizon
    r = max_cosine_subgoal_reward(h, goal)
    assert r.shape == (5, 4)
    assert (r >= -1).all() and (r <= 1).all()
    assert th.allclose(max_cosine_subgoal_reward(goal, goal), th.ones(4))
    assert th.allclose(max_cosine_subgoal_reward(-goal, goal), -th.ones(4))
    # same direction, different norm: the max in the denominator gives the norm ratio
    assert th.allclose(max_cosine_subgoal_reward(0.5 * goal, goal), th.full((4,), 0.5))
    assert th.allclose(max_cosine_subgoal_reward(2.0 * goal, goal), th.full((4,), 0.5))
    # equals cos * min/max of the norms
    hn, gn = h.norm(dim=-1), goal.norm(dim=-1)
    cos = th.nn.functional.cosine_similarity(h, goal.expand_as(h), dim=-1)
    assert th.allclose(r, cos * th.minimum(hn, gn) / th.maximum(hn, gn), atol=1e-6)
    assert max_cosine_subgoal_reward(th.zeros(3), th.zeros(3)) == 0.0
    with pytest.raises(ValueError, match="last"):
        max_cosine_subgoal_reward(h, th.randn(4, 15))


def test_bad_inputs():
    ae = SubgoalAutoencoder(16, hidden=8, layers=1)
    with pytest.raises(ValueError, match=r"h must have shape"):
        ae.encode(th.randn(3, 15))
    with pytest.raises(ValueError, match="subgoal must have shape"):
        ae.decode(th.randn(3, 8, 7))
    with pytest.raises(ValueError, match="beta"):
        SubgoalAutoencoder(16, beta=-1.0)
