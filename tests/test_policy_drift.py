"""benchmarks/policy_drift.py on tiny runs: the window figures, the policy it reads, the cart, and the checks."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch as th
from hieros_helpers import TINY_OVERRIDES, tiny_kwargs
from stable_baselines3.common.env_util import make_vec_env

from benchmarks import policy_drift
from benchmarks.cpu_suite import TASKS, task_vec_env
from sb3_hieros import HIEROS


def test_window_figures():
    taken = np.array([[1.0], [-0.96], [0.5], [0.0]])
    mode = np.array([[0.99], [0.2], [-0.4], [0.97]])
    std = np.array([[0.5], [0.3], [0.2], [0.2]])
    figures = policy_drift.window_figures(
        taken,
        mode,
        std,
        np.array([1.0, 0.0, 0.5, 0.5]),
        np.array([True, True, False, False]),
        np.array([0, 1.9, -2, 1]),
    )
    assert figures == pytest.approx(
        {
            "warmup": 0.5,
            "taken_at_bounds": 0.5,
            "mode_mean": 0.44,
            "mode_abs": 0.64,
            "mode_at_bounds": 0.5,
            "mode_spread": np.std([0.99, 0.2, -0.4, 0.97]),
            "std": 0.3,
            "reward": 0.5,
            "cart_out_of_view": 0.5,
        }
    )
    assert "cart_out_of_view" not in policy_drift.window_figures(taken, mode, std, np.zeros(4), np.zeros(4, bool))
    assert "mode_state_r2" not in figures


def test_mode_state_r2_tells_a_controller_from_a_push():
    states = np.array([[0.1, 1.0], [-0.3, 0.5], [0.2, -1.0], [0.0, 0.3], [0.4, 0.0]])  # (N, S)
    controller = 2.0 * states[:, :1] - 0.1  # a linear state feedback, within the bounds here
    push = np.ones((5, 1))
    zeros, no = np.zeros((5, 1)), np.zeros(5, bool)
    reacts = policy_drift.window_figures(zeros, controller, zeros + 0.2, np.zeros(5), no, None, states)
    assert reacts["mode_state_r2"] == pytest.approx(1.0) and reacts["mode_spread"] > 0.4
    pushes = policy_drift.window_figures(zeros, push, zeros + 0.2, np.zeros(5), no, None, states)
    assert np.isnan(pushes["mode_state_r2"]) and pushes["mode_spread"] == 0.0


def _pinned_actor(model: HIEROS, mean_raw: float, std_raw: float) -> None:
    """Level 0's actor outputs ``mean_raw`` and ``std_raw`` whatever its input."""
    out = model.policy.hierarchy.levels[0].actor_critic.actor.net.out
    with th.no_grad():
        out.weight.zero_()
        out.bias.copy_(th.tensor([mean_raw, std_raw]))


def test_rows_read_the_policy_in_force_and_the_actions_taken():
    # world models learn from step 20, the actors learn and act from step 40
    overrides = {**TINY_OVERRIDES, "actor_learning_starts": 40}
    env = make_vec_env("Pendulum-v1", n_envs=1, seed=0)
    model = HIEROS("MlpPolicy", env, **tiny_kwargs(config_overrides=overrides, learning_starts=20))
    _pinned_actor(model, 10.0, -10.0)  # mode tanh(10) = 1, std at its floor 0.1
    drift = policy_drift.PolicyDrift(20)
    model.learn(60, callback=drift)
    rows = drift.rows
    assert [row["step"] for row in rows] == [20, 40, 60]
    assert [row["warmup"] for row in rows] == [1.0, 1.0, 0.0]
    for row in rows:  # the policy is read in the warm-up too, where it is not followed
        assert row["mode_at_bounds"] == 1.0 and row["mode_mean"] > 0.99
        assert row["mode_spread"] == 0.0 and np.isnan(row["mode_state_r2"])  # the same push in every state
        assert row["std"] == pytest.approx(0.1, abs=0.01)
        assert "cart_out_of_view" not in row
    # uniformly random actions reach |a| > 0.95 one time in twenty; samples of N(1, 0.1) clipped to 1, two in three
    assert rows[0]["taken_at_bounds"] <= 0.2 and rows[1]["taken_at_bounds"] <= 0.2
    assert rows[2]["taken_at_bounds"] >= 0.4
    assert "actor_grad_norm" not in rows[1] and rows[2]["actor_grad_norm"] >= 0.0


def test_main_prints_and_writes_the_rows(tmp_path, capsys):
    kwargs = tiny_kwargs()
    kwargs.pop("seed")
    out = tmp_path / "drift.json"
    args = ["--task", "Pendulum-v1", "--steps", "40", "--window", "20", "--hieros-kwargs", json.dumps(kwargs)]
    rows = policy_drift.main([*args, "--out", str(out)])
    assert json.loads(out.read_text()) == rows and len(rows) == 2
    printed = capsys.readouterr().out
    assert "| step | warmup | taken_at_bounds | mode_mean |" in printed and "\n| 40 | 0 |" in printed


def test_cart_positions_come_from_the_simulator(monkeypatch):
    env = task_vec_env(TASKS["cartpole-balance-proprio"], 1, 0)
    model = HIEROS("MlpPolicy", env, **tiny_kwargs(learning_starts=5))
    drift = policy_drift.PolicyDrift(10, cartpole=True)
    model.learn(10, callback=drift)
    assert drift.rows[0]["cart_out_of_view"] == 0.0  # the cart starts near the centre and stays there for 10 steps
    read, passed = [], []

    def state(env):  # the cart out of view; the second entry counts the reads
        read.append(env.unwrapped.physics)
        return np.array([-1.8, float(len(read))])

    def figures(*args):
        passed.append(args)
        return window_figures(*args)

    window_figures = policy_drift.window_figures
    monkeypatch.setattr(policy_drift, "physical_state", state)
    monkeypatch.setattr(policy_drift, "window_figures", figures)
    model.learn(10, callback=drift, reset_num_timesteps=False)
    assert drift.rows[1]["cart_out_of_view"] == 1.0 and len(read) == 11  # once before the first action, once a step
    states = passed[0][-1]  # the state each action was chosen in: the read before it
    assert states[:, 1].tolist() == list(range(1, 11))
    env.close()


def test_checks():
    with pytest.raises(ValueError, match="window must be an int >= 1, got 0"):
        policy_drift.PolicyDrift(0)
    with pytest.raises(ValueError, match="window must be an int >= 1, got 0"):
        policy_drift.main(["--task", "Pendulum-v1", "--window", "0"])
    with pytest.raises(ValueError, match="'CartPole-v1' has Discrete\\(2\\) actions; policy_drift needs Box actions"):
        policy_drift.run_drift("CartPole-v1", 0, 20, 10)
    with pytest.raises(ValueError, match="unknown task 'Pendulum'"):
        policy_drift.run_drift("Pendulum", 0, 20, 10)
    with pytest.raises(ValueError, match="steps must be an int >= window \\(10\\), got 5"):
        policy_drift.run_drift("Pendulum-v1", 0, 5, 10)
    model = HIEROS("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=2, seed=0), **tiny_kwargs(learning_starts=5))
    with pytest.raises(ValueError, match="PolicyDrift watches one env, got n_envs=2"):
        model.learn(10, callback=policy_drift.PolicyDrift(5))
