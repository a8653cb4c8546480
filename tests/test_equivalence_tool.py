"""benchmarks/equivalence.py: argument checks, the in-tree fingerprint of a case and the comparison report."""

from __future__ import annotations

import pytest

from benchmarks import _equivalence_cases, _gitref, equivalence


def test_arguments_are_checked(capsys):
    with pytest.raises(SystemExit):
        equivalence.main([])  # --ref is required
    with pytest.raises(SystemExit):
        equivalence.main(["--ref", "HEAD", "--cases", "no_such_case"])
    assert "unknown cases ['no_such_case']" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        equivalence.main(["--ref", "no-such-branch-anywhere"])
    assert "names no commit" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        equivalence.main(["--ref", "HEAD", "--steps", "0"])
    assert equivalence.main(["--ref", "HEAD", "--list"]) == 0
    assert "shared_world_model" in capsys.readouterr().out.split()
    with pytest.raises(ValueError, match="git revision"):
        _gitref.resolve("--all")


def test_in_tree_fingerprint_is_reproducible():
    first = _equivalence_cases.run_case("mlp_levels1", steps=28)
    second = _equivalence_cases.run_case("mlp_levels1", steps=28)
    assert first == second
    assert first["counters"]["num_timesteps"] == 28 and first["counters"]["level_updates"][0] > 0
    assert set(equivalence.PARTS) <= set(first) and len(first["params"]) > 10
    lines, same = equivalence.compare({"mlp_levels1": first}, {"mlp_levels1": second})
    assert same and lines == [f"mlp_levels1: identical ({len(first['params'])} tensors, 4 optimisers)"]


def test_comparison_names_what_differs():
    base = {
        "params": {"a": "1", "b": "2"},
        "optimizers": {"o": "3"},
        "counters": {"n": 1},
        "replay": ["r0", "r1"],
        "predict": "p",
        "rng": "g",
    }
    other = {**base, "params": {"a": "1", "b": "X"}, "replay": ["r0", "Y"], "counters": {"n": 2}}
    lines, same = equivalence.compare({"case": base, "gone": base}, {"case": other, "bad": {"error": "boom"}})
    assert not same
    report = "\n".join(lines)
    assert "case: DIFFERENT - params: 1 of 2 differ (b)" in report
    assert "counters: {'n': 1} here, {'n': 2} at the ref" in report and "replay: levels [1] differ" in report
    assert "gone: missing at the ref" in report and "bad: missing here" in report
