import sys

import pytest

from benchmarks import world_model as bench


@pytest.mark.parametrize(
    ("argv", "match"),
    [
        (["--parts", "b", "--presets", "tiny"], "--presets"),
        (["--parts", "b", "--presets", ","], "--presets"),
        (["--parts", "e"], "--parts"),
    ],
)
def test_bad_parts_and_presets_raise_before_any_work(monkeypatch, argv, match):
    monkeypatch.setattr(sys, "argv", ["world_model", *argv])
    with pytest.raises(ValueError, match=match):
        bench.main()


def test_presets_limit_part_b(monkeypatch):
    calls = []
    monkeypatch.setattr(bench, "part_b_small", lambda args: calls.append("small"))
    monkeypatch.setattr(bench, "part_b_paper", lambda args: calls.append("paper"))
    monkeypatch.setattr(sys, "argv", ["world_model", "--parts", "b", "--presets", "small"])
    bench.main()
    assert calls == ["small"]
