"""benchmarks/cpu_suite.py: HIEROS against zoo-configured SB3 baselines (tiny budget only)."""

from __future__ import annotations

import json

import pytest

pytest.importorskip("rl_zoo3", reason="the 'zoo' extra is not installed")

from benchmarks.cpu_suite import TASKS, main, suite_runs, zoo_hyperparams
from benchmarks.sample_efficiency import ZOO_DQN, ZOO_PPO


def test_zoo_hyperparams_read_from_rl_zoo3():
    n_envs, dqn = zoo_hyperparams("dqn", "CartPole-v1")
    expected = {k: v for k, v in ZOO_DQN.items() if k not in ("n_envs", "n_timesteps")}
    assert n_envs == ZOO_DQN["n_envs"] and dqn == expected  # the values benchmarks.sample_efficiency retyped
    n_envs, ppo = zoo_hyperparams("ppo", "CartPole-v1")
    assert n_envs == 8 and ppo["n_steps"] == 32 and ppo["gamma"] == ZOO_PPO["gamma"]
    assert ppo["learning_rate"](1.0) == pytest.approx(1e-3) and ppo["learning_rate"](0.5) == pytest.approx(5e-4)
    assert zoo_hyperparams("sac", "Pendulum-v1") == (1, {"learning_rate": 1e-3})
    with pytest.raises(ValueError, match="no entry"):
        zoo_hyperparams("dqn", "Pendulum-v1")


def test_suite_runs_skip_unsupported_pairs():
    runs = suite_runs(list(TASKS), ["dqn", "sac"], [0], 100)
    assert [(r.task, r.algo) for r in runs] == [
        ("CartPole-v1", "dqn"),
        ("Pendulum-v1", "sac"),
        ("cartpole-balance-proprio", "sac"),
        ("cartpole-balance-pixels", "sac"),
    ]
    with pytest.raises(ValueError, match="unknown algo"):
        suite_runs(["CartPole-v1"], ["a2c"], [0], 100)


def test_tiny_cartpole_suite(tmp_path):
    records = main(
        [
            "--tasks", "CartPole-v1", "--algos", "hieros", "ppo", "dqn", "--seeds", "1", "--steps", "256",
            "--eval-episodes", "2", "--n-evals", "2", "--out", str(tmp_path),
            "--hieros-kwargs", json.dumps({"learning_starts": 1000, "buffer_size": 1000}),
        ]
    )  # fmt: skip
    assert [r["algo"] for r in records] == ["hieros", "ppo", "dqn"]
    for record in records:
        assert record["eval_steps"][0] >= 128 and record["eval_steps"][-1] >= 256 and len(record["eval_returns"]) == 2
        assert record["final_mean"] == record["eval_returns"][-1] > 0 and record["trained_steps"] == 256
    markdown = (tmp_path / "table.md").read_text()
    assert markdown.startswith("| Task | Steps | HIEROS small | PPO | DQN |") and "| CartPole-v1 | 256 |" in markdown
    assert (tmp_path / "cpu_suite.png").is_file()
    assert json.loads((tmp_path / "results.json").read_text()) == records
