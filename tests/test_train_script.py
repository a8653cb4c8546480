"""benchmarks/train.py: one run of a suite task writes monitor logs, evaluations, the model and a result JSON."""

from __future__ import annotations

import json

import numpy as np
import pytest

from benchmarks.train import CHECKPOINT_DIR, RunCheckpoint, main, run_dir, train
from sb3_hieros import HIEROS

TINY = {"learning_starts": 10_000, "buffer_size": 1000}  # no updates: the test checks the bookkeeping


def test_train_classic_run(tmp_path):
    record = main(
        [
            "--suite", "classic", "--task", "CartPole-v1", "--seed", "3", "--preset", "small", "--steps", "120",
            "--eval-freq", "50", "--periodic-eval-episodes", "2", "--eval-episodes", "3", "--out", str(tmp_path),
            "--hieros-kwargs", json.dumps(TINY), "--config-overrides", '{"n_levels": 1}',
        ]
    )  # fmt: skip
    folder = run_dir(tmp_path, "classic", "CartPole-v1", 3)
    assert folder == tmp_path / "classic" / "CartPole-v1" / "seed3"
    for name in ("train.monitor.csv", "eval.monitor.csv", "evaluations.npz", "model.zip", "result.json"):
        assert (folder / name).is_file(), name
    saved = json.loads((folder / "result.json").read_text())
    assert saved == record
    assert (saved["suite"], saved["task"], saved["seed"], saved["preset"]) == ("classic", "CartPole-v1", 3, "small")
    assert saved["steps"] == 120 and saved["env_steps"] == 120
    assert saved["final_episodes"] == len(saved["final_returns"]) == 3
    assert saved["final_mean"] == pytest.approx(np.mean(saved["final_returns"]))
    assert saved["final_std"] == pytest.approx(np.std(saved["final_returns"]))
    assert saved["eval_timesteps"] == [50, 100]
    evaluations = np.load(folder / "evaluations.npz")
    np.testing.assert_allclose(evaluations["results"].mean(1), saved["eval_means"])
    # train.monitor.csv: one line per finished training episode, lengths summing to at most the steps
    lines = (folder / "train.monitor.csv").read_text().splitlines()[2:]
    assert lines and sum(int(line.split(",")[1]) for line in lines) <= 120
    model = HIEROS.load(folder / "model.zip")
    assert model.config.n_levels == 1 and model.learning_starts == 10_000
    assert not (folder / "replay_buffer.pkl").exists()  # only with --save-replay-buffer


def test_train_saves_the_replay_buffer_on_request(tmp_path):
    main(
        [
            "--suite", "classic", "--task", "CartPole-v1", "--preset", "small", "--steps", "40", "--eval-freq", "0",
            "--eval-episodes", "1", "--out", str(tmp_path), "--hieros-kwargs", json.dumps(TINY),
            "--config-overrides", '{"n_levels": 1}', "--save-replay-buffer",
        ]
    )  # fmt: skip
    folder = run_dir(tmp_path, "classic", "CartPole-v1", 0)
    model = HIEROS.load(folder / "model.zip")
    model.load_replay_buffer(folder / "replay_buffer.pkl")
    assert model.level_buffers()[0].size() >= 40  # the 40 steps (and a row per episode start)


def test_train_refuses_bad_arguments(tmp_path):
    with pytest.raises(ValueError, match="unknown suite"):
        train("procgen", "CartPole-v1", out=tmp_path)
    with pytest.raises(ValueError, match="eval_episodes"):
        train("classic", "CartPole-v1", eval_episodes=0, out=tmp_path)
    with pytest.raises(ValueError, match="hieros_kwargs must not contain 'preset'"):
        train("classic", "CartPole-v1", hieros_kwargs={"preset": "small"}, out=tmp_path)


def test_train_refuses_keyword_options_that_are_not_json_objects(tmp_path, capsys):
    base = ["--suite", "classic", "--task", "CartPole-v1", "--steps", "10", "--out", str(tmp_path)]
    with pytest.raises(SystemExit):
        main([*base, "--config-overrides", "[1]"])
    assert "--config-overrides: '[1]' is a JSON list; expected a JSON object" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main([*base, "--env-kwargs", "{bad"])
    assert "--env-kwargs: '{bad' is not JSON" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())  # refused before anything ran


RESUMABLE = {
    "preset": "small",
    "steps": 90,
    "eval_freq": 30,
    "periodic_eval_episodes": 1,
    "eval_episodes": 1,
    "hieros_kwargs": {"learning_starts": 20, "buffer_size": 1000},
    "config_overrides": {"n_levels": 1},
    "checkpoint_freq": 25,
}


def _interrupted_run(tmp_path, monkeypatch, at: int) -> None:
    """A run of RESUMABLE stopped by a KeyboardInterrupt right after its checkpoint at step ``at``."""
    save = RunCheckpoint._on_rollout_start

    def save_then_stop(self):
        save(self)
        if self.last_saved == at:
            raise KeyboardInterrupt

    with monkeypatch.context() as patch:
        patch.setattr(RunCheckpoint, "_on_rollout_start", save_then_stop)
        with pytest.raises(KeyboardInterrupt):
            train("classic", "CartPole-v1", out=tmp_path, **RESUMABLE)


def test_train_resumes_from_its_checkpoint(tmp_path, monkeypatch):
    _interrupted_run(tmp_path / "resumed", monkeypatch, at=50)
    folder = run_dir(tmp_path / "resumed", "classic", "CartPole-v1", 0)
    checkpoint = folder / CHECKPOINT_DIR
    assert sorted(p.name for p in checkpoint.iterdir()) == ["model_50.zip", "progress.json", "replay_50.zip"]
    progress = json.loads((checkpoint / "progress.json").read_text())
    assert progress["step"] == 50 and progress["evaluations"]["timesteps"] == [30] and progress["train_s"] > 0
    monitor_lines = len((folder / "train.monitor.csv").read_text().splitlines())

    record = train("classic", "CartPole-v1", out=tmp_path / "resumed", resume=True, **RESUMABLE)
    assert record["steps"] == 90 and record["resumed_at"] == [50]
    assert record["eval_timesteps"] == [30, 60, 90]  # the same steps as a run that never stopped
    assert record["train_s"] >= progress["train_s"]
    assert not checkpoint.exists()  # removed once the run finished
    lines = (folder / "train.monitor.csv").read_text().splitlines()
    assert len(lines) > monitor_lines and sum(line.startswith("#") for line in lines) == 1  # appended, one header
    np.testing.assert_allclose(np.load(folder / "evaluations.npz")["results"].mean(1), record["eval_means"])

    uninterrupted = train("classic", "CartPole-v1", out=tmp_path / "plain", **RESUMABLE)
    assert uninterrupted["eval_timesteps"] == record["eval_timesteps"] and "resumed_at" not in uninterrupted
    resumed_model = HIEROS.load(folder / "model.zip")
    plain_model = HIEROS.load(run_dir(tmp_path / "plain", "classic", "CartPole-v1", 0) / "model.zip")
    assert resumed_model.level_updates() == plain_model.level_updates() != [0]
    # a finished run is not run again, and not taken for a run with other options
    assert train("classic", "CartPole-v1", out=tmp_path / "resumed", resume=True, **RESUMABLE) == record
    with pytest.raises(ValueError, match=r"result.json belongs to a run with other options: steps 90 \(now 120\)"):
        train("classic", "CartPole-v1", out=tmp_path / "resumed", resume=True, **{**RESUMABLE, "steps": 120})


def test_train_refuses_to_resume_with_other_options(tmp_path, monkeypatch):
    _interrupted_run(tmp_path, monkeypatch, at=25)
    checkpoint = run_dir(tmp_path, "classic", "CartPole-v1", 0) / CHECKPOINT_DIR
    before = sorted(p.name for p in checkpoint.iterdir())
    other = {**RESUMABLE, "config_overrides": {"n_levels": 2}}
    with pytest.raises(ValueError, match=r"config_overrides \{'n_levels': 1\} \(now \{'n_levels': 2\}\)"):
        train("classic", "CartPole-v1", out=tmp_path, resume=True, **other)
    assert sorted(p.name for p in checkpoint.iterdir()) == before  # the checkpoint is left as it was
    with pytest.raises(ValueError, match="checkpoint_freq must be an int >= 0"):
        train("classic", "CartPole-v1", out=tmp_path, **{**RESUMABLE, "checkpoint_freq": -1})
