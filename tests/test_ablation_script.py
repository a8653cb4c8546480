"""benchmarks/ablations.py: the summary statistics and re-tabulating a saved results.json (no training)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from benchmarks.ablations import THESIS_SET, ablation_names, binned_curve, final_return, main, summarise


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


def test_all_runs_the_novelty_ablation_that_changes_the_preset():
    paper, small = ablation_names(["all"], "paper"), ablation_names(["all"], "small")
    assert len(paper) == len(small) == len(THESIS_SET) - 1
    assert "no_novelty" in paper and "with_novelty" not in paper
    assert "with_novelty" in small and "no_novelty" not in small
    assert "levels_2" not in ablation_names(["every"], "small") and "levels_2" in ablation_names(["every"], "paper")
    # the tiny test networks switch novelty back on, so no_novelty changes "small" again
    assert ablation_names(["no_novelty"], "small", {"actor_critic": {"novelty_weight": 0.1}}) == ["no_novelty"]
    with pytest.raises(ValueError, match="'no_novelty' does not change preset 'small'"):
        ablation_names(["no_novelty"], "small")
    with pytest.raises(ValueError, match="unknown ablation 'nope'"):
        ablation_names(["nope"], "small")


def test_hieros_kwargs_that_are_not_a_json_object_are_refused(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["--hieros-kwargs", "{bad", "--out", str(tmp_path)])
    assert "--hieros-kwargs: '{bad' is not JSON" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())
