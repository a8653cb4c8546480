"""SB3's keywords on HIEROS (SB3 test_custom_policy / test_cnn style): ``gamma``, ``policy_kwargs``
(``optimizer_class`` / ``optimizer_kwargs``, ``features_extractor_class`` / ``features_extractor_kwargs``,
``normalize_images``, ``net_arch``), the keywords without a HIEROS meaning, image channel order
(``VecTransposeImage(skip=True)``), and SB3 user code for DQN and SAC with HIEROS swapped in."""

from __future__ import annotations

import functools

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from hieros_helpers import TINY_OVERRIDES, tiny_kwargs
from stable_baselines3 import DQN, SAC
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.envs import BitFlippingEnv, FakeImageEnv
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor, FlattenExtractor, NatureCNN
from stable_baselines3.common.vec_env import (
    DummyVecEnv,
    VecFrameStack,
    VecNormalize,
    VecTransposeImage,
    is_vecenv_wrapped,
)

from sb3_hieros import HIEROS, HierosPolicy
from sb3_hieros.agent.world_model.observations import FeaturesExtractorEncoder


def _optimizers(model: HIEROS) -> list[th.optim.Optimizer]:
    return [level_optimizer for level in model.policy.hierarchy.levels for level_optimizer in level.optimizers.values()]


def test_gamma_is_every_levels_discount(tmp_path):
    model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(gamma=0.9))
    assert model.gamma == 0.9 and model.config.actor_critic.discount == 0.9
    assert all(level.actor_critic.discount == 0.9 for level in model.policy.hierarchy.levels)
    model.save(tmp_path / "model.zip")
    assert HIEROS.load(tmp_path / "model.zip").config.actor_critic.discount == 0.9
    with pytest.raises(ValueError, match="discount"):
        HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(gamma=1.5))


def test_bf16_defaults_to_auto_is_saved_and_a_bad_value_is_named(tmp_path):
    model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs())
    assert model.policy.bf16 == "auto"
    assert all(level.bf16 == "auto" and level.world_model.bf16 == "auto" for level in model.policy.hierarchy.levels)
    forced = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(policy_kwargs=dict(bf16=False)))
    forced.save(tmp_path / "model.zip")
    assert HIEROS.load(tmp_path / "model.zip").policy.bf16 is False
    with pytest.raises(ValueError, match="bf16 must be False, True or 'auto', got 'yes'"):
        HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(policy_kwargs=dict(bf16="yes")))


def test_optimizer_class_and_kwargs_reach_every_optimiser(tmp_path):
    kwargs = tiny_kwargs(
        policy_kwargs=dict(optimizer_class=th.optim.Adam, optimizer_kwargs=dict(eps=1e-6, weight_decay=1e-4))
    )
    model = HIEROS("MlpPolicy", "CartPole-v1", **kwargs)
    level = model.policy.hierarchy.levels[0]
    optimizers = _optimizers(model)
    assert len(optimizers) == 8 and all(type(o) is th.optim.Adam for o in optimizers)
    assert all(g["eps"] == 1e-6 for o in optimizers for g in o.param_groups)
    # learning rates stay per learner (config), weight decay never reaches norms, biases and S5 parameters
    assert level.actor_optimizer.param_groups[0]["lr"] == model.config.actor_critic.actor_lr
    assert level.ae_optimizer.param_groups[0]["lr"] == model.config.subgoal.lr
    decayed, kept = level.wm_optimizer.param_groups
    assert decayed["weight_decay"] == 1e-4 and kept["weight_decay"] == 0.0
    assert model.policy.optimizer is level.wm_optimizer and level.wm_scheduler.optimizer is level.wm_optimizer
    model.learn(40)
    assert level.wm_optimizer.param_groups[0]["lr"] > 0 and len(level.wm_optimizer.state) > 0
    model.save(tmp_path / "model.zip")
    loaded = HIEROS.load(tmp_path / "model.zip")
    assert all(type(o) is th.optim.Adam for o in _optimizers(loaded))
    for name in model.policy.optimizer_names():
        assert len(loaded.get_parameters()[f"policy.{name}"]["state"]) == len(
            model.get_parameters()[f"policy.{name}"]["state"]
        )


def test_optimizer_kwargs_alone_keep_adamw_and_lr_is_refused():
    model = HIEROS(
        "MlpPolicy", "CartPole-v1", **tiny_kwargs(policy_kwargs=dict(optimizer_kwargs=dict(betas=(0.8, 0.9))))
    )
    assert all(type(o) is th.optim.AdamW for o in _optimizers(model))
    assert all(g["betas"] == (0.8, 0.9) and g["eps"] > 0 for o in _optimizers(model) for g in o.param_groups)
    level = model.policy.hierarchy.levels[0]
    assert level.critic_optimizer.param_groups[0]["eps"] == model.config.actor_critic.eps
    with pytest.raises(ValueError, match="must not contain 'lr'"):
        HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(policy_kwargs=dict(optimizer_kwargs=dict(lr=1e-3))))
    with pytest.raises(ValueError, match=r"optimizer_class must be a torch\.optim\.Optimizer subclass"):
        HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(policy_kwargs=dict(optimizer_class=dict)))


class RecordingExtractor(BaseFeaturesExtractor):
    """Flattens every input and records what it received."""

    def __init__(self, observation_space: spaces.Space, features_dim: int = 8) -> None:
        super().__init__(observation_space, features_dim)
        self.seen: list = []
        self.linear = th.nn.Linear(spaces.flatdim(observation_space), features_dim)

    def forward(self, observations):
        self.seen.append(observations)
        parts = observations.values() if isinstance(observations, dict) else [observations]
        return self.linear(th.cat([p.flatten(1) for p in parts], 1))


def test_features_extractor_receives_preprocessed_observations_and_the_decoder_reconstructs(tmp_path):
    env = BitFlippingEnv(n_bits=4, max_steps=8, image_obs_space=True)
    kwargs = tiny_kwargs(policy_kwargs=dict(features_extractor_class=RecordingExtractor))
    model = HIEROS("MultiInputPolicy", env, **kwargs)
    world_model = model.policy.hierarchy.levels[0].world_model
    assert isinstance(world_model.encoder, FeaturesExtractorEncoder) and world_model.embed_dim == 8
    assert isinstance(model.policy.hierarchy.levels[1].world_model.encoder, th.nn.Module)  # level 1: its own encoder
    model.learn(40)
    extractor = world_model.encoder.extractor
    assert extractor.seen, "the extractor never ran"
    for seen in extractor.seen:  # images in [0, 1] as SB3 gives them, one batch dimension
        assert set(seen) == {"observation", "achieved_goal", "desired_goal"}
        image = seen["observation"]
        assert image.dtype == th.float32 and image.dim() == 4 and image.min() >= 0.0 and image.max() <= 1.0
    decoded = world_model.decode(model.policy.hierarchy.initial_state(1).latents[0])
    assert decoded["observation"].shape == (1, *env.observation_space["observation"].shape)
    model.save(tmp_path / "model.zip")
    assert (
        type(HIEROS.load(tmp_path / "model.zip").policy.hierarchy.levels[0].world_model.encoder.extractor)
        is RecordingExtractor
    )


def test_features_extractor_one_hot_and_flatten():
    kwargs = tiny_kwargs(policy_kwargs=dict(features_extractor_class=RecordingExtractor))
    model = HIEROS("MlpPolicy", "FrozenLake-v1", **kwargs)
    model.learn(30)
    seen = model.policy.hierarchy.levels[0].world_model.encoder.extractor.seen
    assert all(s.shape[1:] == (16,) and bool((s.sum(1) == 1).all()) for s in seen)  # one-hot, as preprocess_obs
    model = HIEROS(
        "MlpPolicy", "FrozenLake-v1", **tiny_kwargs(policy_kwargs=dict(features_extractor_class=FlattenExtractor))
    )
    assert model.policy.hierarchy.levels[0].world_model.embed_dim == 16
    with pytest.raises(ValueError, match="BaseFeaturesExtractor subclass"):
        HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(policy_kwargs=dict(features_extractor_class=th.nn.Linear)))


def test_features_extractor_kwargs_alone_configure_sb3s_default_extractor():
    env = FakeImageEnv(screen_height=36, screen_width=36, n_channels=1)
    with pytest.warns(UserWarning, match="NatureCNN instead of HIEROS's own encoder"):
        model = HIEROS(
            "CnnPolicy", env, **tiny_kwargs(policy_kwargs=dict(features_extractor_kwargs=dict(features_dim=32)))
        )
    encoder = model.policy.hierarchy.levels[0].world_model.encoder
    assert isinstance(encoder.extractor, NatureCNN) and encoder.out_dim == 32
    model.learn(30)


def test_normalize_images_false_takes_float_images_as_they_are():
    """SB3's test_image_like_input: a channel-first float image-like input under VecNormalize."""
    env = VecNormalize(
        DummyVecEnv([lambda: FakeImageEnv(screen_height=20, screen_width=20, n_channels=1, channel_first=True)])
    )
    model = HIEROS("CnnPolicy", env, **tiny_kwargs(policy_kwargs=dict(normalize_images=False)))
    spec = model.policy.hierarchy.levels[0].world_model.spec
    assert spec.image_keys == ["obs"] and not spec.scale_images
    model.learn(40)
    assert model.level_updates()[0] > 0
    images = th.full((1, 1, 1, 20, 20), 3.0)  # far outside [0, 255] / 255: no scaling, no clipping
    assert spec.preprocess({"obs": images})["obs"].eq(3.0).all()
    # with scaling (the default) a float rank-3 Box is a vector, as before
    default = HIEROS("MlpPolicy", env, **tiny_kwargs())
    assert default.policy.hierarchy.levels[0].world_model.spec.vector_keys == ["obs"]


def test_net_arch_sizes_the_actor_and_critics():
    model = HIEROS(
        "MlpPolicy", "CartPole-v1", **tiny_kwargs(policy_kwargs=dict(net_arch=dict(pi=[24, 24, 24], qf=[24, 24, 24])))
    )
    assert (model.config.actor_critic.units, model.config.actor_critic.layers) == (24, 3)
    with pytest.raises(ValueError, match="equal hidden widths"):
        HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(policy_kwargs=dict(net_arch=[64, 32])))
    with pytest.raises(ValueError, match="share one size"):
        HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(policy_kwargs=dict(net_arch=dict(pi=[64], qf=[32]))))
    with pytest.raises(ValueError, match="activation_fn: SB3 policy keywords without a HIEROS meaning"):
        HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(policy_kwargs=dict(activation_fn=th.nn.ReLU)))


@pytest.mark.parametrize(
    ("keyword", "value", "instead"),
    [
        ("train_freq", 4, "train_ratio"),
        ("gradient_steps", 2, "train_ratio"),
        ("optimize_memory_usage", True, "stores every observation once"),
        ("action_noise", None, "stochastic actors"),
        ("target_update_interval", 100, "slow_critic_fraction"),
        ("tau", 0.005, "slow_critic_fraction"),
        ("exploration_fraction", 0.1, "stochastic actors"),
        ("ent_coef", "auto", "entropy"),
    ],
)
def test_keywords_without_a_hieros_meaning_are_named(keyword, value, instead):
    with pytest.raises(ValueError, match=rf"{keyword}: an SB3 keyword without a HIEROS meaning \(.*{instead}"):
        HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(**{keyword: value}))


def _channel_first_frame_stack() -> VecFrameStack:
    env = DummyVecEnv([lambda: FakeImageEnv(screen_height=41, screen_width=40, n_channels=10, channel_first=True)])
    return VecFrameStack(env, 5, channels_order="first")  # (50, 41, 40): SB3's heuristic calls it channel-last


def test_vec_transpose_image_skip_is_the_users_word():
    """SB3's test_vec_transpose_skip: a channel-first frame stack that the heuristic takes for channel-last."""
    env = VecTransposeImage(_channel_first_frame_stack(), skip=True)
    model = HIEROS("CnnPolicy", env, **tiny_kwargs())
    assert model.observation_space.shape == (50, 41, 40)
    assert model.policy.hierarchy.levels[0].world_model.encoder.convs["obs"].in_shape == (50, 41, 40)
    model.learn(30)
    model.predict(env.reset(), deterministic=True)
    # without the wrapper, SB3's rule transposes it, as for SB3's own algorithms
    model = HIEROS("CnnPolicy", _channel_first_frame_stack(), **tiny_kwargs())
    assert is_vecenv_wrapped(model.get_env(), VecTransposeImage) and model.observation_space.shape == (40, 50, 41)
    # a policy built on its own checks the order and says what to do
    channel_last = spaces.Box(0, 255, (16, 16, 3), np.uint8)
    with pytest.raises(ValueError, match=r"channel-last.*VecTransposeImage\(env, skip=True\)"):
        HierosPolicy(channel_last, spaces.Discrete(2), lambda _: 1e-3)
    HierosPolicy(channel_last, spaces.Discrete(2), lambda _: 1e-3, config={**TINY_OVERRIDES}, images_channel_first=True)


def dqn_user_code(algo, path) -> None:
    """What an SB3 user writes for DQN: SB3's keywords, learn, evaluate, save / load, the replay buffer."""
    env = make_vec_env("CartPole-v1", n_envs=1, seed=0)
    model = algo(
        "MlpPolicy",
        env,
        learning_rate=1e-3,
        buffer_size=500,
        learning_starts=20,
        batch_size=4,
        gamma=0.98,
        policy_kwargs=dict(net_arch=[32, 32], optimizer_kwargs=dict(eps=1e-5)),
        seed=0,
    )
    model.learn(60)
    evaluate_policy(model, env, n_eval_episodes=2)
    model.save(path / "model")
    model.save_replay_buffer(path / "replay")
    buffer = model.replay_buffer
    assert buffer.dones.shape == buffer.timeouts.shape == buffer.rewards.shape and buffer.size() > 0
    model = algo.load(path / "model", env=env)
    model.load_replay_buffer(path / "replay")
    np.testing.assert_array_equal(model.replay_buffer.dones, buffer.dones)
    infos = [[{"TimeLimit.truncated": bool(t)} for t in row] for row in buffer.timeouts]
    model.replay_buffer.extend(
        buffer.observations, buffer.observations, buffer.actions, buffer.rewards, buffer.dones, infos
    )
    obs = env.reset()
    action, _ = model.predict(obs, deterministic=True)
    assert action.shape == (1,)
    model.learn(20, reset_num_timesteps=False)


def sac_user_code(algo, path) -> None:
    """What an SB3 user writes for SAC: a continuous env, SB3's keywords, learn, predict, save / load."""
    model = algo("MlpPolicy", "Pendulum-v1", learning_starts=20, batch_size=4, gamma=0.95, buffer_size=500, seed=0)
    model.learn(60)
    model.save(path / "sac_model")
    model = algo.load(path / "sac_model", env=gym.make("Pendulum-v1"))
    action, _ = model.predict(np.zeros(3, np.float32), deterministic=True)
    assert action.shape == (1,) and -2.0 <= float(action[0]) <= 2.0
    mean, _ = evaluate_policy(model, model.get_env(), n_eval_episodes=1)
    assert np.isfinite(mean)


#: HIEROS with a tiny network preset, swapped in where the user code names its algorithm
TINY_HIEROS = functools.partial(HIEROS, preset="small", config_overrides={**TINY_OVERRIDES, "batch_length": 8})
TINY_HIEROS.load = HIEROS.load  # type: ignore[attr-defined]


@pytest.mark.parametrize("algo", [DQN, TINY_HIEROS], ids=["DQN", "HIEROS"])
def test_dqn_user_code_runs_with_hieros_swapped_in(algo, tmp_path):
    dqn_user_code(algo, tmp_path)


@pytest.mark.parametrize("algo", [SAC, TINY_HIEROS], ids=["SAC", "HIEROS"])
def test_sac_user_code_runs_with_hieros_swapped_in(algo, tmp_path):
    sac_user_code(algo, tmp_path)
