"""benchmarks/cartpole_failures.py on a tiny model: end causes and the per-|x| estimates."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from hieros_helpers import tiny_kwargs

from benchmarks import cartpole_failures
from sb3_hieros import HIEROS


@pytest.fixture(scope="module")
def cartpole_model(tmp_path_factory):
    model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs())
    model.learn(40)
    path = tmp_path_factory.mktemp("cartpole") / "model.zip"
    model.save(path)
    return path


def test_end_cause_reads_the_thresholds():
    env = gym.make("CartPole-v1")
    assert cartpole_failures.end_cause(np.array([2.5, 0.0, 0.01, 0.0]), True, env) == "x"
    assert cartpole_failures.end_cause(np.array([-2.5, 0.0, 0.01, 0.0]), True, env) == "x"
    assert cartpole_failures.end_cause(np.array([0.1, 0.0, 0.3, 0.0]), True, env) == "theta"
    assert cartpole_failures.end_cause(np.array([2.5, 0.0, 0.3, 0.0]), False, env) == "time_limit"


def test_report_counts_every_episode(cartpole_model, capsys):
    figures = cartpole_failures.main([str(cartpole_model), "--episodes", "3"])
    ends = figures["ended_cart_off_track"] + figures["ended_pole_fell"] + figures["ended_time_limit"]
    assert ends == 3
    assert 1 <= figures["mean_length"] <= 500
    out = capsys.readouterr().out
    assert out.count("episode ") == 3 and "| abs(x) |" in out
    # the same seeds and a deterministic policy replay the same episodes
    assert cartpole_failures.main([str(cartpole_model), "--episodes", "3"]) == figures


def test_refuses_other_models_and_bad_counts(tmp_path, cartpole_model):
    with pytest.raises(ValueError, match="--episodes"):
        cartpole_failures.main([str(cartpole_model), "--episodes", "0"])
    model = HIEROS("MlpPolicy", "Pendulum-v1", **tiny_kwargs())
    model.save(tmp_path / "pendulum.zip")
    with pytest.raises(ValueError, match="not trained on CartPole-v1"):
        cartpole_failures.main([str(tmp_path / "pendulum.zip")])


def test_reset_every_restarts_the_agent_state(cartpole_model, monkeypatch):
    model = HIEROS.load(cartpole_model, device="cpu")
    starts = []
    predict = model.predict

    def spy(obs, state=None, episode_start=None, deterministic=False):
        starts.append(bool(episode_start[0]))
        return predict(obs, state=state, episode_start=episode_start, deterministic=deterministic)

    monkeypatch.setattr(model, "predict", spy)
    obs, _, _ = cartpole_failures.play(model, gym.make("CartPole-v1"), 0, True, reset_every=3)
    assert len(starts) == len(obs) > 3
    assert starts == [t % 3 == 0 for t in range(len(obs))]
    starts.clear()
    cartpole_failures.play(model, gym.make("CartPole-v1"), 0, True)
    assert starts[0] and not any(starts[1:])
    with pytest.raises(ValueError, match="--reset-every must be >= 0"):
        cartpole_failures.main([str(cartpole_model), "--reset-every", "-1"])
