"""benchmarks/cpu_suite.py: HIEROS against zoo-configured SB3 baselines (tiny budget only)."""

from __future__ import annotations

import dataclasses
import json

import pytest

pytest.importorskip("rl_zoo3", reason="the 'zoo' extra is not installed")

from benchmarks.cpu_suite import (
    TASKS,
    drop_unfinished_line,
    finished_runs,
    main,
    recorded_runs,
    run_checkpoint_dir,
    run_key,
    run_suite_run,
    suite_runs,
    zoo_hyperparams,
)
from benchmarks.sample_efficiency import ZOO_DQN, ZOO_PPO
from benchmarks.train import RunCheckpoint


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


def test_cpu_suite_refuses_hieros_kwargs_that_are_not_a_json_object(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["--tasks", "CartPole-v1", "--report", "--out", str(tmp_path), "--hieros-kwargs", "[1]"])
    assert "--hieros-kwargs: '[1]' is a JSON list; expected a JSON object" in capsys.readouterr().err


def test_suite_runs_give_hieros_kwargs_to_hieros_only():
    runs = suite_runs(["Pendulum-v1"], ["hieros", "dreamerv3", "sac"], [0], 100, hieros_kwargs={"n_levels": 1})
    assert [(r.algo, r.hieros_kwargs) for r in runs] == [("hieros", {"n_levels": 1}), ("dreamerv3", {}), ("sac", {})]


def test_tiny_cartpole_suite(tmp_path):
    records = main(
        [
            "--tasks", "CartPole-v1", "--algos", "hieros", "ppo", "dqn", "--seeds", "1", "--steps", "256",
            "--eval-episodes", "2", "--n-evals", "2", "--out", str(tmp_path),
            "--hieros-kwargs", json.dumps({"learning_starts": 1000, "buffer_size": 1000}),
        ]
    )  # fmt: skip
    assert [r["algo"] for r in records] == ["hieros", "ppo", "dqn"]
    assert [bool(r["hieros_kwargs"]) for r in records] == [True, False, False]
    for record in records:
        assert record["eval_steps"][0] >= 128 and record["eval_steps"][-1] >= 256 and len(record["eval_returns"]) == 2
        assert record["final_mean"] == record["eval_returns"][-1] > 0 and record["trained_steps"] == 256
    markdown = (tmp_path / "table.md").read_text()
    assert markdown.startswith("| Task | Steps | Final eval | HIEROS small | PPO | DQN |")
    assert "| CartPole-v1 | 256 | 2 episodes |" in markdown
    assert (tmp_path / "cpu_suite.png").is_file()
    assert json.loads((tmp_path / "results.json").read_text()) == records
    logged = [json.loads(line) for line in (tmp_path / "runs.jsonl").read_text().splitlines()]
    assert sorted(r["algo"] for r in logged) == ["dqn", "hieros", "ppo"] and all(r["commit"] for r in logged)


def test_resume_reuses_recorded_runs_and_runs_the_rest(tmp_path):
    args = ["--tasks", "CartPole-v1", "--seeds", "1", "--steps", "64", "--eval-episodes", "1", "--n-evals", "1"]
    first = main([*args, "--algos", "dqn", "--out", str(tmp_path)])
    both = main([*args, "--algos", "ppo", "dqn", "--out", str(tmp_path), "--resume"])
    assert [r["algo"] for r in both] == ["ppo", "dqn"] and both[1] == first[0]  # dqn taken from runs.jsonl
    assert len((tmp_path / "runs.jsonl").read_text().splitlines()) == 2  # only ppo was trained again
    again = main([*args, "--algos", "dqn", "--steps", "32", "--out", str(tmp_path), "--resume"])
    assert again[0]["steps"] == 32 and again[0] != first[0]  # other settings: a new run
    done = finished_runs(tmp_path / "runs.jsonl")
    assert set(done) == {run_key(r) for r in suite_runs(["CartPole-v1"], ["ppo", "dqn"], [0], 64, 1, 1)} | {
        run_key(suite_runs(["CartPole-v1"], ["dqn"], [0], 32, 1, 1)[0])
    }


def test_report_tables_recorded_runs_of_any_evaluation_settings(tmp_path):
    args = ["--tasks", "CartPole-v1", "--seeds", "1", "--steps", "64", "--n-evals", "1", "--out", str(tmp_path)]
    ppo = main([*args, "--algos", "ppo", "--eval-episodes", "1"])
    dqn = main([*args, "--algos", "dqn", "--eval-episodes", "2"])
    log = (tmp_path / "runs.jsonl").read_text()
    reported = main([*args, "--report"])  # hieros has no record: left out
    assert reported == ppo + dqn and (tmp_path / "runs.jsonl").read_text() == log  # nothing trained
    assert "| CartPole-v1 | 64 | 1/2 episodes |" in (tmp_path / "table.md").read_text()
    with pytest.raises(ValueError, match="records none of the 4 runs"):
        main([*args, "--report", "--steps", "32"])
    main([*args, "--algos", "dqn", "--eval-episodes", "1"])  # the same run, evaluated differently
    with pytest.raises(
        ValueError, match=r"different evaluation settings \(n_evals, eval_episodes\) \(1, 2\) and \(1, 1\)"
    ):
        recorded_runs(tmp_path / "runs.jsonl", suite_runs(["CartPole-v1"], ["dqn"], [0], 64))


def test_finished_runs_names_a_bad_line(tmp_path):
    assert finished_runs(tmp_path / "missing.jsonl") == {}
    log = tmp_path / "runs.jsonl"
    log.write_text('{"task": "CartPole-v1"}\n')
    with pytest.raises(ValueError, match=r"runs\.jsonl:1 is not a cpu_suite run record"):
        finished_runs(log)


def test_an_append_cut_short_is_left_out_and_cut(tmp_path):
    """A crash during the append of a record leaves a last line without newline: it is left out and cut off."""
    run = suite_runs(["CartPole-v1"], ["dqn"], [0], 64)[0]
    log = tmp_path / "runs.jsonl"
    whole = json.dumps(dataclasses.asdict(run)) + "\n"
    log.write_text(whole + whole[:40])
    with pytest.warns(UserWarning, match=r"runs\.jsonl:2 is an unfinished record"):
        assert set(finished_runs(log)) == {run_key(run)}
    drop_unfinished_line(log)
    assert log.read_text() == whole


def test_a_hieros_run_goes_on_from_its_checkpoint(tmp_path, monkeypatch):
    hieros_kwargs = {"learning_starts": 20, "buffer_size": 1000, "config_overrides": {"n_levels": 1}}
    args = [
        "--tasks", "CartPole-v1", "--algos", "hieros", "--seeds", "1", "--steps", "90", "--eval-episodes", "1",
        "--n-evals", "3", "--checkpoint-freq", "25", "--hieros-kwargs", json.dumps(hieros_kwargs),
    ]  # fmt: skip
    run = suite_runs(["CartPole-v1"], ["hieros"], [0], 90, 1, 3, hieros_kwargs)[0]
    folder = run_checkpoint_dir(tmp_path / "resumed", run)
    save = RunCheckpoint._on_rollout_start

    def save_then_stop(self):
        save(self)
        if self.last_saved == 50:
            raise KeyboardInterrupt

    with monkeypatch.context() as patch:
        patch.setattr(RunCheckpoint, "_on_rollout_start", save_then_stop)
        with pytest.raises(KeyboardInterrupt):
            main([*args, "--out", str(tmp_path / "resumed")])
    assert sorted(p.name for p in folder.iterdir()) == ["model_50.zip", "progress.json", "replay_50.zip"]
    progress = json.loads((folder / "progress.json").read_text())
    assert progress["step"] == 50 and [t for t, _ in progress["evaluations"]] == [30] and progress["wall_s"] > 0

    (record,) = main([*args, "--out", str(tmp_path / "resumed"), "--resume"])
    assert record["resumed_at"] == [50] and record["trained_steps"] == 90 and record["wall_s"] > progress["wall_s"]
    assert record["eval_steps"] == [30, 60, 90] and record["eval_returns"][0] == progress["evaluations"][0][1]
    assert not folder.exists()  # removed once the run is recorded
    (plain,) = main([*args, "--out", str(tmp_path / "plain")])
    assert plain["eval_steps"] == record["eval_steps"] and "resumed_at" not in plain

    # without --resume a run starts afresh, whatever checkpoint its folder holds
    with monkeypatch.context() as patch:
        patch.setattr(RunCheckpoint, "_on_rollout_start", save_then_stop)
        with pytest.raises(KeyboardInterrupt):
            main([*args, "--out", str(tmp_path / "again")])
    (fresh,) = main([*args, "--out", str(tmp_path / "again")])
    assert "resumed_at" not in fresh and not run_checkpoint_dir(tmp_path / "again", run).exists()


def test_a_checkpoint_of_other_settings_is_refused(tmp_path):
    run = suite_runs(["CartPole-v1"], ["hieros"], [0], 90, 1, 3)[0]
    folder = tmp_path / "checkpoint"
    folder.mkdir()
    other = {**dataclasses.asdict(run), "steps": 120}
    (folder / "progress.json").write_text(json.dumps({"step": 50, "run": other}))
    with pytest.raises(
        ValueError,
        match=r"progress.json belongs to a run with other options: steps 120 \(now 90\).*remove the run's folder",
    ):
        run_suite_run(run, folder, 25)
    with pytest.raises(ValueError, match="checkpoint_freq must be an int >= 0"):
        run_suite_run(run, folder, -1)


def test_first_seed_selects_the_seeds(tmp_path):
    args = ["--tasks", "CartPole-v1", "--algos", "dqn", "--steps", "32", "--eval-episodes", "1", "--n-evals", "1"]
    records = main([*args, "--first-seed", "2", "--seeds", "2", "--out", str(tmp_path)])
    assert [r["seed"] for r in records] == [2, 3]
    with pytest.raises(SystemExit):
        main([*args, "--first-seed", "-1", "--out", str(tmp_path)])
