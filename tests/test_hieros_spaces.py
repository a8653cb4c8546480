"""Observation and action spaces beyond Box (SB3 test_spaces / test_dict_env style, tiny budgets): Discrete,
MultiDiscrete and MultiBinary observations (also inside a Dict, next to images and vectors), goal-conditioned Dict
envs, Box actions of any shape, and the spaces SB3 itself refuses."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch as th
import torch.nn.functional as F
from gymnasium import spaces
from hieros_helpers import TINY_WORLD_MODEL, tiny_kwargs
from stable_baselines3.common.envs import BitFlippingEnv, IdentityEnv
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.preprocessing import preprocess_obs

from sb3_hieros import HIEROS
from sb3_hieros.agent.world_model import S5WorldModel
from sb3_hieros.agent.world_model.observations import DiscreteLayout, ObservationSpec
from sb3_hieros.config import WorldModelConfig

BOX = spaces.Box(-1.0, 1.0, (2,), np.float32)


class DummyEnv(gym.Env):
    """Random observations of a given space, reward 1 when the first action entry is positive (or action 1).

    :param observation_space: the observation space
    :param action_space: the action space
    """

    def __init__(self, observation_space: spaces.Space, action_space: spaces.Space) -> None:
        self.observation_space, self.action_space = observation_space, action_space
        self.last_action = None

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        if seed is not None:
            self.observation_space.seed(seed)
        return self.observation_space.sample(), {}

    def step(self, action):
        assert np.asarray(action).shape == self.action_space.shape, np.shape(action)
        self.last_action = np.asarray(action)
        reward = float(np.asarray(action).reshape(-1)[0] > 0)
        return self.observation_space.sample(), reward, False, False, {}


def _limited(observation_space: spaces.Space, action_space: spaces.Space = BOX) -> gym.Env:
    return gym.wrappers.TimeLimit(DummyEnv(observation_space, action_space), max_episode_steps=15)


MIXED = spaces.Dict(
    {
        "image": spaces.Box(0, 255, (16, 16, 1), np.uint8),
        "vector": BOX,
        "index": spaces.Discrete(3, start=-1),
        "indices": spaces.MultiDiscrete([2, 5]),
        "bits": spaces.MultiBinary(3),
    }
)

ENVS = {
    "taxi": ("MlpPolicy", lambda: gym.make("Taxi-v4")),  # Taxi-v3 in older gymnasium releases
    "frozen_lake": ("MlpPolicy", lambda: gym.make("FrozenLake-v1")),
    "multi_discrete": ("MlpPolicy", lambda: _limited(spaces.MultiDiscrete([4, 3]))),
    "multi_binary": ("MlpPolicy", lambda: _limited(spaces.MultiBinary(8))),
    "multi_binary_2d": ("MlpPolicy", lambda: _limited(spaces.MultiBinary((3, 2)))),
    "bit_flipping": ("MultiInputPolicy", lambda: BitFlippingEnv(n_bits=4, max_steps=8)),
    "bit_flipping_discrete": (
        "MultiInputPolicy",
        lambda: BitFlippingEnv(n_bits=4, max_steps=8, discrete_obs_space=True),
    ),
    "bit_flipping_image": ("MultiInputPolicy", lambda: BitFlippingEnv(n_bits=4, max_steps=8, image_obs_space=True)),
    "mixed_dict": ("MultiInputPolicy", lambda: _limited(MIXED, spaces.Discrete(2))),
    "box_2x2_actions": ("MlpPolicy", lambda: _limited(BOX, spaces.Box(-2.0, 2.0, (2, 2), np.float32))),
}


def _in_space(space: spaces.Space, value: np.ndarray) -> bool:
    return space.contains(np.asarray(value).astype(space.dtype))


@pytest.mark.parametrize("name", sorted(ENVS))
def test_learn_predict_save_load(name, tmp_path):
    policy, make_env = ENVS[name]
    model = HIEROS(policy, make_env(), **tiny_kwargs())
    model.learn(60)
    assert model.level_updates()[0] > 0, "no gradient update happened"
    env = model.get_env()
    obs = env.reset()
    action, _ = model.predict(obs, deterministic=True)
    assert action.shape == (1, *env.action_space.shape)
    assert _in_space(env.action_space, action[0])
    model.save(tmp_path / "model.zip")
    loaded = HIEROS.load(tmp_path / "model.zip", env=env)
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], action)
    loaded.learn(20, reset_num_timesteps=False)
    mean, _ = evaluate_policy(loaded, env, n_eval_episodes=2, warn=False)
    assert np.isfinite(mean)


@pytest.mark.parametrize("name", ["taxi", "multi_discrete", "multi_binary_2d", "bit_flipping", "mixed_dict"])
def test_decoded_subgoals_are_values_of_the_space(name):
    policy, make_env = ENVS[name]
    model = HIEROS(policy, make_env(), **tiny_kwargs())
    model.learn(40)
    space = model.observation_space
    decoded = model.decoded_subgoals()[1][0]  # level 1's subgoal in the observation space
    items = decoded.items() if isinstance(decoded, dict) else [(None, decoded)]
    for key, value in items:
        sub = space if key is None else space[key]
        if isinstance(sub, spaces.Box):
            continue  # predicted means, not clipped to the bounds
        array = value.cpu().numpy()
        assert array.dtype == (np.int64 if not isinstance(sub, spaces.MultiBinary) else sub.dtype)
        assert all(sub.contains(row) for row in array), (key, array)


@pytest.mark.parametrize(
    ("space", "dtype", "shape"),
    [
        (spaces.Discrete(500), np.int64, (1,)),
        (spaces.MultiDiscrete([4, 3]), np.int64, (2,)),
        (spaces.MultiBinary((3, 2)), np.int8, (3, 2)),
    ],
)
def test_replay_stores_indices_and_bits(space, dtype, shape):
    """As SB3's buffers: indices and bits in the space's dtype, not one-hot vectors."""
    model = HIEROS("MlpPolicy", _limited(space), **tiny_kwargs())
    model.learn(25)
    stored = model.replay_buffer.observations
    assert stored.dtype == dtype and stored.shape == (model.replay_buffer.buffer_size, 1, *shape)
    rows = model.replay_buffer.stored_steps()[0]
    assert all(_in_space(space, row.reshape(space.shape)) for row in stored[:rows, 0])


def _world_model(space: spaces.Space) -> S5WorldModel:
    th.manual_seed(0)
    return S5WorldModel(space, 2, WorldModelConfig(**TINY_WORLD_MODEL))


@pytest.mark.parametrize(
    "space",
    [
        spaces.Discrete(5),
        spaces.MultiDiscrete([4, 3]),
        spaces.MultiBinary(6),
        spaces.Dict({"a": spaces.MultiDiscrete([2, 3, 3]), "b": spaces.MultiBinary((2, 2)), "c": spaces.Discrete(4)}),
    ],
)
def test_one_hot_encoding_is_sb3s(space):
    spec = ObservationSpec(space)
    layout = DiscreteLayout(spec)
    space.seed(0)
    batch = [space.sample() for _ in range(7)]
    if isinstance(space, spaces.Dict):
        obs = {k: th.as_tensor(np.stack([b[k] for b in batch])) for k in space.spaces}
        expected = preprocess_obs(obs, space)
        expected = th.cat([expected[k].reshape(7, -1) for k in spec.discrete_keys], -1)
    else:
        obs = {"obs": th.as_tensor(np.stack(batch))}
        expected = preprocess_obs(obs["obs"], space).reshape(7, -1)
    np.testing.assert_array_equal(layout.one_hot(obs, (7,)).numpy(), expected.numpy())


def test_decoder_likelihood_is_categorical_and_bernoulli():
    """A categorical per discrete entry (cross-entropy over its own classes), a Bernoulli per bit; no squared error on
    one-hot vectors."""
    space = spaces.Dict(
        {"d": spaces.MultiDiscrete([2, 4]), "i": spaces.Discrete(3, start=5), "b": spaces.MultiBinary(2)}
    )
    model = _world_model(space)
    decoder = model.decoder
    obs = {"d": th.tensor([[1, 3], [0, 0]]), "i": th.tensor([7, 5]), "b": th.tensor([[1, 0], [0, 0]], dtype=th.int8)}
    pred = decoder(th.randn(2, model.feat_dim))
    logits = pred["."]  # (2, 2 + 4 + 3 + 2): d's entries, i, then the bits
    assert logits.shape == (2, 11)
    expected = (
        F.cross_entropy(logits[:, 0:2], obs["d"][:, 0], reduction="none")
        + F.cross_entropy(logits[:, 2:6], obs["d"][:, 1], reduction="none")
        + F.cross_entropy(logits[:, 6:9], obs["i"] - 5, reduction="none")
        + F.binary_cross_entropy_with_logits(logits[:, 9:], obs["b"].float(), reduction="none").sum(-1)
    )
    th.testing.assert_close(decoder.nll(pred, obs, (2,)), expected)
    mean = decoder.mean(pred)
    np.testing.assert_array_equal(
        mean["d"].numpy(), th.stack([logits[:, 0:2].argmax(-1), logits[:, 2:6].argmax(-1)], -1)
    )
    np.testing.assert_array_equal(mean["i"].numpy(), logits[:, 6:9].argmax(-1).numpy() + 5)
    np.testing.assert_array_equal(mean["b"].numpy(), (logits[:, 9:] > 0).numpy().astype(np.int8))
    assert mean["b"].dtype == th.int8 and mean["d"].dtype == mean["i"].dtype == th.int64


def test_world_model_takes_discrete_observations_as_sb3_buffers_keep_them():
    """Discrete observations come as (B, T) indices or as SB3's buffers keep them, (B, T, 1)."""
    model = _world_model(spaces.Discrete(6))
    index = th.randint(0, 6, (2, 5))
    actions, first = th.zeros(2, 5, 2), th.zeros(2, 5, dtype=th.bool)
    first[:, 0] = True
    th.manual_seed(1)
    post, _ = model.observe(index, actions, first, deterministic=True)
    th.manual_seed(1)
    post_column, _ = model.observe(index[..., None], actions, first, deterministic=True)
    th.testing.assert_close(post.stoch, post_column.stoch)
    decoded = model.decode(post)
    assert decoded.shape == (2, 5) and decoded.dtype == th.int64 and bool(((decoded >= 0) & (decoded < 6)).all())


def test_box_actions_of_any_shape_are_flattened_for_the_networks():
    env = _limited(BOX, spaces.Box(-2.0, 2.0, (2, 2), np.float32))
    model = HIEROS("MlpPolicy", env, **tiny_kwargs())
    assert model.policy.hierarchy.levels[0].action_dim == 4
    model.learn(30)
    assert env.unwrapped.last_action.shape == (2, 2)  # the env gets its own shape
    assert model.replay_buffer.actions.shape[-1] == 4
    action, _ = model.predict(np.zeros((5, 2), np.float32))
    assert action.shape == (5, 2, 2) and action.dtype == np.float32 and np.all(np.abs(action) <= 2.0)
    action, _ = model.predict(np.zeros(2, np.float32))
    assert action.shape == (2, 2)
    vectors = model.policy.action_vectors(action[None])
    np.testing.assert_allclose(model.policy.env_actions(vectors), action[None], rtol=1e-6)


@pytest.mark.parametrize("action_space", [spaces.MultiDiscrete([2, 3]), spaces.MultiBinary(3)])
def test_unsupported_action_spaces_raise_sb3s_assertion(action_space):
    with pytest.raises(AssertionError, match=type(action_space).__name__):
        HIEROS("MlpPolicy", IdentityEnv(space=action_space), **tiny_kwargs())


def test_unsupported_observation_spaces_are_named():
    env = _limited(spaces.Tuple([BOX, spaces.Discrete(2)]), spaces.Discrete(2))
    with pytest.raises(ValueError, match=r"Tuple.*not supported by HIEROS; supported: Box .*Discrete, MultiDiscrete"):
        HIEROS("MlpPolicy", env, **tiny_kwargs())
