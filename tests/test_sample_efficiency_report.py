"""benchmarks/sample_efficiency.py --report: table and figure from recorded results.json files, no training."""

from __future__ import annotations

import json

import pytest

from benchmarks.sample_efficiency import main


def _results(path, algo, returns_by_seed, kwargs=None, milestones=(5000, 10000)):
    runs = [
        {"algo": algo, "seed": seed, "steps": list(milestones), "returns": returns, "wall_s": 10.0 * (seed + 1)}
        for seed, returns in enumerate(returns_by_seed)
    ]
    path.write_text(json.dumps({"runs": runs, "hieros_kwargs": kwargs or {}, "milestones": list(milestones)}))
    return path


def test_report_merges_files_and_labels_variants(tmp_path):
    preset = _results(tmp_path / "a.json", "hieros", [[400.0, 500.0], [300.0, 400.0]])
    variant = _results(tmp_path / "b.json", "hieros", [[100.0, 200.0]], kwargs={"replay_context": True})
    baseline = _results(tmp_path / "c.json", "ppo", [[150.0, 250.0, 350.0]], milestones=(5000, 10000, 20000))
    table = main(["--report", str(preset), str(variant), str(baseline), "--out", str(tmp_path / "out")])
    assert table["hieros"][10000] == pytest.approx((450.0, 50.0, 2))
    assert table['hieros {"replay_context": true}'][5000] == pytest.approx((100.0, 0.0, 1))
    markdown = (tmp_path / "out" / "table.md").read_text().splitlines()
    assert markdown[0] == "| algorithm | seeds | 5k steps | 10k steps | 20k steps | wall s / run |"
    assert markdown[2] == "| hieros | 2 | 350.0 +- 50.0 (400.0, 300.0) | 450.0 +- 50.0 (500.0, 400.0) | - | 15 |"
    assert markdown[4].startswith("| ppo | 1 | 150.0 +- 0.0 (150.0) |")
    assert (tmp_path / "out" / "sample_efficiency.png").stat().st_size > 1000
    (tmp_path / "bad.json").write_text("{}")
    with pytest.raises(ValueError, match=r"not a results\.json"):
        main(["--report", str(tmp_path / "bad.json"), "--out", str(tmp_path / "out")])


def test_hieros_kwargs_that_are_not_a_json_object_are_refused(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["--hieros-kwargs", '"small"', "--out", str(tmp_path / "out")])
    assert "--hieros-kwargs: '\"small\"' is a JSON str; expected a JSON object" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
