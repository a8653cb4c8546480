"""Reliability of HIEROS (issue 9): resuming a run, non-finite observations, non-finite updates, corrupted or foreign
saves, bad predict input and the replay memory estimate. Tiny configurations (SB3 test-suite style)."""

from __future__ import annotations

import traceback
import warnings
import zipfile
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from hieros_helpers import TINY_OVERRIDES, SmallDictEnv, tiny_kwargs
from stable_baselines3 import DQN
from stable_baselines3.common.callbacks import CheckpointCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import DummyVecEnv, VecCheckNan

import sb3_hieros.buffers.sequence as buffers_module
from sb3_hieros import HIEROS
from sb3_hieros.buffers import ETBSReplayBuffer, SequenceReplayBuffer
from sb3_hieros.buffers.levels import level_buffer_size


class NanEnv(gym.Env):
    """5-step episodes of float observations; the observation of step ``nan_at`` of episode ``episode`` is NaN (and
    the reward of step ``reward_nan_at`` of every episode).

    Step 0 is the reset observation, step 5 the terminal one. ``key`` makes it a Dict env ({"a", "b"}) whose entry
    ``key`` turns NaN.
    """

    def __init__(
        self,
        nan_at: int | None = None,
        episode: int = 0,
        key: str | None = None,
        value: float = np.nan,
        reward_nan_at: int | None = None,
    ):
        box = spaces.Box(-10.0, 10.0, (3,), np.float32)
        self.observation_space = spaces.Dict({"a": box, "b": box}) if key is not None else box
        self.action_space = spaces.Discrete(2)
        self.nan_at, self.nan_episode, self.key, self.value = nan_at, episode, key, value
        self.reward_nan_at = reward_nan_at
        self.t, self.episode = 0, -1

    def _obs(self) -> Any:
        bad = self.t == self.nan_at and self.episode == self.nan_episode
        vec = np.full(3, self.value if bad and self.key in (None, "a") else 0.1 * self.t, np.float32)
        if self.key is None:
            return vec
        other = np.full(3, self.value if bad and self.key == "b" else 0.0, np.float32)
        return {"a": vec, "b": other}

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[Any, dict]:
        super().reset(seed=seed)
        self.t, self.episode = 0, self.episode + 1
        return self._obs(), {}

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict]:
        self.t += 1
        reward = np.nan if self.t == self.reward_nan_at else 1.0
        return self._obs(), reward, self.t >= 5, False, {}


def _adam_steps(model: HIEROS) -> list[float]:
    """Adam's step count of the first parameter of every optimiser (an optimiser state that must survive resume)."""
    steps = []
    for i in range(model.config.n_levels):
        for opt in model.policy.hierarchy.levels[i].optimizers.values():
            state = opt.state[opt.param_groups[0]["params"][0]]
            steps.append(float(state["step"]) if state else 0.0)
    return steps


# ------------------------------------------------------------------------------------------------ resume


def test_resume_continues_where_it_stopped(tmp_path):
    """Stop at N, save model and replay, load both and go on: same counters as a run that never stopped."""
    kwargs = tiny_kwargs(n_levels=2)
    straight = HIEROS("MlpPolicy", "CartPole-v1", **kwargs)
    straight.learn(50)
    straight.learn(20, reset_num_timesteps=False)

    stopped = HIEROS("MlpPolicy", "CartPole-v1", **kwargs)
    stopped.learn(50)
    assert all(n > 0 for n in stopped.level_updates())  # every level trains before the stop
    stopped.save(tmp_path / "model.zip")
    stopped.save_replay_buffer(tmp_path / "replay.pkl")
    sizes = [b.size() for b in stopped.level_buffers()]

    resumed = HIEROS.load(tmp_path / "model.zip", env=make_vec_env("CartPole-v1", n_envs=1))
    resumed.load_replay_buffer(tmp_path / "replay.pkl")
    # the schedule counters, the optimiser states and every level's replay come back
    assert resumed.num_timesteps == 50
    assert resumed._n_updates == stopped._n_updates
    assert resumed.level_updates() == stopped.level_updates()
    assert resumed._update_budget == stopped._update_budget
    assert _adam_steps(resumed) == _adam_steps(stopped)
    assert [b.size() for b in resumed.level_buffers()] == sizes
    for a, b in zip(stopped.level_buffers(), resumed.level_buffers(), strict=True):
        np.testing.assert_array_equal(a.stream_pos, b.stream_pos)
        np.testing.assert_array_equal(a.observations, b.observations)

    resumed.learn(20, reset_num_timesteps=False)
    # training neither restarts (warm-up, burst of catch-up updates) nor waits: the same updates as without the stop
    assert resumed.num_timesteps == straight.num_timesteps == 70
    assert resumed._n_updates == straight._n_updates
    assert resumed.level_updates() == straight.level_updates()
    assert _adam_steps(resumed) == _adam_steps(straight)


def test_resume_from_checkpoint_callback(tmp_path):
    """``CheckpointCallback(save_replay_buffer=True)`` files resume a run (see docs/resume.md)."""
    model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(n_levels=2))
    checkpoint = CheckpointCallback(
        save_freq=25, save_path=str(tmp_path), name_prefix="hieros", save_replay_buffer=True
    )
    model.learn(50, callback=checkpoint)
    assert (tmp_path / "hieros_50_steps.zip").exists()
    resumed = HIEROS.load(tmp_path / "hieros_50_steps.zip", env=make_vec_env("CartPole-v1", n_envs=1))
    resumed.load_replay_buffer(tmp_path / "hieros_replay_buffer_50_steps.pkl")
    assert resumed.num_timesteps == 50
    sizes = [b.size() for b in resumed.level_buffers()]
    assert len(sizes) == 2 and all(s > 0 for s in sizes)
    # the checkpoint of step 50 is taken before step 50's transition is stored: one level-0 row less
    assert sizes[0] == model.replay_buffer.size() - 1
    updates = resumed._n_updates
    resumed.learn(20, reset_num_timesteps=False)
    assert resumed.num_timesteps == 70 and resumed._n_updates > updates


# ------------------------------------------------------------------------------------------------ observations


@pytest.mark.parametrize(
    ("envs", "message"),
    [
        ([lambda: NanEnv(), lambda: NanEnv(nan_at=3)], r"new observation of env 1 contains NaN"),
        ([lambda: NanEnv(nan_at=0, episode=1)], r"observation of env 0 contains NaN"),  # a reset observation
        ([lambda: NanEnv(nan_at=5, value=np.inf)], r"terminal observation of env 0 contains NaN or inf"),
        ([lambda: NanEnv(key="a"), lambda: NanEnv(nan_at=2, key="b")], r"new observation \(key 'b'\) of env 1"),
        ([lambda: NanEnv(), lambda: NanEnv(reward_nan_at=4)], r"reward of env 1 is not finite \(\[nan\]\)"),
    ],
)
def test_nonfinite_observation_raises(envs, message):
    env = DummyVecEnv(envs)
    policy = "MultiInputPolicy" if isinstance(env.observation_space, spaces.Dict) else "MlpPolicy"
    model = HIEROS(policy, env, **tiny_kwargs())
    with pytest.raises(ValueError, match=message):
        model.learn(30)
    for buffer in model.level_buffers():  # nothing non-finite reached the replay
        assert all(np.isfinite(array).all() for array in buffer._obs_arrays().values())


def test_nonfinite_observation_predict_and_vec_check_nan():
    model = HIEROS("MultiInputPolicy", SmallDictEnv(), **tiny_kwargs())
    obs = {k: np.stack([s.sample() for _ in range(3)]) for k, s in model.observation_space.spaces.items()}
    model.predict(obs)
    obs["vec"][2, 1] = np.nan
    with pytest.raises(ValueError, match=r"observation \(key 'vec'\) of env 2 contains NaN"):
        model.predict(obs)
    # SB3's VecCheckNan works with HIEROS: silent on a clean env, raises its own error at the faulty step
    clean = HIEROS("MlpPolicy", VecCheckNan(DummyVecEnv([NanEnv]), raise_exception=True), **tiny_kwargs())
    clean.learn(30)
    assert clean._n_updates > 0
    faulty = HIEROS(
        "MlpPolicy", VecCheckNan(DummyVecEnv([lambda: NanEnv(nan_at=3)]), raise_exception=True), **tiny_kwargs()
    )
    with pytest.raises(ValueError, match="found nan in observations"):
        faulty.learn(30)


# ------------------------------------------------------------------------------------------------ non-finite updates


def test_nonfinite_batch_changes_nothing():
    """Every loss of a level NaN: every step is skipped; parameters, slow critics, return normalisers and optimiser
    states stay as they were, and the next finite batch trains as usual."""
    model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(n_levels=1))
    model.learn(40)
    sub = model.policy.hierarchy.levels[0]
    imagine = sub.imagine

    def nan_imagine(start: Any, codes: Any, replan: Any = None) -> Any:
        imagined = imagine(start, codes, replan)
        states = imagined.states._replace(deter=imagined.states.deter * float("nan"))
        return imagined._replace(states=states, rewards=imagined.rewards * float("nan"))

    before = {k: v.clone() for k, v in sub.state_dict().items()}
    adam = _adam_steps(model)
    samples = model.replay_buffer.sample(2)
    samples.rewards[0, 3] = float("nan")  # world-model loss
    sub.imagine = nan_imagine  # type: ignore[method-assign]  # actor, critic (returns) and autoencoder losses
    metrics = sub.train_step(samples).metrics
    for name in ("world_model", "actor", "critic", "autoencoder"):
        assert metrics[f"nonfinite/{name}"] == 1.0, name
    assert not np.isfinite(metrics["wm/loss"]) and not np.isfinite(metrics["actor/loss"])
    for key, value in sub.state_dict().items():
        assert th.equal(value, before[key]), key
        assert th.isfinite(value).all(), key
    assert _adam_steps(model) == adam

    del sub.imagine
    metrics = sub.train_step(model.replay_buffer.sample(2)).metrics
    assert all(metrics[f"nonfinite/{n}"] == 0.0 for n in ("world_model", "actor", "critic", "autoencoder"))
    assert _adam_steps(model) == [a + 1 for a in adam]
    assert any(not th.equal(value, before[key]) for key, value in sub.state_dict().items())


def test_nan_inside_the_world_model_is_skipped_not_raised():
    """A NaN born inside the network (here the encoder's output, before the S5 stack) is a skipped update."""
    model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(n_levels=1))
    model.learn(40)
    sub = model.policy.hierarchy.levels[0]
    before = {k: v.clone() for k, v in sub.world_model.state_dict().items()}
    encoder = sub.world_model.encoder
    original = encoder.forward
    encoder.forward = lambda *args, **kwargs: original(*args, **kwargs) * float("nan")  # type: ignore[method-assign]
    metrics = sub.train_step(model.replay_buffer.sample(2)).metrics
    assert metrics["nonfinite/world_model"] == 1.0
    for key, value in sub.world_model.state_dict().items():
        assert th.equal(value, before[key]), key


def _poison_world_model(model: HIEROS, level: int, n_bad: int | None) -> None:
    """Make the first ``n_bad`` world-model losses of ``level`` NaN (all of them with None)."""
    wm = model.policy.hierarchy.levels[level].world_model
    loss_fn = wm._loss  # what the training step calls
    calls = [0]

    def loss(samples: Any, state: Any = None) -> Any:
        value, metrics, post = loss_fn(samples, state)
        calls[0] += 1
        if n_bad is None or calls[0] <= n_bad:
            value = value * float("nan")
            metrics["loss"] = value.detach()
        return value, metrics, post

    wm._loss = loss  # type: ignore[method-assign]


def test_nonfinite_updates_skipped_counted_then_stop():
    model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(n_levels=2, train_ratio=8.0), max_nonfinite_updates=3)
    assert model.max_nonfinite_updates == 3
    model.learn(40)
    assert model.level_updates()[1] > 0
    frozen = {k: v.clone() for k, v in model.policy.hierarchy.levels[1].world_model.state_dict().items()}
    level0 = {k: v.clone() for k, v in model.policy.hierarchy.levels[0].world_model.state_dict().items()}
    _poison_world_model(model, 1, None)
    with pytest.raises(FloatingPointError, match=r"level 1: 3 updates in a row .*world_model loss \(wm/loss=nan"):
        model.learn(200, reset_num_timesteps=False)
    assert model.skipped_updates() == [0, 3]
    assert model.logger.name_to_value["train/level1/skipped_updates"] == 3
    for key, value in model.policy.hierarchy.levels[1].world_model.state_dict().items():
        assert th.equal(value, frozen[key]), key  # never a step with the NaN loss
    changed = [not th.equal(v, level0[k]) for k, v in model.policy.hierarchy.levels[0].world_model.state_dict().items()]
    assert any(changed)  # the healthy level went on training


def test_nonfinite_updates_streak_resets():
    model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(n_levels=2, train_ratio=8.0), max_nonfinite_updates=3)
    model.learn(40)
    updates = model.level_updates()[1]
    _poison_world_model(model, 1, 2)  # two bad updates, then finite again
    model.learn(40, reset_num_timesteps=False)
    assert model.level_updates()[1] > updates + 2
    assert model.skipped_updates() == [0, 2] and model._nonfinite_streak == [0, 0]
    with pytest.raises(ValueError, match="max_nonfinite_updates"):
        HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(), max_nonfinite_updates=0)


# ------------------------------------------------------------------------------------------------ load


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    path = tmp_path_factory.mktemp("rel")
    HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs()).save(path / "model.zip")
    return path


def _rewrite(src, dst, name: str | None, keep: float, manifest: bool = True) -> None:
    """Copy the zip ``src`` to ``dst`` with entry ``name`` cut to a fraction ``keep`` (or the whole file cut), without
    the checksum manifest if ``manifest`` is False (a save from before checksums)."""
    data = src.read_bytes()
    if name is None:
        dst.write_bytes(data[: int(len(data) * keep)])
        return
    with zipfile.ZipFile(src) as archive, zipfile.ZipFile(dst, "w") as out:
        for entry in archive.namelist():
            if entry == "hieros_manifest.json" and not manifest:
                continue
            content = archive.read(entry)
            out.writestr(entry, content[: int(len(content) * keep)] if entry == name else content)


@pytest.mark.parametrize(
    ("entry", "keep", "manifest", "message"),
    [
        (None, 0.5, True, "not a HIEROS save|not a readable HIEROS save"),
        (None, 0.001, True, "not a readable HIEROS save"),
        ("policy.pth", 0.3, True, r"member 'policy.pth' does not match the sha256 recorded"),
        ("data", 0.3, True, r"member 'data' does not match the sha256 recorded"),
        ("policy.pth", 0.3, False, r"could not be loaded as a HIEROS model \(corrupted file\?\): RuntimeError"),
        ("data", 0.3, False, "not a readable HIEROS save"),
    ],
)
def test_load_corrupted_zip(saved, tmp_path, entry, keep, manifest, message):
    bad = tmp_path / "bad.zip"
    _rewrite(saved / "model.zip", bad, entry, keep, manifest)
    with pytest.raises(ValueError, match=message) as info:
        HIEROS.load(bad)
    frames = traceback.extract_tb(info.tb)
    assert not any("torch" in frame.filename.split("site-packages")[-1] for frame in frames)
    # the deep cause is in the message, not a chained traceback
    assert info.value.__suppress_context__ or info.value.__context__ is None


def test_load_other_algorithm_and_other_spaces(saved, tmp_path):
    DQN("MlpPolicy", "CartPole-v1", learning_starts=0, buffer_size=10).save(tmp_path / "dqn.zip")
    with pytest.raises(ValueError, match="not saved by HIEROS: its policy class is DQNPolicy"):
        HIEROS.load(tmp_path / "dqn.zip")
    with open(tmp_path / "dqn.zip", "rb") as file, pytest.raises(ValueError, match="DQNPolicy"):
        HIEROS.load(file)
    with pytest.raises(ValueError, match="Observation spaces do not match"):  # SB3's check
        HIEROS.load(saved / "model.zip", env=make_vec_env("MountainCar-v0", n_envs=1))
    with pytest.raises(ValueError, match="Action spaces do not match"):
        HIEROS.load(saved / "model.zip", env=DummyVecEnv([lambda: _CartPoleBox()]))
    with open(saved / "model.zip", "rb") as file:  # a file object is read from where it stands
        assert HIEROS.load(file).config.n_levels == 2


class _CartPoleBox(gym.Env):
    """CartPole's observation space with Box actions."""

    def __init__(self) -> None:
        self.observation_space = gym.make("CartPole-v1").observation_space
        self.action_space = spaces.Box(-1.0, 1.0, (1,), np.float32)

    def reset(self, *, seed=None, options=None):
        return np.zeros(4, np.float32), {}

    def step(self, action):
        return np.zeros(4, np.float32), 0.0, False, False, {}


# ------------------------------------------------------------------------------------------------ predict


def test_predict_wrong_shape_or_foreign_state():
    model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs())
    with pytest.raises(ValueError, match=r"shape \(3,\).*\(4,\)"):
        model.predict(np.zeros(3, np.float32))
    with pytest.raises(ValueError, match=r"shape \(2, 5\).*\(4,\)"):
        model.predict(np.zeros((2, 5), np.float32))
    wider = {**TINY_OVERRIDES, "world_model": {**TINY_OVERRIDES["world_model"], "deter_dim": 32}}
    other = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(config_overrides=wider))
    _, state = other.predict(np.zeros(4, np.float32))
    with pytest.raises(ValueError, match=r"'level0/deter' has shape \(1, 32\), expected \(1, 16\)"):
        model.predict(np.zeros(4, np.float32), state=state)
    _, state = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(n_levels=3)).predict(np.zeros(4, np.float32))
    with pytest.raises(ValueError, match=r"tuple of 14 arrays .* got a tuple of length 21"):
        model.predict(np.zeros(4, np.float32), state=state)
    _, state = model.predict(np.zeros((2, 4), np.float32))  # state of 2 envs, observation of 1
    with pytest.raises(ValueError, match=r"'step' has shape \(2,\), expected \(1,\)"):
        model.predict(np.zeros(4, np.float32), state=state)


# ------------------------------------------------------------------------------------------------ memory


@pytest.mark.parametrize("replay_context", [False, True])
def test_replay_memory_estimate_and_warning(monkeypatch, replay_context):
    overrides = {**TINY_OVERRIDES, "replay_context": replay_context}
    model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(n_levels=3, config_overrides=overrides))
    for level, buffer in enumerate(model.level_buffers()):
        arrays = [buffer.observations, buffer.actions, buffer.rewards, buffer.is_first, buffer.is_terminal]
        arrays += [a for a in (buffer.subgoals, buffer.context, buffer.has_context) if a is not None]
        assert (buffer.context is not None) == replay_context
        estimate = SequenceReplayBuffer.estimate_nbytes(
            level_buffer_size(model.config, model.buffer_size, level, model.n_envs),
            buffer.observation_space,
            buffer.action_space,
            buffer.n_envs,
            buffer.subgoal_shape,
            buffer.context_dim,
        )
        assert estimate == sum(a.nbytes for a in arrays), level
    dict_env = SmallDictEnv()
    buffer = SequenceReplayBuffer(64, dict_env.observation_space, dict_env.action_space, n_envs=2, batch_length=4)
    actual = sum(a.nbytes for a in buffer.observations.values()) + buffer.actions.nbytes + 64 * (4 + 1 + 1 + 1)
    assert SequenceReplayBuffer.estimate_nbytes(64, dict_env.observation_space, dict_env.action_space, 2) == actual

    monkeypatch.setattr(buffers_module, "available_memory", lambda: 10_000)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(n_levels=3))
    messages = [str(w.message) for w in caught if "replay buffer needs" in str(w.message)]
    assert len(messages) == 1, messages  # one warning for all levels, not one more per buffer
    assert "level 0:" in messages[0] and "level 2:" in messages[0] and "0.00 GB of memory" in messages[0]

    # the warning comes before the arrays are allocated
    def no_memory(*args: Any, **kwargs: Any) -> np.ndarray:
        raise MemoryError("allocation attempted")

    space = spaces.Box(-1.0, 1.0, (1000,), np.float32)
    with pytest.warns(UserWarning, match=r"needs about 0\.04 GB"), pytest.raises(MemoryError, match="attempted"):
        with monkeypatch.context() as patch:
            patch.setattr(buffers_module.np, "zeros", no_memory)
            ETBSReplayBuffer(10_000, space, spaces.Discrete(2), batch_length=4)
