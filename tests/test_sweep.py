"""benchmarks/sweep.py: grids of runs, locally and through a local Ray instance."""

from __future__ import annotations

import pytest

from benchmarks.sweep import Run, TrainJob, execute, grid_jobs, run_grid, run_sweep

# a few level-0 updates after 100 random steps: enough to make the records depend on training
TINY = {"preset": "small", "learning_starts": 100, "config_overrides": {"train_ratio": 32}, "buffer_size": 1000}


def _strip(records):
    return [{k: v for k, v in r.items() if k not in ("wall_s", "train_s")} for r in records]


def test_grid_jobs():
    jobs = grid_jobs("dmc_proprio", 2, tasks=["cartpole-balance", "walker-walk"], train_kwargs={"steps": 10})
    assert jobs[1] == TrainJob("dmc_proprio", "cartpole-balance", 1, {"steps": 10})
    assert [(j.task, j.seed) for j in jobs][2:] == [("walker-walk", 0), ("walker-walk", 1)]
    assert len(grid_jobs("atari100k", 3)) == 78
    assert grid_jobs("Pendulum-v1", 1) == [TrainJob("classic", "Pendulum-v1", 0, {})]
    with pytest.raises(ValueError, match="unknown grid"):
        grid_jobs("Pendulum-v9", 1)
    with pytest.raises(ValueError, match="seeds"):
        grid_jobs("atari100k", 0)
    with pytest.raises(ValueError, match="workers"):
        execute(len, [], workers=0)


def test_grid_runs_and_aggregates(tmp_path):
    kwargs = {"preset": "small", "steps": 40, "eval_freq": 20, "eval_episodes": 2, "periodic_eval_episodes": 1,
              "out": tmp_path, "hieros_kwargs": {"learning_starts": 1000, "buffer_size": 1000}}  # fmt: skip
    records, markdown = run_grid(grid_jobs("CartPole-v1", 2, train_kwargs=kwargs), aggregate_out=tmp_path / "agg")
    assert [(r["task"], r["seed"]) for r in records] == [("CartPole-v1", 0), ("CartPole-v1", 1)]
    assert (tmp_path / "classic" / "CartPole-v1" / "seed1" / "result.json").is_file()
    assert "| CartPole-v1 |" in markdown and (tmp_path / "agg" / "classic_curves.png").is_file()


@pytest.mark.timeout(900)  # starting Ray on a loaded 2-core machine can take minutes
def test_ray_matches_local():
    ray = pytest.importorskip("ray", reason="the 'ray' extra is not installed")
    runs = [Run("hieros", "CartPole-v1", seed, 120, TINY) for seed in (0, 1)]
    local = run_sweep(runs, workers=1, verbose=False)
    assert all(sum(r["updates"]) > 0 for r in local)
    assert local[0]["episode_returns"] != local[1]["episode_returns"]
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        remote = run_sweep(runs, verbose=False, ray_address="local")
    finally:
        ray.shutdown()
    assert _strip(remote) == _strip(local)
