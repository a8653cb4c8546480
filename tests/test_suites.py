"""Environment makers of the benchmark suites (benchmarks/suites.py)."""

from __future__ import annotations

import csv
import os

os.environ.setdefault("MUJOCO_GL", "egl")  # before anything imports dm_control: offscreen rendering

import gymnasium as gym
import numpy as np
import pytest

from benchmarks.suites import (
    ATARI100K_GAMES,
    ATARI100K_THESIS_LABELS,
    DATA_DIR,
    DMC_VISION_TASKS,
    DMC_VISION_THESIS_LABELS,
    SUITES,
    ActionRepeat,
    make_atari_env,
    make_dmc_env,
    make_env,
)


def _thesis_table(name: str) -> list[str]:
    """Row labels of a thesis table CSV in benchmarks/data."""
    with open(DATA_DIR / name) as f:
        return [row["task"] for row in csv.DictReader(f)]


def _needs_ale() -> None:
    pytest.importorskip("ale_py", reason="the 'atari' extra is not installed")
    pytest.importorskip("cv2", reason="the 'atari' extra is not installed")


def _needs_dmc() -> None:
    pytest.importorskip("shimmy", reason="the 'dmc' extra (dm-control, shimmy, imageio) is not installed")


def test_task_lists_match_thesis_tables():
    assert len(ATARI100K_GAMES) == len(set(ATARI100K_GAMES)) == 26
    assert len(DMC_VISION_TASKS) == len(set(DMC_VISION_TASKS)) == 20
    assert "UpNDown" in ATARI100K_GAMES and "UpNDown" not in ATARI100K_THESIS_LABELS
    assert sorted(ATARI100K_THESIS_LABELS.values()) == sorted(_thesis_table("thesis_table_5_1_atari100k.csv"))
    assert sorted(DMC_VISION_THESIS_LABELS.values()) == sorted(_thesis_table("thesis_table_5_2_dmc_vision.csv"))
    assert SUITES["atari100k"].agent_steps * SUITES["atari100k"].action_repeat == SUITES["atari100k"].env_steps


def test_atari_pong_protocol():
    _needs_ale()
    env = make_atari_env("Pong", seed=0)
    assert env.observation_space == gym.spaces.Box(0, 255, (64, 64, 3), np.uint8)
    assert env.action_space == gym.spaces.Discrete(6)
    obs, _ = env.reset(seed=1)
    assert obs.shape == (64, 64, 3) and obs.dtype == np.uint8 and obs.max() > obs.min()
    ale = env.unwrapped.ale
    assert ale.getFloat("repeat_action_probability") == 0.0
    assert ale.getInt("max_num_frames_per_episode") == 108_000
    before = ale.getEpisodeFrameNumber()
    obs, *_ = env.step(0)
    assert ale.getEpisodeFrameNumber() - before == 4  # action repeat 4
    assert obs.shape == (64, 64, 3) and obs.dtype == np.uint8
    env.close()


def test_atari_flags():
    _needs_ale()
    env = make_atari_env("Pong", seed=0, sticky=True, size=32, full_action_space=True, noop_max=0)
    assert env.unwrapped.ale.getFloat("repeat_action_probability") == 0.25
    assert env.observation_space.shape == (32, 32, 3)
    assert env.action_space == gym.spaces.Discrete(18)
    env.reset(seed=0)
    assert env.unwrapped.ale.getEpisodeFrameNumber() == 0  # no no-ops
    env.close()
    env = make_atari_env("Pong", seed=0, noop_max=30)
    frames = set()
    for seed in range(6):
        env.reset(seed=seed)
        frames.add(env.unwrapped.ale.getEpisodeFrameNumber())
    assert all(f % 4 == 0 and 0 <= f <= 120 for f in frames) and len(frames) > 1
    env.close()


def test_dmc_pixels():
    _needs_dmc()
    env = make_env("dmc_vision", "cartpole-balance", seed=0)
    assert env.observation_space == gym.spaces.Box(0, 255, (64, 64, 3), np.uint8)
    assert env.action_space == gym.spaces.Box(-1.0, 1.0, (1,), np.float32)
    obs, _ = env.reset(seed=0)
    assert obs.shape == (64, 64, 3) and obs.dtype == np.uint8 and obs.max() > obs.min()
    obs2, reward, terminated, truncated, _ = env.step(env.action_space.sample())
    assert obs2.shape == (64, 64, 3) and obs2.dtype == np.uint8 and not np.array_equal(obs, obs2)
    assert isinstance(reward, float) and not terminated and not truncated
    env.close()


def test_dmc_proprio_and_action_repeat():
    _needs_dmc()
    repeated = make_env("dmc_proprio", "cartpole-balance", seed=3)
    single = make_dmc_env("cartpole-balance", seed=3, pixels=False, action_repeat=1)
    assert repeated.observation_space.shape == (5,) and repeated.observation_space.dtype == np.float32
    obs_r, _ = repeated.reset(seed=3)
    obs_s, _ = single.reset(seed=3)
    assert obs_r.dtype == np.float32
    np.testing.assert_array_equal(obs_r, obs_s)
    action = np.array([0.7], dtype=np.float32)
    obs_r, reward_r, *_ = repeated.step(action)
    reward_s = 0.0
    for _ in range(2):
        obs_s, r, *_ = single.step(action)
        reward_s += float(r)
    np.testing.assert_allclose(obs_r, obs_s)
    assert reward_r == pytest.approx(reward_s) and reward_r > 1.0  # two rewards summed, each in [0, 1]
    # dm_control's 1000 control steps: 500 agent steps at repeat 2, ending in a truncation
    steps, truncated, terminated = 1, False, False
    while not (truncated or terminated):
        *_, terminated, truncated, _ = repeated.step(action)
        steps += 1
    assert steps == 500 and truncated and not terminated
    repeated.close()
    single.close()


def test_unknown_names_refused():
    with pytest.raises(ValueError, match="unknown suite"):
        make_env("procgen", "Pong")
    with pytest.raises(ValueError, match="atari100k task"):
        make_env("atari100k", "Tetris")
    with pytest.raises(ValueError, match="unknown classic task"):
        make_env("classic", "CartPole-v99")
    with pytest.raises(ValueError, match="dmc_vision task"):
        make_env("dmc_vision", "cartpole-two_poles")
    with pytest.raises(ValueError, match="repeat"):
        ActionRepeat(gym.make("CartPole-v1"), 0)
    _needs_ale()
    with pytest.raises(ValueError, match="unknown Atari game"):
        make_atari_env("Pongg")
    with pytest.raises(ValueError, match="size"):
        make_atari_env("Pong", size=0)
    _needs_dmc()
    for task in ("cartpole-nope", "cartpole", "cartpole-balance-v0"):
        with pytest.raises(ValueError, match="unknown DMC task"):
            make_dmc_env(task, pixels=False)
    with pytest.raises(ValueError, match="fixes pixels"):
        make_env("dmc_proprio", "cartpole-balance", pixels=True)


def test_classic_suite():
    assert SUITES["classic"].action_repeat == 1 and "CartPole-v1" in SUITES["classic"].tasks
    starts = [make_env("classic", "Pendulum-v1", seed=seed).reset()[0] for seed in (2, 2, 3)]
    np.testing.assert_array_equal(starts[0], starts[1])  # seeded streams
    assert not np.array_equal(starts[0], starts[2])
    assert make_env("classic", "CartPole-v1").observation_space.shape == (4,)
