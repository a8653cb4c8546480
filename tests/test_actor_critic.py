import math

import pytest
import torch as th

from sb3_hieros.agent.actor_critic import (
    Actor,
    ActorCritic,
    Critic,
    ReplaySequences,
    ReturnNormalizer,
    actor_input,
    actor_input_dim,
    cumulative_discount,
    lambda_returns,
)
from sb3_hieros.agent.returns import replay_lambda_returns
from sb3_hieros.nn.distributions import symlog

# ---------------------------------------------------------------------------------------------------------------------
# lambda-returns
# ---------------------------------------------------------------------------------------------------------------------


def test_lambda_returns_hand_computed():
    # H = 3, gamma = 0.5, lambda = 0.5; rewards[t] = r_{t+1}, values[t] = v(s_t), continues[t] = c_{t+1}, boot = v(s_3)
    rewards = th.tensor([1.0, 2.0, 3.0])
    values = th.tensor([10.0, 20.0, 30.0])
    boot = th.tensor(40.0)
    # R_2 = 3 + 0.5 * 40                           = 23
    # R_1 = 2 + 0.5 * (0.5 * 30 + 0.5 * 23)        = 2 + 0.5 * 26.5  = 15.25
    # R_0 = 1 + 0.5 * (0.5 * 20 + 0.5 * 15.25)     = 1 + 0.5 * 17.625 = 9.8125
    ret = lambda_returns(rewards, values, th.ones(3), boot, discount=0.5, lambda_=0.5)
    assert th.allclose(ret, th.tensor([9.8125, 15.25, 23.0]))
    # an episode end at s_2 (c_2 = 0): R_1 = 2, R_0 = 1 + 0.5 * (0.5 * 20 + 0.5 * 2) = 6.5, R_2 unchanged
    ret = lambda_returns(rewards, values, th.tensor([1.0, 0.0, 1.0]), boot, discount=0.5, lambda_=0.5)
    assert th.allclose(ret, th.tensor([6.5, 2.0, 23.0]))


def test_lambda_returns_limits_and_batch():
    gen = th.Generator().manual_seed(0)
    rewards, values, cont = (th.rand(5, 4, 2, generator=gen) for _ in range(3))
    boot = th.rand(4, 2, generator=gen)
    gamma = 0.9
    next_values = th.cat([values[1:], boot[None]])
    td0 = lambda_returns(rewards, values, cont, boot, gamma, 0.0)
    assert th.allclose(td0, rewards + gamma * cont * next_values)
    mc = lambda_returns(rewards, values, cont, boot, gamma, 1.0)
    expected = boot
    for t in reversed(range(5)):
        expected = rewards[t] + gamma * cont[t] * expected
        assert th.allclose(mc[t], expected)
    # batch elements are independent
    one = lambda_returns(rewards[:, 1, 0], values[:, 1, 0], cont[:, 1, 0], boot[1, 0], gamma, 0.95)
    assert th.allclose(lambda_returns(rewards, values, cont, boot, gamma, 0.95)[:, 1, 0], one)


def test_lambda_returns_bad_shapes():
    x = th.zeros(3, 2)
    with pytest.raises(ValueError, match="same"):
        lambda_returns(x, th.zeros(3, 3), x, th.zeros(2))
    with pytest.raises(ValueError, match="bootstrap"):
        lambda_returns(x, x, x, th.zeros(3))
    with pytest.raises(ValueError, match="lambda_"):
        lambda_returns(x, x, x, th.zeros(2), lambda_=1.5)
    with pytest.raises(ValueError, match="cut must have the shape"):
        lambda_returns(x, x, x, th.zeros(2), cut=th.zeros(2, 2, dtype=th.bool))


def test_replay_lambda_returns_hand_computed_and_cut_at_episode_starts():
    # T = 4, gamma = 0.5, lambda = 0.5; rewards[t] = r_t received with s_t, boot[t] = b_t
    rewards = th.tensor([9.0, 1.0, 2.0, 3.0])
    boot = th.tensor([10.0, 20.0, 30.0, 40.0])
    # R_3 = b_3                                     = 40
    # R_2 = 3 + 0.5 * (0.5 * 40 + 0.5 * 40)         = 23
    # R_1 = 2 + 0.5 * (0.5 * 30 + 0.5 * 23)         = 15.25
    # R_0 = 1 + 0.5 * (0.5 * 20 + 0.5 * 15.25)      = 9.8125 (r_0 = 9 is not used)
    ret, valid = replay_lambda_returns(rewards, th.ones(4), th.zeros(4, dtype=th.bool), boot, 0.5, 0.5)
    assert th.allclose(ret, th.tensor([9.8125, 15.25, 23.0, 40.0]))
    assert valid.tolist() == [True, True, True, False]
    # s_2 starts a new episode: R_1 = b_1 (no target of its own), R_0 = 1 + 0.5 * (0.5 * 20 + 0.5 * 20) = 11
    first = th.tensor([False, False, True, False])
    ret, valid = replay_lambda_returns(rewards, th.ones(4), first, boot, 0.5, 0.5)
    assert th.allclose(ret, th.tensor([11.0, 20.0, 23.0, 40.0]))
    assert valid.tolist() == [True, False, True, False]
    # s_2 terminal (c_2 = 0): R_1 = r_2 = 2, R_0 = 1 + 0.5 * (0.5 * 20 + 0.5 * 2) = 6.5
    ret, _ = replay_lambda_returns(rewards, th.tensor([1.0, 1.0, 0.0, 1.0]), th.zeros(4, dtype=th.bool), boot, 0.5, 0.5)
    assert th.allclose(ret[:2], th.tensor([6.5, 2.0]))
    with pytest.raises(ValueError, match="bootstrap must have the shape"):
        replay_lambda_returns(rewards, th.ones(4), first, boot[:3])
    with pytest.raises(ValueError, match="T >= 2"):
        replay_lambda_returns(rewards[:1], th.ones(1), first[:1], boot[:1])


def test_cumulative_discount():
    cont = th.tensor([[1.0], [1.0], [0.0], [1.0]])
    w = cumulative_discount(cont, 0.5)
    assert th.allclose(w[:, 0], th.tensor([1.0, 0.5, 0.0, 0.0]))


# ---------------------------------------------------------------------------------------------------------------------
# return normalisation
# ---------------------------------------------------------------------------------------------------------------------


def test_return_normalizer_percentiles_and_ema():
    returns = th.arange(0.0, 101.0)  # 5th percentile = 5, 95th = 95
    norm = ReturnNormalizer(decay=0.0)
    offset, scale = norm(returns)
    assert th.isclose(offset, th.tensor(5.0)) and th.isclose(scale, th.tensor(90.0))
    ema = ReturnNormalizer(decay=0.99)
    _, scale = ema(returns)
    assert th.isclose(ema.low, th.tensor(0.05)) and th.isclose(ema.high, th.tensor(0.95))
    assert scale == 1.0  # floored at 1
    for _ in range(999):
        ema.update(returns)
    assert th.isclose(ema.high - ema.low, th.tensor(90.0 * (1 - 0.99**1000)), rtol=1e-4)
    # no update
    before = ema.low.clone()
    ema(returns * 100, update=False)
    assert th.equal(ema.low, before)
    # small returns are never amplified
    small = ReturnNormalizer(decay=0.0)
    assert small(th.linspace(0, 0.1, 50))[1] == 1.0


def test_return_normalizer_state_dict():
    norm = ReturnNormalizer()
    sd = norm.state_dict()
    assert set(sd) == {"low", "high"}
    assert all(v.is_floating_point() and v.numel() > 0 for v in sd.values())
    norm.update(th.arange(10.0))
    clone = ReturnNormalizer()
    clone.load_state_dict(norm.state_dict())
    assert th.equal(clone.high, norm.high)
    with pytest.raises(ValueError, match="percentiles"):
        ReturnNormalizer(percentiles=(95.0, 5.0))


# ---------------------------------------------------------------------------------------------------------------------
# actor input, actor, critic
# ---------------------------------------------------------------------------------------------------------------------


def test_actor_input_concatenation_and_switches():
    h, z, g = th.randn(4, 3, 6), th.randn(4, 3, 2, 5), th.randn(4, 3, 8, 8)
    r, c, e = th.randn(4, 3) * 100, th.rand(4, 3), th.rand(4, 3, 1) * 10
    s = actor_input(h, z, g, r, c, e)
    assert s.shape == (4, 3, actor_input_dim(6, 10, 64)) == (4, 3, 83)
    assert th.equal(s[..., :6], h) and th.equal(s[..., 6:16], z.reshape(4, 3, 10))
    assert th.allclose(s[..., -3], symlog(r)) and th.allclose(s[..., -1], symlog(e[..., 0]))
    top = actor_input(h, z, None, r, c, e, use_extras=False)
    assert top.shape == (4, 3, actor_input_dim(6, 10, 0, use_extras=False)) == (4, 3, 16)
    only_r = actor_input(h, z, None, reward=r, use_extras={"reward"})
    assert only_r.shape == (4, 3, 17) and th.allclose(only_r[..., -1], symlog(r))
    with pytest.raises(ValueError, match="'cont' is enabled"):
        actor_input(h, z, None, reward=r, prior_entropy=e)
    with pytest.raises(ValueError, match="unknown"):
        actor_input(h, z, use_extras={"rewards"})
    with pytest.raises(ValueError, match="leading dims"):
        actor_input(h, th.randn(4, 2, 10), use_extras=False)
    with pytest.raises(ValueError, match="reward must have shape"):
        actor_input(h, z, reward=th.randn(4, 3, 2), cont=c, prior_entropy=e)


def test_actor_distributions_and_acting():
    feat = th.randn(5, 7, 12)
    disc = Actor(12, "discrete", 4, hidden=16, layers=1)
    a = disc.act(feat)
    assert a.shape == (5, 7, 4) and th.equal(a.sum(-1), th.ones(5, 7))
    det = disc.act(feat, deterministic=True)
    assert th.equal(det, disc.act(feat, deterministic=True))
    assert th.equal(det.argmax(-1), disc(feat).probs.argmax(-1))
    groups = Actor(12, "discrete", 8, action_groups=8, hidden=16, layers=1)
    g = groups.act(feat)
    assert g.shape == (5, 7, 8, 8) and groups.action_shape == (8, 8)
    assert groups(feat).log_prob(g).shape == (5, 7) and groups(feat).entropy().shape == (5, 7)
    box = Actor(12, "box", 3, hidden=16, layers=1)
    b = box.act(feat)
    assert b.shape == (5, 7, 3) and (b.abs() <= 1).all()
    assert th.equal(box.act(feat, deterministic=True), box(feat).mode())
    with pytest.raises(ValueError, match="action_kind"):
        Actor(12, "multibinary", 3)
    with pytest.raises(ValueError, match="action_groups"):
        Actor(12, "box", 3, action_groups=2)


def test_critic_zero_init_and_regression():
    th.manual_seed(0)
    critic = Critic(6, hidden=32, layers=2, slow_reg=0.0)
    feat = th.randn(64, 6)
    assert th.equal(critic.value(feat), th.zeros(64))  # zero-initialised output layer
    target = 5.0 * th.tanh(feat[:, 0]) + 20.0
    opt = th.optim.Adam(critic.parameters(), lr=1e-2)
    losses = []
    for _ in range(50):
        opt.zero_grad()
        loss, _ = critic.loss(feat, target)
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0]
    assert (critic.value(feat) - target).abs().mean() < 0.1 * target.abs().mean()


def test_slow_critic_ema_and_regulariser():
    critic = Critic(4, hidden=8, layers=1, slow_fraction=0.02)
    for slow, fast in zip(critic.slow_net.parameters(), critic.net.parameters(), strict=True):
        assert th.equal(slow, fast) and not slow.requires_grad
    with th.no_grad():
        for p in critic.net.parameters():
            p.add_(1.0)
    old = [p.clone() for p in critic.slow_net.parameters()]
    critic.update_slow()
    for slow, fast, prev in zip(critic.slow_net.parameters(), critic.net.parameters(), old, strict=True):
        assert th.allclose(slow, 0.98 * prev + 0.02 * fast)
    critic.update_slow(1.0)
    assert all(th.equal(s, f) for s, f in zip(critic.slow_net.parameters(), critic.net.parameters(), strict=True))
    # the regulariser adds the NLL of the slow critic's mean
    feat, target = th.randn(10, 4), th.randn(10)
    reg = Critic(4, hidden=8, layers=1, slow_reg=1.0)
    plain = Critic(4, hidden=8, layers=1, slow_reg=0.0)
    plain.load_state_dict(reg.state_dict())
    extra = -reg(feat).log_prob(reg.slow_value(feat)).mean()
    assert th.isclose(reg.loss(feat, target)[0], plain.loss(feat, target)[0] + extra)
    assert "bins" not in reg.state_dict()  # constant buffer kept out of the state_dict


# ---------------------------------------------------------------------------------------------------------------------
# the actor-critic
# ---------------------------------------------------------------------------------------------------------------------


def _batch(h=4, n=6, feat_dim=10, terms=("extrinsic", "subgoal", "novelty"), action_shape=(3,)):
    gen = th.Generator().manual_seed(3)
    feats = th.randn(h + 1, n, feat_dim, generator=gen)
    idx = th.randint(0, action_shape[-1], (h, n, *action_shape[:-1]), generator=gen)
    actions = th.nn.functional.one_hot(idx, action_shape[-1]).float()
    rewards = {k: th.randn(h + 1, n, generator=gen) for k in terms}
    continues = th.ones(h + 1, n)
    return feats, actions, rewards, continues


def test_active_terms_and_input_validation():
    ac = ActorCritic(10, "discrete", 3, hidden=16, layers=1, reward_weights={"extrinsic": 1.0, "novelty": 0.1})
    assert ac.active_terms == ("extrinsic", "novelty") and set(ac.critics) == {"extrinsic", "novelty"}
    feats, actions, rewards, cont = _batch()
    ac.loss(feats, actions, rewards, cont)  # the inactive "subgoal" reward is ignored
    zero = ActorCritic(10, "discrete", 3, hidden=16, layers=1, reward_weights={"extrinsic": 1, "subgoal": 0})
    assert zero.active_terms == ("extrinsic",)
    assert ActorCritic(10, "discrete", 3, hidden=16, layers=1).active_terms == ("extrinsic", "subgoal", "novelty")
    with pytest.raises(ValueError, match="lack the active terms"):
        ac.loss(feats, actions, {"extrinsic": rewards["extrinsic"]}, cont)
    with pytest.raises(ValueError, match="unknown"):
        ac.loss(feats, actions, {**rewards, "bonus": rewards["extrinsic"]}, cont)
    with pytest.raises(ValueError, match="actions must have shape"):
        ac.loss(feats, actions[:-1], rewards, cont)
    with pytest.raises(ValueError, match="continues"):
        ac.loss(feats, actions, rewards, cont[1:])
    with pytest.raises(ValueError, match="feats"):
        ac.loss(feats[..., :-1], actions, rewards, cont)
    with pytest.raises(ValueError, match="reward_weights keys"):
        ActorCritic(10, "discrete", 3, reward_weights={"extrinsic": 1, "curiosity": 1})
    with pytest.raises(ValueError, match="at least one"):
        ActorCritic(10, "discrete", 3, reward_weights={"extrinsic": 0})
    with pytest.raises(ValueError, match="gradient"):
        ActorCritic(10, "discrete", 3, gradient="both")


def test_per_term_advantage_is_weighted_sum_of_normalised_terms():
    weights = {"extrinsic": 1.0, "subgoal": 0.3, "novelty": 0.1}
    ac = ActorCritic(
        10,
        "discrete",
        3,
        hidden=16,
        layers=1,
        reward_weights=weights,
        entropy_coef=0.0,
        return_normalization="per_term",
    )
    feats, actions, rewards, cont = _batch(h=3)
    rewards = {k: v * 50 for k, v in rewards.items()}
    scales = {"extrinsic": 4.0, "subgoal": 0.5, "novelty": 10.0}  # 0.5 is floored to 1
    for k, s in scales.items():
        ac.normalizers[k].low.fill_(-1.0)
        ac.normalizers[k].high.fill_(-1.0 + s)
    _, _, metrics = ac.loss(feats, actions, rewards, cont, update_normalizers=False)
    # critics are zero-initialised: v = 0 everywhere, so A = sum_k alpha_k R_k / max(1, S_k)
    expected = sum(
        w * lambda_returns(rewards[k][1:], th.zeros(3, 6), cont[1:], th.zeros(6), 0.997, 0.95) / max(1.0, scales[k])
        for k, w in weights.items()
    )
    assert th.isclose(metrics["advantage_mean"], expected.mean(), rtol=1e-5)
    # REINFORCE: the actor loss uses exactly these normalised advantages
    dist = ac.actor(feats[:-1])
    w = cumulative_discount(cont)[:-1]
    assert th.isclose(
        ac.loss(feats, actions, rewards, cont, update_normalizers=False)[0],
        -(w * dist.log_prob(actions) * expected).mean(),
        rtol=1e-5,
    )
    assert th.isclose(metrics["subgoal/return_scale"], th.tensor(1.0))


def test_combined_advantage_divides_the_mixed_return_by_one_scale():
    weights = {"extrinsic": 1.0, "subgoal": 0.3}
    ac = ActorCritic(10, "box", 2, hidden=16, layers=1, reward_weights=weights, entropy_coef=0.0)
    assert ac.return_normalization == "combined" and set(ac.normalizers) == {"combined"}
    feats, _, rewards, cont = _batch(h=3)
    actions = th.rand(3, 6, 2) * 2 - 1
    rewards = {"extrinsic": rewards["extrinsic"] * 50, "subgoal": rewards["subgoal"]}
    ac.normalizers["combined"].low.fill_(-2.0)
    ac.normalizers["combined"].high.fill_(18.0)  # S = 20
    _, _, metrics = ac.loss(feats, actions, rewards, cont, update_normalizers=False)
    # zero-initialised critics: A = (R_extr + 0.3 R_sg) / 20, the subgoal term in reward units, not rescaled
    returns = {k: lambda_returns(rewards[k][1:], th.zeros(3, 6), cont[1:], th.zeros(6), 0.997, 0.95) for k in weights}
    expected = (returns["extrinsic"] + 0.3 * returns["subgoal"]) / 20.0
    assert th.isclose(metrics["advantage_mean"], expected.mean(), rtol=1e-5)
    assert th.isclose(metrics["subgoal/return_scale"], th.tensor(20.0))
    assert th.isclose(ac.return_scale("subgoal"), th.tensor(20.0))
    assert th.isclose(ac.return_scale("extrinsic"), th.tensor(20.0))
    # the normaliser follows the percentiles of the mixed return, not of any one term
    ac.loss(feats, actions, rewards, cont)
    low, high = th.quantile((returns["extrinsic"] + 0.3 * returns["subgoal"]).reshape(-1), th.tensor([0.05, 0.95]))
    assert th.isclose(ac.normalizers["combined"].low, 0.99 * -2.0 + 0.01 * low, rtol=1e-4)
    assert th.isclose(ac.normalizers["combined"].high, 0.99 * 18.0 + 0.01 * high, rtol=1e-4)
    with pytest.raises(ValueError, match="return_normalization"):
        ActorCritic(10, "box", 2, return_normalization="mixed")
    with pytest.raises(ValueError, match="active terms"):
        ac.return_scale("novelty")


def test_reinforce_gradient_reaches_only_the_actor():
    ac = ActorCritic(10, "discrete", 3, hidden=16, layers=1)
    feats, actions, rewards, cont = _batch()
    feats.requires_grad_(True)
    rewards = {k: v.requires_grad_(True) for k, v in rewards.items()}
    actions.requires_grad_(True)
    actor_loss, critic_loss, _ = ac.loss(feats, actions, rewards, cont)
    actor_loss.backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in ac.actor_parameters())
    assert all(p.grad is None for p in ac.critic_parameters())
    assert feats.grad is None and actions.grad is None
    assert all(r.grad is None for r in rewards.values())
    critic_loss.backward()
    assert all(p.grad is not None for p in ac.critic_parameters())
    assert all(p.grad is None for c in ac.critics.values() for p in c.slow_net.parameters())


def test_dynamics_gradient_flows_through_actions():
    ac = ActorCritic(5, "box", 2, hidden=16, layers=1, reward_weights={"extrinsic": 1.0})
    gen = th.Generator().manual_seed(4)
    h, n = 3, 8
    actions = (th.rand(h, n, 2, generator=gen) * 2 - 1).requires_grad_(True)
    # a differentiable toy "world model": s_{t+1} = tanh(s_t + W a_t), reward = -|a_t - 0.5|^2
    mix = th.randn(2, 5, generator=gen)
    states = [th.randn(n, 5, generator=gen)]
    for t in range(h):
        states.append(th.tanh(states[-1] + actions[t] @ mix))
    feats = th.stack(states)
    reward = th.cat([th.zeros(1, n), -(actions - 0.5).pow(2).sum(-1)])
    actor_loss, _, _ = ac.loss(feats, actions, {"extrinsic": reward}, th.ones(h + 1, n))
    actor_loss.backward()
    assert actions.grad is not None and actions.grad.abs().sum() > 0
    # maximising the return pushes the actions towards 0.5
    assert (actions.grad * (actions.detach() - 0.5) > 0).float().mean() > 0.9
    assert all(p.grad is None for p in ac.critic_parameters())
    # the same setup under REINFORCE does not differentiate through the actions
    rf = ActorCritic(5, "box", 2, hidden=16, layers=1, reward_weights={"extrinsic": 1.0}, gradient="reinforce")
    acts = actions.detach().requires_grad_(True)
    rf.loss(feats.detach(), acts, {"extrinsic": reward.detach()}, th.ones(h + 1, n))[0].backward()
    assert acts.grad is None


@pytest.mark.parametrize("value_gradient", ["all", "returns", "none"])
def test_dynamics_value_gradient_chooses_the_values_that_pass_gradient(value_gradient):
    ac = ActorCritic(5, "box", 2, hidden=16, layers=1, reward_weights={"extrinsic": 1.0}, value_gradient=value_gradient)
    gen = th.Generator().manual_seed(5)
    with th.no_grad():  # a critic that has learned something (its output layer starts at zero)
        for p in ac.critics["extrinsic"].net.parameters():
            p.copy_(th.randn(p.shape, generator=gen) * 0.5)
    h, n = 4, 8
    feats = th.randn(h + 1, n, 5, generator=gen).requires_grad_(True)
    actions = th.rand(h, n, 2, generator=gen) * 2 - 1
    rewards = {"extrinsic": th.zeros(h + 1, n)}  # no reward path: only the critic's values can carry gradient
    actor_loss, _, _ = ac.loss(feats, actions, rewards, th.ones(h + 1, n))
    if value_gradient == "none":
        assert not actor_loss.requires_grad or th.autograd.grad(actor_loss, feats, allow_unused=True)[0] is None
        return
    (grad,) = th.autograd.grad(actor_loss, feats)  # (H+1, N, F)
    # v(s_0) is only the baseline of R_0; the later values also enter the lambda-returns
    assert (grad[0].abs().sum() > 0) == (value_gradient == "all")
    assert grad[1:].abs().sum() > 0
    # the lambda-returns' gradient alone: -mean_t,n(w_t R_t) / S, with the values of s_1..s_H differentiable
    values = ac.critics["extrinsic"].value(feats, detach_params=True)
    returns = lambda_returns(rewards["extrinsic"][1:], values[:-1], th.ones(h, n), values[-1], ac.discount, ac.lambda_)
    weights = ac.discount ** th.arange(h, dtype=th.float32).unsqueeze(-1)
    (expected,) = th.autograd.grad(-(weights * returns).mean() / ac.return_scale("extrinsic"), feats)
    assert th.allclose(grad, expected, atol=1e-6) == (value_gradient == "returns")
    with pytest.raises(ValueError, match="value_gradient must be one of"):
        ActorCritic(5, "box", 2, value_gradient="baseline")


@pytest.mark.parametrize("gradient", ["dynamics", "reinforce"])
def test_slow_return_critic_values_the_returns_and_baseline(gradient):
    ac = ActorCritic(
        5, "box", 2, hidden=16, layers=1, reward_weights={"extrinsic": 1.0}, gradient=gradient, return_critic="slow"
    )
    critic = ac.critics["extrinsic"]
    gen = th.Generator().manual_seed(7)
    with th.no_grad():  # fast and slow copies that disagree
        for fast, slow in zip(critic.net.parameters(), critic.slow_net.parameters(), strict=True):
            fast.copy_(th.randn(fast.shape, generator=gen) * 0.5)
            slow.copy_(th.randn(slow.shape, generator=gen) * 0.5)
    h, n = 4, 8
    feats = th.randn(h + 1, n, 5, generator=gen).requires_grad_(True)
    actions = th.rand(h, n, 2, generator=gen) * 2 - 1
    rewards = {"extrinsic": th.rand(h + 1, n, generator=gen)}
    actor_loss, critic_loss, metrics = ac.loss(feats, actions, rewards, th.ones(h + 1, n), update_normalizers=False)

    def returns_of(slow):
        with th.no_grad():
            values = critic.value(feats, slow=slow)
        return lambda_returns(rewards["extrinsic"][1:], values[:-1], th.ones(h, n), values[-1], ac.discount, ac.lambda_)

    assert th.allclose(metrics["extrinsic/return_mean"], returns_of(slow=True).mean())
    assert not th.allclose(returns_of(slow=True).mean(), returns_of(slow=False).mean())
    critic_loss.backward(retain_graph=True)  # the fast critic learns; the slow copy only follows it by EMA
    assert all(p.grad is not None for p in critic.net.parameters())
    assert all(p.grad is None for p in critic.slow_net.parameters())
    if gradient == "dynamics":  # the slow copy's input gradient reaches the imagined states
        (grad,) = th.autograd.grad(actor_loss, feats)
        assert grad[1:].abs().sum() > 0
    with pytest.raises(ValueError, match="return_critic must be one of"):
        ActorCritic(5, "box", 2, return_critic="target")


def test_reinforce_learns_a_bandit():
    th.manual_seed(0)
    ac = ActorCritic(4, "discrete", 3, hidden=16, layers=1, reward_weights={"extrinsic": 1.0}, discount=1.0)
    opt = th.optim.Adam(ac.actor_parameters(), lr=1e-2)
    copt = th.optim.Adam(ac.critic_parameters(), lr=1e-2)
    feats = th.randn(2, 64, 4)
    for _ in range(60):
        with th.no_grad():
            actions = ac.actor(feats[:1]).sample()
        reward = th.zeros(2, 64)
        reward[1] = actions[0, :, 2]  # only class 2 pays
        a_loss, c_loss, _ = ac.loss(feats, actions, {"extrinsic": reward}, th.ones(2, 64))
        opt.zero_grad()
        copt.zero_grad()
        (a_loss + c_loss).backward()
        opt.step()
        copt.step()
        ac.update_slow_critics()
    assert ac.actor(feats[0]).probs[:, 2].mean() > 0.8


def test_state_dict_contents():
    ac = ActorCritic(6, "discrete", 8, action_groups=8, hidden=8, layers=1)
    sd = ac.state_dict()
    assert all(v.is_floating_point() and v.numel() > 0 for v in sd.values())
    assert not any(k.endswith("bins") for k in sd)
    assert {f"normalizers.combined.{b}" for b in ("low", "high")} <= set(sd)
    per_term = ActorCritic(6, "discrete", 8, hidden=8, layers=1, return_normalization="per_term").state_dict()
    assert {f"normalizers.{k}.{b}" for k in ac.active_terms for b in ("low", "high")} <= set(per_term)
    assert any(k.startswith("critics.extrinsic.slow_net.") for k in sd)
    n_actor = sum(p.numel() for p in ac.actor_parameters())
    assert n_actor == sum(p.numel() for p in ac.actor.parameters())
    assert math.isclose(ac.entropy_coef, 3e-4)


def _replay(b=3, t=4, feat_dim=10, terms=("extrinsic",), starts=None):
    gen = th.Generator().manual_seed(5)
    feats = th.randn(b, t, feat_dim, generator=gen)
    rewards = {k: th.zeros(b, t) for k in terms}
    return ReplaySequences(feats, rewards, th.ones(b, t), th.zeros(b, t, dtype=th.bool), starts)


def test_replay_value_loss_bootstraps_with_the_imagined_returns():
    ac = ActorCritic(10, "box", 2, hidden=16, layers=1, reward_weights={"extrinsic": 1.0}, lambda_=0.0)
    gamma = ac.discount
    start_returns = th.arange(12, dtype=th.float32)  # R_0 of the rollout from flat state b * 4 + t
    # rewards 0 and lambda 0: R_t = gamma * b_{t+1} on the rows t = 0..2 of every sequence
    _, mean = ac.replay_value_loss("extrinsic", _replay(), start_returns)
    boot = start_returns.reshape(3, 4)
    assert th.allclose(mean, gamma * boot[:, 1:].mean())
    # imagination from half the states: the others are bootstrapped with the critic's value (0 at initialisation)
    starts = th.tensor([1, 2, 5, 7, 9, 11])
    _, mean = ac.replay_value_loss("extrinsic", _replay(starts=starts), start_returns[starts])
    full = th.zeros(12).index_copy(0, starts, start_returns[starts]).reshape(3, 4)
    assert th.allclose(mean, gamma * full[:, 1:].mean())
    with pytest.raises(ValueError, match=r"replay\.starts has 6 entries"):
        ac.replay_value_loss("extrinsic", _replay(starts=starts), start_returns)
    with th.autocast("cpu", dtype=th.bfloat16):  # the returns stay float32 under a bf16 autocast
        loss, mean = ac.replay_value_loss("extrinsic", _replay(), start_returns)
    assert mean.dtype == th.float32 and th.allclose(mean, gamma * boot[:, 1:].mean()) and th.isfinite(loss)


def test_replay_value_loss_trains_only_the_critics_and_only_when_weighted():
    feats, actions, rewards, cont = _batch(n=12, terms=("extrinsic",))
    weights = {"extrinsic": 1.0}
    grads = {}
    for scale in (0.0, 0.5):
        th.manual_seed(0)
        ac = ActorCritic(10, "discrete", 3, hidden=16, layers=1, reward_weights=weights, replay_value_scale=scale)
        actor_loss, critic_loss, metrics = ac.loss(feats, actions, rewards, cont, replay=_replay())
        assert ("extrinsic/replay_critic_loss" in metrics) == (scale > 0)
        actor_loss.backward(retain_graph=True)
        assert all(p.grad is None for p in ac.critic_parameters())
        critic_loss.backward()
        grads[scale] = [p.grad.clone() for p in ac.critic_parameters()]
    assert any(not th.allclose(a, b) for a, b in zip(grads[0.0], grads[0.5], strict=True))
    with pytest.raises(ValueError, match="replay_value_scale must be >= 0"):
        ActorCritic(10, "discrete", 3, replay_value_scale=-0.1)
