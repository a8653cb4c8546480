"""benchmarks/speed.py agent's PhaseClock and phase table on tiny models."""

from __future__ import annotations

import time
from types import SimpleNamespace

import pytest
import torch as th
from hieros_helpers import tiny_kwargs

from benchmarks._timing import Timing
from benchmarks.speed import (
    PhaseClock,
    agent_phase_table,
    matmul_flops,
    operator_summary,
    profile_parts,
    world_model_speedup_needed,
)
from sb3_hieros import HIEROS


def _tiny(seed: int = 0, **overrides) -> HIEROS:
    kwargs = tiny_kwargs(seed=seed)
    if overrides:
        kwargs["config_overrides"] = {**kwargs["config_overrides"], **overrides}
    return HIEROS("MlpPolicy", "CartPole-v1", **kwargs)


def test_phases_split_the_wall_time():
    model = _tiny()
    model.learn(40)  # past learning_starts: every later step trains
    clock = PhaseClock(model)
    start = time.perf_counter()
    model.learn(32, reset_num_timesteps=False)
    wall = time.perf_counter() - start
    phases = clock.phases(wall)
    assert tuple(phases) == PhaseClock.PHASES
    assert all(seconds >= 0.0 for seconds in phases.values()), phases
    assert sum(phases.values()) == pytest.approx(wall)
    for trained in ("acting", "world_model", "imagination", "actor_critic_ae"):
        assert phases[trained] > 0.0, trained
    clock.reset()
    assert all(seconds == 0.0 for seconds in clock.phases(0.0).values())


def test_clock_leaves_training_unchanged():
    # one model after the other: constructing a model seeds the global generators that learn draws from
    timed = _tiny()
    timed.learn(40)
    PhaseClock(timed)
    timed.learn(24, reset_num_timesteps=False)
    plain = _tiny()
    plain.learn(40)
    plain.learn(24, reset_num_timesteps=False)
    for (name, a), b in zip(timed.policy.state_dict().items(), plain.policy.state_dict().values(), strict=True):
        assert th.equal(a, b), name


def test_shared_world_model_phases_stay_disjoint():
    model = _tiny(hierarchical_world_models=False)
    model.learn(40)
    clock = PhaseClock(model)
    start = time.perf_counter()
    model.learn(16, reset_num_timesteps=False)
    wall = time.perf_counter() - start
    phases = clock.phases(wall)
    # level 0's world-model step, the joint imagination in its world model and the levels' actor-critic updates
    for trained in ("world_model", "imagination", "actor_critic_ae", "replay_and_rest"):
        assert phases[trained] > 0.0, trained
    assert all(seconds >= 0.0 for seconds in phases.values()), phases
    assert sum(phases.values()) == pytest.approx(wall)


def test_phase_table_ratios():
    class FixedClock(PhaseClock):
        def __init__(self, seconds: dict[str, float]) -> None:
            self.seconds = dict(seconds)

    def inside(acting: float, train: float, train_step: float, world_model: float, imagination: float) -> FixedClock:
        return FixedClock(
            {
                "acting": acting,
                "train": train,
                "train_step": train_step,
                "world_model": world_model,
                "imagination": imagination,
                "world_model in train_step": world_model,
                "imagination in train_step": imagination,
            }
        )

    s5 = inside(1.0, 6.0, 5.0, 3.0, 1.0)
    rssm = inside(1.0, 7.5, 6.5, 3.0, 2.5)
    timings = {"S5WM": Timing(1.0, 1.0, 8, 8.0), "RSSM": Timing(1.0, 1.0, 8, 9.5)}
    table = agent_phase_table({"S5WM": s5, "RSSM": rssm}, timings, env_steps=1000)
    figures = dict(line.split(": ") for line in table.splitlines() if ": " in line)
    assert float(figures["imagination_speedup"]) == pytest.approx(2.5)
    assert float(figures["world_model_speedup"]) == pytest.approx(1.0)
    assert float(figures["s5wm_world_model_share"]) == pytest.approx(3.0 / 8.0, abs=1e-3)
    assert float(figures["rssm_env_and_rest_share"]) == pytest.approx(1.0 / 9.5, abs=1e-3)
    total_row = next(line for line in table.splitlines() if line.startswith("total"))
    assert total_row.split()[-1] == f"{9.5 / 8.0:.2f}"


def test_world_model_speedup_needed():
    s5 = {"acting": 1.0, "world_model": 4.0, "imagination": 2.0, "actor_critic_ae": 2.0, "env_and_rest": 1.0}
    # RSSM: 12 s in all, 6 s of world model; 1.5x allows 8 s, the other parts take 6 s: 2 s of world model left
    assert world_model_speedup_needed(s5, 6.0, 12.0, 1.5) == pytest.approx(3.0)
    # with imagination and acting free, 3 s of other parts leave 5 s
    assert world_model_speedup_needed(s5, 6.0, 12.0, 1.5, ("imagination", "acting")) == pytest.approx(1.2)
    # the other parts alone take longer than the goal allows
    assert world_model_speedup_needed(s5, 6.0, 12.0, 3.0) == float("inf")


def test_s5_table_runs_on_tiny_sizes_and_prints_every_ratio(capsys):
    from benchmarks.speed import main

    main(["s5", "--reps", "1", "--warmup", "0", "--threads", "1", "--lengths", "8", "--d-model", "8", "--d-state", "4"])
    main_out = capsys.readouterr().out
    for name in ("s5_vs_grucell_T8", "scan_vs_reference_scan_T8", "scan_vs_autograd_backward_T8"):
        assert f"{name}: " in main_out
    assert "scan (ours, autograd bwd)" in main_out


def test_matmul_flops_from_profiler_shapes():
    assert matmul_flops("aten::mm", [[4, 3], [3, 5]]) == 2 * 4 * 3 * 5
    assert matmul_flops("aten::addmm", [[5], [4, 3], [3, 5], [], []]) == 2 * 4 * 3 * 5
    assert matmul_flops("aten::bmm", [[2, 4, 3], [2, 3, 5]]) == 2 * 2 * 4 * 3 * 5
    with pytest.raises(ValueError, match="aten::add"):
        matmul_flops("aten::add", [[4, 3], [4, 3]])
    with pytest.raises(ValueError, match="not a"):
        matmul_flops("aten::mm", [[4, 3], [2, 5]])


def test_operator_summary_counts_matrix_products_against_all_operators():
    def event(key, count, self_us, shapes):
        return SimpleNamespace(key=key, count=count, self_cpu_time_total=self_us, input_shapes=shapes)

    events = [
        event("aten::mm", 2, 300.0, [[100, 100], [100, 100]]),  # 2 calls x 2e6 flops in 300 us
        event("aten::add", 10, 600.0, [[100, 100], [100, 100], []]),
        event("ProfilerStep", 1, 50.0, []),  # not an aten operator
    ]
    summary = operator_summary(events, wall_seconds=0.004, calls=2)
    assert summary["wall_ms"] == pytest.approx(2.0)
    assert summary["aten_calls"] == pytest.approx(6.0)
    assert summary["operator_ms"] == pytest.approx(0.45)
    assert summary["matmul_ms"] == pytest.approx(0.15)
    assert summary["matmul_share"] == pytest.approx(1 / 3)
    assert summary["matmul_gflops"] == pytest.approx(4e6 / 300e-6 / 1e9)
    assert summary["overhead_free_speedup"] == pytest.approx(2.0 / 0.15)


def test_profile_parts_on_a_short_run():
    results = profile_parts(
        steps=40, learning_starts=20, updates=1, predict_calls=3, seed=0, policy_kwargs={"bf16": False}
    )
    assert set(results) == {"update", "predict"}
    for figures in results.values():
        assert figures["aten_calls"] > 10 and figures["wall_ms"] > 0
        assert 0.0 < figures["matmul_share"] < 1.0 and figures["matmul_gflops"] > 0
    with pytest.raises(ValueError, match="must exceed learning_starts"):
        profile_parts(steps=20, learning_starts=20, updates=1, predict_calls=1, seed=0, policy_kwargs={})
