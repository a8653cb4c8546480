"""The ablation switches of thesis 5.3 and the reference-compat switches: each changes what it claims, trains, and
refuses the combinations that cannot apply."""

from __future__ import annotations

import numpy as np
import pytest
import torch as th
from hieros_helpers import TINY_OVERRIDES, CountingEnv, tiny_kwargs
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_hieros import HIEROS
from sb3_hieros.ablations import (
    ABLATIONS,
    ablation_changes_preset,
    ablation_config,
    ablation_overrides,
    merge_overrides,
)
from sb3_hieros.agent.actor_critic import ActorCritic, lambda_returns
from sb3_hieros.agent.shared import SharedLevel, SharedWorldModelHierarchy, start_windows
from sb3_hieros.agent.subactor import Subactor, current_action_alignment
from sb3_hieros.agent.world_model import RSSMWorldModel, S5WorldModel
from sb3_hieros.config import REFERENCE_BEHAVIOUR, get_preset

K = 2  # subgoal_interval of the tiny models
NO_TRAINING = 10**9


@pytest.fixture(autouse=True)
def _one_thread():
    threads = th.get_num_threads()
    th.set_num_threads(1)
    yield
    th.set_num_threads(threads)


def model_with(
    env="CartPole-v1", n_levels: int | None = 2, learning_starts: int = 20, imag_horizon: int = 4, **overrides
) -> HIEROS:
    """A tiny HIEROS with config ``overrides`` on top of the tiny networks (``n_levels=None``: from the overrides)."""
    kwargs = tiny_kwargs(
        config_overrides=merge_overrides(TINY_OVERRIDES, overrides),
        n_levels=n_levels,
        learning_starts=learning_starts,
        imag_horizon=imag_horizon,
    )
    return HIEROS("MlpPolicy", env, **kwargs)


def n_params(module: th.nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


# ---------------------------------------------------------------------------------------------------------- registry


def test_registry_covers_every_thesis_ablation_and_resolves_on_both_presets():
    sections = {a.section for a in ABLATIONS.values()}
    assert {f"5.3.{i}" for i in range(1, 13)} <= sections
    assert "reference" in sections
    # the preset itself: its own depth; the paper preset has the novelty reward, the small one has none,
    # and the thesis' h_t readout, where the small one has a GRU state
    same = {
        ("levels_3", "paper"),
        ("with_novelty", "paper"),
        ("deter_from_state", "paper"),
        ("levels_2", "small"),
        ("no_novelty", "small"),
    }
    for name in ABLATIONS:
        for preset in ("paper", "small"):
            assert ablation_changes_preset(name, preset) == ((name, preset) not in same), (name, preset)
            assert (ablation_config(name, preset) != get_preset(preset)) == ((name, preset) not in same), name
    assert ablation_config("small_s5", "paper").world_model.s5_layers == 4  # thesis: 4 instead of 8 blocks
    assert ablation_config("small_s5", "small").world_model.s5_layers == 1
    assert ablation_overrides("hieros", "small", {"n_levels": 3}) == {"n_levels": 3}
    with pytest.raises(ValueError, match="unknown ablation"):
        ablation_overrides("nope")


def test_merge_overrides_merges_sections_field_by_field():
    merged = merge_overrides({"world_model": {"deter_dim": 16}, "n_levels": 2}, {"world_model": {"kind": "rssm"}})
    assert merged == {"world_model": {"deter_dim": 16, "kind": "rssm"}, "n_levels": 2}


@pytest.mark.parametrize("name", sorted(ABLATIONS))
def test_every_ablation_trains(name):
    overrides = ablation_overrides(name, "small", TINY_OVERRIDES)
    model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(config_overrides=overrides, n_levels=None))
    model.learn(36)
    # the model runs the ablation's configuration (apart from the tiny run's explicit keywords)
    keywords = ("batch_size", "batch_length", "imag_horizon", "train_ratio", "buffer_size", "learning_starts")
    expected = ablation_config(name, "small", TINY_OVERRIDES).replace(
        **{key: getattr(model.config, key) for key in (*keywords, "subgoal_interval")},
        world_model={"lr": model.config.world_model.lr},
    )
    assert model.config == expected
    assert model.level_updates()[0] > 0


# ---------------------------------------------------------------------------------------------------------- 5.3.1


def test_shared_world_model_builds_levels_without_world_models():
    hier = model_with(n_levels=3, hierarchical_world_models=False)
    base = model_with(n_levels=3)
    policy = hier.policy
    level0 = policy.hierarchy.levels[0]
    assert isinstance(level0, Subactor)
    assert all(isinstance(policy.hierarchy.levels[i], SharedLevel) for i in (1, 2))
    assert not any(hasattr(policy.hierarchy.levels[i], "world_model") for i in (1, 2))
    assert n_params(policy) < n_params(base.policy)
    # level i observes the last k**i world states of level 0
    for i in (1, 2):
        assert policy.hierarchy.levels[i].observation_space.shape == (K**i * level0.latent_dim,)
        assert policy.hierarchy.history_length(i) == K**i
    assert len(hier.level_buffers()) == 1 and len(base.level_buffers()) == 3
    assert "level1/stoch" not in policy.state_names() and "level1/history" in policy.state_names()
    # acting threads the state and refuses nothing
    obs = np.zeros((2, 4), dtype=np.float32)
    actions, state = hier.predict(obs)
    actions, state = hier.predict(obs, state=state, episode_start=np.zeros(2, bool))
    assert len(state) == len(policy.state_names()) and actions.shape == (2,)


def test_shared_world_model_trains_all_levels_in_level_zero_imagination(monkeypatch):
    model = model_with(n_levels=3, hierarchical_world_models=False)  # imag_horizon 4: level 2 acts at t = 0, 4
    calls = []
    original = SharedWorldModelHierarchy.train_step

    def spy(self, batches):
        out = original(self, batches)
        calls.append([update.metrics for update in out])
        return out

    monkeypatch.setattr(SharedWorldModelHierarchy, "train_step", spy)
    monkeypatch.setattr(Subactor, "train_step", lambda *a, **k: pytest.fail("hierarchical training was called"))
    model.learn(36)
    assert calls and model.level_updates() == [len(calls)] * 3
    level0, level1, level2 = calls[-1]
    assert "wm/loss" in level0 and "wm/loss" not in level1
    assert level1["n_steps"] == 4 // K and level2["n_steps"] == 4 // K**2  # one step every k**i imagined steps
    for metrics in calls[-1]:
        assert all(np.isfinite(v) for v in metrics.values())
    assert "reward/subgoal" in level1 and "reward/subgoal" not in level2  # top level: no subgoal


def test_shared_world_model_trains_box_actions_by_dynamics_backpropagation():
    model = model_with("Pendulum-v1", hierarchical_world_models=False)
    assert model.policy.hierarchy.levels[0].imag_gradient == "dynamics"
    actor = model.policy.hierarchy.levels[0].actor_critic.actor
    before = [p.detach().clone() for p in actor.parameters()]
    model.learn(30)
    assert model.level_updates() == [model.level_updates()[0]] * 2 and model.level_updates()[0] > 0
    assert any(not th.equal(a, b) for a, b in zip(before, actor.parameters(), strict=True))


def test_start_windows_hold_the_last_states_of_the_same_episode():
    feats = th.arange(1, 7, dtype=th.float32).reshape(1, 6, 1)  # states 1..6
    is_first = th.tensor([[False, False, True, False, False, False]])
    windows = start_windows(feats, is_first, 3)[0, :, :, 0]  # (T, 3)
    assert windows.tolist() == [[0, 0, 1], [0, 1, 2], [0, 0, 3], [0, 3, 4], [3, 4, 5], [4, 5, 6]]


def test_shared_world_model_save_load_and_decode(tmp_path):
    model = model_with(n_levels=3, hierarchical_world_models=False)
    model.learn(30)
    decoded = model.decoded_subgoals()[1]
    assert len(decoded) == 2 and all(d.shape == (1, 4) for d in decoded)
    model.save(tmp_path / "shared")
    loaded = HIEROS.load(tmp_path / "shared")
    assert not loaded.config.hierarchical_world_models and isinstance(
        loaded.policy.hierarchy, SharedWorldModelHierarchy
    )
    for a, b in zip(model.policy.parameters(), loaded.policy.parameters(), strict=True):
        assert th.equal(a, b)


# ---------------------------------------------------------------------------------------------------------- 5.3.2-5


def test_rssm_replay_depth_and_deter_switches_change_their_modules():
    assert isinstance(model_with(world_model={"kind": "rssm"}).policy.hierarchy.levels[0].world_model, RSSMWorldModel)
    assert isinstance(model_with().policy.hierarchy.levels[0].world_model, S5WorldModel)
    for mode in ("etbs", "uniform", "reference", "count"):
        assert all(b.mode == mode for b in model_with(replay=mode).level_buffers())
    for depth in (1, 4):
        model = model_with(n_levels=depth)
        assert len(model.policy.hierarchy.levels) == depth and len(model.level_buffers()) == depth
    # the small preset's h_t is a GRU state; the thesis' readout (paper preset) and the ablation's read the S5 stack
    state = model_with(world_model={"deter_from": "state"}).policy.hierarchy.levels[0].world_model
    output = model_with(world_model={"deter_from": "output"}).policy.hierarchy.levels[0].world_model
    wm = TINY_OVERRIDES["world_model"]
    assert state.deter_out.in_features == 2 * wm["s5_layers"] * wm["s5_state_dim"]
    assert output.deter_out.in_features == wm["s5_model_dim"]
    assert hasattr(model_with().policy.hierarchy.levels[0].world_model, "deter_cell")


# ---------------------------------------------------------------------------------------------------------- 5.3.6


def test_last_state_only_shrinks_the_higher_observation_and_stores_the_newest_state():
    env = DummyVecEnv([lambda: CountingEnv(length=None)])
    model = model_with(env, higher_level_input="last", learning_starts=NO_TRAINING)
    full = model_with(DummyVecEnv([lambda: CountingEnv(length=None)]))
    latent = model.policy.hierarchy.levels[0].latent_dim
    assert model.policy.hierarchy.levels[1].observation_space.shape == (latent,)
    assert full.policy.hierarchy.levels[1].observation_space.shape == (K * latent,)
    assert n_params(model.policy.hierarchy.levels[1]) < n_params(full.policy.hierarchy.levels[1])
    model.learn(8)  # steps t = 0..7; level 1 writes rows at t = 0, 2, 4, 6
    buffer = model.level_buffers()[1]
    n = int(buffer.stream_pos[0])
    assert n == 4 and buffer.observations.shape[-1] == latent
    history = model.hierarchy_state.histories[0][0]  # (k, D): level-0 states of t = 6, 7
    assert np.allclose(buffer.observations[n - 1, 0], history[-2].numpy())  # the newest state at t = 6 only


# ---------------------------------------------------------------------------------------------------------- 5.3.7-8


def test_small_s5_and_decoded_subgoals_change_the_sizes():
    base = model_with(n_levels=None, world_model={"s5_layers": 2})
    small = model_with(n_levels=None, world_model={"s5_layers": 1})
    assert len(small.policy.hierarchy.levels[0].world_model.sequence_model.blocks) == 1
    assert n_params(small.policy) < n_params(base.policy)
    code = model_with().policy.hierarchy.levels[0]
    decoded = model_with(decoded_subgoal_input=True).policy.hierarchy.levels[0]
    assert decoded.feat_dim - code.feat_dim == code.h_dim - code.subgoal_dim
    with pytest.raises(ValueError, match="config_overrides"):  # one way to set it
        HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(policy_kwargs={"decoded_subgoal_input": True}))


# ---------------------------------------------------------------------------------------------------------- 5.3.9


def test_update_subgoals_calls_the_level_above_every_k_imagined_steps():
    model = model_with(update_subgoals_in_imagination=True)
    hierarchy = model.policy.hierarchy
    level0 = hierarchy.levels[0]
    assert hierarchy.replan_of(0) is not None and hierarchy.replan_of(1) is None  # the top level has none
    assert model_with().policy.hierarchy.replan_of(0) is None
    calls = []
    real = hierarchy.replan

    def record(level, window, subgoal, carry):
        calls.append((tuple(window.shape), carry is None))
        return real(level, window, subgoal, carry)

    hierarchy.replan = record
    model.learn(24)
    horizon = model.config.imag_horizon
    per_rollout = horizon // K  # at t = k, 2k, ... <= H
    assert len(calls) == per_rollout * model.level_updates()[0]
    assert all(shape[1:] == (K, level0.latent_dim) for shape, _ in calls)
    assert [first for _, first in calls[:per_rollout]] == [True] + [False] * (per_rollout - 1)


def test_imagined_subgoals_replace_the_replay_subgoal_in_the_subgoal_reward():
    model = model_with(update_subgoals_in_imagination=True)
    level0 = model.policy.hierarchy.levels[0]
    code_a = th.zeros(6, level0.subgoal_dim)
    code_a[:, ::4] = 1.0  # one class per group
    code_b = code_a.roll(1, -1)
    start = level0.initial_state(6)
    with th.no_grad():
        targets = level0.imagine(start, code_a, lambda window, subgoal, carry: (code_b, carry)).targets
    decoded_a, decoded_b = level0.decode_subgoal(code_a), level0.decode_subgoal(code_b)
    horizon = model.config.imag_horizon
    # s_0..s_k are rewarded against the replay subgoal, later states against the re-planned one
    for t in range(horizon + 1):
        expected = decoded_a if t <= K else decoded_b
        assert th.allclose(targets[t], expected), t


def test_imagination_subgoals_of_a_three_level_policy_thread_the_carry():
    model = model_with(n_levels=3, update_subgoals_in_imagination=True)
    updater = model.policy.hierarchy.replan_of(0)
    level0 = model.policy.hierarchy.levels[0]
    window = th.randn(5, K, level0.latent_dim)
    subgoal = th.zeros(5, level0.subgoal_dim)
    new, carry = updater(window, subgoal, None)
    assert new.shape == (5, level0.subgoal_dim)
    assert th.all(new.reshape(5, -1, model.policy.hierarchy.levels[1].action_classes).sum(-1) == 1)
    state, own_goal = carry
    assert own_goal is not None and own_goal.shape == (5, model.policy.hierarchy.levels[1].subgoal_dim)
    _, (state2, own_goal2) = updater(window, new, carry)
    assert own_goal2 is own_goal and not th.equal(state2.deter, state.deter)


# ---------------------------------------------------------------------------------------------------------- 5.3.10-12


def test_reward_switches_change_the_critics():
    top = model_with(n_levels=3, extrinsic_reward_levels="top").policy
    assert [top.hierarchy.levels[i].reward_terms for i in range(3)] == [
        ("subgoal", "novelty"),
        ("subgoal", "novelty"),
        ("extrinsic", "novelty"),
    ]
    default = model_with(n_levels=3).policy
    assert all("extrinsic" in default.hierarchy.levels[i].reward_terms for i in range(3))
    no_novelty = model_with(actor_critic={"novelty_weight": 0.0}).policy
    assert all("novelty" not in no_novelty.hierarchy.levels[i].actor_critic.critics for i in range(2))
    shared_top = model_with(hierarchical_world_models=False, extrinsic_reward_levels="top").policy
    assert shared_top.hierarchy.levels[0].reward_terms == ("subgoal", "novelty")
    assert shared_top.hierarchy.levels[1].reward_terms == ("extrinsic", "novelty")


def test_extrinsic_top_only_keeps_the_extrinsic_return_out_of_level_zero():
    model = model_with(extrinsic_reward_levels="top")
    model.learn(30)
    buffers = model.level_buffers()
    level0, level1 = (model.policy.hierarchy.levels[i].train_step(b.sample(2)).metrics for i, b in enumerate(buffers))
    assert "return/subgoal" in level0 and "return/extrinsic" not in level0
    assert "return/extrinsic" in level1


def test_actor_extras_switch_removes_three_inputs():
    with_extras = model_with().policy
    without = model_with(actor_critic={"actor_extras": False}).policy
    for i in range(2):
        assert with_extras.hierarchy.levels[i].feat_dim - without.hierarchy.levels[i].feat_dim == 3
    shared_without = model_with(hierarchical_world_models=False, actor_critic={"actor_extras": False}).policy
    shared_with = model_with(hierarchical_world_models=False).policy
    assert shared_with.hierarchy.levels[1].feat_dim - shared_without.hierarchy.levels[1].feat_dim == 3


# ---------------------------------------------------------------------------------------------------------- reference


def test_current_action_alignment_moves_a_t_to_row_t():
    actions = th.arange(1, 7, dtype=th.float32).reshape(1, 6, 1)  # row t holds a_{t-1} = t + 1
    is_first = th.tensor([[True, False, False, True, False, False]])
    shifted = current_action_alignment(actions, is_first)[0, :, 0]
    # row 0 is an episode start (zeroed), row 2 precedes a start (its a_t is a placeholder), row 5 is the last
    assert shifted.tolist() == [0.0, 3.0, 0.0, 0.0, 6.0, 0.0]


def test_reference_action_alignment_feeds_the_world_model_the_current_action(monkeypatch):
    seen = []
    for alignment in ("previous", "current"):
        model = model_with(n_levels=1, reference={"action_alignment": alignment})
        level0 = model.policy.hierarchy.levels[0]
        original = level0.world_model_step

        def spy(batch, context, original=original, alignment=alignment):
            seen.append((alignment, batch.actions.clone(), batch.is_first.clone()))
            return original(batch, context)

        monkeypatch.setattr(level0, "world_model_step", spy)
        th.manual_seed(0)
        model.learn(30)
    prev = [a for name, a, _ in seen if name == "previous"]
    cur = [(a, f) for name, a, f in seen if name == "current"]
    assert prev and cur
    actions, is_first = cur[0]
    assert th.all(actions[:, -1] == 0)  # the last row's a_t is not in the chunk
    assert th.all(actions[is_first] == 0)
    assert th.all(actions.sum(-1)[:, :-1][~is_first[:, :-1] & ~is_first[:, 1:]] == 1)  # one-hot a_t elsewhere


def test_raw_reinforce_advantage_is_the_unnormalised_weighted_average():
    th.manual_seed(0)
    feats = th.randn(4, 3, 8)
    actions = th.nn.functional.one_hot(th.randint(0, 2, (3, 3)), 2).float()
    rewards = {"extrinsic": 50 * th.randn(4, 3), "novelty": 30 * th.randn(4, 3)}
    continues = th.ones(4, 3)
    weights = {"extrinsic": 1.0, "novelty": 0.1}
    out = {}
    for mode in ("normalized", "raw"):
        th.manual_seed(1)
        ac = ActorCritic(8, "discrete", 2, hidden=8, layers=1, reward_weights=weights, reinforce_advantage=mode)
        out[mode] = ac.loss(feats, actions, rewards, continues)[2]
    assert not th.isclose(out["raw"]["advantage_mean"], out["normalized"]["advantage_mean"])
    # same critics (same seed): raw = sum_k w_k (R^k - v^k) / sum_k w_k; rebuild it from the returns' statistics
    th.manual_seed(1)
    ac = ActorCritic(8, "discrete", 2, hidden=8, layers=1, reward_weights=weights, reinforce_advantage="raw")
    raw = th.zeros(3, 3)
    with th.no_grad():
        for term, weight in weights.items():
            values = ac.critics[term](feats).mean  # (H+1, B)
            returns = lambda_returns(rewards[term][1:], values[:-1], continues[1:], values[-1], ac.discount, ac.lambda_)
            raw += weight * (returns - values[:-1])
    raw /= sum(weights.values())
    assert th.allclose(out["raw"]["advantage_mean"], raw.mean(), atol=1e-5)
    with pytest.raises(ValueError, match="reinforce_advantage"):
        ActorCritic(8, "discrete", 2, reinforce_advantage="nope")


def test_reference_terminal_reward_is_stored_as_zero_at_every_level():
    stored = {}
    for mode in ("kept", "zeroed"):
        env = DummyVecEnv([lambda: CountingEnv(length=3, final_reward=10.0)])
        model = model_with(env, learning_starts=NO_TRAINING, reference={"terminal_reward": mode})
        model.learn(6)
        level0, level1 = model.level_buffers()
        n0, n1 = int(level0.stream_pos[0]), int(level1.stream_pos[0])
        stored[mode] = (
            level0.rewards[:n0, 0][level0.is_terminal[:n0, 0]].tolist(),
            level1.rewards[:n1, 0][level1.is_terminal[:n1, 0]].tolist(),
        )
    assert stored["kept"][0] == [10.0, 10.0] and stored["zeroed"][0] == [0.0, 0.0]
    assert all(r > 0 for r in stored["kept"][1]) and stored["zeroed"][1] == [0.0, 0.0]


def test_reference_behaviour_constant_sets_all_three():
    config = get_preset("small").replace(reference=REFERENCE_BEHAVIOUR)
    assert (config.reference.action_alignment, config.reference.reinforce_advantage) == ("current", "raw")
    assert config.reference.terminal_reward == "zeroed"
    assert (
        model_with(reference=REFERENCE_BEHAVIOUR).policy.hierarchy.levels[0].actor_critic.reinforce_advantage == "raw"
    )


# ---------------------------------------------------------------------------------------------------------- invalid


@pytest.mark.parametrize(
    "changes",
    [
        {"hierarchical_world_models": False},
        {"higher_level_input": "last"},
        {"decoded_subgoal_input": True},
        {"update_subgoals_in_imagination": True},
        {"extrinsic_reward_levels": "top"},
    ],
)
def test_hierarchy_switches_with_one_level_raise(changes):
    with pytest.raises(ValueError, match="n_levels=1"):
        get_preset("small").replace(n_levels=1, **changes)
    with pytest.raises(ValueError, match="n_levels=1"):
        HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(n_levels=1, config_overrides={**TINY_OVERRIDES, **changes}))


def test_invalid_combinations_raise_with_reasons():
    small = get_preset("small")
    with pytest.raises(ValueError, match="implied by hierarchical_world_models=False"):
        small.replace(hierarchical_world_models=False, update_subgoals_in_imagination=True)
    with pytest.raises(ValueError, match=r"imag_horizon \(8\) must be >= k\*\*\(n_levels-1\) = 16"):
        small.replace(hierarchical_world_models=False, n_levels=3, imag_horizon=8)
    with pytest.raises(ValueError, match="would never do so"):
        small.replace(update_subgoals_in_imagination=True, imag_horizon=3)
    with pytest.raises(ValueError, match="subgoal_weight and novelty_weight are both 0"):
        small.replace(extrinsic_reward_levels="top", actor_critic={"subgoal_weight": 0.0, "novelty_weight": 0.0})
    with pytest.raises(ValueError, match="uses no REINFORCE"):
        small.replace(reference={"reinforce_advantage": "raw"}, actor_critic={"imag_gradient": "dynamics"})
    with pytest.raises(ValueError, match="action_alignment"):
        small.replace(reference={"action_alignment": "next"})
    with pytest.raises(ValueError, match="higher_level_input"):
        small.replace(higher_level_input="first")
    with pytest.raises(ValueError, match="must be a bool"):
        small.replace(hierarchical_world_models="no")
    with pytest.raises(ValueError, match="decoded_subgoal_input is not a policy keyword"):
        HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(n_levels=1, policy_kwargs={"decoded_subgoal_input": True}))
