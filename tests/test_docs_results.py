"""The results tables in docs/ are what the benchmark scripts make from the recorded runs next to them."""

from __future__ import annotations

import json
import pathlib
import shutil

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"

pytest.importorskip("matplotlib")


#: The HIEROS keywords of the main table's runs: the `small` preset's two world-model updates written out, in float32.
MAIN_HIEROS_KWARGS = '{"config_overrides": {"world_model_updates": 2}, "policy_kwargs": {"bf16": false}}'


def test_cpu_suite_table_is_made_from_runs_jsonl(tmp_path):
    from benchmarks import cpu_suite

    shutil.copy(DOCS / "cpu_suite" / "runs.jsonl", tmp_path / "runs.jsonl")
    args = ["--seeds", "3", "--steps", "10000", "--report", "--hieros-kwargs", MAIN_HIEROS_KWARGS]
    cpu_suite.main([*args, "--out", str(tmp_path)])
    assert (tmp_path / "table.md").read_text() == (DOCS / "cpu_suite" / "table.md").read_text()


def with_config_overrides(hieros_kwargs: str, **overrides: object) -> str:
    """``hieros_kwargs`` (a ``--hieros-kwargs`` JSON string) with ``overrides`` added to its ``config_overrides``.

    ``benchmarks.cpu_suite`` matches records by the parsed keywords, so the key order of the string is free.
    """
    parsed = json.loads(hieros_kwargs)
    parsed["config_overrides"].update(overrides)
    return json.dumps(parsed)


#: The HIEROS keywords of the RSSM setting's runs (three-seed and five-seed folders): RSSM, four updates, float32.
RSSM_WM4_KWARGS = (
    '{"config_overrides": {"world_model": {"kind": "rssm"}, "world_model_updates": 4}, '
    '"policy_kwargs": {"bf16": false}}'
)


#: The HIEROS keywords of the runs of the three levers together: RSSM, four updates, horizon 32, float32.
RSSM_WM4_H32_KWARGS = with_config_overrides(RSSM_WM4_KWARGS, imag_horizon=32)

#: The RSSM setting whose actors and critics start at 2000 steps (the world models at the preset's 500).
RSSM_WM4_ALS2000_KWARGS = with_config_overrides(RSSM_WM4_KWARGS, actor_learning_starts=2000)

#: The HIEROS keywords of the S5 world model with the posterior that reads h_t: four updates, float32.
POSTERIOR_STATE_WM4_KWARGS = (
    '{"config_overrides": {"world_model": {"posterior": "state"}, "world_model_updates": 4}, '
    '"policy_kwargs": {"bf16": false}}'
)


#: The HIEROS keywords of the S5 world model with the posterior that reads h_t, four updates and horizon 32, float32.
POSTERIOR_STATE_WM4_H32_KWARGS = with_config_overrides(POSTERIOR_STATE_WM4_KWARGS, imag_horizon=32)


#: The HIEROS keywords of the RSSM setting with DreamerV3 XS's latent sizes (deter and hidden 256, 32 x 32 classes).
RSSM_XS_LATENT_WM4_KWARGS = (
    '{"config_overrides": {"world_model": {"kind": "rssm", "deter_dim": 256, "hidden": 256, "stoch_groups": 32, '
    '"stoch_classes": 32}, "world_model_updates": 4}, "policy_kwargs": {"bf16": false}}'
)


#: The same whose actors and critics start at 3000 steps.
RSSM_XS_LATENT_WM4_ALS3000_KWARGS = with_config_overrides(RSSM_XS_LATENT_WM4_KWARGS, actor_learning_starts=3000)


#: The same with the imagination horizon of 32.
RSSM_XS_LATENT_WM4_H32_KWARGS = with_config_overrides(RSSM_XS_LATENT_WM4_KWARGS, imag_horizon=32)


#: The single-change suites next to the main one: folder under docs/cpu_suite -> arguments of their --report
#: (three seeds unless the arguments name --seeds).
CHANGE_SUITES = {
    "bf16": [
        "--tasks", "CartPole-v1", "cartpole-balance-proprio", "Pendulum-v1",
        "--hieros-kwargs", '{"policy_kwargs": {"bf16": true}}',
    ],
    "replay_value_loss": [
        "--tasks", "cartpole-balance-proprio", "CartPole-v1", "Pendulum-v1",
        "--hieros-kwargs", '{"config_overrides": {"actor_critic": {"replay_value_loss": 0.3}}}',
    ],
    "deter_from_output": ["--tasks", "cartpole-balance-proprio", "CartPole-v1", "Pendulum-v1"],
    "deter_from_gru": [
        "--tasks", "cartpole-balance-proprio", "cartpole-balance-pixels", "CartPole-v1", "Pendulum-v1",
        "--hieros-kwargs", '{"config_overrides": {"world_model": {"deter_from": "gru"}}}',
    ],
    "value_gradient_returns": [
        "--tasks", "cartpole-balance-proprio",
        "--hieros-kwargs",
        '{"config_overrides": {"world_model": {"deter_from": "gru"}, "actor_critic": {"value_gradient": "returns"}}}',
    ],
    "value_gradient_none": [
        "--tasks", "cartpole-balance-proprio",
        "--hieros-kwargs",
        '{"config_overrides": {"world_model": {"deter_from": "gru"}, "actor_critic": {"value_gradient": "none"}}}',
    ],
    "world_model_updates": [
        "--tasks", "cartpole-balance-proprio", "cartpole-balance-pixels", "CartPole-v1", "Pendulum-v1",
        "--hieros-kwargs", '{"config_overrides": {"world_model": {"deter_from": "gru"}, "world_model_updates": 4}}',
    ],
    "action_input_separate": [
        "--tasks", "cartpole-balance-proprio",
        "--hieros-kwargs",
        '{"config_overrides": {"world_model": {"deter_from": "gru", "action_input": "separate"}, '
        '"world_model_updates": 4}}',
    ],
    "world_model_updates_8": [
        "--tasks", "cartpole-balance-proprio",
        "--hieros-kwargs", '{"config_overrides": {"world_model": {"deter_from": "gru"}, "world_model_updates": 8}}',
    ],
    "actor_lr_3e-5": [
        "--tasks", "cartpole-balance-proprio",
        "--hieros-kwargs", '{"config_overrides": {"actor_critic": {"actor_lr": 3e-5}}}',
    ],
    "critic_lr_3e-4": [
        "--tasks", "cartpole-balance-proprio",
        "--hieros-kwargs", '{"config_overrides": {"actor_critic": {"critic_lr": 3e-4}}}',
    ],
    "world_model_updates_2": [
        "--tasks", "cartpole-balance-proprio", "CartPole-v1",
        "--hieros-kwargs", '{"config_overrides": {"world_model_updates": 2}}',
    ],
    "world_model_updates_2_bf16": [
        "--tasks", "cartpole-balance-proprio", "CartPole-v1", "Pendulum-v1",
        "--hieros-kwargs", '{"config_overrides": {"world_model_updates": 2}, "policy_kwargs": {"bf16": true}}',
    ],
    "world_model_updates_2_float32": [
        "--tasks", "Pendulum-v1", "cartpole-balance-pixels",
        "--hieros-kwargs", '{"config_overrides": {"world_model_updates": 2}, "policy_kwargs": {"bf16": false}}',
    ],
    "preset_imag_gradient_reinforce": [
        "--tasks", "cartpole-balance-proprio",
        "--hieros-kwargs",
        '{"config_overrides": {"world_model_updates": 2, "actor_critic": {"imag_gradient": "reinforce"}}, '
        '"policy_kwargs": {"bf16": false}}',
    ],
    "preset_imag_horizon_32": [
        "--tasks", "cartpole-balance-proprio",
        "--hieros-kwargs",
        '{"config_overrides": {"world_model_updates": 2, "imag_horizon": 32}, "policy_kwargs": {"bf16": false}}',
    ],
    "preset_imag_horizon_32_starts_025": [
        "--tasks", "cartpole-balance-proprio",
        "--hieros-kwargs",
        '{"config_overrides": {"world_model_updates": 2, "imag_horizon": 32, "imag_start_fraction": 0.25}, '
        '"policy_kwargs": {"bf16": false}}',
    ],
    "preset_world_model_updates_4": [
        "--tasks", "cartpole-balance-proprio",
        "--hieros-kwargs", '{"config_overrides": {"world_model_updates": 4}, "policy_kwargs": {"bf16": false}}',
    ],
    "batch_size_32": [
        "--tasks", "cartpole-balance-proprio",
        "--hieros-kwargs",
        '{"config_overrides": {"world_model_updates": 2, "batch_size": 32}, "policy_kwargs": {"bf16": false}}',
    ],
    "imag_start_fraction_1": [
        "--tasks", "cartpole-balance-proprio",
        "--hieros-kwargs",
        '{"config_overrides": {"world_model_updates": 2, "imag_start_fraction": 1.0}, '
        '"policy_kwargs": {"bf16": false}}',
    ],
    "rssm_world_model_updates_2": [
        "--tasks", "cartpole-balance-proprio",
        "--hieros-kwargs",
        '{"config_overrides": {"world_model": {"kind": "rssm"}, "world_model_updates": 2}, '
        '"policy_kwargs": {"bf16": false}}',
    ],
    "preset_return_critic_slow": [
        "--tasks", "cartpole-balance-proprio",
        "--hieros-kwargs",
        '{"config_overrides": {"world_model_updates": 2, "actor_critic": {"return_critic": "slow"}}, '
        '"policy_kwargs": {"bf16": false}}',
    ],
    "rssm_world_model_updates_4": [
        "--tasks", "CartPole-v1", "Pendulum-v1", "cartpole-balance-proprio", "cartpole-balance-pixels",
        "--hieros-kwargs",
        RSSM_WM4_KWARGS,
    ],
    "rssm_world_model_updates_4_imag_horizon_32": [
        "--tasks", "CartPole-v1", "Pendulum-v1", "cartpole-balance-proprio", "cartpole-balance-pixels",
        "--hieros-kwargs",
        RSSM_WM4_H32_KWARGS,
    ],
    "rssm_world_model_updates_4_imag_horizon_32_five_seeds": [
        "--tasks", "CartPole-v1", "Pendulum-v1", "cartpole-balance-proprio", "--seeds", "5",
        "--hieros-kwargs",
        RSSM_WM4_H32_KWARGS,
    ],
    "posterior_state_world_model_updates_4": [
        "--tasks", "cartpole-balance-proprio",
        "--hieros-kwargs",
        POSTERIOR_STATE_WM4_KWARGS,
    ],
    "posterior_state_world_model_updates_4_imag_horizon_32": [
        "--tasks", "cartpole-balance-proprio", "--hieros-kwargs", POSTERIOR_STATE_WM4_H32_KWARGS,
    ],
    "posterior_state_world_model_updates_4_five_seeds": [
        "--tasks", "cartpole-balance-proprio", "--seeds", "5",
        "--hieros-kwargs",
        POSTERIOR_STATE_WM4_KWARGS,
    ],
    "preset_five_seeds": [
        "--tasks", "cartpole-balance-proprio", "--seeds", "5", "--hieros-kwargs", MAIN_HIEROS_KWARGS,
    ],
    "rssm_world_model_updates_4_five_seeds": [
        "--tasks", "cartpole-balance-proprio", "--seeds", "5",
        "--hieros-kwargs",
        RSSM_WM4_KWARGS,
    ],
    "rssm_world_model_updates_4_actor_learning_starts_2000_five_seeds": [
        "--tasks", "cartpole-balance-proprio", "--seeds", "5",
        "--hieros-kwargs",
        RSSM_WM4_ALS2000_KWARGS,
    ],
    "rssm_posterior_observation_world_model_updates_4": [
        "--tasks", "cartpole-balance-proprio",
        "--hieros-kwargs",
        '{"config_overrides": {"world_model": {"kind": "rssm", "posterior": "observation"}, '
        '"world_model_updates": 4}, "policy_kwargs": {"bf16": false}}',
    ],
    "rssm_world_model_updates_4_bf16": [
        "--tasks", "CartPole-v1", "Pendulum-v1", "cartpole-balance-proprio",
        "--hieros-kwargs",
        '{"config_overrides": {"world_model": {"kind": "rssm"}, "world_model_updates": 4}, '
        '"policy_kwargs": {"bf16": true}}',
    ],
    "rssm_xs_latent_world_model_updates_4": [
        "--tasks", "cartpole-balance-proprio", "cartpole-balance-pixels",
        "--hieros-kwargs",
        RSSM_XS_LATENT_WM4_KWARGS,
    ],
    "rssm_xs_latent_world_model_updates_4_five_seeds": [
        "--tasks", "cartpole-balance-pixels", "--seeds", "5",
        "--hieros-kwargs",
        RSSM_XS_LATENT_WM4_KWARGS,
    ],
    "rssm_xs_latent_world_model_updates_4_actor_learning_starts_3000": [
        "--tasks", "cartpole-balance-pixels",
        "--hieros-kwargs",
        RSSM_XS_LATENT_WM4_ALS3000_KWARGS,
    ],
    "rssm_xs_latent_world_model_updates_4_imag_horizon_32": [
        "--tasks", "cartpole-balance-proprio",
        "--hieros-kwargs",
        RSSM_XS_LATENT_WM4_H32_KWARGS,
    ],
    "rssm_stoch_32_world_model_updates_4": [
        "--tasks", "cartpole-balance-pixels",
        "--hieros-kwargs",
        '{"config_overrides": {"world_model": {"kind": "rssm", "stoch_groups": 32, "stoch_classes": 32}, '
        '"world_model_updates": 4}, "policy_kwargs": {"bf16": false}}',
    ],
    "rssm_deter_256_world_model_updates_4": [
        "--tasks", "cartpole-balance-proprio", "cartpole-balance-pixels",
        "--hieros-kwargs",
        '{"config_overrides": {"world_model": {"kind": "rssm", "deter_dim": 256, "hidden": 256}, '
        '"world_model_updates": 4}, "policy_kwargs": {"bf16": false}}',
    ],
}  # fmt: skip


@pytest.mark.parametrize("name", sorted(CHANGE_SUITES))
def test_change_suite_tables_are_made_from_their_runs(tmp_path, name):
    from benchmarks import cpu_suite

    folder = DOCS / "cpu_suite" / name
    shutil.copy(folder / "runs.jsonl", tmp_path / "runs.jsonl")
    seeds = [] if "--seeds" in CHANGE_SUITES[name] else ["--seeds", "3"]
    args = [*CHANGE_SUITES[name], "--algos", "hieros", *seeds, "--steps", "10000", "--report"]
    cpu_suite.main([*args, "--out", str(tmp_path)])
    assert (tmp_path / "table.md").read_text() == (folder / "table.md").read_text()


def test_sample_efficiency_table_is_made_from_results_json(tmp_path):
    from benchmarks import sample_efficiency

    files = [DOCS / "sample_efficiency" / name for name in SAMPLE_EFFICIENCY_FILES]
    sample_efficiency.main(["--report", *map(str, files), "--out", str(tmp_path)])
    assert (tmp_path / "table.md").read_text() == (DOCS / "sample_efficiency" / "table.md").read_text()


#: The recorded runs behind docs/sample_efficiency/table.md (the order of its rows).
SAMPLE_EFFICIENCY_FILES = ("amd_small_preset_replay_context.json", "intel_amx_ppo_dqn.json")


def test_readme_shows_the_cpu_suite_table():
    table = (DOCS / "cpu_suite" / "table.md").read_text().strip()
    readme = (ROOT / "README.md").read_text()
    assert table in readme
    assert f"--hieros-kwargs\n'{MAIN_HIEROS_KWARGS}'" in readme  # the command that makes it


def test_demo_run_is_recorded_and_its_curve_redrawn(tmp_path):
    import numpy as np

    from benchmarks import demo

    for name in ("final_eval.json", "evaluations.npz"):
        shutil.copy(DOCS / "demo" / name, tmp_path / name)
    summary = demo.main(["--report", str(tmp_path)])
    results = np.load(tmp_path / "evaluations.npz")["results"]
    assert summary["eval_mean_returns"] == pytest.approx(results.mean(1).tolist())
    assert (tmp_path / "learning_curve.png").stat().st_size > 10_000


def test_atari100k_table_is_made_from_result_json(tmp_path):
    from benchmarks import aggregate

    folder = DOCS / "atari100k"
    aggregate.main([str(folder), "--out", str(tmp_path)])
    assert (tmp_path / "aggregate.md").read_text() == (folder / "aggregate.md").read_text()
    assert "```{include} ../atari100k/aggregate.md" in (DOCS / "results" / "atari100k.md").read_text()
