"""benchmarks/zoo.py: HIEROS trained, saved and replayed through rl_zoo3's own train/enjoy entry points."""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import gymnasium as gym
import numpy as np
import pytest
import torch as th
import yaml

pytest.importorskip("rl_zoo3", reason="the 'zoo' extra is not installed")

from benchmarks._equivalence_cases import TINY_NETWORKS
from benchmarks.suites import DMC_VISION_TASKS, make_atari_env
from benchmarks.zoo import HYPERPARAMS_FILE, dmc_env_id, main, register_hieros, sample_hieros_params
from sb3_hieros import HIEROS


def test_train_then_enjoy(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    main(
        [
            "train", "--algo", "hieros", "--env", "CartPole-v1", "-n", "600", "--seed", "1", "--num-threads", "1",
            "--eval-freq", "300", "--eval-episodes", "2", "--verbose", "0",
            "-params", "learning_starts:560", "config_overrides:dict(train_ratio=32)",
        ]
    )  # fmt: skip
    folder = tmp_path / "logs" / "hieros" / "CartPole-v1_1"
    for name in ("CartPole-v1.zip", "best_model.zip", "evaluations.npz", "0.monitor.csv", "CartPole-v1/config.yml"):
        assert (folder / name).is_file(), name
    model = HIEROS.load(folder / "CartPole-v1.zip")
    assert model.num_timesteps == 600 and model.preset == "small" and model.learning_starts == 560
    assert sum(model.level_updates()) > 0  # it trained
    assert np.load(folder / "evaluations.npz")["timesteps"].tolist() == [300, 600]
    main(["enjoy", "--algo", "hieros", "--env", "CartPole-v1", "-f", "logs", "--no-render", "-n", "60",
          "--reward-log", "rewards", "--num-threads", "1", "--deterministic"])  # fmt: skip
    episodes = (tmp_path / "rewards" / "0.monitor.csv").read_text().splitlines()[2:]
    assert episodes and all(float(line.split(",")[0]) > 0 for line in episodes)


def test_yml_with_gamma_and_policy_kwargs_trains(tmp_path, monkeypatch):
    """A zoo yml written for SB3's algorithms: gamma, policy_kwargs (a string the zoo evaluates, with optimizer and
    net_arch), a learning-rate schedule."""
    monkeypatch.chdir(tmp_path)
    entry = {
        "n_timesteps": 120,
        "policy": "MlpPolicy",
        "preset": "small",
        "gamma": 0.95,
        "learning_rate": "lin_1e-3",
        "learning_starts": 60,
        "batch_size": 2,
        "policy_kwargs": "dict(net_arch=[32, 32], optimizer_class=th.optim.Adam, optimizer_kwargs=dict(eps=1e-6))",
        "config_overrides": {**TINY_NETWORKS, "batch_length": 8, "train_ratio": 16},
    }
    (tmp_path / "hyperparams.yml").write_text(yaml.safe_dump({"FrozenLake-v1": entry}))
    main(
        [
            "train", "--algo", "hieros", "--env", "FrozenLake-v1", "--seed", "1", "--num-threads", "1",
            "--eval-freq", "-1", "--verbose", "0", "-conf", "hyperparams.yml",
        ]
    )  # fmt: skip
    model = HIEROS.load(tmp_path / "logs" / "hieros" / "FrozenLake-v1_1" / "FrozenLake-v1.zip")
    assert model.gamma == 0.95 and model.config.actor_critic.discount == 0.95
    assert (model.config.actor_critic.units, model.config.actor_critic.layers) == (32, 2)
    levels = model.policy.hierarchy.levels
    assert all(type(o) is th.optim.Adam and o.param_groups[0]["eps"] == 1e-6 for o in levels[0].optimizers.values())
    assert model.num_timesteps == 120 and model.level_updates()[0] > 0


def test_hyperparams_file_and_registration():
    hyperparams = yaml.safe_load(HYPERPARAMS_FILE.read_text())
    assert {"atari", "CartPole-v1", "Pendulum-v1", dmc_env_id("cartpole-balance")} <= set(hyperparams)
    assert hyperparams["atari"]["n_timesteps"] == 100_000 and hyperparams["atari"]["preset"] == "paper"
    for task in DMC_VISION_TASKS:
        assert hyperparams[dmc_env_id(task)]["policy"] == "CnnPolicy"
        assert hyperparams[dmc_env_id(task, pixels=False)]["policy"] == "MlpPolicy"
    register_hieros()
    import rl_zoo3
    from rl_zoo3.hyperparams_opt import HYPERPARAMS_SAMPLER

    assert rl_zoo3.ALGOS["hieros"] is HIEROS and "hieros" in HYPERPARAMS_SAMPLER
    optuna = pytest.importorskip("optuna")
    trial = optuna.trial.FixedTrial(
        {"learning_rate": 3e-4, "train_ratio": 64, "imag_horizon": 8, "subgoal_interval": 4}
    )
    assert sample_hieros_params(trial, 2, 1, {}) == {
        "learning_rate": 3e-4,
        "config_overrides": {"train_ratio": 64, "imag_horizon": 8, "subgoal_interval": 4},
    }


def test_atari_key_is_the_suite_protocol():
    pytest.importorskip("ale_py", reason="the 'atari' extra is not installed")
    from rl_zoo3.utils import get_wrapper_class

    entry = yaml.safe_load(HYPERPARAMS_FILE.read_text())["atari"]
    zoo_env = get_wrapper_class(entry)(gym.make("ALE/Pong-v5", **entry["env_kwargs"]))
    suite_env = make_atari_env("Pong", seed=0)
    assert zoo_env.observation_space == suite_env.observation_space
    assert zoo_env.action_space == suite_env.action_space
    for seed in (0, 7):
        np.testing.assert_array_equal(zoo_env.reset(seed=seed)[0], suite_env.reset(seed=seed)[0])
    for _ in range(5):
        a, b = zoo_env.step(2), suite_env.step(2)
        np.testing.assert_array_equal(a[0], b[0])
        assert a[1:4] == b[1:4]


def test_dmc_ids():
    pytest.importorskip("shimmy", reason="the 'dmc' extra is not installed")
    register_hieros()
    env = gym.make(dmc_env_id("cartpole-balance", pixels=False))
    assert env.observation_space.shape == (5,) and env.action_space.shape == (1,)
    env.close()
