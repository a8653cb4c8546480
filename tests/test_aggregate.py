"""benchmarks/aggregate.py: human-normalised scores, aggregate statistics, bootstrap CIs and the thesis tables."""

from __future__ import annotations

import json

import numpy as np
import pytest

from benchmarks.aggregate import (
    aggregate,
    aggregate_iqm,
    aggregate_mean,
    aggregate_median,
    aggregate_optimality_gap,
    atari_table,
    dmc_table,
    human_normalized_score,
    load_results,
    run_cost,
    stratified_bootstrap_ci,
    thesis_table,
)


def _record(suite, task, seed, score, curve=((10, 1.0), (20, 2.0)), wall_s=7200.0):
    return {
        "suite": suite,
        "task": task,
        "seed": seed,
        "preset": "small",
        "final_mean": score,
        "wall_s": wall_s,
        "steps": 20,
        "eval_timesteps": [t for t, _ in curve],
        "eval_means": [m for _, m in curve],
    }


def test_human_normalized_score():
    assert human_normalized_score(5, -21, 15) == pytest.approx(26 / 36)  # thesis HIEROS on Pong
    np.testing.assert_allclose(human_normalized_score(np.array([228, 7128]), 228, 7128), [0.0, 1.0])
    with pytest.raises(ValueError, match="differ"):
        human_normalized_score(1, 3, 3)


def test_aggregates_hand_computed():
    # one task with runs 0..7: IQM drops 2 at each end -> mean(2, 3, 4, 5)
    assert aggregate_iqm([np.arange(8.0)]) == pytest.approx(3.5)
    # across tasks the same pooling: 4 scores, drop one at each end
    assert aggregate_iqm([np.array([10.0]), np.array([1.0, 2.0]), np.array([-5.0])]) == pytest.approx(1.5)
    assert aggregate_optimality_gap([np.array([0.5, 1.5]), np.array([0.2])]) == pytest.approx((0.5 + 0 + 0.8) / 3)
    assert aggregate_optimality_gap([np.array([50.0])], gamma=100.0) == pytest.approx(50.0)
    # mean / median of per-task means: task means 1, 3, 10
    tasks = [np.array([0.0, 2.0]), np.array([3.0]), np.array([10.0, 10.0])]
    assert aggregate_mean(tasks) == pytest.approx(14 / 3)
    assert aggregate_median(tasks) == pytest.approx(3.0)
    with pytest.raises(ValueError, match="at least one score"):
        aggregate_mean([np.array([1.0]), np.array([])])


def test_matches_rliable():
    rliable = pytest.importorskip("rliable.metrics")
    scores = np.random.default_rng(0).normal(1.0, 0.7, (3, 6))  # (runs, tasks)
    per_task = list(scores.T)
    assert aggregate_iqm(per_task) == pytest.approx(rliable.aggregate_iqm(scores))
    assert aggregate_optimality_gap(per_task) == pytest.approx(rliable.aggregate_optimality_gap(scores))
    assert aggregate_mean(per_task) == pytest.approx(rliable.aggregate_mean(scores))
    assert aggregate_median(per_task) == pytest.approx(rliable.aggregate_median(scores))


def test_bootstrap_ci():
    rng = np.random.default_rng(1)
    tasks = [rng.normal(mu, 0.3, 5) for mu in (0.2, 0.8, 1.5, 3.0)]
    for statistic in (aggregate_mean, aggregate_median, aggregate_iqm, aggregate_optimality_gap):
        low, high = stratified_bootstrap_ci(tasks, statistic, reps=300)
        assert low <= statistic(tasks) <= high and low < high
    narrow = stratified_bootstrap_ci(tasks, aggregate_mean, reps=300, confidence=0.5)
    wide = stratified_bootstrap_ci(tasks, aggregate_mean, reps=300, confidence=0.99)
    assert wide[0] <= narrow[0] and narrow[1] <= wide[1]
    # one run per task: nothing to resample, the interval collapses onto the point estimate
    assert stratified_bootstrap_ci([np.array([1.0]), np.array([3.0])], aggregate_mean, reps=20) == (2.0, 2.0)
    with pytest.raises(ValueError, match="confidence"):
        stratified_bootstrap_ci(tasks, aggregate_mean, confidence=1.0)


def test_atari_table_has_thesis_numbers():
    table = thesis_table("atari100k")
    assert len(table) == 25 and table["Pong"] == {
        "random": -21, "human": 15, "simple": 13, "twm": 18, "iris": 15, "director": -18, "dreamerv3": 18, "hieros": 5,
    }  # fmt: skip
    records = [_record("atari100k", "Pong", s, v, wall_s=w) for s, v, w in ((0, 5.0, 9000.0), (1, -3.0, 18000.0))]
    records += [_record("atari100k", "Krull", 0, 1598.0), _record("atari100k", "UpNDown", 0, 3000.0)]
    markdown, summary = atari_table(records, reps=50)
    pong = next(line for line in markdown.splitlines() if line.startswith("| Pong |"))
    assert "| -21 | 15 | 1.0 +- 4.0 (2) |" in pong and pong.endswith("| small, 3.8 h | 5 | 18 |")
    assert summary["hns"]["Pong"] == pytest.approx([26 / 36, 18 / 36])
    assert summary["hns"]["Krull"] == [0.0] and "UpNDown" not in summary["hns"]  # no thesis row
    assert summary["mean"]["value"] == pytest.approx(100 * (22 / 36 + 0.0) / 2)
    low, high = summary["mean"]["ci"]
    assert low <= summary["mean"]["value"] <= high
    # two of 25 games: the thesis' aggregates (over all 25) are left out of the comparison
    assert "| **IQM** (HNS %, 2 of the thesis' 25 games) |" in markdown
    assert markdown.splitlines()[-1].endswith("] | | - | - |")
    # every game: the thesis' aggregates next to ours
    from benchmarks.suites import ATARI100K_THESIS_LABELS

    records = [_record("atari100k", game, 0, table[label]["human"]) for game, label in ATARI100K_THESIS_LABELS.items()]
    markdown, summary = atari_table(records, reps=20)
    assert summary["mean"]["value"] == pytest.approx(100.0)
    assert "| **IQM** (HNS %, 25 games) | | | | 100.0 [100.0, 100.0] | | 53 | N/A |" in markdown


def test_dmc_table_and_files(tmp_path):
    table = thesis_table("dmc_vision")
    assert len(table) == 20 and table["Cup Catch"]["hieros"] == 942.8
    records = [_record("dmc_vision", "ball_in_cup-catch", s, v) for s, v in enumerate((900.0, 950.0))]
    markdown, summary = dmc_table(records)
    assert "| Cup Catch | 925.0 +- 25.0 (2) | small, 2.0 h | 942.8 | 957.1 |" in markdown
    assert summary == {"mean": 925.0, "median": 925.0}
    assert "| **Mean** (1 of the thesis' 20 tasks) | 925.0 | | - | - |" in markdown
    # the whole pipeline from result files
    for i, record in enumerate([*records, _record("classic", "CartPole-v1", 0, 500.0)]):
        folder = tmp_path / "runs" / str(i)
        folder.mkdir(parents=True)
        (folder / "result.json").write_text(json.dumps(record))
    loaded = load_results(tmp_path / "runs")
    assert [r["task"] for r in loaded] == ["CartPole-v1", "ball_in_cup-catch", "ball_in_cup-catch"]
    markdown, _ = aggregate(loaded, out=tmp_path / "agg", reps=20)
    assert "### classic" in markdown and "| CartPole-v1 | 500.0 +- 0.0 (1) | 20 | small, 2.0 h |" in markdown
    for name in ("aggregate.md", "aggregate.json", "dmc_vision_curves.png", "classic_curves.png"):
        assert (tmp_path / "agg" / name).is_file(), name
    with pytest.raises(ValueError, match="no such result"):
        load_results(tmp_path / "missing")


def test_run_cost():
    records = [_record("classic", "CartPole-v1", 0, 500.0, wall_s=3600.0), _record("classic", "CartPole-v1", 1, 490.0)]
    records[1]["preset"] = "paper"
    assert run_cost(records, "classic", "CartPole-v1") == "small/paper, 1.5 h"
    del records[0]["wall_s"], records[1]["wall_s"]
    assert run_cost(records, "classic", "CartPole-v1") == "small/paper"  # older records without a wall time
    assert run_cost(records, "classic", "Pendulum-v1") == ""
