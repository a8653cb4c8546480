"""SubgoalDecodeCallback on vector observations: labelled bars per entry and rendered frames of the subgoals."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from hieros_helpers import SmallDictEnv, tiny_kwargs
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import VecNormalize

import sb3_hieros.callbacks as callbacks_module
from sb3_hieros import HIEROS, SubgoalDecodeCallback
from sb3_hieros.callbacks import CLASSIC_CONTROL_OBSERVATIONS, ClassicControlRenderer, observation_labels

pytest.importorskip("matplotlib")
from matplotlib.image import imread

CARTPOLE = ["cart position", "cart velocity", "pole angle", "pole angular velocity"]


class RecordingRenderer:
    """A renderer that keeps what it was asked to draw and returns a grey frame."""

    def __init__(self) -> None:
        self.calls: list[np.ndarray] = []

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        self.calls.append(np.array(obs))
        return np.full((30, 45, 3), 128, dtype=np.uint8)


def test_observation_labels():
    assert observation_labels("obs", 4, "CartPole-v1") == CARTPOLE
    assert observation_labels("obs", 3, "Pendulum-v1") == ["cos(angle)", "sin(angle)", "angular velocity"]
    assert observation_labels("obs", 3, "MyEnv-v0") == ["obs[0]", "obs[1]", "obs[2]"]
    assert observation_labels("obs", 5, "CartPole-v1") == [f"obs[{i}]" for i in range(5)]  # not CartPole's layout
    assert observation_labels("vec", 2, None) == ["vec[0]", "vec[1]"]
    assert observation_labels("obs", 2, "CartPole-v1", ["a", "b"]) == ["a", "b"]
    with pytest.raises(ValueError, match="must name its 4 entries"):
        observation_labels("obs", 4, None, ["a", "b"])
    assert all(len(layout.labels) > 0 for layout in CLASSIC_CONTROL_OBSERVATIONS.values())


def test_cartpole_bars_are_labelled_and_every_subgoal_is_rendered(tmp_path):
    renderer = RecordingRenderer()
    model = HIEROS("MlpPolicy", make_vec_env("CartPole-v1", n_envs=1, seed=0), **tiny_kwargs(n_levels=3))
    plain = SubgoalDecodeCallback(every=30, save_dir=tmp_path / "bars", tensorboard=False, renderer=None)
    framed = SubgoalDecodeCallback(every=30, save_dir=tmp_path / "frames", tensorboard=False, renderer=renderer)
    model.learn(60, callback=[plain, framed])
    assert plain.entry_labels == framed.entry_labels == {"obs": CARTPOLE}
    # per picture: the real observation and the subgoals of levels 1 and 2, each one CartPole state
    assert len(renderer.calls) == 2 * 3 and all(call.shape == (4,) for call in renderer.calls)
    assert len(framed.saved_files) == len(plain.saved_files) == 2
    bars, frames = imread(plain.saved_files[0]), imread(framed.saved_files[0])
    assert frames.shape[0] > bars.shape[0]  # a row of frames below the bars
    assert bars[..., :3].std() > 0.01


def test_labels_argument_and_its_checks(tmp_path):
    model = HIEROS("MlpPolicy", make_vec_env("CartPole-v1", n_envs=1, seed=0), **tiny_kwargs())
    names = ["x", "x dot", "theta", "theta dot"]
    callback = SubgoalDecodeCallback(every=25, save_dir=tmp_path, labels=names, renderer=None, tensorboard=False)
    model.learn(25, callback=callback)
    assert callback.entry_labels == {"obs": names} and len(callback.saved_files) == 1
    with pytest.raises(ValueError, match="must name its 4 entries"):
        model.learn(5, callback=SubgoalDecodeCallback(every=10, save_dir=tmp_path, labels=["x"]))
    with pytest.raises(ValueError, match="Box observation space must be a sequence"):
        model.learn(5, callback=SubgoalDecodeCallback(every=10, save_dir=tmp_path, labels={"obs": names}))
    with pytest.raises(ValueError, match="labels must be"):
        SubgoalDecodeCallback(every=10, save_dir=tmp_path, labels="x")
    with pytest.raises(ValueError, match="renderer must be"):
        SubgoalDecodeCallback(every=10, save_dir=tmp_path, renderer="pygame")

    dict_model = HIEROS("MultiInputPolicy", SmallDictEnv(discrete=True), **tiny_kwargs())
    with pytest.raises(ValueError, match="not vector or discrete keys"):
        dict_model.learn(5, callback=SubgoalDecodeCallback(every=10, save_dir=tmp_path, labels={"img": ["a"]}))
    callback = SubgoalDecodeCallback(every=10, save_dir=tmp_path, tensorboard=False)
    dict_model.learn(10, callback=callback)
    assert callback.entry_labels == {"vec": [f"vec[{i}]" for i in range(3)]}  # images keep the grid, no renderer
    assert callback._state_renderer is None


def test_renderer_gets_observations_in_the_env_units_under_vec_normalize(tmp_path):
    venv = VecNormalize(make_vec_env("CartPole-v1", n_envs=1, seed=0), norm_reward=False)
    model = HIEROS("MlpPolicy", venv, **tiny_kwargs())
    expected: list[np.ndarray] = []

    def renderer(obs: np.ndarray) -> np.ndarray:
        if not expected:  # the first call of a picture draws the real observation
            expected.append(venv.unnormalize_obs(model._last_obs[0]))
            assert not np.allclose(model._last_obs[0], expected[0])  # the model sees normalised values
            np.testing.assert_allclose(obs, expected[0], rtol=1e-5, atol=1e-5)
        return np.zeros((10, 10, 3), dtype=np.uint8)

    model.learn(40, callback=SubgoalDecodeCallback(every=40, save_dir=tmp_path, renderer=renderer, tensorboard=False))
    assert expected


def test_auto_renderer_without_pygame_warns_and_draws_bars(tmp_path, monkeypatch):
    def missing(self, env_id):
        raise gym.error.DependencyNotInstalled("pygame is not installed")

    monkeypatch.setattr(callbacks_module.ClassicControlRenderer, "__init__", missing)
    model = HIEROS("MlpPolicy", make_vec_env("CartPole-v1", n_envs=1, seed=0), **tiny_kwargs())
    callback = SubgoalDecodeCallback(every=25, save_dir=tmp_path, tensorboard=False)
    with pytest.warns(UserWarning, match="cannot render without pygame.*bars only"):
        model.learn(25, callback=callback)
    assert callback._state_renderer is None and len(callback.saved_files) == 1


def test_classic_control_renderer_draws_the_given_state():
    pytest.importorskip("pygame")
    renderer = ClassicControlRenderer("CartPole-v1")
    left, right = renderer(np.array([-1.5, 0.0, 0.0, 0.0])), renderer(np.array([1.5, 0.0, 0.0, 0.0]))
    assert left.shape == (400, 600, 3) and left.dtype == np.uint8
    assert not np.array_equal(left, right)
    np.testing.assert_array_equal(left, renderer(np.array([-1.5, 0.0, 0.0, 0.0])))  # the state alone decides
    renderer.close()

    pendulum = ClassicControlRenderer("Pendulum-v1")
    pendulum(np.array([0.0, 1.0, 2.0]))  # (cos, sin, velocity) -> (angle, velocity)
    np.testing.assert_allclose(pendulum.env.unwrapped.state, [np.pi / 2, 2.0])
    with pytest.raises(ValueError, match="expected an observation of 3 entries"):
        pendulum(np.zeros(4))
    with pytest.raises(ValueError, match="classic-control task"):
        ClassicControlRenderer("ALE/Pong-v5")
