"""HIEROS runs end to end with SB3's API: learn + predict for every policy and space, predict's recurrent state,
determinism, spaces refused, tensorboard (SB3 test-suite style, tiny budgets)."""

from __future__ import annotations

import os

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from hieros_helpers import TINY_OVERRIDES, SmallDictEnv, tiny_kwargs
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.envs import FakeImageEnv, IdentityEnv
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.vec_env import VecNormalize

from sb3_hieros import HIEROS, CnnPolicy, HierosPolicy, MlpPolicy, MultiInputPolicy


class TupleObsEnv(gym.Env):
    observation_space = spaces.Tuple((spaces.Box(-1, 1, (2,)), spaces.Box(-1, 1, (3,))))
    action_space = spaces.Discrete(2)

    def reset(self, *, seed=None, options=None):
        return self.observation_space.sample(), {}

    def step(self, action):
        return self.observation_space.sample(), 0.0, False, False, {}


@pytest.mark.parametrize(
    ("policy", "env_fn"),
    [
        ("MlpPolicy", lambda: gym.make("CartPole-v1")),
        ("MlpPolicy", lambda: gym.make("Pendulum-v1")),
        ("CnnPolicy", lambda: FakeImageEnv(screen_height=36, screen_width=36, n_channels=1)),
        ("CnnPolicy", lambda: FakeImageEnv(screen_height=40, screen_width=40, n_channels=3, discrete=False)),
        ("MultiInputPolicy", lambda: SmallDictEnv(discrete=True)),
        ("MultiInputPolicy", lambda: SmallDictEnv(discrete=False)),
    ],
)
def test_learn_and_predict(policy, env_fn):
    env = env_fn()
    model = HIEROS(policy, env, **tiny_kwargs())
    model.learn(60)
    assert model.num_timesteps == 60
    assert model._n_updates > 0, "no gradient update happened"
    obs = model.env.reset()
    action, state = model.predict(obs, deterministic=True)
    assert action.shape == (1, *env.action_space.shape)
    assert all(env.action_space.contains(a) for a in action)
    assert isinstance(state, tuple) and all(isinstance(s, np.ndarray) and s.shape[0] == 1 for s in state)
    # a single (unbatched) observation gives a single action
    single = {k: v[0] for k, v in obs.items()} if isinstance(obs, dict) else obs[0]
    action, _ = model.predict(single)
    assert action.shape == env.action_space.shape
    assert env.action_space.contains(action)


def test_predict_takes_views_with_negative_strides():
    # dm_control's renders reach an env's observation as flipped views, which torch cannot wrap as they are
    env = FakeImageEnv(screen_height=36, screen_width=36, n_channels=3, discrete=False)
    model = HIEROS("CnnPolicy", env, **tiny_kwargs())
    obs = np.random.default_rng(0).integers(0, 256, size=(36, 36, 3), dtype=np.uint8)
    view = np.flip(np.flip(obs, 0).copy(), 0)
    assert view.strides[0] < 0 and np.array_equal(view, obs)
    expected, _ = model.predict(obs, deterministic=True)
    np.testing.assert_array_equal(model.predict(view, deterministic=True)[0], expected)
    np.testing.assert_array_equal(model.predict(view[None], deterministic=True)[0], expected[None])


def test_policy_aliases():
    assert HIEROS.policy_aliases == {
        "MlpPolicy": MlpPolicy,
        "CnnPolicy": CnnPolicy,
        "MultiInputPolicy": MultiInputPolicy,
    }
    assert MlpPolicy is HierosPolicy
    assert issubclass(CnnPolicy, HierosPolicy) and issubclass(MultiInputPolicy, HierosPolicy)


@pytest.mark.parametrize("n_levels", [1, 2, 3])
def test_hierarchy_depths_train(n_levels):
    model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(n_levels=n_levels, train_ratio=16.0))
    model.learn(60)
    assert len(model.policy.hierarchy.levels) == n_levels
    assert len(model.level_buffers()) == n_levels
    updates = model.level_updates()
    assert updates[0] == model._n_updates > 0
    # level i trains every k**i level-0 updates once its buffer holds a chunk
    for i in range(1, n_levels):
        assert 0 < updates[i] <= -(-updates[0] // 2**i)


def test_update_budget_carries_fractions_of_updates():
    # tiny run: train_ratio 4 / (batch 2 x length 8) = 0.25 level-0 updates per vec-env step
    model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs())
    model.learn(40)
    before, done = model.update_budget, model.level_updates()[0]
    assert 0.0 <= before < 1.0 and done > 0
    model.train(gradient_steps=3, batch_size=2)
    assert model.update_budget == pytest.approx((before + 0.75) % 1.0)
    assert model.level_updates()[0] == done + int(before + 0.75)


def test_actors_start_learning_and_acting_at_actor_learning_starts(monkeypatch):
    overrides = {**TINY_OVERRIDES, "world_model_updates": 2, "actor_learning_starts": 60}
    model = HIEROS("MlpPolicy", "Pendulum-v1", **tiny_kwargs(config_overrides=overrides, learning_starts=20))
    level0 = model.policy.hierarchy.levels[0]
    random_steps = []
    draw = model.policy.random_action_vectors
    monkeypatch.setattr(model.policy, "random_action_vectors", lambda n: random_steps.append(n) or draw(n))

    def snapshot(module):
        return [p.detach().clone() for p in module.parameters()]

    def changed(module, before):
        return any(not th.equal(p, b) for p, b in zip(module.parameters(), before, strict=True))

    actor, critics, world_model = (
        snapshot(m) for m in (level0.actor_critic.actor, level0.actor_critic, level0.world_model)
    )
    assert model.actors_start == 60
    model.learn(50)
    assert len(random_steps) == 50, "every level acts at random until actor_learning_starts"
    assert model.level_updates()[0] > 0 and changed(level0.world_model, world_model)
    assert not changed(level0.actor_critic.actor, actor) and not changed(level0.actor_critic, critics)
    model.learn(30, reset_num_timesteps=False)
    assert len(random_steps) == 60
    assert changed(level0.actor_critic.actor, actor)


def test_actors_start_is_the_later_of_the_two_starts():
    model = HIEROS("MlpPolicy", "Pendulum-v1", **tiny_kwargs(learning_starts=20))
    assert model.config.actor_learning_starts == 0 and model.actors_start == 20
    model.learning_starts = 70  # as HIEROS.load(..., learning_starts=70) sets it
    assert model.actors_start == 70


@pytest.mark.parametrize("hierarchical", [True, False])
def test_world_model_updates_train_world_models_on_batches_of_their_own(hierarchical, monkeypatch):
    overrides = {**TINY_OVERRIDES, "world_model_updates": 3, "hierarchical_world_models": hierarchical}
    model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(config_overrides=overrides, train_ratio=16.0))
    model.learn(40)
    levels = model.policy.hierarchy.levels
    with_world_model = range(2 if hierarchical else 1)
    steps: dict[int, list] = {i: [] for i in with_world_model}
    imagined: dict[int, int] = {i: 0 for i in with_world_model}
    for i in with_world_model:
        world_model_step, imagine = levels[i].world_model_step, levels[i].imagine

        def spy(batch, context, i=i, world_model_step=world_model_step):
            steps[i].append(batch.observations)
            return world_model_step(batch, context)

        def counted(*args, i=i, imagine=imagine, **kwargs):
            imagined[i] += 1
            return imagine(*args, **kwargs)

        monkeypatch.setattr(levels[i], "world_model_step", spy)
        monkeypatch.setattr(levels[i], "imagine", counted)
    before = model.level_updates()
    model.learn(40, reset_num_timesteps=False)
    updates = [after - b for after, b in zip(model.level_updates(), before, strict=True)]
    assert updates[0] == 40 * 16 // (2 * 8)
    assert len(steps[0]) == 3 * updates[0] and imagined[0] == (updates[0] if hierarchical else 0)
    if hierarchical:
        assert updates[1] > 0 and len(steps[1]) == 3 * updates[1] and imagined[1] == updates[1]
    first, second, third = steps[0][:3]
    assert not th.equal(first, second) and not th.equal(second, third), "every update draws a batch of its own"


def test_multi_env_and_progress_bar():
    env = make_vec_env("CartPole-v1", n_envs=3, seed=0)
    model = HIEROS("MlpPolicy", env, **tiny_kwargs())
    model.learn(45, progress_bar=True)
    assert model.num_timesteps == 45
    assert model._n_updates > 0
    action, state = model.predict(env.reset())
    assert action.shape == (3,)
    assert state[0].shape == (3,)


def test_dump_logs_records_level_metrics():
    model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(train_ratio=16.0))
    model.learn(60)
    # the means are flushed at each dump; record one more update and inspect the pending values
    model.train(gradient_steps=4, batch_size=2)
    keys = set(model.logger.name_to_value)
    for level in (0, 1):
        for name in ("wm/loss", "actor/loss", "critic/loss", "ae/loss", "reward/extrinsic", "reward/novelty"):
            assert f"train/level{level}/{name}" in keys
    assert "train/level0/reward/subgoal" in keys and "train/level0/subgoal/success" in keys
    assert "train/level1/reward/subgoal" not in keys  # the top level has no subgoal
    assert "train/learning_rate" in keys and "train/n_updates" in keys


def test_learning_rate_schedule_drives_world_model_lr():
    model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(learning_rate=lambda progress: 1e-4 + 1e-3 * progress))
    assert model.policy.hierarchy.levels[0].wm_optimizer.param_groups[0]["lr"] == pytest.approx(1.1e-3 * 0.5)  # warm-up
    model.learn(50)
    assert model._n_updates > 2
    # warm-up (2 updates) is over: the last update (within the last few steps) used the schedule's late value
    lr = model.policy.hierarchy.levels[0].wm_optimizer.param_groups[0]["lr"]
    assert 1e-4 <= lr < 3e-4


def test_predict_threads_state_and_episode_start():
    model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(n_levels=3))
    obs = np.random.default_rng(0).normal(size=(4, 4)).astype(np.float32)
    fresh, state = model.predict(obs, deterministic=True)
    # deterministic predictions do not sample anything
    again, _ = model.predict(obs, deterministic=True)
    np.testing.assert_array_equal(fresh, again)
    assert state[0].tolist() == [1, 1, 1, 1]  # step counters
    names = model.policy.state_names()
    assert len(names) == len(state)
    seq = state[names.index("level0/seq")]
    assert np.iscomplexobj(seq)
    # a few more steps with the state, then a reset of env 0 and 2 only
    for _ in range(3):
        _, state = model.predict(obs, state=state, episode_start=np.zeros(4, dtype=bool), deterministic=True)
    starts = np.array([True, False, True, False])
    reset, new_state = model.predict(obs, state=state, episode_start=starts, deterministic=True)
    np.testing.assert_array_equal(reset[starts], fresh[starts])
    history = new_state[names.index("level1/history")]
    assert np.all(history[starts][:, :-1] == 0.0), "history slots from before the reset must be zeroed"
    assert np.any(history[~starts][:, :-1] != 0.0)
    # stochastic predictions vary
    samples = {int(model.predict(obs[0])[0]) for _ in range(30)}
    assert samples == {0, 1}


def test_predict_input_errors():
    model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs())
    with pytest.raises(ValueError, match=r"\(5,\).*\(4,\)"):
        model.predict(np.zeros(5, dtype=np.float32))
    obs = np.zeros((2, 4), dtype=np.float32)
    _, state = model.predict(obs)
    with pytest.raises(ValueError, match="state must be the tuple"):
        model.predict(obs, state=state[:-1])
    with pytest.raises(ValueError, match=r"expected \(3,"):
        model.predict(np.zeros((3, 4), dtype=np.float32), state=state)
    bad = list(state)
    bad[3] = bad[3].real  # level0/seq must stay complex
    with pytest.raises(ValueError, match="level0/seq"):
        model.predict(obs, state=tuple(bad))
    with pytest.raises(ValueError, match="episode_start"):
        model.predict(obs, state=state, episode_start=np.zeros(3, dtype=bool))
    with pytest.raises(ValueError, match="mixing Gym API"):
        model.predict((np.zeros(4, dtype=np.float32), {}))


def test_box_actions_keep_dtype_and_bounds():
    env = gym.make("Pendulum-v1")
    env.action_space = spaces.Box(-2.0, 2.0, (1,), np.float64)
    model = HIEROS("MlpPolicy", env, **tiny_kwargs())
    action, _ = model.predict(np.zeros((8, 3), dtype=np.float32))
    assert action.dtype == np.float64
    assert np.all(np.abs(action) <= 2.0)


def test_unsupported_spaces_are_refused():
    with pytest.raises(AssertionError, match="MultiDiscrete"):
        HIEROS("MlpPolicy", IdentityEnv(space=spaces.MultiDiscrete([2, 3])), **tiny_kwargs())
    with pytest.raises(ValueError, match="Tuple"):
        HIEROS("MlpPolicy", TupleObsEnv(), **tiny_kwargs())
    with pytest.raises(AssertionError, match="finite"):  # SB3's own check
        HIEROS("MlpPolicy", IdentityEnv(space=spaces.Box(-np.inf, np.inf, (2,))), **tiny_kwargs())
    with pytest.raises(ValueError, match="config_overrides"):
        HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(policy_kwargs={"config": {}}))
    with pytest.raises(ValueError, match="preset"):
        HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(preset="huge"))


def test_preset_overrides_and_keywords():
    model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(n_levels=None, imag_horizon=None))
    # fields left out of config_overrides come from the preset (small: 2 levels, horizon 16)
    assert model.config.n_levels == 2 and model.config.imag_horizon == 16
    assert model.config.batch_size == 2 and model.config.world_model.s5_model_dim == 16  # keyword, config_overrides
    assert model.gamma == model.config.actor_critic.discount
    # SB3's keywords win over config_overrides
    overrides = {**TINY_OVERRIDES, "actor_critic": {"discount": 0.9}, "buffer_size": 900}
    model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(config_overrides=overrides, buffer_size=300))
    assert model.gamma == 0.9 and model.replay_buffer.buffer_size == 300 and model.config.buffer_size == 300
    # every other hyperparameter is set with config_overrides only, and a keyword says so
    with pytest.raises(ValueError, match=r"n_levels: not HIEROS constructor keywords; set them with config_overrides="):
        HIEROS("MlpPolicy", "CartPole-v1", n_levels=3)
    with pytest.raises(TypeError, match="unexpected keywords"):
        HIEROS("MlpPolicy", "CartPole-v1", n_level=3)
    with pytest.raises(ValueError, match="decoded_subgoal_input is not a policy keyword: set it with config_overrides"):
        HIEROS("MlpPolicy", "CartPole-v1", policy_kwargs={"decoded_subgoal_input": True})


def test_evaluate_policy():
    model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs())
    eval_env = make_vec_env("CartPole-v1", n_envs=2, seed=1)
    mean, std = evaluate_policy(model, eval_env, n_eval_episodes=3, deterministic=True)
    assert mean > 0 and std >= 0
    rewards, lengths = evaluate_policy(model, eval_env, n_eval_episodes=2, return_episode_rewards=True)
    assert len(rewards) == len(lengths) == 2


@pytest.mark.parametrize("hierarchical", [True, False])
def test_replay_context_is_stored_and_trained_from(hierarchical, monkeypatch):
    overrides = {**TINY_OVERRIDES, "replay_context": True, "hierarchical_world_models": hierarchical}
    model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(config_overrides=overrides, train_ratio=16.0))
    model.learn(120)
    buffers = model.level_buffers()
    assert len(buffers) == (2 if hierarchical else 1)
    for i, buffer in enumerate(buffers):
        assert buffer.context_dim == model.policy.hierarchy.levels[i].world_model.context_dim > 0
        assert buffer.has_context.any(), f"level {i} stored no context"
    level0 = model.policy.hierarchy.levels[0]
    contexts = []
    world_model_step = level0.world_model_step

    def spy(batch, context):
        contexts.append(context)
        return world_model_step(batch, context)

    monkeypatch.setattr(level0, "world_model_step", spy)
    model.learn(40, reset_num_timesteps=False)
    assert contexts and all(context is not None for context in contexts)
    assert any(context.abs().sum() > 0 for context in contexts), "no chunk started from a stored state"
    # off (the paper preset's and HierosConfig's default): no context kept, every chunk starts from zeros
    plain_overrides = {**TINY_OVERRIDES, "replay_context": False}
    plain = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(config_overrides=plain_overrides))
    plain.learn(60)
    assert all(b.context is None and not b.has_context.any() for b in plain.level_buffers())
    update = plain.policy.hierarchy.train_step([b.sample(2) for b in plain.level_buffers()])
    assert all(u is not None and u.context is None for u in update)


def test_seeded_runs_are_identical():
    def run():
        model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(seed=3, n_levels=3))
        model.learn(60)
        return model

    first, second = run(), run()
    assert first._n_updates > 0
    for (name, a), b in zip(first.policy.state_dict().items(), second.policy.state_dict().values(), strict=True):
        assert th.equal(a, b), name
    for a, b in zip(first.level_buffers(), second.level_buffers(), strict=True):
        np.testing.assert_array_equal(a.observations, b.observations)
        np.testing.assert_array_equal(a.rewards, b.rewards)
    third = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(seed=4, n_levels=3))
    third.learn(60)
    pairs = zip(first.policy.state_dict().values(), third.policy.state_dict().values(), strict=True)
    assert any(not th.equal(a, b) for a, b in pairs), "another seed must give other parameters"


def test_tensorboard(tmp_path):
    pytest.importorskip("tensorboard")
    model = HIEROS("MlpPolicy", "CartPole-v1", tensorboard_log=str(tmp_path), verbose=1, **tiny_kwargs())
    model.learn(40)
    model.learn(20, reset_num_timesteps=False)
    assert os.path.isdir(tmp_path / "HIEROS_1")
    assert not os.path.isdir(tmp_path / "HIEROS_2")
    assert any(name.startswith("events") for name in os.listdir(tmp_path / "HIEROS_1"))


def test_vec_normalize_and_continued_learning():
    env = VecNormalize(make_vec_env("CartPole-v1", n_envs=2, seed=0), norm_obs=True, norm_reward=True)
    model = HIEROS("MlpPolicy", env, **tiny_kwargs())
    model.learn(60)
    assert model._n_updates > 0
    # the level-0 replay stores raw observations (VecNormalize normalises them when sampling)
    buffer = model.replay_buffer
    last = buffer.observations[buffer.stream_pos - 1, np.arange(2)]
    assert not model._last_episode_starts.all()
    for j in np.flatnonzero(~model._last_episode_starts):
        np.testing.assert_allclose(last[j], model._last_original_obs[j])
        assert not np.allclose(last[j], model._last_obs[j])
    steps = int(model.hierarchy_state.step[0])
    model.learn(20, reset_num_timesteps=False)
    assert int(model.hierarchy_state.step[0]) == steps + 10  # the hierarchy carries on (no reset between learn calls)
    model.learn(20)
    assert int(model.hierarchy_state.step[0]) == 10  # reset_num_timesteps resets the envs and the hierarchy


def test_training_mode_and_device_shortcuts():
    """predict skips the module walk when the mode is already right; the cached device follows ``to``/``cpu``."""
    model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs())
    policy = model.policy
    policy.set_training_mode(True)
    assert all(m.training for m in policy.modules())
    policy.hierarchy.levels[0].world_model.train(
        False
    )  # a child out of step: the next switch still reaches every module
    policy.set_training_mode(True)
    assert all(m.training for m in policy.modules())
    model.predict(np.zeros(4, np.float32))
    assert not any(m.training for m in policy.modules())
    assert policy.device == next(policy.parameters()).device
    assert "_cached_device" in policy.__dict__
    policy.cpu()
    assert "_cached_device" not in policy.__dict__
    assert policy.device == th.device("cpu")


def test_replay_value_loss_trains_every_levels_critics_on_the_replayed_rewards(monkeypatch):
    from sb3_hieros.agent.subgoal import max_cosine_subgoal_reward

    overrides = {**TINY_OVERRIDES, "actor_critic": {"replay_value_loss": 0.3}, "imag_start_fraction": 0.5}
    model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(config_overrides=overrides))
    level0 = model.policy.hierarchy.levels[0]
    seen = []
    replay_sequences = level0.replay_sequences

    def spy(batch, post, subgoals, starts):
        replay = replay_sequences(batch, post, subgoals, starts)
        # the subgoal reward of s_t is measured against the subgoal in force at s_{t-1}, when a_{t-1} was chosen
        with th.no_grad():
            expected = max_cosine_subgoal_reward(post.deter[:, 1:], level0.autoencoder.decode(subgoals[:, :-1]))
        seen.append((batch, starts, replay, expected))
        return replay

    monkeypatch.setattr(level0, "replay_sequences", spy)
    model.learn(60)
    logged = model.logger.name_to_value
    for key in ("level0/critic/extrinsic", "level0/critic/subgoal", "level1/critic/extrinsic"):
        assert np.isfinite(logged[f"train/{key}_replay_loss"])
    assert seen
    batch, starts, replay, expected = seen[-1]
    b, t = batch.rewards.shape
    assert replay.feats.shape[:2] == (b, t) and starts.shape == (b * t // 2,)
    assert th.equal(replay.rewards["extrinsic"], batch.rewards)
    assert th.equal(replay.is_first, batch.is_first)
    assert th.allclose(replay.rewards["subgoal"][:, 1:], expected) and not replay.rewards["subgoal"][:, 0].any()
    plain = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs())
    plain.learn(60)
    assert not any("replay_loss" in key for key in plain.logger.name_to_value)
