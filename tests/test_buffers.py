import pickle

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3 import DQN
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.utils import set_random_seed

from sb3_hieros.buffers import (
    DictSequenceReplayBuffer,
    ETBSReplayBuffer,
    SequenceReplayBuffer,
    SequenceSamples,
)

OBS_SPACE = spaces.Box(0, 1e6, (2,), np.float32)  # obs = (env, id); ids are consecutive within a stream
ACT_SPACE = spaces.Box(-1e6, 1e6, (1,), np.float32)


class StreamFeeder:
    """Feeds SB3-style transitions whose observations encode (env, id).

    The action taken at observation id k is k, its reward k + 0.5. At a done, next_obs is the terminal
    observation (id k + 1) and the reset observation gets id k + 2, so the rows of a stream, written in
    the Dreamer convention, carry consecutive ids.
    """

    def __init__(self, n_envs: int, episode_length: tuple[int, ...], truncate_every: int = 0, seed: int = 0):
        self.n_envs = n_envs
        self.ids = 100 * np.arange(n_envs, dtype=np.float64)
        self.steps = np.zeros(n_envs, dtype=np.int64)
        self.episodes = np.zeros(n_envs, dtype=np.int64)
        self.episode_length = episode_length
        self.truncate_every = truncate_every
        self.terminal_ids: list[set[float]] = [set() for _ in range(n_envs)]
        self.truncated_ids: list[set[float]] = [set() for _ in range(n_envs)]
        self.rng = np.random.default_rng(seed)

    def obs(self, ids: np.ndarray) -> np.ndarray:
        return np.stack([np.arange(self.n_envs), ids], axis=1).astype(np.float32)

    def step(self, buffer: SequenceReplayBuffer, subgoal: bool = False) -> None:
        self.steps += 1
        cycle = self.episodes * self.n_envs + np.arange(self.n_envs)
        lengths = np.array(self.episode_length)[cycle % len(self.episode_length)]
        done = self.steps >= lengths
        truncated = done & (self.truncate_every > 0) & (self.episodes % max(self.truncate_every, 1) == 1)
        infos = [{"TimeLimit.truncated": bool(t)} if d else {} for d, t in zip(done, truncated, strict=True)]
        for e in np.flatnonzero(done):
            (self.truncated_ids if truncated[e] else self.terminal_ids)[e].add(self.ids[e] + 1)
        kwargs = {"subgoal": np.stack([self.ids, -self.ids], axis=1)} if subgoal else {}
        buffer.add(self.obs(self.ids), self.obs(self.ids + 1), self.ids[:, None], self.ids + 0.5, done, infos, **kwargs)
        self.ids = np.where(done, self.ids + 2, self.ids + 1)
        self.steps[done] = 0
        self.episodes[done] += 1


def fill(buffer, steps, n_envs=1, episode_length=(5,), **kwargs):
    feeder = StreamFeeder(n_envs, episode_length, **kwargs)
    for _ in range(steps):
        feeder.step(buffer)
    return feeder


def check_chunks(samples: SequenceSamples, feeder: StreamFeeder, handle_timeout: bool = True) -> None:
    obs = samples.observations.numpy()
    env, ids = obs[..., 0], obs[..., 1]
    assert (env == env[:, :1]).all(), "a chunk mixes env streams"
    np.testing.assert_array_equal(ids - ids[:, :1], np.broadcast_to(np.arange(ids.shape[1]), ids.shape))
    is_first = samples.is_first.numpy()
    for b in range(ids.shape[0]):
        e = int(env[b, 0])
        terminal = feeder.terminal_ids[e] | (set() if handle_timeout else feeder.truncated_ids[e])
        ended = feeder.terminal_ids[e] | feeder.truncated_ids[e]
        for t in range(ids.shape[1]):
            k = ids[b, t]
            assert samples.is_terminal[b, t] == (k in terminal)
            assert is_first[b, t] == (k - 1 in ended or k == 100 * e)
            expected_action, expected_reward = (0.0, 0.0) if is_first[b, t] else (k - 1, k - 0.5)
            assert samples.actions[b, t, 0] == expected_action
            assert samples.rewards[b, t] == expected_reward


def test_storage_is_tight_and_subclasses_replay_buffer():
    image_space = spaces.Box(0, 255, (8, 8, 3), np.uint8)
    buffer = SequenceReplayBuffer(100, image_space, spaces.Discrete(4), batch_length=4)
    assert isinstance(buffer, ReplayBuffer)
    assert not hasattr(buffer, "next_observations")
    assert buffer.observations.dtype == np.uint8
    assert buffer.observations.shape == (100, 1, 8, 8, 3)
    assert buffer.rewards.dtype == np.float32
    assert buffer.is_first.dtype == buffer.is_terminal.dtype == np.bool_
    assert buffer.subgoals is None


@pytest.mark.parametrize("n_envs", [1, 3])
def test_chunks_are_consecutive_from_one_stream_and_aligned(n_envs):
    buffer = SequenceReplayBuffer(60 * n_envs, OBS_SPACE, ACT_SPACE, n_envs=n_envs, batch_length=8)
    feeder = fill(buffer, 200, n_envs=n_envs, episode_length=(5, 3, 11, 4), truncate_every=3)
    assert buffer.stream_full.all()
    samples = buffer.sample(64)
    assert samples.observations.shape == (64, 8, 2)
    assert samples.actions.shape == (64, 8, 1)
    assert samples.rewards.shape == samples.is_first.shape == samples.is_terminal.shape == (64, 8)
    assert samples.rewards.dtype == th.float32
    assert samples.is_first.dtype == samples.is_terminal.dtype == th.bool
    assert samples.subgoals is None
    check_chunks(samples, feeder)
    assert samples.is_first.any() and samples.is_terminal.any()


def test_terminal_observation_has_its_own_row_with_reward():
    buffer = SequenceReplayBuffer(50, OBS_SPACE, ACT_SPACE, batch_length=4)
    fill(buffer, 4, episode_length=(4,))  # one episode: reset obs 0, obs 1..3, terminal obs 4
    ids = buffer.observations[: buffer.stream_pos[0], 0, 1]
    np.testing.assert_array_equal(ids, [0, 1, 2, 3, 4])
    np.testing.assert_array_equal(buffer.is_terminal[:5, 0], [False, False, False, False, True])
    np.testing.assert_array_equal(buffer.is_first[:5, 0], [True, False, False, False, False])
    assert buffer.rewards[4, 0] == 3.5  # reward received on arriving at the terminal observation
    fill_more = StreamFeeder(1, (4,))
    fill_more.ids[:] = 6  # next episode starts: reset obs row, then its successor
    fill_more.step(buffer)
    np.testing.assert_array_equal(buffer.observations[5:7, 0, 1], [6, 7])
    np.testing.assert_array_equal(buffer.is_first[5:7, 0], [True, False])


@pytest.mark.parametrize("handle_timeout", [True, False])
def test_time_limit_truncation_is_not_terminal(handle_timeout):
    buffer = SequenceReplayBuffer(200, OBS_SPACE, ACT_SPACE, batch_length=6, handle_timeout_termination=handle_timeout)
    feeder = fill(buffer, 60, episode_length=(4, 6), truncate_every=2)
    assert any(feeder.truncated_ids[0]) and any(feeder.terminal_ids[0])
    set_random_seed(0)
    check_chunks(buffer.sample(64), feeder, handle_timeout=handle_timeout)


def test_discontinuous_obs_starts_a_new_episode():
    buffer = SequenceReplayBuffer(50, OBS_SPACE, ACT_SPACE, batch_length=2)
    feeder = fill(buffer, 3, episode_length=(100,))  # rows 0, 1, 2, 3; no done
    feeder.ids[:] = 40  # e.g. learn() reset the env without a done
    feeder.step(buffer)
    np.testing.assert_array_equal(buffer.observations[:6, 0, 1], [0, 1, 2, 3, 40, 41])
    np.testing.assert_array_equal(buffer.is_first[:6, 0], [True, False, False, False, True, False])
    assert buffer.actions[4, 0, 0] == 0 and buffer.rewards[4, 0] == 0


def test_fifo_overwrite_and_every_valid_start_reachable_but_none_across_the_head():
    rows, length = 20, 5
    buffer = SequenceReplayBuffer(rows, OBS_SPACE, ACT_SPACE, batch_length=length)
    feeder = fill(buffer, 47, episode_length=(7,))
    newest = feeder.ids[0]  # id of the last stored next_obs
    stored = np.sort(buffer.observations[:, 0, 1])
    np.testing.assert_array_equal(stored, np.arange(newest - rows + 1, newest + 1))  # the oldest were overwritten
    set_random_seed(1)
    first_ids = buffer.sample(2000).observations[:, 0, 1].numpy()
    expected_starts = np.arange(newest - rows + 1, newest - length + 2)
    np.testing.assert_array_equal(np.unique(first_ids), expected_starts)


def test_streams_with_different_fill_levels():
    buffer = SequenceReplayBuffer(60, OBS_SPACE, ACT_SPACE, n_envs=2, batch_length=6)
    feeder = StreamFeeder(2, (2, 50))  # env 0 ends an episode every 2 steps: 3 rows per 2 steps
    for _ in range(8):
        feeder.step(buffer)
    np.testing.assert_array_equal(buffer.stored_steps(), [12, 9])
    assert buffer.size() == 21
    set_random_seed(2)
    samples = buffer.sample(500)
    check_chunks(samples, feeder)
    env_share = samples.observations[:, 0, 0].numpy().mean()
    assert env_share == pytest.approx(4 / 11, abs=0.06)  # 7 and 4 valid starts


def test_sample_needs_batch_length_steps():
    buffer = SequenceReplayBuffer(40, OBS_SPACE, ACT_SPACE, n_envs=2, batch_length=8)
    with pytest.raises(ValueError, match=r"need at least 8 steps .* hold \[0, 0\] steps"):
        buffer.sample(4)
    fill(buffer, 6, n_envs=2, episode_length=(100,))  # 7 rows per stream
    assert not buffer.can_sample()
    with pytest.raises(ValueError, match=r"hold \[7, 7\] steps"):
        buffer.sample(4)
    fill(buffer, 1, n_envs=2, episode_length=(100,))
    assert buffer.can_sample()
    with pytest.raises(ValueError, match="batch_size"):
        buffer.sample(0)


@pytest.mark.parametrize(
    "field, args, match",
    [
        ("obs", dict(obs=np.zeros((2, 3))), r"obs has shape \(2, 3\), expected \(2, 2\)"),
        ("next_obs", dict(next_obs=np.zeros((1, 2))), r"next_obs has shape \(1, 2\), expected \(2, 2\)"),
        ("action", dict(action=np.zeros((2, 2))), r"action has shape \(2, 2\), expected \(2, 1\)"),
        ("reward", dict(reward=np.zeros(3)), r"reward has shape \(3,\), expected \(2,\)"),
        ("done", dict(done=np.zeros((2, 1))), r"done has shape \(2, 1\), expected \(2,\)"),
        ("infos", dict(infos=[{}]), "infos has length 1"),
        ("subgoal", dict(subgoal=np.zeros((2, 4))), "subgoal_shape=None"),
    ],
)
def test_add_rejects_wrong_shapes(field, args, match):
    buffer = SequenceReplayBuffer(40, OBS_SPACE, ACT_SPACE, n_envs=2, batch_length=4)
    good = dict(obs=np.zeros((2, 2)), next_obs=np.ones((2, 2)), action=np.zeros((2, 1)), reward=np.zeros(2))
    good |= dict(done=np.zeros(2, bool), infos=[{}, {}])
    with pytest.raises(ValueError, match=match):
        buffer.add(**(good | args))
    assert buffer.size() == 0


def test_constructor_bad_input():
    with pytest.raises(ValueError, match="optimize_memory_usage"):
        SequenceReplayBuffer(40, OBS_SPACE, ACT_SPACE, optimize_memory_usage=True, handle_timeout_termination=False)
    with pytest.raises(ValueError, match=r"batch_length=30 exceeds .* = 20"):
        SequenceReplayBuffer(40, OBS_SPACE, ACT_SPACE, n_envs=2, batch_length=30)
    with pytest.raises(ValueError, match="subgoal_shape"):
        SequenceReplayBuffer(40, OBS_SPACE, ACT_SPACE, batch_length=4, subgoal_shape=(0,))
    with pytest.raises(ValueError, match=r"spaces\.Dict"):
        DictSequenceReplayBuffer(40, OBS_SPACE, ACT_SPACE, batch_length=4)
    with pytest.raises(ValueError, match="mode"):
        ETBSReplayBuffer(40, OBS_SPACE, ACT_SPACE, batch_length=4, mode="greedy")
    with pytest.raises(ValueError, match="temperature"):
        ETBSReplayBuffer(40, OBS_SPACE, ACT_SPACE, batch_length=4, temperature=2.0)
    with pytest.raises(ValueError, match="draws_per_insert"):
        ETBSReplayBuffer(40, OBS_SPACE, ACT_SPACE, batch_length=4, mode="meanfield")


def test_subgoals_follow_their_observation():
    buffer = SequenceReplayBuffer(60, OBS_SPACE, ACT_SPACE, n_envs=2, batch_length=5, subgoal_shape=(2,))
    feeder = StreamFeeder(2, (4, 6))
    for _ in range(20):
        feeder.step(buffer, subgoal=True)
    samples = buffer.sample(50)
    check_chunks(samples, feeder)
    obs, goals = samples.observations.numpy(), samples.subgoals.numpy()
    assert goals.shape == (50, 5, 2)
    ids = obs[..., 1]
    newest = ids == feeder.ids[obs[..., 0].astype(int)]  # the stream's newest row when no episode just ended
    # g_t was given with o_t; a terminal (or the newest) observation keeps the last subgoal given
    expected = np.where(samples.is_terminal.numpy() | newest, ids - 1, ids)
    np.testing.assert_array_equal(goals[..., 0], expected)
    np.testing.assert_array_equal(goals[..., 1], -expected)
    # SB3's add (and extend) without a subgoal stores the all-zero code; add_step of the higher levels needs one
    buffer.add(np.full((2, 2), 99.0), np.full((2, 2), 98.0), np.zeros((2, 1)), np.zeros(2), np.zeros(2), [{}, {}])
    newest = (buffer.stream_pos - 1) % buffer.buffer_size
    np.testing.assert_array_equal(buffer.subgoals[newest, [0, 1]], 0.0)
    np.testing.assert_array_equal(buffer.subgoals[newest - 1, [0, 1]], 0.0)  # the is_first row of o = 99
    with pytest.raises(ValueError, match="subgoal is required"):
        buffer.add_step(np.zeros((2, 2)), np.zeros((2, 1)), np.zeros(2), np.ones(2, bool), np.zeros(2, bool))


def test_add_step_writes_dreamer_rows_directly():
    buffer = SequenceReplayBuffer(30, OBS_SPACE, ACT_SPACE, n_envs=2, batch_length=3, subgoal_shape=(1,))
    for t in range(6):
        obs = np.array([[0, t], [1, t]], np.float32)
        first = np.array([t % 3 == 0, t == 0])
        buffer.add_step(
            obs, np.full((2, 1), 10.0 + t), np.full(2, 20.0 + t), first, np.array([t == 2, False]), obs[:, 1:]
        )
    np.testing.assert_array_equal(buffer.stored_steps(), [6, 6])
    samples = buffer._get_chunks(np.array([0, 1]), np.array([1, 3]))
    np.testing.assert_array_equal(samples.observations[..., 1], [[1, 2, 3], [3, 4, 5]])
    np.testing.assert_array_equal(samples.actions[..., 0], [[11, 12, 0], [13, 14, 15]])  # zero at is_first
    np.testing.assert_array_equal(samples.rewards, [[21, 22, 0], [23, 24, 25]])
    np.testing.assert_array_equal(samples.is_first, [[False, False, True], [False, False, False]])
    np.testing.assert_array_equal(samples.is_terminal, [[False, True, False], [False, False, False]])
    np.testing.assert_array_equal(samples.subgoals[..., 0], [[1, 2, 3], [3, 4, 5]])
    with pytest.raises(ValueError, match=r"is_first has shape \(3,\), expected \(2,\)"):
        buffer.add_step(obs, np.zeros((2, 1)), np.zeros(2), np.zeros(3, bool), np.zeros(2, bool), obs[:, 1:])


def test_add_step_with_envs_writes_only_those_streams():
    buffer = SequenceReplayBuffer(30, OBS_SPACE, ACT_SPACE, n_envs=3, batch_length=2)
    ones = np.ones(3, bool)
    buffer.add_step(np.zeros((3, 2), np.float32), np.zeros((3, 1)), np.zeros(3), ones, ~ones)
    # stream 2 alone gets a terminal row; the others keep their write heads
    buffer.add_step(np.array([[2, 7]], np.float32), np.array([[5.0]]), np.array([3.0]), [False], [True], envs=[2])
    np.testing.assert_array_equal(buffer.stored_steps(), [1, 1, 2])
    samples = buffer._get_chunks(np.array([2]), np.array([0]))
    np.testing.assert_array_equal(samples.observations[0, :, 1], [0, 7])
    np.testing.assert_array_equal(samples.actions[0, :, 0], [0, 5])
    np.testing.assert_array_equal(samples.rewards[0], [0, 3])
    np.testing.assert_array_equal(samples.is_terminal[0], [False, True])
    row = (np.zeros((1, 2), np.float32), np.zeros((1, 1)), np.zeros(1), [False], [False])
    for bad in ([3], [1, 1], [], [[0]], [0.5]):
        with pytest.raises(ValueError, match="envs must be a non-empty 1-d array of distinct integer"):
            buffer.add_step(*row, envs=bad)
    with pytest.raises(ValueError, match=r"reward has shape \(3,\), expected \(1,\)"):
        buffer.add_step(row[0], row[1], np.zeros(3), [False], [False], envs=[0])


def test_dict_observations_and_uint8_images():
    obs_space = spaces.Dict({"vec": OBS_SPACE, "image": spaces.Box(0, 255, (4, 4, 3), np.uint8)})
    buffer = DictSequenceReplayBuffer(40, obs_space, spaces.Discrete(3), n_envs=2, batch_length=4)
    assert buffer.observations["image"].dtype == np.uint8

    def observation(ids):
        image = (ids % 256).astype(np.uint8)[:, None, None, None] * np.ones((2, 4, 4, 3), np.uint8)
        return {"vec": np.stack([np.arange(2), ids], axis=1).astype(np.float32), "image": image}

    lengths, steps, ids, terminal = np.array([3, 5]), np.zeros(2), np.array([0.0, 100.0]), set()
    for _ in range(15):
        steps += 1
        done = steps >= lengths
        buffer.add(observation(ids), observation(ids + 1), (ids % 3).astype(np.int64), ids + 0.5, done, [{}, {}])
        terminal |= set((ids + 1)[done])
        ids, steps = np.where(done, ids + 2, ids + 1), np.where(done, 0, steps)
    samples = buffer.sample(32)
    assert samples.observations["image"].dtype == th.uint8
    assert samples.observations["image"].shape == (32, 4, 4, 4, 3)
    sampled_ids = samples.observations["vec"][..., 1].numpy()
    np.testing.assert_array_equal(sampled_ids - sampled_ids[:, :1], np.broadcast_to(np.arange(4), (32, 4)))
    np.testing.assert_array_equal(samples.observations["image"][..., 0, 0, 0], sampled_ids % 256)
    np.testing.assert_array_equal(samples.is_terminal, np.isin(sampled_ids, list(terminal)))
    first = samples.is_first.numpy()
    assert samples.actions.shape == (32, 4, 1)
    np.testing.assert_array_equal(samples.actions[..., 0], np.where(first, 0, (sampled_ids - 1) % 3))
    with pytest.raises(ValueError, match="keys"):
        buffer.add({"vec": ids}, {"vec": ids}, np.zeros(2), np.zeros(2), np.zeros(2), [{}, {}])


@pytest.mark.parametrize("buffer_class", [SequenceReplayBuffer, ETBSReplayBuffer])
def test_replay_context_is_the_stored_state_of_the_row_before(buffer_class):
    buffer = buffer_class(2 * 30, OBS_SPACE, ACT_SPACE, n_envs=2, batch_length=4, context_dim=2)
    feeder = fill(buffer, 100, n_envs=2, episode_length=(5, 3, 11, 4))
    assert buffer.stream_full.all() and not buffer.has_context.any()
    samples = buffer.sample(64)
    assert samples.context.shape == (64, 2) and not samples.context.any()  # nothing stored yet: zeros
    # store each row's (env, id) as its "state"
    buffer.store_context(samples.index, samples.observations)
    rows, envs = samples.index
    assert buffer.has_context[rows, envs[:, None]].all()
    for _ in range(20):
        samples = buffer.sample(64)
        ids = samples.observations[:, 0, 1].numpy()
        context = samples.context.numpy()
        rows, envs = samples.index
        oldest = (rows[:, 0] == buffer.stream_pos[envs]) & buffer.stream_full[envs]
        has = context.any(-1)
        # where there is a context it is the previous row of the same stream, never one across the write head
        np.testing.assert_array_equal(context[has, 0], envs[has])
        np.testing.assert_array_equal(context[has, 1], ids[has] - 1)
        assert not has[oldest].any()
        buffer.store_context(samples.index, samples.observations)
    assert has.any()
    # a new step in a row drops its stored state
    head = buffer.stream_pos.copy()
    feeder.step(buffer)
    assert not buffer.has_context[head, np.arange(2)].any()
    with pytest.raises(ValueError, match="context has shape"):
        buffer.store_context(samples.index, np.zeros((64, 4, 3)))
    plain = buffer_class(60, OBS_SPACE, ACT_SPACE, batch_length=4)
    fill(plain, 10)
    batch = plain.sample(2)
    assert batch.context is None
    with pytest.raises(ValueError, match="keeps no replay context"):
        plain.store_context(batch.index, np.zeros((2, 4, 1)))
    with pytest.raises(ValueError, match="context_dim must be an integer >= 0"):
        buffer_class(60, OBS_SPACE, ACT_SPACE, batch_length=4, context_dim=-1)
    # a buffer pickled before replay context existed loads as one without it and keeps working
    old_state = {k: v for k, v in plain.__dict__.items() if k not in ("context_dim", "context", "has_context")}
    old = buffer_class.__new__(buffer_class)
    old.__setstate__(old_state)
    fill(old, 5)
    assert old.context is None and old.sample(2).context is None and not old.has_context.any()


def test_sampling_is_reproducible_under_global_seed():
    buffer = ETBSReplayBuffer(100, OBS_SPACE, ACT_SPACE, n_envs=2, batch_length=4)
    fill(buffer, 40, n_envs=2, episode_length=(6,))
    set_random_seed(5)
    a = buffer.sample(16)
    set_random_seed(5)
    b = buffer.sample(16)
    np.testing.assert_array_equal(a.observations, b.observations)


@pytest.mark.parametrize("buffer_class, kwargs", [(SequenceReplayBuffer, {}), (ETBSReplayBuffer, dict(mode="count"))])
def test_pickle_round_trip(buffer_class, kwargs):
    buffer = buffer_class(80, OBS_SPACE, ACT_SPACE, n_envs=2, batch_length=5, subgoal_shape=(2,), **kwargs)
    feeder = StreamFeeder(2, (4, 7))
    for _ in range(50):
        feeder.step(buffer, subgoal=True)
    buffer.sample(8)
    restored = pickle.loads(pickle.dumps(buffer, protocol=pickle.HIGHEST_PROTOCOL))
    for name in ["observations", "actions", "rewards", "is_first", "is_terminal", "subgoals", "stream_pos"]:
        np.testing.assert_array_equal(getattr(restored, name), getattr(buffer, name))
    set_random_seed(3)
    a = buffer.sample(8)
    set_random_seed(3)
    b = restored.sample(8)
    for x, y in zip(a[:6], b[:6], strict=True):
        np.testing.assert_array_equal(x, y)
    assert a.context is None and b.context is None
    for x, y in zip(a.index, b.index, strict=True):
        np.testing.assert_array_equal(x, y)
    feeder.step(restored, subgoal=True)  # keeps working after loading
    check_chunks(restored.sample(16), feeder)


class CountingEnv(gym.Env):
    """obs = (episode, step); even episodes terminate after 4 steps, odd ones run until a TimeLimit of 6."""

    observation_space = spaces.Box(0, 1e4, (2,), np.float32)
    action_space = spaces.Discrete(2)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.episode = getattr(self, "episode", -1) + 1
        self.t = 0
        return np.array([self.episode, 0], np.float32), {}

    def step(self, action):
        self.t += 1
        terminated = self.episode % 2 == 0 and self.t == 4
        return np.array([self.episode, self.t], np.float32), float(self.t), terminated, False, {}


def test_sb3_store_transition_and_save_load_replay_buffer(tmp_path):
    env = gym.wrappers.TimeLimit(CountingEnv(), max_episode_steps=6)
    model = DQN(
        "MlpPolicy",
        env,
        learning_starts=10_000,
        buffer_size=200,
        replay_buffer_class=ETBSReplayBuffer,
        replay_buffer_kwargs=dict(batch_length=4),
        policy_kwargs=dict(net_arch=[8]),
        seed=0,
    )
    model.learn(40)
    buffer = model.replay_buffer
    assert isinstance(buffer, ETBSReplayBuffer)
    n = buffer.stored_steps()[0]
    assert n > 40
    episode, step = buffer.observations[:n, 0, 0], buffer.observations[:n, 0, 1]
    np.testing.assert_array_equal(buffer.is_first[:n, 0], step == 0)
    last_of_episode = np.append(episode[1:] != episode[:-1], False)
    assert last_of_episode.sum() >= 5
    # the final observations (step 4 of even episodes, the time limit at step 6 of odd ones) are stored
    np.testing.assert_array_equal(step[last_of_episode], np.where(episode[last_of_episode] % 2 == 0, 4, 6))
    np.testing.assert_array_equal(buffer.is_terminal[:n, 0], (episode % 2 == 0) & (step == 4))
    np.testing.assert_array_equal(buffer.rewards[:n, 0], step)  # reward of arriving at step k is k here

    model.save_replay_buffer(tmp_path / "buffer.pkl")
    model.replay_buffer = None
    model.load_replay_buffer(tmp_path / "buffer.pkl")
    np.testing.assert_array_equal(model.replay_buffer.observations, buffer.observations)
    np.testing.assert_array_equal(model.replay_buffer.is_terminal, buffer.is_terminal)
    assert model.replay_buffer.sample(4).observations.shape == (4, 4, 2)


@pytest.mark.parametrize("mode", ["etbs", "uniform", "reference", "count", "meanfield"])
def test_etbs_buffer_modes_sample_valid_chunks(mode):
    buffer = ETBSReplayBuffer(90, OBS_SPACE, ACT_SPACE, n_envs=3, batch_length=6, mode=mode, draws_per_insert=2.0)
    feeder = fill(buffer, 50, n_envs=3, episode_length=(5, 8))
    for _ in range(5):
        check_chunks(buffer.sample(16), feeder)


def start_ages(buffer: ETBSReplayBuffer, draws: int) -> np.ndarray:
    envs, ages = buffer._sample_starts(draws)
    return ages / buffer.valid_starts()[envs]


def test_etbs_buffer_prefers_recent_chunks_and_reference_skips_old_ones():
    def make(mode):
        buffer = ETBSReplayBuffer(100_000, OBS_SPACE, ACT_SPACE, batch_length=4, mode=mode)
        fill(buffer, 1003, episode_length=(50,))  # ~1000 valid starts, capacity ~100000
        return buffer

    set_random_seed(0)
    uniform, etbs, reference = (start_ages(make(m), 20_000) for m in ["uniform", "etbs", "reference"])
    assert uniform.mean() == pytest.approx(0.5, abs=0.02)
    assert etbs.mean() > uniform.mean() + 0.05
    assert (reference < 0.3).mean() < 0.01 < 0.15 < (etbs < 0.3).mean()


def test_count_mode_spreads_draws_and_clears_overwritten_counters():
    buffer = ETBSReplayBuffer(40, OBS_SPACE, ACT_SPACE, batch_length=4, mode="count", count_temperature=0.05)
    fill(buffer, 20, episode_length=(100,))  # 21 rows -> 18 valid starts
    set_random_seed(0)
    for _ in range(36):
        buffer.sample(1)  # the least drawn starts win, so every start is drawn twice
    counts = buffer.counter.counts[: buffer.stored_steps()[0]]
    np.testing.assert_array_equal(counts[:18], 2)
    assert not counts[18:].any()
    fill_more = StreamFeeder(1, (100,))
    fill_more.ids[:] = 20  # continues the same episode
    for _ in range(25):  # wraps: rows overwritten get fresh counters
        fill_more.step(buffer)
    assert buffer.stream_full[0] and buffer.stream_pos[0] == 6
    assert not buffer.counter.counts[:6].any()
    assert buffer.counter.counts[6:18].all()


@pytest.mark.parametrize("handle_timeout", [True, False])
@pytest.mark.parametrize("steps", [30, 200])  # part-filled and wrapped streams
def test_sb3_dones_and_timeouts_mark_every_episode_end(handle_timeout, steps):
    buffer = SequenceReplayBuffer(
        120, OBS_SPACE, ACT_SPACE, n_envs=2, batch_length=4, handle_timeout_termination=handle_timeout
    )
    feeder = fill(buffer, steps, n_envs=2, episode_length=(4, 6, 3), truncate_every=2)
    assert "dones" not in vars(buffer) and "timeouts" not in vars(buffer)  # computed, not stored
    dones, timeouts = buffer.dones, buffer.timeouts
    assert dones.shape == timeouts.shape == buffer.rewards.shape and dones.dtype == timeouts.dtype == np.float32
    stored = buffer.stored_steps()
    for e in range(2):
        rows = np.arange(buffer.buffer_size) < stored[e]
        ids = buffer.observations[:, e, 1]
        ended = np.isin(ids, list(feeder.terminal_ids[e] | feeder.truncated_ids[e])) & rows
        truncated = np.isin(ids, list(feeder.truncated_ids[e])) & rows
        assert ended.any() and truncated.any()
        np.testing.assert_array_equal(dones[:, e], ended)
        np.testing.assert_array_equal(timeouts[:, e], truncated if handle_timeout else 0.0)


def test_sample_transitions_are_sb3s_replay_buffer_samples():
    from stable_baselines3.common.type_aliases import DictReplayBufferSamples, ReplayBufferSamples

    buffer = SequenceReplayBuffer(60, OBS_SPACE, ACT_SPACE, n_envs=2, batch_length=4)
    feeder = fill(buffer, 100, n_envs=2, episode_length=(5, 3), truncate_every=2)
    set_random_seed(0)
    samples = buffer.sample_transitions(300)
    assert isinstance(samples, ReplayBufferSamples)
    obs, next_obs = samples.observations.numpy(), samples.next_observations.numpy()
    assert obs.shape == next_obs.shape == (300, 2) and samples.dones.shape == samples.rewards.shape == (300, 1)
    k = obs[:, 1]
    np.testing.assert_array_equal(next_obs, np.stack([obs[:, 0], k + 1], 1))  # o_{t+1} of the same stream
    np.testing.assert_array_equal(samples.actions[:, 0].numpy(), k)  # the action taken at id k is k
    np.testing.assert_array_equal(samples.rewards[:, 0].numpy(), k + 0.5)
    terminal = [next_id in feeder.terminal_ids[int(e)] for e, next_id in next_obs]
    np.testing.assert_array_equal(samples.dones[:, 0].numpy(), terminal)  # truncations are not dones (as SB3)
    ended = [kk in feeder.terminal_ids[int(e)] | feeder.truncated_ids[int(e)] for e, kk in obs]
    assert samples.dones.any() and not any(ended), "a transition crossed an episode border"

    dict_space = spaces.Dict({"a": OBS_SPACE, "b": spaces.Discrete(3)})
    dict_buffer = DictSequenceReplayBuffer(20, dict_space, spaces.Discrete(2), batch_length=2)
    for t in range(5):
        pair = [{"a": np.full((1, 2), t + i, np.float32), "b": np.array([(t + i) % 3])} for i in (0, 1)]
        dict_buffer.add(*pair, np.array([t % 2]), np.ones(1), np.zeros(1), [{}])
    dict_samples = dict_buffer.sample_transitions(8)
    assert isinstance(dict_samples, DictReplayBufferSamples)
    np.testing.assert_array_equal(dict_samples.next_observations["a"][:, 0], dict_samples.observations["a"][:, 0] + 1)
    with pytest.raises(ValueError, match="no transition"):
        SequenceReplayBuffer(20, OBS_SPACE, ACT_SPACE, batch_length=2).sample_transitions(4)


def test_extend_as_sb3s_tests_call_it():
    """SB3's test_save_load_replay_buffer extends a buffer with its own arrays; a buffer that stores subgoals takes
    them too (the subgoals are zero)."""
    buffer = SequenceReplayBuffer(200, OBS_SPACE, ACT_SPACE, n_envs=2, batch_length=4, subgoal_shape=(2,))
    feeder = StreamFeeder(2, (4,))
    for _ in range(10):
        feeder.step(buffer, subgoal=True)
    before = buffer.size()
    infos = [[{"TimeLimit.truncated": bool(t)} for t in row] for row in buffer.timeouts]
    arrays = [
        a.copy() for a in (buffer.observations, buffer.observations, buffer.actions, buffer.rewards, buffer.dones)
    ]
    buffer.extend(*arrays, infos)
    assert buffer.size() > before and buffer.stream_full.all()  # 100 transitions per stream, at least one row each
    newest = (buffer.stream_pos - 1) % buffer.buffer_size
    assert not buffer.subgoals[newest, [0, 1]].any()
