"""SB3 callbacks with HIEROS (SB3 test_callbacks style): checkpoints with replay, evaluation, stopping, events."""

from __future__ import annotations

import os

import numpy as np
import pytest
import torch as th
from hieros_helpers import tiny_kwargs
from stable_baselines3.common.callbacks import (
    BaseCallback,
    CallbackList,
    CheckpointCallback,
    EvalCallback,
    EveryNTimesteps,
    StopTrainingOnMaxEpisodes,
)
from stable_baselines3.common.env_util import make_vec_env

from sb3_hieros import HIEROS


class RecordingCallback(BaseCallback):
    def __init__(self) -> None:
        super().__init__()
        self.seen_new_obs = 0

    def _on_step(self) -> bool:
        assert "new_obs" in self.locals and "dones" in self.locals and "infos" in self.locals
        self.seen_new_obs += 1
        return True


def test_checkpoint_eval_and_event_callbacks(tmp_path):
    model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs())
    checkpoint = CheckpointCallback(save_freq=30, save_path=str(tmp_path / "ckpt"), save_replay_buffer=True)
    eval_env = make_vec_env("CartPole-v1", n_envs=3, seed=2)
    evaluation = EvalCallback(
        eval_env, eval_freq=25, n_eval_episodes=3, log_path=str(tmp_path / "eval"), best_model_save_path=str(tmp_path)
    )
    recording = RecordingCallback()
    event = EveryNTimesteps(n_steps=20, callback=CheckpointCallback(save_freq=1, save_path=str(tmp_path / "event")))
    model.learn(60, callback=CallbackList([checkpoint, evaluation, recording, event]))
    assert recording.n_calls == model.num_timesteps == recording.seen_new_obs == 60
    assert os.path.isfile(tmp_path / "ckpt" / "rl_model_60_steps.zip")
    assert os.path.isfile(tmp_path / "ckpt" / "rl_model_replay_buffer_60_steps.pkl")
    assert os.path.isfile(tmp_path / "best_model.zip")
    results = np.load(tmp_path / "eval" / "evaluations.npz")
    assert results["timesteps"].tolist() == [25, 50] and results["results"].shape == (2, 3)
    assert len(os.listdir(tmp_path / "event")) == 3
    # a checkpoint and its replay restore every level (saved in on_step, i.e. before the last transition is stored)
    loaded = HIEROS.load(tmp_path / "ckpt" / "rl_model_60_steps.zip")
    loaded.load_replay_buffer(tmp_path / "ckpt" / "rl_model_replay_buffer_60_steps.pkl")
    sizes, final = [b.size() for b in loaded.level_buffers()], [b.size() for b in model.level_buffers()]
    assert len(sizes) == 2 and final[0] - 2 <= sizes[0] < final[0] and 0 < sizes[1] <= final[1]


@pytest.mark.parametrize("stop_value", [False, np.bool_(0), th.tensor(False)])
def test_callback_returning_false_stops_at_once(stop_value):
    class Stop(BaseCallback):
        def _on_step(self):
            return stop_value

    model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs())
    callback = Stop()
    model.learn(50, callback=callback)
    assert callback.n_calls == 1
    assert model.num_timesteps == 1


def test_stop_on_max_episodes_and_functional_callback():
    calls = []

    def count(locals_, globals_):
        calls.append(locals_["self"].num_timesteps)
        return True

    model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs())
    stop = StopTrainingOnMaxEpisodes(max_episodes=2)
    model.learn(10_000, callback=[stop])
    assert stop.n_episodes == 2 and model.num_timesteps < 200
    model.learn(5, callback=count)
    assert calls == [1, 2, 3, 4, 5]
