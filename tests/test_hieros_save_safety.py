"""Saving and loading under faults (issue 24): atomic saves under SIGKILL, a rejected replay that leaves the model as
it was, the pickle-free replay format, loading without unpickling, checksums, config and predict-state checks, and
the fault mode of ``benchmarks/soak.py``."""

from __future__ import annotations

import argparse
import base64
import io
import json
import os
import pathlib
import pickle
import subprocess
import sys
import time
import zipfile
from typing import Any

import cloudpickle
import numpy as np
import pytest
import torch as th
from hieros_helpers import TINY_OVERRIDES, SmallDictEnv, tiny_kwargs
from stable_baselines3 import DQN
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.save_util import save_to_pkl
from stable_baselines3.common.utils import LinearSchedule

from benchmarks.soak import run_fault_soak
from sb3_hieros import HIEROS
from sb3_hieros.save_util import MANIFEST_NAME, add_manifest

TESTS = pathlib.Path(__file__).resolve().parent
ROOT = TESTS.parent


def _arrays(model: HIEROS) -> list[dict[str, Any]]:
    """Copies of every array of every level's replay (Dict observations by key)."""
    out = []
    for buffer in model.level_buffers():
        level = {}
        for name, value in vars(buffer).items():
            if isinstance(value, np.ndarray):
                level[name] = value.copy()
            elif isinstance(value, dict) and all(isinstance(v, np.ndarray) for v in value.values()):
                level.update({f"{name}/{k}": v.copy() for k, v in value.items()})
        out.append(level)
    return out


def _assert_same_arrays(a: list[dict[str, Any]], b: list[dict[str, Any]]) -> None:
    assert len(a) == len(b)
    for level_a, level_b in zip(a, b, strict=True):
        assert level_a.keys() == level_b.keys()
        for name in level_a:
            np.testing.assert_array_equal(level_a[name], level_b[name], err_msg=name)


def _rezip(src: pathlib.Path, dst: pathlib.Path, change: dict[str, bytes], manifest: bool = False) -> None:
    """Copy a zip with some members replaced; with ``manifest`` the checksums are recomputed (as an attacker would)."""
    with zipfile.ZipFile(src) as archive:
        members = {name: archive.read(name) for name in archive.namelist()}
    old = json.loads(members.pop(MANIFEST_NAME, b"{}"))
    members.update(change)
    with zipfile.ZipFile(dst, "w") as out:
        for name, content in members.items():
            out.writestr(name, content)
        if old and not manifest:
            out.writestr(MANIFEST_NAME, json.dumps(old))
    if manifest:
        add_manifest(dst, {k: v for k, v in old.items() if k not in ("sha256", "version")})


# ------------------------------------------------------------------------------------------------ atomic saves

_SAVER = """
import sys, time
sys.path.insert(0, sys.argv[2])
import numpy as np
import torch
from hieros_helpers import tiny_kwargs
from sb3_hieros import HIEROS

save, write_array = torch.save, np.lib.format.write_array

def slow_save(*args, **kwargs):  # every tensor file (model) and array (replay) takes longer: kills land mid-save
    save(*args, **kwargs)
    time.sleep(0.02)

def slow_write(*args, **kwargs):
    write_array(*args, **kwargs)
    time.sleep(0.02)

torch.save, np.lib.format.write_array = slow_save, slow_write
model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs())
model.learn(30)
for i in range(1000):
    model.num_timesteps = i
    print("begin", i, flush=True)
    start = time.perf_counter()
    model.save(sys.argv[1] + "/model.zip")
    model.save_replay_buffer(sys.argv[1] + "/replay.pkl")
    print("end", i, time.perf_counter() - start, flush=True)
"""


def test_kill_during_save_keeps_the_previous_checkpoint(tmp_path):
    """SIGKILL at a random moment of a save over an existing checkpoint (model and replay): the old files load."""
    rng = np.random.default_rng(0)
    script, folder = tmp_path / "saver.py", tmp_path / "checkpoints"
    script.write_text(_SAVER)
    folder.mkdir()
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
    killed_mid_save = 0
    for _ in range(3):
        process = subprocess.Popen(
            [sys.executable, str(script), str(folder), str(TESTS)], stdout=subprocess.PIPE, text=True, env=env
        )
        assert process.stdout is not None
        finished, durations = -1, []
        for line in process.stdout:
            word, step, *rest = line.split()
            if word == "end":
                finished, durations = int(step), [*durations, float(rest[0])]
            elif word == "begin" and durations:  # one save over the previous process' files is done: kill the next
                time.sleep(rng.uniform(0.05, 0.95) * durations[-1])
                process.kill()
                break
        process.wait()
        if any(line.startswith("end") for line in process.stdout.read().splitlines()):
            finished += 1  # the save had finished before the kill landed
        killed_mid_save += any(folder.glob(".*.tmp"))
        model = HIEROS.load(folder / "model.zip")
        assert model.num_timesteps in (finished, finished + 1)  # the model file of the killed save may be complete
        model.load_replay_buffer(folder / "replay.pkl")
    assert killed_mid_save >= 1  # at least one kill interrupted a save (else the test tested nothing)
    HIEROS.load(folder / "model.zip").save(folder / "model.zip")
    assert not any(folder.glob(".model.zip.*.tmp"))  # a later save removes what a killed save left


def test_failed_save_leaves_the_file_and_no_temporary(tmp_path, monkeypatch):
    model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs())
    model.save(tmp_path / "model.zip")
    model.save_replay_buffer(tmp_path / "replay.pkl")
    before = (tmp_path / "model.zip").read_bytes(), (tmp_path / "replay.pkl").read_bytes()

    def full_disk(*args: Any, **kwargs: Any) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(th, "save", full_disk)
    monkeypatch.setattr(np.lib.format, "write_array", full_disk)
    with pytest.raises(OSError, match="No space"):
        model.save(tmp_path / "model.zip")
    with pytest.raises(OSError, match="No space"):
        model.save_replay_buffer(tmp_path / "replay.pkl")
    assert ((tmp_path / "model.zip").read_bytes(), (tmp_path / "replay.pkl").read_bytes()) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model.zip", "replay.pkl"]


def test_save_and_load_through_file_objects(saved):
    model, _ = saved
    model_file, replay_file = io.BytesIO(), io.BytesIO()
    model.save(model_file)
    model.save_replay_buffer(replay_file)
    for safe in (False, True):
        model_file.seek(0)
        loaded = HIEROS.load(model_file, env=make_vec_env("CartPole-v1", n_envs=1), safe=safe)
        assert loaded._level_updates == model._level_updates
    replay_file.seek(0)
    loaded.load_replay_buffer(replay_file)
    _assert_same_arrays(_arrays(loaded), _arrays(model))


# ------------------------------------------------------------------------------------------------ replay files


@pytest.fixture(scope="module")
def replays(tmp_path_factory):
    """A trained 2-level model and replay files of models with other n_envs / n_levels (new and legacy format)."""
    path = tmp_path_factory.mktemp("replays")
    no_context = {**TINY_OVERRIDES, "replay_context": False}
    model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(n_levels=2))
    model.learn(40)
    for name, other in (
        ("two_envs", HIEROS("MlpPolicy", make_vec_env("CartPole-v1", n_envs=2), **tiny_kwargs(n_levels=2))),
        ("three_levels", HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(n_levels=3))),
        ("no_context", HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(config_overrides=no_context))),
    ):
        other.learn(30)
        other.save_replay_buffer(path / f"{name}.pkl")
        save_to_pkl(path / f"{name}_legacy.pkl", other.replay_buffer)
    return model, path


@pytest.mark.parametrize("legacy", [False, True])
@pytest.mark.parametrize(
    ("name", "message"),
    [
        ("two_envs", "holds a replay of 2 envs, but this model has n_envs=1"),
        ("three_levels", "holds the replay of 3 levels"),
        ("no_context", r"level 0 does not hold the arrays of this model's replay \(missing: \['context'\]"),
    ],
)
def test_rejected_replay_leaves_the_model_intact(replays, name, message, legacy):
    model, path = replays
    buffer, arrays, updates = model.replay_buffer, _arrays(model), model._n_updates
    with warnings_if(legacy), pytest.raises(ValueError, match=message):
        model.load_replay_buffer(path / f"{name}{'_legacy' if legacy else ''}.pkl")
    assert model.replay_buffer is buffer
    _assert_same_arrays(_arrays(model), arrays)
    model.learn(16, reset_num_timesteps=False)  # the model still trains
    assert model._n_updates > updates


def warnings_if(legacy: bool) -> Any:
    """``pytest.warns`` for the legacy-pickle warning, or nothing."""
    return pytest.warns(UserWarning, match="unpickling runs any code") if legacy else _nothing()


class _nothing:
    def __enter__(self) -> None:
        return None

    def __exit__(self, *args: Any) -> None:
        return None


@pytest.mark.parametrize(
    ("env", "overrides"),
    [
        ("CartPole-v1", {"replay": "count"}),
        ("CartPole-v1", {"replay_context": True}),
        ("dict", {"replay_context": True}),
    ],
)
def test_replay_file_round_trip_without_pickle(tmp_path, monkeypatch, env, overrides):
    """Every attribute of every level (arrays, write heads, context, ETBS draw counters) comes back, unpickled."""
    policy, env_fn = ("MultiInputPolicy", SmallDictEnv) if env == "dict" else ("MlpPolicy", lambda: env)
    kwargs = tiny_kwargs(n_levels=2, config_overrides={**TINY_OVERRIDES, **overrides})
    model = HIEROS(policy, env_fn(), **kwargs)
    model.learn(60)
    model.save_replay_buffer(tmp_path / "replay")  # ".pkl" appended, as in SB3; the content is a zip
    path = tmp_path / "replay.pkl"
    assert path.read_bytes()[:4] == b"PK\x03\x04"
    with np.load(path) as npz:  # an npz: the arrays open with numpy alone
        np.testing.assert_array_equal(npz["level0/rewards"], model.replay_buffer.rewards)

    def refuse(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("the replay was unpickled")

    fresh = HIEROS(policy, env_fn(), **kwargs)
    with monkeypatch.context() as patch:
        patch.setattr(pickle, "load", refuse)
        patch.setattr(pickle, "loads", refuse)
        fresh.load_replay_buffer(path)
    for old, new in zip(model.level_buffers(), fresh.level_buffers(), strict=True):
        assert type(old) is type(new) and new.device == fresh.device
        for name, value in vars(old).items():
            if name in ("observation_space", "action_space", "device", "higher_levels"):
                continue
            if name == "counter" and value is not None:
                np.testing.assert_array_equal(new.counter.counts, value.counts)
                assert value.counts.sum() > 0
            elif isinstance(value, dict) and name == "observations":
                for key in value:
                    np.testing.assert_array_equal(getattr(new, name)[key], value[key])
            else:
                np.testing.assert_array_equal(getattr(new, name), value, err_msg=name)
    assert fresh.level_buffers()[0].higher_levels == fresh.level_buffers()[1:]
    fresh.learn(24)  # after learning_starts=20 it trains at once on the loaded replay
    assert fresh._n_updates > 0


def test_legacy_pickle_replay_loads_with_a_warning(replays, tmp_path):
    model, _ = replays
    save_to_pkl(tmp_path / "old.pkl", model.replay_buffer)
    fresh = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(n_levels=2))
    with pytest.warns(UserWarning, match="pickled replay .* unpickling runs any code"):
        fresh.load_replay_buffer(tmp_path / "old.pkl")
    _assert_same_arrays(_arrays(fresh), _arrays(model))


def test_tampered_replay_is_refused(replays, tmp_path):
    model, _ = replays
    model.save_replay_buffer(tmp_path / "replay.pkl")
    with zipfile.ZipFile(tmp_path / "replay.pkl") as archive:
        rewards = bytearray(archive.read("level0/rewards.npy"))
    rewards[-1] ^= 0x40  # one float of the last row changes; the zip's own CRC is recomputed by the re-zip
    _rezip(tmp_path / "replay.pkl", tmp_path / "bad.pkl", {"level0/rewards.npy": bytes(rewards)})
    buffer = model.replay_buffer
    with pytest.raises(ValueError, match=r"member 'level0/rewards.npy' does not match the sha256"):
        model.load_replay_buffer(tmp_path / "bad.pkl")
    assert model.replay_buffer is buffer
    cut = (tmp_path / "replay.pkl").read_bytes()
    (tmp_path / "cut.pkl").write_bytes(cut[: len(cut) // 2])
    with pytest.raises(ValueError, match="not a readable HIEROS replay"):
        model.load_replay_buffer(tmp_path / "cut.pkl")


# ------------------------------------------------------------------------------------------------ model files


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    path = tmp_path_factory.mktemp("safe")
    model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(n_levels=2))
    model.learn(40)
    model.save(path / "model.zip")
    return model, path


def test_tampered_tensor_is_refused(saved, tmp_path):
    _, path = saved
    with zipfile.ZipFile(path / "model.zip") as archive:
        state = th.load(io.BytesIO(archive.read("policy.pth")), weights_only=True)
    key = next(iter(state))
    state[key] = state[key] + 1.0  # a well-formed tensor file with other values
    changed = io.BytesIO()
    th.save(state, changed)
    _rezip(path / "model.zip", tmp_path / "bad.zip", {"policy.pth": changed.getvalue()})
    with pytest.raises(ValueError, match=r"member 'policy.pth' does not match the sha256 recorded"):
        HIEROS.load(tmp_path / "bad.zip")


class _Payload:
    """Pickles as code that appends ``x`` to ``marker`` and evaluates to ``result`` (an expression)."""

    def __init__(self, marker: pathlib.Path, result: str) -> None:
        self.marker, self.result = marker, result

    def __reduce__(self) -> tuple[Any, ...]:
        return (eval, (f"(open({str(self.marker)!r}, 'a').write('x'), {self.result})[1]",))


def _crafted(src: pathlib.Path, dst: pathlib.Path, key: str, payload: _Payload) -> None:
    with zipfile.ZipFile(src) as archive:
        data = json.loads(archive.read("data"))
    data[key][":serialized:"] = base64.b64encode(cloudpickle.dumps(payload)).decode()
    _rezip(src, dst, {"data": json.dumps(data).encode()}, manifest=True)


def test_safe_load_runs_no_code_and_plain_load_runs_it_once(saved, tmp_path):
    model, path = saved
    marker = tmp_path / "ran"
    crafted = tmp_path / "crafted.zip"
    _crafted(path / "model.zip", crafted, "policy_class", _Payload(marker, "__import__('sb3_hieros').MlpPolicy"))
    env = make_vec_env("CartPole-v1", n_envs=1)
    loaded = HIEROS.load(crafted, env=env, safe=True)
    assert not marker.exists()
    obs = np.random.default_rng(0).normal(size=(5, 4)).astype(np.float32)
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], model.predict(obs, deterministic=True)[0])
    for name in ("num_timesteps", "_n_updates", "_level_updates", "_update_budget", "learning_rate"):
        assert getattr(loaded, name) == getattr(model, name), name
    assert len(loaded.ep_info_buffer) == len(model.ep_info_buffer) > 0
    HIEROS.load(crafted)  # without safe=True the file's code runs, but once: the pre-check unpickles nothing twice
    assert marker.read_text() == "x"
    with pytest.raises(ValueError, match=r"safe=True\) takes the spaces from the env"):
        HIEROS.load(crafted, safe=True)
    with pytest.raises(ValueError, match="observation space does not match"):
        HIEROS.load(crafted, env=make_vec_env("MountainCar-v0", n_envs=1), safe=True)


def test_safe_load_of_other_files(saved, tmp_path):
    _, path = saved
    env = make_vec_env("CartPole-v1", n_envs=1)
    marker = tmp_path / "ran"
    crafted = tmp_path / "crafted.zip"
    _crafted(path / "model.zip", crafted, "_last_obs", _Payload(marker, "None"))
    HIEROS.load(crafted, env=env, safe=True)
    assert not marker.exists()
    DQN("MlpPolicy", "CartPole-v1", learning_starts=0, buffer_size=10).save(tmp_path / "dqn.zip")
    with pytest.raises(ValueError, match="not saved by HIEROS: its policy class comes from module stable_baselines3"):
        HIEROS.load(tmp_path / "dqn.zip", env=env, safe=True)
    assert not marker.exists()


def test_entry_that_cannot_be_unpickled(saved, tmp_path):
    """As SB3 warns and goes on when a pickled entry fails (e.g. a schedule from another Python), a plain load rebuilds
    such an entry from plain values with a warning; an entry that plain values cannot rebuild is named in an error."""
    _, path = saved
    with zipfile.ZipFile(path / "model.zip") as archive:
        data = json.loads(archive.read("data"))
    for key in ("lr_schedule", "observation_space"):
        broken = json.loads(json.dumps(data))
        broken[key][":serialized:"] = base64.b64encode(b"not a pickle").decode()
        _rezip(path / "model.zip", tmp_path / f"{key}.zip", {"data": json.dumps(broken).encode()}, manifest=True)
    with pytest.warns(UserWarning, match="entry 'lr_schedule' of its data could not be unpickled.*rebuilt"):
        assert HIEROS.load(tmp_path / "lr_schedule.zip").lr_schedule(1.0) == pytest.approx(1e-3)
    with pytest.raises(ValueError, match="entry 'observation_space' of its data could not be unpickled"):
        HIEROS.load(tmp_path / "observation_space.zip")


def test_safe_load_rebuilds_schedules(tmp_path):
    linear = LinearSchedule(1e-3, 1e-4, 0.5)
    model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(learning_rate=linear))
    model.learn(30)
    model.save(tmp_path / "linear.zip")
    env = make_vec_env("CartPole-v1", n_envs=1)
    loaded = HIEROS.load(tmp_path / "linear.zip", env=env, safe=True)
    assert isinstance(loaded.learning_rate, LinearSchedule)
    assert vars(loaded.learning_rate) == vars(linear)
    custom = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(learning_rate=lambda progress: 5e-4 * progress))
    custom.save(tmp_path / "custom.zip")
    with pytest.warns(UserWarning, match="Python callable.*constant 0.0005"):
        loaded = HIEROS.load(tmp_path / "custom.zip", env=env, safe=True)
    assert loaded.learning_rate == 5e-4


# ------------------------------------------------------------------------------------------------ checks


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"train_ratio": float("nan")}, "HierosConfig.train_ratio must be a finite number, got nan"),
        ({"train_ratio": float("inf")}, "HierosConfig.train_ratio must be a finite number, got inf"),
        ({"batch_size": 2.0}, r"HierosConfig.batch_size must be an integer, got 2.0 \(float\)"),
        ({"n_levels": True}, r"HierosConfig.n_levels must be an integer, got True \(bool\)"),
        ({"learning_rate": float("nan")}, "WorldModelConfig.lr must be a finite number, got nan"),
        (
            {"config_overrides": {**TINY_OVERRIDES, "world_model": {**TINY_OVERRIDES["world_model"], "dropout": True}}},
            r"WorldModelConfig.dropout must be a finite number, got True \(bool\)",
        ),
        ({"config_overrides": {**TINY_OVERRIDES, "replay_context": 1}}, "HierosConfig.replay_context must be a bool"),
    ],
)
def test_config_refuses_non_finite_and_wrong_types(changes, message):
    with pytest.raises(ValueError, match=message):
        HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs(**changes))


def test_predict_refuses_a_non_finite_state():
    model = HIEROS("MlpPolicy", "CartPole-v1", **tiny_kwargs())
    obs = np.zeros(4, np.float32)
    _, state = model.predict(obs)
    names = model.policy.state_names()
    bad = list(state)
    bad[names.index("level0/deter")] = np.full_like(state[names.index("level0/deter")], np.inf)
    with pytest.raises(ValueError, match="state entry 'level0/deter' contains NaN or inf"):
        model.predict(obs, state=tuple(bad))
    bad = list(state)
    bad[0] = state[0].astype(np.float32)
    with pytest.raises(ValueError, match="state entry 'step' has dtype float32"):
        model.predict(obs, state=tuple(bad))


# ------------------------------------------------------------------------------------------------ soak


def test_soak_fault_mode_small_budget():
    """Two SIGKILLs (random points) and resumes: nothing corrupt, every resume works, the same counters."""
    args = argparse.Namespace(
        faults=2,
        steps=300,
        checkpoint_every=50,
        kill_after=100,
        train_ratio=8.0,
        learning_starts=50,
        buffer_size=500,
        threads=1,
        seed=0,
        timeout=120.0,
    )
    report = run_fault_soak(args)
    assert len(report.kills) == 2 and all(k.resumed_from is not None for k in report.kills)
    assert report.failed_resumes == 0 and report.corrupt == []
    assert report.counters["num_timesteps"] == report.uninterrupted["num_timesteps"] == 300
    assert report.counters_equal, (report.counters, report.uninterrupted)
    assert report.temp_files_at_end == 0
