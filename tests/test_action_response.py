"""benchmarks/action_response.py: the data policies, the argument checks and a tiny end-to-end run."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest

from benchmarks import action_response as bench
from benchmarks.control_failures import physical_state


@pytest.mark.parametrize(
    ("argv", "match"),
    [
        (["--kinds", "gru"], "--kinds"),
        (["--kinds", ","], "--kinds"),
        (["--seeds", ","], "--seeds"),
        (["--updates", "0"], "--updates"),
        (["--updates", "4800,2400"], "--updates"),
        (["--updates", "2400,2400"], "--updates"),
        (["--updates", "many"], "--updates"),
        (["--episodes", "0"], "--episodes"),
        (["--wm-overrides", '{"kind": "rssm"}'], "--wm-overrides"),
    ],
)
def test_bad_arguments_raise_before_any_work(monkeypatch, argv, match):
    monkeypatch.setattr(bench, "run", lambda *args: pytest.fail("trained despite a bad argument"))
    with pytest.raises(ValueError, match=match):
        bench.main(argv)


def test_wm_overrides_that_are_not_a_json_object_are_refused(monkeypatch, capsys):
    monkeypatch.setattr(bench, "run", lambda *args: pytest.fail("trained despite a bad argument"))
    with pytest.raises(SystemExit):
        bench.main(["--wm-overrides", "[1]"])
    assert "--wm-overrides: '[1]' is a JSON list; expected a JSON object" in capsys.readouterr().err


@pytest.mark.parametrize("kind", ["uniform", "smooth", "small"])
def test_open_loop_actions_lie_in_the_bounds(kind):
    actions = bench.open_loop_actions(kind, 200, np.random.default_rng(0))
    assert actions.shape == (200, 1) and actions.dtype == np.float32
    assert np.all(np.abs(actions) <= 1.0) and actions.std() > 0.05


def test_unknown_action_kind_is_named():
    with pytest.raises(ValueError, match="'bang'"):
        bench.open_loop_actions("bang", 3, np.random.default_rng(0))


def test_feedback_policy_follows_the_sign_of_the_projection():
    rng = np.random.default_rng(0)
    w = np.array([1.0, 0.0])
    plus = np.array([bench.feedback_at_bounds(np.array([2.0, 5.0]), w, rng)[0] for _ in range(500)])
    minus = np.array([bench.feedback_at_bounds(np.array([-2.0, 5.0]), w, rng)[0] for _ in range(500)])
    assert np.all(np.abs(plus) <= 1.0)
    assert plus.mean() > 0.5 and minus.mean() < -0.5  # at the bound, noise clipped to [-1, 1]
    assert (plus == 1.0).mean() > 0.4


def test_held_out_copies_replay_the_recorded_episode():
    data, copies = bench.collect(["small"], seed=3, branch=True)
    assert data["obs"].shape[0] == 1 and bool(data["is_first"][0, 0]) and not bool(data["is_first"][0, 1:].any())
    episode, step, env = copies[0]
    obs, *_ = env.step(data["prev_action"][episode, step + 1].numpy())
    np.testing.assert_allclose(obs, data["obs"][episode, step + 1].numpy(), rtol=1e-5, atol=1e-6)


def test_the_policies_act_on_the_simulator_state_which_is_the_proprio_observation():
    data, copies = bench.collect(["feedback"], seed=2, branch=True)
    assert data["state"].shape == data["obs"].shape
    np.testing.assert_array_equal(data["state"].float().numpy(), data["obs"].numpy())
    episode, step, env = copies[0]
    env.step(data["prev_action"][episode, step + 1].numpy())
    np.testing.assert_allclose(physical_state(env), data["state"][episode, step + 1].numpy(), rtol=1e-6, atol=1e-9)


def test_train_pauses_after_each_count_and_goes_on():
    data, _ = bench.collect(["uniform"], seed=1, branch=False)
    model = bench.make_world_model(bench.world_model_space("dmc_proprio"), 1, bench.get_preset("small").world_model)
    before = [p.detach().clone() for p in model.parameters()]
    counts = []
    for count, metrics in bench.train(model, data, [1, 3], seed=0):
        counts.append(count)
        assert math.isfinite(metrics["obs_loss"])
        changed = [
            not np.array_equal(b.numpy(), p.detach().numpy()) for b, p in zip(before, model.parameters(), strict=True)
        ]
        assert any(changed)  # an update ran before every pause
        before = [p.detach().clone() for p in model.parameters()]
    assert counts == [1, 3]


@pytest.fixture
def short_episodes(monkeypatch):
    """Episodes of 40 agent steps, so that pixel episodes render quickly."""
    make_env = bench.make_env
    monkeypatch.setattr(
        bench, "make_env", lambda *args, **kwargs: gym.wrappers.TimeLimit(make_env(*args, **kwargs), 40)
    )


def test_pixel_episodes_are_channel_first_and_their_copies_replay_the_state(short_episodes):
    data, copies = bench.collect(["small", "feedback"], seed=3, branch=True, suite="dmc_vision")
    assert data["obs"].shape == (2, 41, 3, 64, 64) and data["obs"].dtype == bench.th.uint8
    assert data["state"].shape == (2, 41, 5)
    assert bench.world_model_space("dmc_vision").shape == (3, 64, 64)
    assert len(copies) == 2  # step 12 of each episode; step 37 leaves no room for the driven steps
    for episode, step, env in copies:  # usable after collect, though the original env is the one that renders
        env.step(data["prev_action"][episode, step + 1].numpy())
        np.testing.assert_allclose(physical_state(env), data["state"][episode, step + 1].numpy(), rtol=1e-6)


def test_tiny_pixel_run_reads_the_state_with_the_probe(short_episodes, capsys):
    argv = ["--suite", "dmc_vision", "--kinds", "rssm", "--updates", "1,2", "--episodes", "3"]
    results = bench.main(argv)
    for count in (1, 2):
        prefix = f"rssm/0/{count}_updates/"
        for name in bench.OBS_NAMES:
            r2 = results[prefix + f"{name}_probe_r2"]
            assert math.isfinite(r2) and r2 <= 1.0
            assert results[prefix + f"{name}_recon_rmse"] > 0  # the probe's error on the episodes it was fitted on
            assert math.isfinite(results[prefix + f"mode_{name}_slope"])
        assert math.isfinite(results[prefix + "sampled_reward_corr"])
    assert results["rssm/0/2_updates/train_seconds"] > results["rssm/0/1_updates/train_seconds"]
    assert "rssm seed 0: 2 updates" in capsys.readouterr().out


def test_tiny_run_reports_every_figure(capsys):
    results = bench.main(["--kinds", "s5", "--updates", "2", "--episodes", "2", "--data", "balancing"])
    names = [*bench.OBS_NAMES, "reward"]
    for mode in ("mode", "sampled"):
        for name in names:
            assert f"s5/0/{mode}_{name}_slope" in results
            assert f"s5/0/{mode}_{name}_corr" in results
    assert math.isfinite(results["s5/0/mode_pole_angular_velocity_slope"])
    for name in bench.OBS_NAMES:
        rmse, effect = results[f"s5/0/{name}_recon_rmse"], results[f"s5/0/{name}_step_effect"]
        assert rmse > 0 and effect >= 0
        if effect > 0:
            assert results[f"s5/0/{name}_resolution"] == pytest.approx(rmse / effect)
    assert results["s5/0/cart_velocity_step_effect"] > 0  # the held action moves the cart within one step
    assert results["s5/0/pole_angular_velocity_recon_rmse_upright"] > 0  # every episode starts upright
    assert results["s5/0/pole_cos_std_upright"] >= 0
    assert results["s5/0/kl"] >= 0 and results["s5/0/post_entropy"] > 0 and results["s5/0/obs_loss"] > 0
    for name in bench.OBS_NAMES:
        assert results[f"s5/0/{name}_probe_r2"] <= 1.0
    assert results["data/0/return_mean"] > 800  # one balancing episode besides the random one
    assert (
        0.0 < results["data/0/cart_out_of_view"] < 0.05
    )  # the random episode leaves the view briefly, balancing never
    assert 0.0 < results["held_out/cart_out_of_view"] < 0.5  # the random actions sometimes do
    out = capsys.readouterr().out
    assert "s5 seed 0: 2 updates" in out and "1 balancing episodes, return" in out


@pytest.mark.parametrize(("kind", "shared"), [("one_policy", True), ("feedback", False)])
def test_one_policy_data_uses_one_feedback_gain_for_every_episode(monkeypatch, kind, shared):
    gains = []
    policy = bench.feedback_at_bounds

    def record(obs, w, rng):
        gains.append(tuple(w))
        return policy(obs, w, rng)

    monkeypatch.setattr(bench, "feedback_at_bounds", record)
    data, _ = bench.collect([kind, kind], seed=4, branch=False)
    assert data["obs"].shape[0] == 2
    assert (len(set(gains)) == 1) is shared


def test_balancing_data_keeps_the_pole_up():
    data, _ = bench.collect(["balancing", "one_policy"], seed=0, branch=False)
    upright = data["obs"][..., bench.OBS_NAMES.index("pole_cos")] > bench.UPRIGHT_COS
    returns = data["reward"].sum(1)
    assert bool(upright[0].all()) and returns[0] > 800  # the noisy linear feedback balances
    assert upright[1].float().mean() < 0.9 and returns[1] < returns[0]  # the bang-bang feedback does not
