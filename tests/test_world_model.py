"""Tests of the world models (thesis 4.4): S5WM and RSSM behind one interface."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from hieros_helpers import TINY_WORLD_MODEL

from sb3_hieros import HierosPolicy
from sb3_hieros.agent.world_model import (
    LatentState,
    RSSMWorldModel,
    S5WorldModel,
    cat_states,
    make_world_model,
    stack_states,
    world_model_lr_scheduler,
    world_model_optimizer,
)
from sb3_hieros.config import WorldModelConfig
from sb3_hieros.nn.augment import random_shift
from sb3_hieros.spaces import check_observation_space

# the sequence models under test: kind plus the options that change what they compute
VARIANTS = {
    "s5": ("s5", {}),
    "rssm": ("rssm", {}),
    # h_t from a GRU cell on the stack output, part of the recurrent memory
    "s5-gru": ("s5", {"deter_from": "gru"}),
    # posteriors that read h_t (S5WM then steps its stack in training) or the observation alone (RSSM)
    "s5-gru-post-state": ("s5", {"deter_from": "gru", "posterior": "state"}),
    "s5-post-state": ("s5", {"posterior": "state"}),
    "rssm-post-observation": ("rssm", {"posterior": "observation"}),
}
KINDS = ("s5", "rssm", "s5-gru")
#: for the tests of what observe computes (chunk against steps, context, resets, gradients, learning)
ALL_KINDS = tuple(VARIANTS)
TINY = TINY_WORLD_MODEL


def tiny_config(kind: str, **changes) -> WorldModelConfig:
    kind, options = VARIANTS[kind]
    return WorldModelConfig(kind=kind, **{**TINY, **options, **changes})


def vector_model(kind: str, obs_dim: int = 3, action_dim: int = 2, **changes):
    th.manual_seed(0)
    space = spaces.Box(-10.0, 10.0, (obs_dim,), np.float32)
    return make_world_model(space, action_dim, tiny_config(kind, **changes))


def random_chunk(batch: int, length: int, obs_dim: int = 3, action_dim: int = 2, reset_at: tuple = ()):
    obs = th.randn(batch, length, obs_dim)
    actions = th.randn(batch, length, action_dim).clamp(-1, 1)
    is_first = th.zeros(batch, length, dtype=th.bool)
    is_first[:, 0] = True
    for b, t in reset_at:
        is_first[b, t] = True
    actions[is_first] = 0.0
    return obs, actions, is_first


def assert_states_close(a: LatentState, b: LatentState, atol: float = 1e-5) -> None:
    for name, x, y in zip(LatentState._fields, a, b, strict=True):
        assert x.shape == y.shape, name
        assert th.allclose(x, y, atol=atol), f"{name}: max diff {(x - y).abs().max()}"


@pytest.mark.parametrize("kind", ALL_KINDS)
def test_factory_selects_kind(kind):
    model = vector_model(kind)
    assert isinstance(model, RSSMWorldModel if kind.startswith("rssm") else S5WorldModel)
    assert model.kind == kind.split("-")[0]
    reads_state = kind in ("rssm", "s5-gru-post-state", "s5-post-state")
    assert model.config.posterior_reads_state == reads_state
    assert model.feat_dim == TINY["deter_dim"] + TINY["stoch_groups"] * TINY["stoch_classes"]


@pytest.mark.parametrize("kind", ALL_KINDS)
def test_observe_matches_obs_step_with_resets(kind):
    check_observe_matches_obs_step(vector_model(kind))


def check_observe_matches_obs_step(model) -> None:
    obs, actions, is_first = random_chunk(3, 12, reset_at=((1, 5), (2, 7), (2, 8)))
    # two consecutive chunks, the second continuing from the last state of the first
    post_a, prior_a = model.observe(obs[:, :6], actions[:, :6], is_first[:, :6], deterministic=True)
    post_b, prior_b = model.observe(
        obs[:, 6:], actions[:, 6:], is_first[:, 6:], state=post_a.select((slice(None), -1)), deterministic=True
    )
    post = cat_states([post_a, post_b], 1)
    prior = th.cat([prior_a, prior_b], 1)
    state = None
    for t in range(obs.shape[1]):
        state = model.obs_step(state, obs[:, t], actions[:, t], is_first[:, t], deterministic=True)
        assert_states_close(state, post.select((slice(None), t)))
        assert th.allclose(state.prior_logits, prior[:, t], atol=1e-5)
    assert th.equal(post.prior_logits, prior)


@pytest.mark.parametrize("kind", ALL_KINDS)
def test_posterior_reads_the_state_where_configured(kind):
    model = vector_model(kind)
    obs, actions, is_first = random_chunk(3, 4)
    last = (slice(None), -1)
    start = model.observe(obs, actions, is_first, deterministic=True)[0].select(last)
    other = model.observe(3.0 * th.randn_like(obs), -actions, is_first, deterministic=True)[0].select(last)
    is_first[:] = False  # the state before row 0 is carried into it
    post, _ = model.observe(obs, actions, is_first, state=start, deterministic=True)
    post_other, _ = model.observe(obs, actions, is_first, state=other, deterministic=True)
    # the same observations after other histories: h_t differs, and so does q(z_t | .) exactly where it reads h_t
    assert not th.allclose(post.deter, post_other.deter)
    same_posterior = th.allclose(post.logits, post_other.logits, atol=1e-6)
    assert same_posterior != model.config.posterior_reads_state


@pytest.mark.parametrize("kind", ALL_KINDS)
def test_packed_context_continues_a_chunk(kind):
    model = vector_model(kind)
    obs, actions, is_first = random_chunk(3, 10, reset_at=((1, 6),))
    whole, _ = model.observe(obs, actions, is_first, deterministic=True)
    first, _ = model.observe(obs[:, :5], actions[:, :5], is_first[:, :5], deterministic=True)
    context = model.pack_context(first)  # (B, T, C), as replay stores it
    assert context.shape == (3, 5, model.context_dim) and context.dtype == th.float32 and not context.requires_grad
    # the second half from the unpacked context of row 4 equals the same rows of the whole chunk
    second, _ = model.observe(
        obs[:, 5:], actions[:, 5:], is_first[:, 5:], state=model.unpack_context(context[:, -1]), deterministic=True
    )
    tail = whole.select((slice(None), slice(5, None)))
    for name in ("stoch", "deter", "seq", "logits", "prior_logits"):
        assert th.allclose(getattr(second, name), getattr(tail, name), atol=1e-5), name
    # zeros unpack to the initial state (observe reads only z and the memory)
    zero = model.unpack_context(th.zeros(3, model.context_dim))
    initial = model.initial_state(3)
    assert th.equal(zero.stoch, initial.stoch) and th.equal(zero.seq, initial.seq)
    with pytest.raises(ValueError, match=rf"context must have shape \(B, {model.context_dim}\)"):
        model.unpack_context(th.zeros(3, model.context_dim + 1))


@pytest.mark.parametrize("kind", ALL_KINDS)
def test_reset_equals_fresh_start(kind):
    model = vector_model(kind)
    obs, actions, is_first = random_chunk(2, 6, reset_at=((0, 3), (1, 3)))
    post, _ = model.observe(obs, actions, is_first, deterministic=True)
    # a state after a reset equals the successor of a fresh initial state
    fresh = model.obs_step(None, obs[:, 3], th.randn(2, 2), th.ones(2, dtype=th.bool), deterministic=True)
    from_initial = model.obs_step(
        model.initial_state(2), obs[:, 3], th.zeros(2, 2), th.zeros(2, dtype=th.bool), deterministic=True
    )
    assert_states_close(post.select((slice(None), 3)), fresh)
    assert_states_close(fresh, from_initial)
    # the garbage carried into the reset step does not matter
    busy = post.select((slice(None), 2))
    after_busy = model.obs_step(busy, obs[:, 3], th.randn(2, 2), th.ones(2, dtype=th.bool), deterministic=True)
    assert_states_close(after_busy, fresh)
    # and the observe chunk restarted at row 3 gives the same later states
    post_restart, _ = model.observe(obs[:, 3:], actions[:, 3:], is_first[:, 3:], deterministic=True)
    assert_states_close(post.select((slice(None), slice(3, None))), post_restart)


@pytest.mark.parametrize("kind", KINDS)
def test_action_alignment(kind):
    """Row t holds a_{t-1}: changing a_t (the action taken after o_t) changes nothing up to step t."""
    model = vector_model(kind)
    obs, actions, is_first = random_chunk(2, 8)
    post, prior = model.observe(obs, actions, is_first, deterministic=True)
    t = 4
    changed = actions.clone()
    changed[:, t + 1] = -changed[:, t + 1] + 0.7  # a_t lives in row t+1
    post2, prior2 = model.observe(obs, changed, is_first, deterministic=True)
    assert th.equal(prior[:, : t + 1], prior2[:, : t + 1])
    assert th.equal(post.deter[:, : t + 1], post2.deter[:, : t + 1])
    assert not th.allclose(post.deter[:, t + 1], post2.deter[:, t + 1])
    assert not th.allclose(prior[:, t + 1], prior2[:, t + 1])
    # the same pairing in imagination: img_step(s_t, a_t) gives the state of row t+1
    nxt, nxt_prior = model.img_step(post.select((slice(None), t)), actions[:, t + 1], deterministic=True)
    assert th.allclose(nxt.deter, post.deter[:, t + 1], atol=1e-5)
    assert th.allclose(nxt_prior, prior[:, t + 1], atol=1e-5)


@pytest.mark.parametrize("kind", KINDS)
def test_imagine_shapes_and_no_inplace(kind):
    model = vector_model(kind)
    obs, actions, is_first = random_chunk(2, 5)
    post, _ = model.observe(obs, actions, is_first)
    start = post.flatten_batch()
    before = start.map_fields(th.clone)
    horizon, n = 4, 10

    def policy(state: LatentState) -> th.Tensor:
        return th.tanh(state.deter[:, :2])

    states, acts, entropy = model.imagine(start, policy, horizon)
    assert tuple(states.batch_shape) == (horizon + 1, n)
    assert acts.shape == (horizon + 1, n, 2)
    assert entropy.shape == (horizon + 1, n)
    assert th.all(entropy >= 0)
    assert_states_close(states.select(0)._replace(seq=before.seq), before, atol=0.0)
    assert_states_close(start, before, atol=0.0)  # start not overwritten
    assert states.seq.shape == (horizon + 1, n, 0)  # recurrent memory not kept by default
    full, _, _ = model.imagine(start, policy, horizon, deterministic=True, keep_seq=True)
    assert full.seq.shape[2:] == start.seq.shape[1:]
    assert_states_close(full.select(0), before, atol=0.0)
    again, _, _ = model.imagine(start, policy, horizon, deterministic=True)
    assert_states_close(again._replace(seq=full.seq), full, atol=0.0)
    assert model.training  # mode restored
    # imagined z are one-hot per group
    groups = states.stoch.reshape(horizon + 1, n, model.groups, model.classes)
    assert th.all(groups.sum(-1) == 1)
    assert th.allclose(acts[1], policy(states.select(1)))


def test_rollout_runs_without_dropout_in_training_mode():
    model = vector_model("s5", dropout=0.5)
    obs, actions, is_first = random_chunk(2, 5)
    model.train(True)
    post, _ = model.observe(obs, actions, is_first)
    start = post.flatten_batch().detach()
    recorded = th.rand(4, start.deter.shape[0], 2) * 2 - 1
    action = recorded[0].clone().requires_grad_(True)

    def step(t: int, state: LatentState) -> th.Tensor | None:
        return (action if t == 0 else recorded[t]) if t < 4 else None

    first, _ = model.rollout(start, 4, step, deterministic=True)
    second, _ = model.rollout(start, 4, step, deterministic=True)
    assert_states_close(first, second, atol=0.0)  # dropout would make the two rollouts differ
    assert model.training  # the mode is restored
    first.deter[-1].sum().backward()  # gradients still reach the actions (dynamics backpropagation)
    assert action.grad is not None and action.grad.abs().sum() > 0
    # the observation path in training mode does use dropout: two posteriors of one chunk differ
    again, _ = model.observe(obs, actions, is_first, deterministic=True)
    once_more, _ = model.observe(obs, actions, is_first, deterministic=True)
    assert not th.allclose(again.deter, once_more.deter)


@pytest.mark.parametrize("kind", ALL_KINDS)
def test_imagination_gradients_flow_through_recurrent_state(kind):
    model = vector_model(kind)
    obs, actions, is_first = random_chunk(2, 3)
    post, _ = model.observe(obs, actions, is_first)
    start = post.flatten_batch().detach()
    seq0 = start.seq.clone().requires_grad_(True)
    first_action = th.zeros(6, 2, requires_grad=True)
    calls = []

    def policy(state: LatentState) -> th.Tensor:
        calls.append(1)
        return first_action if len(calls) == 1 else th.tanh(state.deter[:, :2])

    # the RSSM's recurrent memory is its deterministic state (seq and deter are one tensor)
    start = start._replace(seq=seq0, deter=seq0) if kind.startswith("rssm") else start._replace(seq=seq0)
    deter0 = start.deter.clone().requires_grad_(True)
    gru_deter = kind.startswith("s5-gru")
    if gru_deter:  # its deterministic state is memory besides the S5 states
        start = start._replace(deter=deter0)
    states, _, _ = model.imagine(start, policy, 5, keep_seq=True)
    states.deter[-1].sum().backward()
    # memory of the sequence model is not detached between steps
    assert seq0.grad is not None and seq0.grad.abs().sum() > 0
    if gru_deter:
        assert deter0.grad is not None and deter0.grad.abs().sum() > 0
    # dynamics backpropagation reaches the first action through five steps
    assert first_action.grad is not None and first_action.grad.abs().sum() > 0


@pytest.mark.parametrize("kind", ALL_KINDS)
def test_gradients_reach_all_parts(kind):
    model = vector_model(kind)
    obs, actions, is_first = random_chunk(2, 6, reset_at=((0, 3),))
    samples = SimpleNamespace(
        observations=obs,
        actions=actions,
        rewards=th.randn(2, 6),
        is_first=is_first,
        is_terminal=th.zeros(2, 6, dtype=th.bool),
    )
    loss, metrics, post = model.loss(samples)
    assert th.isfinite(loss) and loss.dim() == 0
    assert set(metrics) >= {"loss", "obs_loss", "reward_loss", "cont_loss", "kl", "dyn_loss", "rep_loss"}
    assert all(isinstance(v, float) for v in metrics.values())
    assert tuple(post.batch_shape) == (2, 6)
    loss.backward()
    parts = {
        "encoder": model.encoder,
        "decoder": model.decoder,
        "reward_head": model.reward_head,
        "cont_head": model.cont_head,
        "prior_net": model.prior_net,
        "inp": model.inp,
    }
    if model.config.posterior_reads_state:
        parts.update(post_deter=model.post_deter, post_embed=model.post_embed, post_out=model.post_out)
    elif model.kind == "s5":
        parts.update(post_net=model.post_net)
    else:
        parts.update(post_embed=model.post_embed, post_out=model.post_out)
        assert model.post_deter is None
    if model.kind == "s5":
        parts.update(sequence_model=model.sequence_model)
        if kind.startswith("s5-gru"):
            parts.update(deter_cell=model.deter_cell)
        else:
            parts.update(deter_out=model.deter_out)
        ssm = list(model.sequence_model.ssm_parameters())
        assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in ssm)
    else:
        parts.update(gru=model.gru)
    for name, module in parts.items():
        grads = [p.grad for p in module.parameters() if p.grad is not None]
        assert grads and any(g.abs().sum() > 0 for g in grads), name


def cycling_samples(batch: int, length: int, generator: th.Generator):
    """A deterministic toy world: position s in {0..3} moves by 1 + a each step; obs = one-hot(s) scaled."""
    pos = th.randint(0, 4, (batch,), generator=generator)
    choice = th.randint(0, 2, (batch, length), generator=generator)
    obs, acts, rews = [], [], []
    prev = th.zeros(batch, 2)
    for t in range(length):
        obs.append(th.nn.functional.one_hot(pos, 4).float() * 2.0 - 0.5)
        acts.append(prev)
        rews.append((pos == 0).float())
        prev = th.nn.functional.one_hot(choice[:, t], 2).float()
        pos = (pos + 1 + choice[:, t]) % 4
    is_first = th.zeros(batch, length, dtype=th.bool)
    is_first[:, 0] = True
    return SimpleNamespace(
        observations=th.stack(obs, 1),
        actions=th.stack(acts, 1),
        rewards=th.stack(rews, 1),
        is_first=is_first,
        is_terminal=th.zeros(batch, length),
    )


@pytest.mark.parametrize("kind", ALL_KINDS)
def test_learns_toy_world_and_predicts_open_loop(kind):
    th.manual_seed(1)
    model = make_world_model(
        spaces.Box(-1.0, 2.0, (4,), np.float32), 2, tiny_config(kind, deter_dim=32, hidden=32, mlp_units=32, lr=3e-3)
    )
    optimizer = world_model_optimizer(model)
    gen = th.Generator().manual_seed(0)
    first = None
    for _ in range(100):
        metrics, _ = model.train_step(cycling_samples(8, 12, gen), optimizer)
        first = metrics if first is None else first
    final = np.mean([model.loss(cycling_samples(8, 12, gen))[1]["loss"] for _ in range(3)])
    assert final < 0.5 * first["loss"], (first["loss"], final)
    # open loop: observe 4 steps, then imagine 8 with the recorded actions
    test = cycling_samples(32, 12, gen)
    context, horizon = 4, 8
    with th.no_grad():
        post, _ = model.observe(
            test.observations[:, :context], test.actions[:, :context], test.is_first[:, :context], deterministic=True
        )
        step = iter(range(context, context + horizon + 1))

        def replay_actions(state: LatentState) -> th.Tensor:
            t = next(step)
            return test.actions[:, t] if t < test.actions.shape[1] else th.zeros(32, 2)

        states, _, _ = model.imagine(post.select((slice(None), -1)), replay_actions, horizon, deterministic=True)
        pred = model.decode(states.select(slice(1, None)))  # (H, B, 4)
    truth = test.observations[:, context : context + horizon].transpose(0, 1)
    model_err = (pred - truth).pow(2).mean()
    repeat_err = (test.observations[:, context - 1].unsqueeze(0) - truth).pow(2).mean()
    assert model_err < 0.5 * repeat_err, (model_err, repeat_err)


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("size", [64, 40])
def test_image_observations(kind, size):
    th.manual_seed(0)
    space = spaces.Box(0, 255, (3, size, size), np.uint8)
    model = make_world_model(space, 3, tiny_config(kind))
    obs = th.randint(0, 256, (2, 3, 3, size, size), dtype=th.uint8)
    actions = th.nn.functional.one_hot(th.randint(0, 3, (2, 3)), 3).float()
    is_first = th.tensor([[True, False, False], [True, False, True]])
    samples = SimpleNamespace(
        observations=obs, actions=actions, rewards=th.zeros(2, 3), is_first=is_first, is_terminal=th.zeros(2, 3)
    )
    loss, _, post = model.loss(samples)
    loss.backward()
    assert th.isfinite(loss)
    decoded = model.decode(post)
    assert decoded.shape == (2, 3, 3, size, size)
    assert decoded.min() >= 0 and decoded.max() <= 255
    state = model.obs_step(None, obs[:, 0], actions[:, 0], is_first[:, 0])
    assert tuple(state.batch_shape) == (2,)


@pytest.mark.parametrize("kind", KINDS)
def test_dict_observations(kind):
    th.manual_seed(0)
    space = spaces.Dict(
        {"image": spaces.Box(0, 255, (1, 16, 16), np.uint8), "vec": spaces.Box(-1, 1, (2, 3), np.float32)}
    )
    model = make_world_model(space, 2, tiny_config(kind))
    obs = {"image": th.randint(0, 256, (2, 4, 1, 16, 16), dtype=th.uint8), "vec": th.randn(2, 4, 2, 3)}
    _, actions, is_first = random_chunk(2, 4)
    post, _ = model.observe(obs, actions, is_first)
    decoded = model.decode(post)
    assert decoded["image"].shape == (2, 4, 1, 16, 16) and decoded["vec"].shape == (2, 4, 2, 3)
    samples = SimpleNamespace(
        observations=obs, actions=actions, rewards=th.zeros(2, 4), is_first=is_first, is_terminal=th.zeros(2, 4)
    )
    loss, _, _ = model.loss(samples)
    loss.backward()
    assert model.encoder.convs["image"].net[0].weight.grad.abs().sum() > 0
    assert model.encoder.mlp.hidden[0].weight.grad.abs().sum() > 0
    step_obs = {k: v[:, 0] for k, v in obs.items()}
    assert tuple(model.obs_step(None, step_obs, actions[:, 0], is_first[:, 0]).batch_shape) == (2,)
    with pytest.raises(ValueError, match="lacks the keys"):
        model.observe({"image": obs["image"]}, actions, is_first)


@pytest.mark.parametrize("kind", KINDS)
def test_heads_and_helpers(kind):
    model = vector_model(kind)
    obs, actions, is_first = random_chunk(2, 5)
    post, _ = model.observe(obs, actions, is_first)
    assert model.features(post).shape == (2, 5, model.feat_dim)
    assert model.reward(post).shape == (2, 5)
    assert th.allclose(model.reward(post), th.zeros(2, 5))  # zero-initialised reward output
    cont = model.cont(post)
    assert cont.shape == (2, 5) and th.all((cont >= 0) & (cont <= 1))
    assert model.decode(post).shape == (2, 5, 3)
    flat = post.flatten_batch()
    assert tuple(flat.batch_shape) == (10,)
    assert_states_close(flat.reshape_batch(2, 5), post, atol=0.0)
    stacked = stack_states([post.select((slice(None), 0)), post.select((slice(None), 1))], 1)
    assert_states_close(stacked, post.select((slice(None), slice(0, 2))), atol=0.0)
    keep = th.tensor([True, False])
    masked = post.select((slice(None), 4)).masked(keep)
    assert all(th.count_nonzero(field[1]) == 0 for field in masked)
    assert th.equal(masked.deter[0], post.deter[0, 4])
    with pytest.raises(ValueError, match="batch shape"):
        post.masked(keep)


@pytest.mark.parametrize("kind", ALL_KINDS)
def test_optimizer_groups(kind):
    model = vector_model(kind, weight_decay=0.1)
    optimizer = world_model_optimizer(model)
    decay, no_decay = optimizer.param_groups
    assert decay["weight_decay"] == 0.1 and no_decay["weight_decay"] == 0.0
    assert len(decay["params"]) + len(no_decay["params"]) == len(list(model.parameters()))
    no_decay_ids = {id(p) for p in no_decay["params"]}
    if model.kind == "s5":
        assert all(id(p) in no_decay_ids for p in model.sequence_model.ssm_parameters())
    assert all(p.dim() >= 2 for p in decay["params"])
    scheduler = world_model_lr_scheduler(optimizer, warmup=4)
    assert optimizer.param_groups[0]["lr"] == pytest.approx(model.config.lr / 4)
    for _ in range(5):
        optimizer.step()
        scheduler.step()
    assert optimizer.param_groups[0]["lr"] == pytest.approx(model.config.lr)


@pytest.mark.parametrize("kind", ALL_KINDS)
def test_bf16_autocast_opt_in(kind):
    space = spaces.Box(0, 255, (3, 16, 16), np.uint8)
    th.manual_seed(0)
    model = make_world_model(space, 2, tiny_config(kind), bf16=True)
    full = make_world_model(space, 2, tiny_config(kind))
    full.load_state_dict(model.state_dict())
    obs = th.randint(0, 256, (2, 4, 3, 16, 16), dtype=th.uint8)
    _, actions, is_first = random_chunk(2, 4)
    samples = SimpleNamespace(
        observations=obs, actions=actions, rewards=th.ones(2, 4), is_first=is_first, is_terminal=th.zeros(2, 4)
    )
    th.manual_seed(1)
    loss, _, post = model.loss(samples)
    th.manual_seed(1)
    full_loss, _, _ = full.loss(samples)
    loss.backward()
    assert th.isfinite(loss) and loss.dtype == th.float32
    assert th.allclose(loss, full_loss, rtol=0.05), (loss, full_loss)  # bf16 products: close, not equal
    assert all(p.grad is None or (p.grad.dtype == th.float32 and th.isfinite(p.grad).all()) for p in model.parameters())
    assert post.deter.dtype == th.float32 and post.logits.dtype == th.float32
    # acting and imagination (step form, small batches) stay in float32: the same as the float32 model, bit for bit
    state = model.obs_step(None, obs[:, 0], actions[:, 0], is_first[:, 0], deterministic=True)
    full_state = full.obs_step(None, obs[:, 0], actions[:, 0], is_first[:, 0], deterministic=True)
    assert_states_close(state, full_state, atol=0.0)
    states, _, _ = model.imagine(state, lambda s: th.zeros(2, 2), 2, deterministic=True)
    full_states, _, _ = full.imagine(full_state, lambda s: th.zeros(2, 2), 2, deterministic=True)
    assert_states_close(states, full_states, atol=0.0)


@pytest.mark.parametrize("kind", KINDS)
def test_separate_action_input(kind):
    model = vector_model(kind, action_input="separate")
    inp = model.inp
    # half the width for each part; the z half does not see the action and the action half does not see z
    z, a = th.randn(4, model.stoch_dim), th.randn(4, 2)
    out = inp(z, a)
    half = out.shape[-1] - inp.action.out_features
    assert inp.action.out_features == out.shape[-1] // 2 and inp.action.bias is not None
    other_a, other_z = inp(z, -a), inp(th.randn_like(z), a)
    assert th.equal(out[:, :half], other_a[:, :half]) and not th.allclose(out[:, half:], other_a[:, half:])
    assert th.equal(out[:, half:], other_z[:, half:]) and not th.allclose(out[:, :half], other_z[:, :half])
    # the RSSM hoists the action part out of its loop: chunk and step forms still agree
    check_observe_matches_obs_step(model)
    # the joint default keeps its parameters (saved models load)
    joint = vector_model(kind).inp.state_dict()
    assert sorted(joint) == ["action.weight", "norm.bias", "norm.weight", "stoch.weight"]


def test_deter_from_output():
    model = vector_model("s5", deter_from="output")
    obs, actions, is_first = random_chunk(2, 4)
    post, _ = model.observe(obs, actions, is_first, deterministic=True)
    state = None
    for t in range(4):
        state = model.obs_step(state, obs[:, t], actions[:, t], is_first[:, t], deterministic=True)
    assert_states_close(state, post.select((slice(None), 3)))


@pytest.mark.parametrize("kind", KINDS)
def test_bad_inputs(kind):
    model = vector_model(kind)
    obs, actions, is_first = random_chunk(2, 4)
    with pytest.raises(ValueError, match=r"observations has shape \(2, 4, 5\)"):
        model.observe(th.randn(2, 4, 5), actions, is_first)
    with pytest.raises(ValueError, match=r"observations has shape \(3, 4, 3\)"):
        model.observe(th.randn(3, 4, 3), actions, is_first)
    with pytest.raises(ValueError, match="prev_actions must have shape"):
        model.observe(obs, th.randn(2, 4, 3), is_first)
    with pytest.raises(ValueError, match=r"is_first has shape \(2, 3\)"):
        model.observe(obs, actions, is_first[:, :3])
    with pytest.raises(ValueError, match=r"observations must be a torch\.Tensor"):
        model.observe(obs.numpy(), actions, is_first)
    with pytest.raises(ValueError, match="prev_action must have shape"):
        model.obs_step(None, obs[:, 0], actions, is_first[:, 0])
    with pytest.raises(ValueError, match="must be a float tensor"):
        model.obs_step(None, obs[:, 0], actions[:, 0].long(), is_first[:, 0])
    with pytest.raises(ValueError, match="state has batch shape"):
        model.obs_step(model.initial_state(3), obs[:, 0], actions[:, 0], is_first[:, 0])
    post, _ = model.observe(obs, actions, is_first)
    with pytest.raises(ValueError, match="batch shape \\(N,\\)"):
        model.imagine(post, lambda s: th.zeros(8, 2), 2)
    with pytest.raises(ValueError, match="policy must return actions of shape"):
        model.imagine(post.flatten_batch(), lambda s: th.zeros(8, 3), 2)
    with pytest.raises(ValueError, match="horizon"):
        model.imagine(post.flatten_batch(), lambda s: th.zeros(8, 2), 0)
    with pytest.raises(ValueError, match=r"samples\.rewards"):
        model.loss(
            SimpleNamespace(
                observations=obs, actions=actions, rewards=th.zeros(2), is_first=is_first, is_terminal=th.zeros(2, 4)
            )
        )


def test_bad_spaces_are_refused_where_a_model_is_built():
    # the world model trusts its spaces: sb3_hieros.spaces checks them once, in HierosPolicy
    channel_last = spaces.Box(0, 255, (16, 16, 3), np.uint8)
    with pytest.raises(ValueError, match="channel-first"):
        check_observation_space(channel_last)
    with pytest.raises(ValueError, match="channel-first"):
        HierosPolicy(channel_last, spaces.Discrete(2), lambda _: 1e-3)
    with pytest.raises(ValueError, match=r"Tuple.*not supported by HIEROS"):
        check_observation_space(spaces.Tuple([spaces.Discrete(4)]))
    with pytest.raises(ValueError, match=r"MultiDiscrete.*at least one entry"):
        check_observation_space(spaces.Dict({"a": spaces.MultiDiscrete([])}))
    with pytest.raises(ValueError, match=r"WorldModelConfig\.kind"):
        tiny_config("s5").__class__(kind="gru")


@pytest.mark.parametrize("kind", KINDS)
def test_loss_on_replay_buffer_samples(kind):
    """The world model consumes SequenceReplayBuffer.sample() as it comes (Dreamer row layout)."""
    from sb3_hieros.buffers import SequenceReplayBuffer

    obs_space = spaces.Box(-10.0, 10.0, (3,), np.float32)
    action_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
    buffer = SequenceReplayBuffer(100, obs_space, action_space, device="cpu", n_envs=2, batch_length=6)
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(2, 3)).astype(np.float32)
    for t in range(20):
        next_obs = rng.normal(size=(2, 3)).astype(np.float32)
        done = np.array([t % 7 == 6, False])
        action = rng.uniform(-1, 1, (2, 2)).astype(np.float32)
        buffer.add(obs, next_obs, action, np.ones(2, np.float32), done, [{}, {}])
        obs = next_obs
    samples = buffer.sample(4)
    model = make_world_model(obs_space, 2, tiny_config(kind))
    loss, _, post = model.loss(samples)
    loss.backward()
    assert th.isfinite(loss) and tuple(post.batch_shape) == (4, 6)


def test_imagination_without_dropout():
    """With dropout in the S5 blocks, imagination with prior modes is still deterministic (dropout is off there)."""
    model = vector_model("s5", dropout=0.5)
    obs, actions, is_first = random_chunk(2, 3)
    post, _ = model.observe(obs, actions, is_first)
    start = post.flatten_batch().detach()
    first, _, _ = model.imagine(start, lambda s: th.zeros(6, 2), 4, deterministic=True)
    second, _, _ = model.imagine(start, lambda s: th.zeros(6, 2), 4, deterministic=True)
    assert th.equal(first.deter, second.deter)
    assert model.training


def test_grouped_kl_matches_categorical_kl():
    from sb3_hieros.agent.world_model.base import _grouped_kl
    from sb3_hieros.nn.distributions import categorical_kl

    log_p = th.log_softmax(th.randn(3, 5, 4, 6), -1)
    log_q = th.log_softmax(th.randn(3, 5, 4, 6), -1)
    assert th.allclose(_grouped_kl(log_p, log_q), categorical_kl(log_p, log_q), atol=1e-6)


def test_grouped_kl_with_given_probabilities_keeps_value_and_gradients():
    from sb3_hieros.agent.world_model.base import _grouped_kl

    raw_p = th.randn(3, 5, 4, 6, requires_grad=True)
    raw_q = th.randn(3, 5, 4, 6, requires_grad=True)
    log_p, log_q = th.log_softmax(raw_p, -1), th.log_softmax(raw_q, -1)
    weights = th.rand(3, 5)
    expected = _grouped_kl(log_p, log_q)
    want = th.autograd.grad((expected * weights).sum(), (raw_p, raw_q), retain_graph=True)
    given = _grouped_kl(log_p, log_q, log_p.exp())
    got = th.autograd.grad((given * weights).sum(), (raw_p, raw_q), retain_graph=True)
    assert th.allclose(given, expected, atol=1e-6)
    for g, w in zip(got, want, strict=True):
        assert th.allclose(g, w, atol=1e-6)
    # the loss' dynamics term: detached posterior and probabilities, so only the prior gets a gradient
    dyn = _grouped_kl(log_p.detach(), log_q, log_p.exp().detach())
    grad_p, grad_q = th.autograd.grad(dyn.sum(), (raw_p, raw_q), allow_unused=True)
    assert grad_p is None and grad_q.abs().sum() > 0


@pytest.mark.parametrize("kind", KINDS)
def test_image_shift_trains_on_shifted_frames_as_input_and_target(kind):
    th.manual_seed(0)
    space = spaces.Box(0, 255, (3, 16, 16), np.uint8)
    shifting = make_world_model(space, 2, tiny_config(kind, image_shift=3))
    plain = make_world_model(space, 2, tiny_config(kind))
    plain.load_state_dict(shifting.state_dict())
    obs = th.randint(0, 256, (2, 3, 3, 16, 16), dtype=th.uint8)
    chunk = dict(actions=th.rand(2, 3, 2) * 2 - 1, rewards=th.rand(2, 3), is_terminal=th.zeros(2, 3))
    chunk["is_first"] = th.tensor([[True, False, False], [True, False, False]])
    # the same draws: the shift comes first, then the latent samples
    th.manual_seed(1)
    shifted_loss, _, _ = shifting.loss(SimpleNamespace(observations=obs, **chunk))
    th.manual_seed(1)
    mapped = random_shift(obs.float() / 255.0 - 0.5, 3)  # float images are taken as already mapped
    assert not th.equal(mapped, obs.float() / 255.0 - 0.5)
    plain_loss, _, _ = plain.loss(SimpleNamespace(observations=mapped, **chunk))
    assert th.allclose(shifted_loss, plain_loss, rtol=1e-5)
    # evaluation sees the frames as they are
    shifting.eval(), plain.eval()
    th.manual_seed(2)
    eval_loss, _, _ = shifting.loss(SimpleNamespace(observations=obs, **chunk))
    th.manual_seed(2)
    assert th.allclose(eval_loss, plain.loss(SimpleNamespace(observations=obs, **chunk))[0], rtol=1e-5)
    with pytest.raises(ValueError, match=r"WorldModelConfig\.image_shift must be a number >= 0, got -1"):
        tiny_config(kind, image_shift=-1)


@pytest.mark.parametrize("kind", KINDS)
def test_reward_overshoot_adds_the_open_loop_reward_likelihood(kind):
    plain = vector_model(kind, reward_scale=2.0)
    with th.no_grad():  # the reward head starts at zero (a uniform two-hot): give it a slope to score
        for p in plain.reward_head.parameters():
            p.normal_(0.0, 0.5)
    overshooting = vector_model(kind, reward_scale=2.0, reward_overshoot=2)
    overshooting.load_state_dict(plain.state_dict())
    obs, actions, is_first = random_chunk(2, 4, reset_at=((0, 2),))
    rewards = th.rand(2, 4)
    chunk = SimpleNamespace(
        observations=obs, actions=actions, is_first=is_first, rewards=rewards, is_terminal=th.zeros(2, 4)
    )
    th.manual_seed(1)
    plain_loss, plain_metrics, _ = plain.loss(chunk)
    th.manual_seed(1)
    loss, metrics, post = overshooting.loss(chunk)
    assert "reward_overshoot_loss" not in plain_metrics
    assert metrics["reward_overshoot_loss"] > 0
    # the posterior draws come first, so the term is exactly what is added, weighted by reward_scale
    assert loss.item() == pytest.approx(plain_loss.item() + 2.0 * metrics["reward_overshoot_loss"], rel=1e-5)

    def open_loop(model, targets, seed=2):
        th.manual_seed(seed)
        return model.open_loop_reward_nll(post, actions, targets, is_first)

    base = open_loop(overshooting, rewards)
    # row 0 is never a target; nor is row 2 of sequence 0, where an episode starts
    unreached = rewards.clone()
    unreached[:, 0] += 5.0
    unreached[0, 2] += 5.0
    assert open_loop(overshooting, unreached).item() == pytest.approx(base.item(), rel=1e-6)
    reached = rewards.clone()
    reached[0, 3] += 5.0  # one step from row 2 of sequence 0, where its second episode starts
    assert open_loop(overshooting, reached).item() > base.item()
    # more steps than the chunk holds count the same pairs as the chunk's length allows
    longer = vector_model(kind, reward_scale=2.0, reward_overshoot=10)
    longer.load_state_dict(plain.state_dict())
    three = vector_model(kind, reward_scale=2.0, reward_overshoot=3)
    three.load_state_dict(plain.state_dict())
    assert open_loop(longer, rewards).item() == pytest.approx(open_loop(three, rewards).item(), rel=1e-6)
    # its gradient reaches the dynamics and, through the start states, the encoder
    overshooting.zero_grad()
    open_loop(overshooting, rewards).backward()
    for module in (overshooting.reward_head, overshooting.prior_net, overshooting.encoder):
        assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in module.parameters())
    assert all(p.grad is None for p in overshooting.decoder.parameters())
    with pytest.raises(ValueError, match=r"WorldModelConfig\.reward_overshoot must be a number >= 0, got -1"):
        tiny_config(kind, reward_overshoot=-1)


def plain_and_changed_losses(kind, **overrides):
    """The loss of one random chunk under a default vector model and under a copy of its weights with ``overrides``,
    each drawing its posteriors from seed 1: (changed model, chunk, plain loss, changed loss)."""
    plain = vector_model(kind)
    changed = vector_model(kind, **overrides)
    changed.load_state_dict(plain.state_dict())
    obs, actions, is_first = random_chunk(2, 4)
    chunk = SimpleNamespace(
        observations=obs, actions=actions, is_first=is_first, rewards=th.rand(2, 4), is_terminal=th.zeros(2, 4)
    )
    th.manual_seed(1)
    plain_out = plain.loss(chunk)
    th.manual_seed(1)
    return changed, chunk, plain_out, changed.loss(chunk)


@pytest.mark.parametrize("kind", KINDS)
def test_prior_decoder_adds_the_observation_likelihood_of_the_prior_state(kind):
    with_prior, chunk, (plain_loss, plain_metrics, _), (loss, metrics, post) = plain_and_changed_losses(
        kind, prior_decoder_scale=0.5
    )
    obs, actions, is_first = chunk.observations, chunk.actions, chunk.is_first
    assert "prior_obs_loss" not in plain_metrics
    assert metrics["prior_obs_loss"] > 0
    # the posterior draws come first, so the term is exactly what is added, weighted by prior_decoder_scale
    assert loss.item() == pytest.approx(plain_loss.item() + 0.5 * metrics["prior_obs_loss"], rel=1e-5)
    target = with_prior.spec.preprocess(with_prior.spec.as_dict(obs))
    _, prior_logits = with_prior._observe(target, actions, is_first, None, False)
    # with a prior that is certain of one class per group, the decoder reads exactly that one-hot z^ beside h_t
    certain = th.full_like(prior_logits, -1e4)
    certain[..., 3] = 0.0
    one_hot = th.zeros_like(prior_logits)
    one_hot[..., 3] = 1.0
    decoded = with_prior.decoder(with_prior.features(post._replace(stoch=one_hot.flatten(-2))))
    expected = with_prior.decoder.nll(decoded, target, (2, 4)).mean()
    got = with_prior.prior_observation_nll(post, certain, target)
    assert got.item() == pytest.approx(expected.item(), rel=1e-5)
    # the posterior's z is not what it reads: decoding the posterior state scores differently
    posterior = with_prior.decoder.nll(with_prior.decoder(with_prior.features(post)), target, (2, 4)).mean()
    assert got.item() != pytest.approx(posterior.item(), rel=1e-3)
    # its gradient reaches the decoder, the prior and, through the states, the encoder
    with_prior.zero_grad()
    with_prior.prior_observation_nll(post, prior_logits, target).backward()
    for module in (with_prior.decoder, with_prior.prior_net, with_prior.encoder):
        assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in module.parameters())
    with pytest.raises(ValueError, match=r"WorldModelConfig\.prior_decoder_scale must be a number >= 0, got -1"):
        tiny_config(kind, prior_decoder_scale=-1.0)


@pytest.mark.parametrize("kind", KINDS)
def test_reward_scale_weights_the_reward_likelihood_alone(kind):
    _, _, (plain_loss, plain_metrics, _), (weighted_loss, weighted_metrics, _) = plain_and_changed_losses(
        kind, reward_scale=3.0
    )
    assert weighted_metrics["reward_loss"] == pytest.approx(plain_metrics["reward_loss"])
    assert plain_metrics["reward_loss"] > 0
    # only the reward term changes: L(3) - L(1) = 2 * reward NLL
    assert weighted_loss.item() - plain_loss.item() == pytest.approx(2.0 * plain_metrics["reward_loss"], rel=1e-4)
    with pytest.raises(ValueError, match=r"WorldModelConfig\.reward_scale must be a number >= 0, got -1"):
        tiny_config(kind, reward_scale=-1.0)
