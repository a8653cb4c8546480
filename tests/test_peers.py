"""benchmarks/peers.py: sheeprl's DreamerV3 as CPU-suite runs (the end-to-end run only where sheeprl is installed)."""

from __future__ import annotations

import importlib.util
import json

import numpy as np
import pytest

from benchmarks import cpu_suite, peers
from benchmarks.cpu_suite import SuiteRun, suite_runs
from benchmarks.peers import checkpoint_steps, sheeprl_env, sheeprl_overrides


def _value(overrides: list[str], key: str) -> str:
    values = [o.split("=", 1)[1] for o in overrides if o.split("=", 1)[0] == key]
    assert len(values) == 1, (key, overrides)
    return values[0]


def test_overrides_of_a_vector_task(tmp_path):
    overrides = sheeprl_overrides("CartPole-v1", 2, 10_000, 5, tmp_path, ["algo.learning_starts=64"])
    assert overrides[:3] == ["exp=dreamer_v3", "env=gym", "algo=dreamer_v3_XS"]
    for key, value in {
        "algo.per_rank_sequence_length": "16",
        "algo.replay_ratio": "0.25",
        "algo.cnn_keys.encoder": "[]",
        "algo.cnn_keys.decoder": "[]",
        "algo.mlp_keys.encoder": "[state]",
        "algo.mlp_keys.decoder": "[state]",
        "algo.total_steps": "10000",
        "checkpoint.every": "2000",
        "+env.wrapper.seed": "2",
        "seed": "2",
        "env.num_envs": "1",
        "num_threads": "1",
        "env.id": "CartPole-v1",
        "env.wrapper._target_": "benchmarks.peers.sheeprl_env",
        "log_root": str(tmp_path.resolve()),
    }.items():
        assert _value(overrides, key) == value
    assert overrides[-1] == "algo.learning_starts=64"  # the extra ones come last, so they win


def test_overrides_of_a_pixel_task(tmp_path):
    overrides = sheeprl_overrides("cartpole-balance-pixels", 0, 10_000, 5, tmp_path)
    assert _value(overrides, "algo.cnn_keys.encoder") == _value(overrides, "algo.cnn_keys.decoder") == "[rgb]"
    assert _value(overrides, "algo.mlp_keys.encoder") == "[]"


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("Acrobot-v1", 0, 100, 2), "unknown task 'Acrobot-v1'"),
        (("CartPole-v1", 0, 1, 2), "steps must be >= n_evals"),
        (("CartPole-v1", -1, 100, 2), "seed must be an int >= 0, got -1"),
        (("CartPole-v1", 0, 100, 0), "n_evals must be an int >= 1, got 0"),
    ],
)
def test_overrides_refuse_bad_settings(tmp_path, args, message):
    with pytest.raises(ValueError, match=message):
        sheeprl_overrides(*args, tmp_path)


def test_checkpoint_steps_pick_the_first_at_or_after_each_evaluation_point():
    assert checkpoint_steps(10_000, 5, [2000, 4000, 6000, 8000, 10_000]) == [2000, 4000, 6000, 8000, 10_000]
    assert checkpoint_steps(10, 3, [4, 8, 10]) == [4, 8, 10]  # points 3, 6, 10
    assert checkpoint_steps(10, 2, [2, 4, 6, 8, 10]) == [6, 10]
    with pytest.raises(RuntimeError, match="no checkpoint at or after step 10"):
        checkpoint_steps(10, 2, [5, 9])


def test_sheeprl_env_is_the_suite_env():
    from benchmarks.suites import make_env

    ours, suite = sheeprl_env("CartPole-v1", seed=3), make_env("classic", "CartPole-v1", seed=3)
    np.testing.assert_array_equal(ours.reset()[0], suite.reset()[0])  # the same seeded stream
    with pytest.raises(ValueError, match="unknown CPU-suite task 'CartPole-v0'"):
        sheeprl_env("CartPole-v0")


def test_recorded_extra_overrides_are_read_back(tmp_path):
    overrides = sheeprl_overrides("Pendulum-v1", 1, 100, 2, tmp_path, ["algo.learning_starts=8"])
    record = {"task": "Pendulum-v1", "seed": 1, "steps": 100, "n_evals": 2}
    command = ["python", "-m", "sheeprl", *[o for o in overrides if not peers._is_path_override(o)]]
    assert peers._recorded_extra({**record, "sheeprl": {"command": command}}) == ["algo.learning_starts=8"]
    assert peers._recorded_extra(record) is None


def _record(task: str, algo: str, seed: int, final: float) -> dict:
    run = SuiteRun(task, algo, seed, 100, eval_episodes=2, n_evals=2)
    return {
        **cpu_suite.asdict(run),
        "eval_steps": [50, 100],
        "eval_returns": [final / 2, final],
        "trained_steps": 100,
        "final_mean": final,
        "final_std": 0.0,
        "wall_s": 10.0 * (seed + 1),
        "commit": None,
    }


def test_report_has_a_dreamerv3_column(tmp_path):
    records = [_record("CartPole-v1", "hieros", s, 100.0 + s) for s in (0, 1)]
    records += [_record("CartPole-v1", "dreamerv3", s, 20.0 * (s + 1)) for s in (0, 1)]
    (tmp_path / "runs.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    args = ["--tasks", "CartPole-v1", "--seeds", "2", "--steps", "100", "--out", str(tmp_path), "--report"]
    assert cpu_suite.main(args) == records
    lines = (tmp_path / "table.md").read_text().splitlines()
    assert lines[0] == "| Task | Steps | Final eval | HIEROS small | DreamerV3 XS (sheeprl) |"
    assert lines[2].endswith("| 30.0 +- 10.0 (2 seeds, 15 s/run) |")
    assert (tmp_path / "cpu_suite.png").is_file()


def test_cpu_suite_refuses_dreamerv3_runs_without_sheeprl_before_training(tmp_path, monkeypatch):
    find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: None if name == "sheeprl" else find_spec(name))
    args = ["--tasks", "CartPole-v1", "--algos", "dqn", "dreamerv3", "--seeds", "1", "--steps", "64"]
    with pytest.raises(ImportError, match="'peers' extra"):
        cpu_suite.main([*args, "--out", str(tmp_path)])
    assert not (tmp_path / "runs.jsonl").exists()  # dqn, first in the order, did not run either


def test_run_dreamerv3_refuses_other_runs():
    with pytest.raises(ValueError, match="runs algo 'dreamerv3', got 'dqn'"):
        peers.run_dreamerv3(suite_runs(["CartPole-v1"], ["dqn"], [0], 64)[0])
    with pytest.raises(ValueError, match="takes no HIEROS keywords"):
        peers.run_dreamerv3(SuiteRun("CartPole-v1", "dreamerv3", 0, 64, hieros_kwargs={"n_levels": 1}))


def test_tiny_dreamerv3_run_is_recorded_and_resumed(tmp_path, capsys):
    pytest.importorskip("sheeprl", reason="the 'peers' extra is not installed")
    args = ["--tasks", "CartPole-v1", "--seeds", "1", "--steps", "64", "--eval-episodes", "1", "--n-evals", "2"]
    args += ["--out", str(tmp_path), "--sheeprl-overrides", "algo.learning_starts=16", "--resume"]
    (record,) = peers.main(args)
    assert record["algo"] == "dreamerv3" and record["eval_steps"] == [32, 64] and record["trained_steps"] == 64
    assert record["final_mean"] == record["eval_returns"][-1] >= 8  # CartPole lasts at least 8 steps
    assert record["sheeprl"]["version"] == "0.8.4" and record["sheeprl"]["command"][-1] == "algo.learning_starts=16"
    assert [json.loads(line) for line in (tmp_path / "runs.jsonl").read_text().splitlines()] == [record]
    assert peers.main(args) == [record]  # resumed: nothing trained again
    assert "already in" in capsys.readouterr().out
    assert len((tmp_path / "runs.jsonl").read_text().splitlines()) == 1
