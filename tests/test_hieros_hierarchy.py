"""Replay bookkeeping of the hierarchy (thesis 4.6.1, Algorithm 1): rows of every level at the right rate (k**i), with
correct flags, rewards and histories around episode ends, per env."""

from __future__ import annotations

import numpy as np
import pytest
from gymnasium.wrappers import TimeLimit
from hieros_helpers import CountingEnv, tiny_kwargs
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_hieros import HIEROS

K = 2
NO_TRAINING = 10**9  # learning_starts: random actions, no updates, the hierarchy still encodes every step


def stream(buffer, env: int) -> dict[str, np.ndarray]:
    """Rows of one env stream in write order (the buffers here never wrap)."""
    n = int(buffer.stream_pos[env])
    assert not buffer.stream_full[env]
    rows = {
        "obs": buffer.observations[:n, env],
        "action": buffer.actions[:n, env],
        "reward": buffer.rewards[:n, env],
        "is_first": buffer.is_first[:n, env],
        "is_terminal": buffer.is_terminal[:n, env],
    }
    if buffer.subgoals is not None:
        rows["subgoal"] = buffer.subgoals[:n, env]
    return rows


def expected_rows(n_steps: int, length: int, level: int, terminated: bool, final_reward: float):
    """Flags and rewards of the rows that level ``level`` must write for one env with episodes of ``length`` steps.

    Acting step t observes o_t; a row is written when ``t % k**level == 0`` or o_t starts an episode, and a terminal
    row after the step that ends an episode. Rewards: 1 per step, ``final_reward`` for the step that terminates
    (a truncated episode's last step pays 1), summed since the previous row of this env.
    """
    rows, pending = [], 0.0
    for t in range(n_steps):
        start = t % length == 0
        if t % K**level == 0 or start:
            rows.append((start, False, 0.0 if start else pending))
            pending = 0.0
        ends = (t + 1) % length == 0
        pending += final_reward if ends and terminated else 1.0
        if ends:
            rows.append((False, terminated, pending))
            pending = 0.0
    return rows, pending


def make_model(env_fns, n_levels=3):
    env = DummyVecEnv(env_fns)
    return HIEROS("MlpPolicy", env, **tiny_kwargs(n_levels=n_levels, subgoal_interval=K, learning_starts=NO_TRAINING))


def test_rows_at_rate_k_pow_i_without_episode_ends():
    model = make_model([lambda: CountingEnv(length=None)] * 2)
    model.learn(2 * 20)  # 20 steps of each env
    assert model._n_updates == 0
    buffers = model.level_buffers()
    assert buffers[0].stored_steps().tolist() == [21, 21]  # reset row + one row per step
    for level in (1, 2):
        assert buffers[level].stored_steps().tolist() == [-(-20 // K**level)] * 2
        rows = stream(buffers[level], 0)
        assert rows["is_first"].tolist() == [True] + [False] * (len(rows["is_first"]) - 1)
        assert not rows["is_terminal"].any()
        # reward = sum of the K**level env rewards (1 each) since the previous row
        assert rows["reward"][1:].tolist() == [float(K**level)] * (len(rows["reward"]) - 1)


@pytest.mark.parametrize("truncate", [False, True])
def test_rows_flags_and_rewards_around_episode_ends(truncate):
    lengths = (5, 7)
    final_reward = 10.0

    def make(length):
        if truncate:
            return lambda: TimeLimit(CountingEnv(length=None), max_episode_steps=length)
        return lambda: CountingEnv(length=length, final_reward=final_reward)

    model = make_model([make(length) for length in lengths])
    n_steps = 30
    model.learn(len(lengths) * n_steps)
    latent_dims = [model.policy.hierarchy.levels[i].latent_dim for i in range(3)]
    for level in (1, 2):
        buffer = model.level_buffers()[level]
        for env, length in enumerate(lengths):
            expected, pending = expected_rows(n_steps, length, level, not truncate, final_reward)
            rows = stream(buffer, env)
            got = list(
                zip(rows["is_first"].tolist(), rows["is_terminal"].tolist(), rows["reward"].tolist(), strict=True)
            )
            assert got == expected, f"level {level}, env {env}"
            # nothing is lost: the rewards not yet written wait in this env's running sum
            assert model._rows.reward_sums[level][env] == pytest.approx(pending)
            # an episode's first row sees only its first state: the slots from before the reset are zero
            slot = latent_dims[level - 1]
            obs = rows["obs"].reshape(len(got), K, slot)
            assert np.all(obs[rows["is_first"], :-1] == 0.0)
            assert np.all(np.abs(obs[rows["is_first"], -1]).sum(-1) > 0)
            # a terminal row ends with the encoded final observation (a new state, not a copy of the one before)
            ends = np.flatnonzero(~rows["is_first"] & np.roll(rows["is_first"], -1))
            assert len(ends) >= 1
            assert np.all(np.abs(obs[ends, -1] - obs[ends, -2]).sum(-1) > 0)
            # subgoals from the level above are one-hot codes; the top level receives none
            if level == 1:
                groups = rows["subgoal"].reshape(len(got), 4, 4)
                assert np.all(groups.sum(-1) == 1.0)
            else:
                assert "subgoal" not in rows


def test_subgoal_held_between_updates():
    length = 7
    model = make_model([lambda: CountingEnv(length=length)], n_levels=2)
    n_steps = 40
    model.learn(n_steps)
    rows = stream(model.replay_buffer, 0)
    # map acting steps to level-0 rows: each episode = is_first row, then one row per step (the last is terminal)
    acting_rows, row = [], 0
    for t in range(n_steps):
        if t % length == 0 and t > 0:
            row += 1  # skip the previous episode's terminal row
        acting_rows.append(row)
        row += 1
    goals = rows["subgoal"][acting_rows]  # subgoal in force at o_t
    for t in range(1, n_steps):
        update = t % K == 0 or t % length == 0
        if not update:
            np.testing.assert_array_equal(goals[t], goals[t - 1], err_msg=f"subgoal changed at step {t}")
    changes = [t for t in range(1, n_steps) if not np.array_equal(goals[t], goals[t - 1])]
    assert len(changes) >= n_steps // (2 * K)  # random subgoals are redrawn at the updates


def test_level0_rows_follow_sb3_transitions():
    model = make_model([lambda: CountingEnv(length=4, final_reward=3.0)], n_levels=2)
    model.learn(8)
    rows = stream(model.replay_buffer, 0)
    # two episodes of 4 steps: reset row, 3 rows, terminal row (reward 3), twice
    assert rows["is_first"].tolist() == [True, False, False, False, False] * 2
    assert rows["is_terminal"].tolist() == [False, False, False, False, True] * 2
    assert rows["reward"].tolist() == [0.0, 1.0, 1.0, 1.0, 3.0] * 2
    assert rows["obs"][:, 0].tolist() == [0.0, 1.0, 2.0, 3.0, 4.0] * 2
