"""benchmarks/train.py: one run of a suite task writes monitor logs, evaluations, the model and a result JSON."""

from __future__ import annotations

import json

import numpy as np
import pytest

from benchmarks.train import main, run_dir, train
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
