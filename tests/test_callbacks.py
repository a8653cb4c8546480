"""SubgoalDecodeCallback and ImaginationCallback: image and vector paths, PNG and TensorBoard output, n_levels 1-3,
the every-schedule, loaded models, and no effect on training (tiny configurations)."""

from __future__ import annotations

import os
import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from hieros_helpers import SmallDictEnv, tiny_kwargs
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.logger import configure

from sb3_hieros import HIEROS, ImaginationCallback, SubgoalDecodeCallback
from sb3_hieros.buffers import SequenceReplayBuffer
from sb3_hieros.callbacks import recent_window

pytest.importorskip("matplotlib")
from matplotlib.image import imread


class MovingSquareEnv(gym.Env):
    """16x16 RGB frames (channel-last uint8) of a red square that the actions move left, not at all, or right."""

    observation_space = spaces.Box(0, 255, (16, 16, 3), np.uint8)
    action_space = spaces.Discrete(3)

    def __init__(self) -> None:
        self.x = self.y = self.t = 0

    def _obs(self) -> np.ndarray:
        frame = np.full((16, 16, 3), 40, dtype=np.uint8)
        frame[self.y : self.y + 4, self.x : self.x + 4] = (220, 30, 30)
        return frame

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.x, self.y = (int(v) for v in self.np_random.integers(0, 12, size=2))
        self.t = 0
        return self._obs(), {}

    def step(self, action):
        self.x = int(np.clip(self.x + int(action) - 1, 0, 12))
        self.t += 1
        return self._obs(), float(self.x == 6), False, self.t >= 15, {}


def _pngs(directory) -> list[str]:
    return sorted(name for name in os.listdir(directory) if name.endswith(".png"))


@pytest.mark.parametrize("env_fn", [MovingSquareEnv, lambda: SmallDictEnv(discrete=False)])
def test_image_path_writes_pngs(tmp_path, env_fn):
    policy = "MultiInputPolicy" if env_fn is not MovingSquareEnv else "CnnPolicy"
    model = HIEROS(policy, env_fn(), **tiny_kwargs())
    subgoals = SubgoalDecodeCallback(every=20, save_dir=tmp_path / "sg", tensorboard=False)
    imagination = ImaginationCallback(every=20, horizon=5, context=3, save_dir=tmp_path / "im", tensorboard=False)
    model.learn(40, callback=[subgoals, imagination])
    assert _pngs(tmp_path / "sg") == ["subgoals_000000020_env0.png", "subgoals_000000040_env0.png"]
    assert _pngs(tmp_path / "im") == ["imagination_000000020.png", "imagination_000000040.png"]
    assert subgoals.saved_files == [tmp_path / "sg" / name for name in _pngs(tmp_path / "sg")]
    for path in [*subgoals.saved_files, *imagination.saved_files]:
        image = imread(path)
        assert image.ndim == 3 and image.shape[0] > 100 and image.shape[1] > 100
        assert image[..., :3].std() > 0.01, f"{path} is blank"
    errors = imagination.last_errors
    keys = ["img", "vec"] if policy == "MultiInputPolicy" else ["obs"]
    assert sorted(errors) == keys
    assert all(e.shape == (5,) and np.isfinite(e).all() and (e >= 0).all() for e in errors.values())
    assert errors[keys[0]].max() <= 1.0  # images: squared error of pixels scaled to [0, 1]
    lines = (tmp_path / "im" / "imagination_errors.csv").read_text().splitlines()
    assert lines[0].startswith("num_timesteps,key,error_t1") and len(lines) == 1 + 2 * len(keys)


def test_vector_path_and_tensorboard_images(tmp_path):
    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    env = make_vec_env("CartPole-v1", n_envs=2, seed=0)
    model = HIEROS("MlpPolicy", env, tensorboard_log=str(tmp_path / "tb"), **tiny_kwargs(n_levels=3))
    subgoals = SubgoalDecodeCallback(every=30, n_envs_shown=2, save_dir=tmp_path / "png")
    imagination = ImaginationCallback(every=40, horizon=4, context=2)
    model.learn(80, callback=[subgoals, imagination])
    assert _pngs(tmp_path / "png") == [f"subgoals_{s:09d}_env{j}.png" for s in (30, 60) for j in (0, 1)]
    run = tmp_path / "tb" / "HIEROS_1"
    events = EventAccumulator(str(run), size_guidance={"images": 0})
    events.Reload()
    assert sorted(events.Tags()["images"]) == ["imagination/env0", "subgoals/env0", "subgoals/env1"]
    assert [e.step for e in events.Images("subgoals/env1")] == [30, 60]
    assert [e.step for e in events.Images("imagination/env0")] == [40, 80]
    assert events.Images("subgoals/env0")[0].width > 100
    assert imagination.saved_files == [] and not (tmp_path / "tb" / "imagination_errors.csv").exists()


@pytest.mark.parametrize("n_levels", [1, 2, 3])
def test_decode_subgoals_every_depth(n_levels, tmp_path):
    model = HIEROS("CnnPolicy", MovingSquareEnv(), **tiny_kwargs(n_levels=n_levels))
    callback = SubgoalDecodeCallback(every=10, save_dir=tmp_path)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model.learn(20, callback=callback)
        model.learn(10, callback=callback, reset_num_timesteps=False)
    said = [w for w in caught if "n_levels=1" in str(w.message)]
    assert len(said) == (1 if n_levels == 1 else 0)
    decoded = model.decoded_subgoals()[1]
    assert len(decoded) == n_levels - 1
    for obs in decoded:
        assert obs.shape == (1, 3, 16, 16) and obs.dtype == th.float32
        assert float(obs.min()) >= 0.0 and float(obs.max()) <= 255.0
    assert len(callback.saved_files) == (0 if n_levels == 1 else 3)
    assert len(_pngs(tmp_path)) == len(callback.saved_files)


def test_decode_chain_goes_through_each_level():
    model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(n_levels=3))
    model.learn(30)
    policy, hier = model.policy, model.hierarchy_state
    sub0, sub1 = policy.hierarchy.levels[0], policy.hierarchy.levels[1]
    # the split of a decoded higher-level observation relies on the world state being [h, z]
    th.testing.assert_close(
        sub0.encoded_observation(hier.latents[0]), th.cat([hier.latents[0].deter, hier.latents[0].stoch], -1)
    )
    level1, level2 = policy.hierarchy.decode_subgoals(hier)
    th.testing.assert_close(
        level1, sub0.decode_state_observation(sub0.decode_subgoal(hier.actions[1]), hier.latents[0].stoch)
    )
    stacked = sub1.decode_state_observation(sub1.decode_subgoal(hier.actions[2]), hier.latents[1].stoch)
    last = stacked.reshape(1, policy.hierarchy.subgoal_interval, sub0.latent_dim)[:, -1]
    th.testing.assert_close(level2, sub0.decode_state_observation(last[:, : sub0.h_dim], last[:, sub0.h_dim :]))
    assert level1.shape == level2.shape == (1, 4)


def test_draws_only_on_its_steps():
    class Counting(SubgoalDecodeCallback):
        def __init__(self, every):
            super().__init__(every, tensorboard=True)
            self.drawn_at: list[int] = []

        def _draw(self):
            self.drawn_at.append(self.num_timesteps)

    env = make_vec_env("CartPole-v1", n_envs=3, seed=0)
    model = HIEROS("MlpPolicy", env, **tiny_kwargs())
    callback = Counting(every=10)
    model.learn(45, callback=callback)
    assert callback.drawn_at == [12, 21, 30, 42]  # once per crossed multiple of 10, counted in env steps
    model.learn(15, callback=callback, reset_num_timesteps=False)
    assert callback.drawn_at[4:] == [51, 60]


def _parameters_after_learning(callbacks) -> dict[str, th.Tensor]:
    model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(seed=5, n_levels=3, learning_starts=10))
    model.learn(40, callback=callbacks)
    assert model._n_updates > 0 and model.level_updates()[2] > 0
    state = {f"policy.{k}": v.clone() for k, v in model.policy.state_dict().items()}
    state.update({f"level{i}.rewards": th.as_tensor(b.rewards.copy()) for i, b in enumerate(model.level_buffers())})
    return state


def test_no_effect_on_training(tmp_path):
    class Leaky(BaseCallback):
        """Draws one number from numpy's global generator, as an unisolated drawing might."""

        def _on_step(self):
            if self.num_timesteps % 10 == 0:
                np.random.random()  # noqa: NPY002
            return True

    reference = _parameters_after_learning([])
    drawing = [
        SubgoalDecodeCallback(every=7, save_dir=tmp_path),
        ImaginationCallback(every=9, horizon=4, context=2, save_dir=tmp_path),
    ]
    with_callbacks = _parameters_after_learning(drawing)
    assert len(drawing[0].saved_files) == 5 and len(drawing[1].saved_files) > 0
    for name, value in reference.items():
        assert th.equal(value, with_callbacks[name]), name
    # the comparison can fail: a callback that touches the replay sampler's random state changes training
    leaky = _parameters_after_learning([Leaky()])
    assert any(not th.equal(value, leaky[name]) for name, value in reference.items())


def test_works_on_a_loaded_model(tmp_path):
    model = HIEROS("CnnPolicy", MovingSquareEnv(), **tiny_kwargs())
    model.learn(40)
    model.save(tmp_path / "model.zip")
    loaded = HIEROS.load(tmp_path / "model.zip", env=MovingSquareEnv())
    callbacks = [
        SubgoalDecodeCallback(every=10, save_dir=tmp_path / "png", tensorboard=False),
        ImaginationCallback(every=20, horizon=3, context=2, save_dir=tmp_path / "png", tensorboard=False),
    ]
    loaded.learn(20, callback=callbacks)
    assert len(callbacks[0].saved_files) == 2 and len(callbacks[1].saved_files) == 1
    assert all(path.is_file() for callback in callbacks for path in callback.saved_files)


def test_recent_window_avoids_episode_starts_in_the_imagined_part():
    buffer = SequenceReplayBuffer(40, spaces.Box(-1, 1, (2,), np.float32), spaces.Discrete(2), n_envs=1, batch_length=4)
    firsts = [True, False, False, False, True, False, False, False, False, True, False]
    for t, first in enumerate(firsts):
        buffer.add_step(np.full((1, 2), t, np.float32), np.zeros((1, 1)), np.zeros(1), np.array([first]), np.zeros(1))
    rows = recent_window(buffer, 0, context=2, horizon=3)
    assert rows.tolist() == [4, 5, 6, 7, 8]
    assert recent_window(buffer, 0, context=1, horizon=1).tolist() == [9, 10]
    assert recent_window(buffer, 0, context=1, horizon=5) is None
    assert recent_window(buffer, 0, context=10, horizon=2) is None  # 12 > 11 stored steps


def test_argument_checks():
    with pytest.raises(ValueError, match="every"):
        SubgoalDecodeCallback(every=0)
    with pytest.raises(ValueError, match="write nothing"):
        ImaginationCallback(every=10, tensorboard=False)
    with pytest.raises(ValueError, match="horizon"):
        ImaginationCallback(every=10, horizon=0)
    with pytest.raises(ValueError, match="n_envs_shown"):
        SubgoalDecodeCallback(every=10, n_envs_shown=0)
    model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs())
    with pytest.raises(ValueError, match="n_envs_shown=2 exceeds"):
        model.learn(5, callback=SubgoalDecodeCallback(every=10, n_envs_shown=2))


def test_reward_terms_are_logged_per_level(tmp_path):
    model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(learning_starts=10))
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(60, log_interval=1)
    assert model.level_updates()[1] > 0
    header = (tmp_path / "progress.csv").read_text().splitlines()[0].split(",")
    for key in ("level0/reward/extrinsic", "level0/reward/subgoal", "level0/reward/novelty", "level1/reward/extrinsic"):
        assert f"train/{key}" in header, key
    assert "train/level1/reward/subgoal" not in header  # the top level has no subgoal reward
