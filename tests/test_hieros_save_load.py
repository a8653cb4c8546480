"""Save / load of HIEROS (SB3 test_save_load style): parameters (complex S5 states included), optimisers, policy
save/load, env changes, replay buffers of every level."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from hieros_helpers import TINY_OVERRIDES, tiny_kwargs
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.envs import FakeImageEnv
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_hieros import HIEROS, CnnPolicy, MlpPolicy, config
from sb3_hieros.ablations import merge_overrides


def _assert_same_params(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for name in a:
        if "optim" in name:
            continue
        for key, value in a[name].items():
            assert th.equal(value, b[name][key]), f"{name}/{key}"


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A tiny 3-level model after some training, saved once with its replay."""
    path = tmp_path_factory.mktemp("hieros")
    model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(n_levels=3, train_ratio=8.0))
    model.learn(70)
    assert all(n > 0 for n in model.level_updates())
    model.save(path / "model.zip")
    model.save_replay_buffer(path / "replay.pkl")
    return model, path


def test_save_load_same_predictions_and_parameters(trained):
    model, path = trained
    obs = np.random.default_rng(0).normal(size=(10, 4)).astype(np.float32)
    actions, state = model.predict(obs, deterministic=True)
    loaded = HIEROS.load(path / "model.zip", env=make_vec_env("CartPole-v1", n_envs=1))
    new_actions, new_state = loaded.predict(obs, deterministic=True)
    np.testing.assert_array_equal(actions, new_actions)
    for a, b in zip(state, new_state, strict=True):
        np.testing.assert_array_equal(a, b)
    _assert_same_params(model.get_parameters(), loaded.get_parameters())
    # optimiser states (Adam moments included) round-trip too
    for name in model.policy.optimizer_names():
        saved = model.get_parameters()[f"policy.{name}"]["state"]
        restored = loaded.get_parameters()[f"policy.{name}"]["state"]
        assert saved.keys() == restored.keys() and len(saved) > 0
        for key in saved:
            assert th.equal(saved[key]["exp_avg"], restored[key]["exp_avg"])
    # hyperparameters and schedule counters come back; the hierarchy's training state is rebuilt, not saved
    assert loaded.config.n_levels == 3 and loaded.config == model.config
    assert loaded.level_updates() == model.level_updates()
    assert loaded._hier is None
    # training resumes with an empty replay (training is guarded until level 0 can sample)
    loaded.learn(30)
    assert loaded.num_timesteps == 30


@pytest.mark.parametrize("safe", [False, True])
def test_load_keeps_the_saved_configuration(trained, monkeypatch, safe):
    # a later change of the preset's values must not change a saved model
    model, path = trained
    changed = {"actor_critic": {"entropy": 0.5}, "world_model": {"free_bits": 0.25}}
    small = config.PRESETS["small"]
    monkeypatch.setitem(config.PRESETS, "small", lambda: small().replace(**changed))
    assert HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs()).config.actor_critic.entropy == 0.5
    loaded = HIEROS.load(path / "model.zip", env=gym.make("CartPole-v1") if safe else None, safe=safe)
    assert loaded.config == model.config
    # keywords given to load still win, as SB3's load sets them before the model is built
    assert HIEROS.load(path / "model.zip", learning_starts=3).config.learning_starts == 3


def test_load_of_a_save_without_its_configuration(tmp_path, monkeypatch):
    # saves made before the configuration was saved with the model were trained with per-term return scales and
    # the thesis' h_t readout and one world-model update per level update
    small = config.PRESETS["small"]
    old_small = lambda: small().replace(  # noqa: E731
        actor_critic={"return_normalization": "per_term"}, world_model={"deter_from": "state"}, world_model_updates=1
    )
    monkeypatch.setitem(config.PRESETS, "small", old_small)
    model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs())
    model.learn(30)
    model.save(tmp_path / "old.zip", exclude=["_config_fields"])
    monkeypatch.setitem(config.PRESETS, "small", small)
    now = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs()).config
    assert now.actor_critic.return_normalization == "combined" and now.world_model.deter_from == "gru"
    assert now.world_model_updates == 2
    loaded = HIEROS.load(tmp_path / "old.zip")
    assert loaded.config == model.config
    _assert_same_params(loaded.get_parameters(), model.get_parameters())


def test_torch_save_params_layout(trained):
    model, _ = trained
    names, variables = model._get_torch_save_params()
    assert names[0] == "policy" and names[1] == "policy.optimizer" and variables == []
    assert all("optim" in n for n in names[1:])
    assert len(names) == 1 + 4 * model.config.n_levels
    assert model.policy.optimizer is model.policy.hierarchy.levels[0].wm_optimizer
    # the saved state dicts are all real-valued (the S5 parameters are stored as real pairs)
    assert not any(v.is_complex() for v in model.policy.state_dict().values())


def test_set_parameters(trained):
    model, path = trained
    obs = np.random.default_rng(1).normal(size=(10, 4)).astype(np.float32)
    params = model.get_parameters()
    original = {k: v.clone() for k, v in params["policy"].items()}
    randomised = {k: th.rand_like(v) for k, v in original.items()}
    model.set_parameters({"policy": randomised}, exact_match=False)
    for key, value in model.policy.state_dict().items():
        assert th.equal(value, randomised[key]), key
    with pytest.raises(ValueError):
        model.set_parameters({"policy": original}, exact_match=True)  # optimisers missing
    with pytest.raises(ValueError):
        model.set_parameters({"no_such_object": {}}, exact_match=False)
    truncated = dict(original)
    truncated.pop(next(reversed(truncated)))
    with pytest.raises(RuntimeError):
        model.set_parameters({"policy": truncated}, exact_match=True)
    model.set_parameters(path / "model.zip")
    np.testing.assert_array_equal(
        model.predict(obs, deterministic=True)[0], HIEROS.load(path / "model.zip").predict(obs, deterministic=True)[0]
    )


def test_load_without_env_and_custom_objects(trained):
    _, path = trained
    loaded = HIEROS.load(path / "model.zip", custom_objects={"learning_starts": 7, "dummy": 1})
    assert loaded.env is None and loaded.learning_starts == 7 and not hasattr(loaded, "dummy")
    assert loaded.config.learning_starts == 7
    action, state = loaded.predict(np.zeros(4, dtype=np.float32), deterministic=True)
    assert action.shape == () and state[0].shape == (1,)


def test_replay_buffer_round_trip_with_higher_levels(trained):
    model, path = trained
    loaded = HIEROS.load(path / "model.zip", env=make_vec_env("CartPole-v1", n_envs=1))
    assert loaded.replay_buffer.size() == 0
    loaded.load_replay_buffer(path / "replay.pkl")
    old, new = model.level_buffers(), loaded.level_buffers()
    assert len(new) == 3
    for a, b in zip(old, new, strict=True):
        assert b.size() == a.size() > 0
        for field in ("observations", "actions", "rewards", "is_first", "is_terminal"):
            np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
        assert b.device == loaded.device
    assert new[1].subgoals is not None and new[2].subgoals is None  # the top level receives no subgoal
    updates = list(loaded.level_updates())
    loaded.learn(20, reset_num_timesteps=False)
    assert loaded.level_updates()[0] > updates[0]
    wrong = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(n_levels=2))
    with pytest.raises(ValueError, match="3 levels"):
        wrong.load_replay_buffer(path / "replay.pkl")


def test_set_env_and_load_with_other_n_envs(tmp_path):
    model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs())
    model.learn(40)
    with pytest.raises(AssertionError):
        model.set_env(make_vec_env("CartPole-v1", n_envs=2))
    model.set_env(make_vec_env("CartPole-v1", n_envs=1))
    assert model._last_obs is None
    model.learn(24, reset_num_timesteps=False)
    assert model.num_timesteps == 64
    model.save(tmp_path / "model.zip")
    env2 = make_vec_env("CartPole-v1", n_envs=2)
    loaded = HIEROS.load(tmp_path / "model.zip", env=env2)
    assert loaded.n_envs == 2 and loaded.replay_buffer.n_envs == 2
    assert all(b.n_envs == 2 for b in loaded.level_buffers())
    loaded.learn(50)
    assert loaded._n_updates > 0
    assert loaded._hier is not None and loaded._hier.n_envs == 2


@pytest.mark.parametrize(
    ("policy_class", "env_fn"),
    [
        (MlpPolicy, lambda: gym.make("Pendulum-v1")),
        (CnnPolicy, lambda: FakeImageEnv(screen_height=40, screen_width=40, n_channels=2, discrete=True)),
    ],
)
def test_save_load_policy(tmp_path, policy_class, env_fn):
    env = DummyVecEnv([env_fn])
    model = HIEROS(policy_class, env, **tiny_kwargs(n_levels=2))
    model.learn(30)
    obs = np.stack([env.observation_space.sample() for _ in range(5)])
    policy = model.policy
    actions, _ = policy.predict(obs, deterministic=True)
    policy.save(tmp_path / "policy.pkl")
    loaded = policy_class.load(tmp_path / "policy.pkl")
    assert type(loaded) is type(policy)
    new_actions, _ = loaded.predict(obs, deterministic=True)
    np.testing.assert_array_equal(actions, new_actions)
    for (key, a), b in zip(policy.state_dict().items(), loaded.state_dict().values(), strict=True):
        assert th.equal(a, b), key
    # every entry changes under randomisation (no constant or empty persistent buffers)
    state = policy.state_dict()
    for key, value in state.items():
        assert not th.allclose(value, th.rand_like(value)), key


def test_gru_deterministic_state_trains_and_round_trips(tmp_path):
    """``deter_from="gru"``: its recurrent h_t travels in the replay context and the predict state, and survives
    save/load (Box actions, two levels)."""
    overrides = merge_overrides(TINY_OVERRIDES, {"world_model": {"deter_from": "gru"}})
    model = HIEROS("MlpPolicy", "Pendulum-v1", **tiny_kwargs(config_overrides=overrides))
    level0 = model.policy.hierarchy.levels[0].world_model
    assert level0.context_dim == level0.stoch_dim + 2 * level0.sequence_model.state_size + level0.deter_dim
    model.learn(60)
    assert all(n > 0 for n in model.level_updates())
    stored = model.level_buffers()[0].context  # (rows, n_envs, context_dim): the h_t part is written back
    assert np.abs(stored[..., -level0.deter_dim :]).sum() > 0
    obs = np.random.default_rng(0).normal(size=(3, 3)).astype(np.float32)
    _, state = model.predict(obs, deterministic=True)
    _, state = model.predict(obs, state, deterministic=True)
    model.save(tmp_path / "gru.zip")
    loaded = HIEROS.load(tmp_path / "gru.zip")
    assert loaded.config.world_model.deter_from == "gru"
    np.testing.assert_array_equal(
        model.predict(obs, state, deterministic=True)[0], loaded.predict(obs, state, deterministic=True)[0]
    )
