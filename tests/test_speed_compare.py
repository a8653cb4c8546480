"""benchmarks/speed.py compare: the speed-up table and a run against HEAD on tiny settings (nothing is timed here)."""

from __future__ import annotations

import pytest

from benchmarks import _speed_cases
from benchmarks.speed import compare_table, main


def test_speedups_are_ref_over_here_for_times_and_here_over_ref_for_rates():
    samples = {
        "learn": {"here": [10.0, 20.0, 12.0], "ref": [30.0, 30.0, 48.0]},  # paired speed-ups 3.0, 1.5, 4.0
        "pong": {"here": [21.0, 22.0, 20.0], "ref": [7.0, 11.0, 5.0]},  # 3.0, 2.0, 4.0
    }
    figures = dict(line.split(": ") for line in compare_table(samples).splitlines() if ": " in line)
    assert float(figures["learn_speedup"]) == pytest.approx(3.0)
    assert float(figures["learn_speedup_of_medians"]) == pytest.approx(30.0 / 12.0, abs=0.005)
    assert float(figures["pong_speedup"]) == pytest.approx(3.0)
    assert float(figures["pong_speedup_of_medians"]) == pytest.approx(3.0)
    assert float(figures["pong_env_steps_per_s"]) == pytest.approx(21.0)
    assert float(figures["pong_env_steps_per_s_ref"]) == pytest.approx(7.0)
    learn_row = next(line for line in compare_table(samples).splitlines() if line.startswith("learn"))
    assert "[1.500, 4.000]" in learn_row  # range of the paired speed-ups


#: one repetition against HEAD with a learn part of 8 training steps
TINY = ["compare", "--ref", "HEAD", "--reps", "1", "--learn-steps", "24", "--learning-starts", "16"]


def test_compare_against_head_on_tiny_settings(capsys):
    main([*TINY, "--parts", "learn", "predict", "--predict-calls", "3", "--policy-kwargs", '{"bf16": true}'])
    out = capsys.readouterr().out
    assert "policy_kwargs here {'bf16': True}, ref {}" in out
    for name in ("learn_speedup", "predict_speedup", "learn_speedup_of_medians"):
        assert f"\n{name}: " in out
    assert "rep 1 learn    here" in out and "rep 1 learn    ref " in out
    assert "pong" not in out.split("\n\n")[-1]  # a part not asked for is not timed


def test_compare_passes_learn_env_and_config_overrides_to_each_side(capsys):
    main([*TINY, "--parts", "learn", "--learn-env", "Pendulum-v1", "--config-overrides", '{"world_model_updates": 2}'])
    out = capsys.readouterr().out
    assert "learn: Pendulum-v1 learn(24)" in out
    assert "config_overrides here {'world_model_updates': 2}, ref {}" in out
    assert "rep 1 learn    here" in out and "rep 1 learn    ref " in out


def test_learn_part_builds_the_model_it_is_asked_for(monkeypatch):
    import sb3_hieros

    built = {}

    class Recording(sb3_hieros.HIEROS):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            built["env"] = self.env.envs[0].spec.id
            built["world_model_updates"] = self.config.world_model_updates

    monkeypatch.setattr(sb3_hieros, "HIEROS", Recording)
    result = _speed_cases.time_learn(24, 16, 0, env_id="Pendulum-v1", config_overrides={"world_model_updates": 3})
    assert built == {"env": "Pendulum-v1", "world_model_updates": 3}
    assert result["seconds"] > 0 and result["level_updates"][0] > 0
    _speed_cases.time_learn(24, 16, 0)  # the defaults: CartPole-v1, no config_overrides
    assert built == {"env": "CartPole-v1", "world_model_updates": sb3_hieros.get_preset("small").world_model_updates}


def test_compare_checks_its_arguments(capsys):
    with pytest.raises(SystemExit):
        main(["compare"])  # --ref is required
    with pytest.raises(SystemExit):
        main(["compare", "--ref", "HEAD", "--parts", "walk"])
    with pytest.raises(ValueError, match="--reps must be >= 1, got 0"):
        main(["compare", "--ref", "HEAD", "--reps", "0"])
    with pytest.raises(SystemExit):
        main(["compare", "--ref", "HEAD", "--config-overrides", "[1]"])
    assert "--config-overrides: '[1]' is a JSON list; expected a JSON object" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["compare", "--ref", "HEAD", "--ref-policy-kwargs", "{bad"])
    assert "--ref-policy-kwargs: '{bad' is not JSON" in capsys.readouterr().err
    with pytest.raises(ValueError, match="names no commit"):
        main(["compare", "--ref", "no-such-branch-anywhere"])


def test_pong_part_trains_on_tiny_settings():
    pytest.importorskip("ale_py", reason="the 'atari' extra is not installed")
    result = _speed_cases.time_pong(steps=4, warmup=2, learning_starts=24, seed=0)
    assert result["steps_per_s"] > 0 and len(result["level_updates"]) == 2
    assert result["level_updates"][0] > 0  # level 0 trained in the timed segment


def test_speed_cases_refuse_keyword_options_that_are_not_json_objects(tmp_path, capsys):
    out = tmp_path / "result.json"
    with pytest.raises(SystemExit):
        _speed_cases.main(["--part", "predict", "--out", str(out), "--policy-kwargs", "[1]"])
    assert "--policy-kwargs: '[1]' is a JSON list; expected a JSON object" in capsys.readouterr().err
    assert not out.exists()
