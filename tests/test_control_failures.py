"""benchmarks/control_failures.py on tiny models: every figure is computed, and the argument checks."""

from __future__ import annotations

import math

import pytest
from hieros_helpers import tiny_kwargs

from benchmarks import control_failures
from sb3_hieros import HIEROS


@pytest.fixture(scope="module")
def pendulum_models(tmp_path_factory):
    folder = tmp_path_factory.mktemp("pendulum")
    paths = {}
    for name, levels in (("one", 1), ("two", 2)):
        model = HIEROS("MlpPolicy", "Pendulum-v1", **tiny_kwargs(n_levels=levels))
        model.learn(40)
        paths[name] = folder / f"{name}.zip"
        model.save(paths[name])
    return paths


def test_every_figure_of_both_models(pendulum_models, capsys):
    args = [f"{name}={path}" for name, path in pendulum_models.items()]
    results = control_failures.main(
        [*args, "--suite", "classic", "--task", "Pendulum-v1", "--episodes", "1", "--horizon", "3", "--stride", "50"]
    )
    assert set(results) == {"one", "two"}
    for figures in results.values():
        assert 0.0 <= figures["level0/at_bounds"] <= 1.0
        assert figures["level0/policy_std"] > 0.0
        assert figures["return/deterministic"] < 0.0  # Pendulum's rewards are never positive
        shares = [v for k, v in figures.items() if k.startswith("level0/grad_share/")]
        assert math.isclose(sum(shares), 1.0, rel_tol=1e-6)
        assert figures["world_model/reward_mae"] >= 0.0
    # the two-level model has a subgoal term at level 0 and a level above whose subgoals change or not
    assert "level0/grad_share/subgoal" in results["two"] and "level0/grad_share/subgoal" not in results["one"]
    assert 0.0 <= results["two"]["level1/subgoal_change_rate"] <= 1.0
    out = capsys.readouterr().out
    assert "| figure | one | two |" in out and "two/level0/grad_share/subgoal:" in out


def test_argument_checks(pendulum_models, tmp_path):
    with pytest.raises(ValueError, match="does not exist"):
        control_failures.main([str(tmp_path / "missing.zip"), "--suite", "classic", "--task", "Pendulum-v1"])
    with pytest.raises(ValueError, match="--episodes must be >= 1"):
        control_failures.main(
            [str(pendulum_models["one"]), "--suite", "classic", "--task", "Pendulum-v1", "--episodes", "0"]
        )
    same = [f"a={pendulum_models['one']}", f"a={pendulum_models['two']}"]
    with pytest.raises(ValueError, match="distinct"):
        control_failures.main([*same, "--suite", "classic", "--task", "Pendulum-v1"])
