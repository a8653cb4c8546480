"""benchmarks/ablations.py: the summary statistics and re-tabulating a saved results.json (no training)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from benchmarks.ablations import binned_curve, final_return, main, summarise


def _record(variant: str, ends: list[int], returns: list[float], wall: float = 1.0) -> dict:
    return {
        "variant": variant,
        "env_id": "CartPole-v1",
        "seed": 0,
        "episode_end_steps": ends,
        "episode_returns": returns,
        "wall_s": wall,
    }


def test_mean_return_is_the_area_under_the_curve_not_the_episode_mean():
    # ten short episodes in the first half of 100 steps, one long one in the second half
    record = _record("hieros", [5 * (i + 1) for i in range(10)] + [100], [5.0] * 10 + [50.0])
    np.testing.assert_allclose(binned_curve(record, 100, 2), [5.0, 50.0])
    row = summarise([record], 100, bins=2)[("CartPole-v1", "hieros")]
    assert row["mean_return"] == pytest.approx(27.5)  # the episode mean would be 100 / 11
    assert row["final_mean"] == pytest.approx(final_return(record, 100)) == pytest.approx(50.0)


def test_from_results_tabulates_without_training(tmp_path):
    runs = [
        _record("hieros", [50, 100], [10.0, 30.0]),
        _record("no_novelty", [40, 100], [8.0, 12.0]),
    ]
    path = tmp_path / "results.json"
    path.write_text(json.dumps({"args": {"steps": "100"}, "runs": runs}))
    table = main(
        ["--ablation", "no_novelty", "--from-results", str(path), "--out", str(tmp_path / "out"), "--bins", "2"]
    )
    assert table[("CartPole-v1", "no_novelty")]["final_mean"] == pytest.approx(12.0)
    text = (tmp_path / "out" / "table.md").read_text()
    assert "| CartPole-v1 | no_novelty | 5.3.12 | 12.0 +- 0.0 | 10.0 | -18.0 |" in text
    assert (tmp_path / "out" / "no_novelty.png").is_file()
