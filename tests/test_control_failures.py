"""benchmarks/control_failures.py on tiny models: every figure is computed, and the argument checks."""

from __future__ import annotations

import math
import warnings
from copy import deepcopy
from types import SimpleNamespace
from typing import Any, NamedTuple

import numpy as np
import pytest
import torch as th
from hieros_helpers import tiny_kwargs

from benchmarks import control_failures
from benchmarks.suites import make_env
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
        [
            *args,
            "--suite",
            "classic",
            "--task",
            "Pendulum-v1",
            "--episodes",
            "1",
            "--horizon",
            "3",
            "--stride",
            "50",
            "--response-steps",
            "2",
        ]
    )
    assert set(results) == {"one", "two"}
    for figures in results.values():
        assert 0.0 <= figures["level0/at_bounds"] <= 1.0
        assert figures["level0/policy_std"] > 0.0
        assert figures["return/deterministic"] < 0.0  # Pendulum's rewards are never positive
        shares = [v for k, v in figures.items() if k.startswith("level0/grad_share/")]
        assert math.isclose(sum(shares), 1.0, rel_tol=1e-6)
        assert figures["world_model/reward_mae"] >= 0.0
        # Pendulum's observation is (cos, sin, angular velocity): one slope per entry, and the reward's
        slopes = [k for k in figures if k.startswith("world_model/action_slope_obs")]
        assert len(slopes) == 3 and all(math.isfinite(figures[k]) for k in slopes)
        assert math.isfinite(figures["world_model/action_slope_reward"])
        assert figures["level0/feedback_r2"] <= 1.0 and {f"state/abs_mean_obs{k}" for k in range(3)} <= set(figures)
        assert {f"level0/feedback_gain_a0_obs{k}" for k in range(3)} <= set(figures)
        ascent = [figures[f"level0/ascent_corr_a0_obs{k}"] for k in range(3)]
        assert figures["level0/pull_snr"] >= 0.0 and -1.0 <= figures["level0/pull_split_half"] <= 1.0
        assert figures["level0/pull_obs_r2"] <= 1.0
        assert all(-1.0 <= c <= 1.0 for c in ascent if not math.isnan(c))
        assert figures["imagination/starts"] >= 1 and figures["imagination/reward_real"] <= 0.0
        # Pendulum's simulator state is (angle, angular velocity): one probe figure per entry
        for behaviour in ("agent", "random"):
            probe = f"state_probe/{behaviour}"
            assert {f"{probe}/posterior_r2/s{d}" for d in range(2)} <= set(figures)
            assert figures[f"{probe}/posterior_r2"] <= 1.0 and figures[f"{probe}/open_loop_vs_repeat"] >= 0.0
            assert figures[f"{probe}/observation_r2"] <= 1.0
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


def test_feedback_fit_recovers_a_linear_controller():
    model = HIEROS("MlpPolicy", "Pendulum-v1", **tiny_kwargs(n_levels=1))
    rng = np.random.default_rng(0)
    gains, bias = np.array([0.5, -1.0, 0.25]), 0.1
    episodes = []
    for _ in range(2):
        episode = control_failures.Episode()
        for _ in range(30):
            obs = rng.normal(size=3)
            episode.observations.append(obs)
            episode.mode.append(np.array([gains @ obs + bias]))
        episodes.append(episode)
    figures = control_failures.feedback_figures(model, episodes)
    assert figures["level0/feedback_r2"] == pytest.approx(1.0)
    assert figures["level0/feedback_bias_a0"] == pytest.approx(bias)
    assert [figures[f"level0/feedback_gain_a0_obs{k}"] for k in range(3)] == pytest.approx(list(gains))
    constant = deepcopy(episodes)
    for episode in constant:
        episode.mode = [np.array([0.3])] * len(episode.mode)  # a policy that ignores the state
    assert math.isnan(control_failures.feedback_figures(model, constant)["level0/feedback_r2"])


def test_ascent_correlations_follow_the_start_states():
    model = HIEROS("MlpPolicy", "Pendulum-v1", **tiny_kwargs(n_levels=1))
    rng = np.random.default_rng(1)
    episodes = [control_failures.Episode(observations=list(rng.normal(size=(20, 3)))) for _ in range(2)]
    chosen = th.tensor([3, 25, 7, 39, 0, 12, 30, 18])
    stacked = np.concatenate([np.stack(e.observations) for e in episodes])[chosen.numpy()]
    ascent = th.as_tensor(-2.0 * stacked[:, 1:2])  # pulls against the second entry of the start observation
    figures = control_failures.ascent_figures(model, episodes, chosen, ascent)
    assert figures["level0/ascent_corr_a0_obs1"] == pytest.approx(-1.0)
    assert abs(figures["level0/ascent_corr_a0_obs0"]) < 1.0


def test_action_slope():
    env = np.array([1.0, -2.0, 0.5])
    assert control_failures._slope(0.5 * env, env) == pytest.approx(0.5)
    assert control_failures._slope(np.zeros(3), env) == 0.0
    assert math.isnan(control_failures._slope(env, np.zeros(3)))


def test_action_response_of_a_perfect_model_is_one(pendulum_models, monkeypatch):
    # a world model whose imagination is the real environment itself must respond with slope 1 everywhere
    model = HIEROS.load(pendulum_models["one"], device="cpu")
    episode = control_failures.play(model, make_env("classic", "Pendulum-v1", seed=5), 5, True)
    replayed = {}

    def fresh_env(suite, task, seed):
        replayed["env"] = make_env(suite, task, seed=seed)
        return replayed["env"]

    class Imagined(NamedTuple):
        env: Any
        obs: th.Tensor
        reward: float

    def img_step(state, action, deterministic):
        # the imagined state is a copy of the replayed environment, stepped as the branch is
        env = state.env if isinstance(state, Imagined) else deepcopy(replayed["env"])
        obs, reward, *_ = env.step(model.policy.env_actions(action)[0])
        return Imagined(env, th.as_tensor(obs, dtype=th.float64)[None], float(reward)), None

    wm = model.policy.hierarchy.levels[0].world_model
    monkeypatch.setattr(control_failures, "make_env", fresh_env)
    monkeypatch.setattr(wm, "img_step", img_step)
    monkeypatch.setattr(wm, "reward", lambda state: th.tensor([state.reward]))
    monkeypatch.setattr(wm, "decode", lambda state: state.obs)
    figures = control_failures.action_response_figures(model, "classic", "Pendulum-v1", [5], [episode], 3, 40)
    assert len(figures) == 5
    for key, value in figures.items():
        assert value == pytest.approx(1.0), key


def test_imagination_of_a_model_that_predicts_the_episode_has_no_bias(pendulum_models, monkeypatch):
    # imagined rewards at steps 1..H must be set beside the rewards the episode received at t..t+H-1
    model = HIEROS.load(pendulum_models["two"], device="cpu")
    th.manual_seed(0)
    episode = control_failures.play(model, make_env("classic", "Pendulum-v1", seed=5), 5, False)
    episode.latents[0] = [s._replace(stoch=th.full_like(s.stoch, t)) for t, s in enumerate(episode.latents[0])]
    level = model.policy.hierarchy.levels[0]
    horizon = level.config.imag_horizon
    received = th.tensor(episode.rewards + [0.0] * horizon)

    def imagine(start, codes):
        t = start.stoch[:, 0].long()  # (N,)
        steps = th.arange(-1, horizon).unsqueeze(1)  # the reward of imagined step k is the one received at t + k - 1
        return SimpleNamespace(rewards=received[(t.unsqueeze(0) + steps).clamp(min=0)])

    monkeypatch.setattr(level, "imagine", imagine)
    figures = control_failures.imagination_figures(model, [episode], stride=7)
    assert figures["imagination/starts"] == len(range(0, len(episode.rewards) - horizon + 1, 7))
    assert figures["imagination/reward_imagined"] == pytest.approx(figures["imagination/reward_real"])
    assert figures["imagination/reward_bias_first"] == pytest.approx(0.0, abs=1e-6)
    assert figures["imagination/reward_bias_last"] == pytest.approx(0.0, abs=1e-6)


def test_pull_is_split_into_its_reward_and_critic_paths(pendulum_models, monkeypatch):
    model = HIEROS.load(pendulum_models["one"], device="cpu")
    env = make_env("classic", "Pendulum-v1", seed=0)
    episodes = [control_failures.play(model, env, 0, False)]
    env.close()
    figures = control_failures.pull_figures(model, episodes, starts=16, samples=4)
    assert 0.0 < figures["level0/pull_critic_share"] < 1.0
    assert -1.0 <= figures["level0/pull_paths_corr"] <= 1.0
    # critics whose values do not depend on the state pull on nothing: the whole pull comes through the rewards
    for critic in model.policy.hierarchy.levels[0].actor_critic.critics.values():
        monkeypatch.setattr(critic, "value", lambda feat, detach_params=False: feat.sum(-1) * 0.0)
    flat = control_failures.pull_figures(model, episodes, starts=16, samples=4)
    assert flat["level0/pull_critic_share"] == 0.0
    assert flat["level0/pull_obs_r2"] == pytest.approx(flat["level0/pull_reward_obs_r2"])


def test_physical_state_is_what_proprioception_observes_also_behind_pixels():
    proprio, pixels = (
        make_env("dmc_proprio", "cartpole-balance", seed=4),
        make_env("dmc_vision", "cartpole-balance", seed=4),
    )
    obs, _ = proprio.reset(seed=4)
    pixels.reset(seed=4)
    state = control_failures.physical_state(proprio)
    assert state.shape == (5,) and np.allclose(np.sort(state), np.sort(obs), atol=1e-6)  # the same entries
    assert np.allclose(control_failures.physical_state(pixels), state)  # the same seed starts in the same state
    action = np.full(proprio.action_space.shape, 0.5, dtype=np.float32)
    obs, *_ = proprio.step(action)
    pixels.step(action)
    assert np.allclose(np.sort(control_failures.physical_state(proprio)), np.sort(obs), atol=1e-6)
    assert np.allclose(control_failures.physical_state(pixels), control_failures.physical_state(proprio))
    proprio.close()
    pixels.close()
    pendulum = make_env("classic", "Pendulum-v1", seed=0)
    pendulum.reset(seed=0)
    assert np.array_equal(control_failures.physical_state(pendulum), pendulum.unwrapped.state)
    assert control_failures.physical_state(SimpleNamespace(unwrapped=SimpleNamespace())) is None


def test_state_probe_recovers_a_linear_map():
    rng = np.random.default_rng(0)
    weights = rng.normal(size=(12, 3))
    features = np.concatenate([rng.normal(size=(300, 12)), np.ones((300, 2))], axis=1)  # two constant columns
    probe = control_failures.fit_state_probe(features, features[:, :12] @ weights + 0.01 * rng.normal(size=(300, 3)))
    new = np.concatenate([rng.normal(size=(50, 12)), np.ones((50, 2))], axis=1)
    assert probe(new) == pytest.approx(new[:, :12] @ weights, abs=0.05)
    noise = control_failures.fit_state_probe(features, rng.normal(size=(300, 3)))  # nothing to find: close to the mean
    assert np.abs(noise(new)).mean() < 0.5
    # each entry has its penalty: an entry with nothing to find does not pull the others' fit towards the mean
    mixed = control_failures.fit_state_probe(
        features, np.column_stack([features[:, 0], 1e3 * rng.normal(size=300), features[:, 1]])
    )
    assert mixed(new)[:, [0, 2]] == pytest.approx(new[:, :2], abs=0.05)


def test_state_probe_of_a_model_that_holds_and_predicts_the_state(pendulum_models, monkeypatch):
    # features that are the simulator state, and an imagination that steps to the next recorded state, must be read
    # with R^2 = 1 and predict with no open-loop error; a model whose imagination stands still must equal the baseline
    model = HIEROS.load(pendulum_models["one"], device="cpu")
    wm = model.policy.hierarchy.levels[0].world_model
    env = make_env("classic", "Pendulum-v1", seed=3)
    first, second = (control_failures.play(model, env, seed, False) for seed in (3, 4))
    env.close()
    states = {}
    for e in (first, second):
        for t, latent in enumerate(e.latents[0]):
            e.latents[0][t] = latent._replace(stoch=th.full_like(latent.stoch, float(len(states))))
            states[len(states)] = th.as_tensor(e.states[t], dtype=th.float32)
    monkeypatch.setattr(wm, "features", lambda state: th.stack([states[int(i)] for i in state.stoch[:, 0]]))

    def img_step(state, action, deterministic):
        return state._replace(stoch=state.stoch + 1.0), None

    monkeypatch.setattr(wm, "img_step", img_step)
    figures = control_failures.state_probe_figures(model, [first, second], horizon=4, stride=20)
    assert figures["state_probe/posterior_r2"] == pytest.approx(1.0, abs=1e-3)
    # Pendulum's observation (cos, sin, angular velocity) holds its angular velocity linearly, not its unwrapped angle
    assert figures["state_probe/observation_r2/s1"] == pytest.approx(1.0, abs=1e-3)
    assert figures["state_probe/open_loop_vs_repeat"] == pytest.approx(0.0, abs=1e-3)
    monkeypatch.setattr(wm, "img_step", lambda state, action, deterministic: (state, None))
    still = control_failures.state_probe_figures(model, [first, second], horizon=4, stride=20)
    assert still["state_probe/open_loop_vs_repeat"] == pytest.approx(1.0, abs=1e-2)
    second.states[5] = None  # an env without a simulator state: no figures
    assert control_failures.state_probe_figures(model, [first, second], horizon=4, stride=20) == {}


def test_random_actions_are_taken_and_filtered(pendulum_models):
    model = HIEROS.load(pendulum_models["one"], device="cpu")
    env = make_env("classic", "Pendulum-v1", seed=2)
    first, again = (control_failures.play(model, env, 2, True, random_actions=True) for _ in range(2))
    greedy = control_failures.play(model, env, 2, True)
    env.close()
    taken = np.stack(first.actions)
    assert np.array_equal(taken, np.stack(again.actions)) and first.rewards == again.rewards  # seeded draws
    assert np.abs(taken).max() <= 1.0 and taken.std() > 0.3  # uniform in [-1, 1], not the policy's modes
    assert not np.allclose(taken, np.stack(first.mode))
    assert first.rewards != greedy.rewards
    # the recorded actions are the ones the env received: replayed in a fresh env they give the same rewards
    replay = make_env("classic", "Pendulum-v1", seed=2)
    replay.reset(seed=2)
    rewards = [float(replay.step(model.policy.env_actions(th.as_tensor(a)[None])[0])[1]) for a in first.actions]
    assert rewards == pytest.approx(first.rewards)


def test_correlation_of_a_constant_series_is_nan_without_a_warning():
    x = np.arange(5.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert math.isnan(control_failures._corr(x, np.ones(5)))
        assert math.isnan(control_failures._corr(np.zeros(5), x))
    assert control_failures._corr(x, 2 * x + 1) == pytest.approx(1.0)
    assert control_failures._corr(x, -x) == pytest.approx(-1.0)


def test_the_cart_is_out_of_the_pixel_cameras_view_from_the_limit_on():
    env = make_env("dmc_vision", "cartpole-balance", seed=0)
    physics = env.unwrapped.physics
    orange = []
    for x in (control_failures.CARTPOLE_OUT_OF_VIEW - 0.1, control_failures.CARTPOLE_OUT_OF_VIEW + 0.01):
        with physics.reset_context():
            physics.named.data.qpos["slider"] = x
            physics.named.data.qpos["hinge_1"] = 0.0
        image = env.render()  # the pixel suite's frame of the same camera
        assert image.shape == (64, 64, 3)
        orange.append(int(((image[..., 0] > 150) & (image[..., 2] < 120)).sum()))  # the cart and pole's colour
    env.close()
    assert orange[0] > 0 and orange[1] == 0


def test_out_of_view_share_counts_the_cart_beyond_the_limit_on_cartpole_tasks_only():
    limit = control_failures.CARTPOLE_OUT_OF_VIEW
    episode = control_failures.Episode()
    episode.states = [np.array([x, 1.0, 0.0, 0.0, 0.0]) for x in (0.0, limit, -limit - 0.1, 1.0)]
    figures = control_failures.out_of_view_figures("cartpole-balance", [episode], [episode, episode])
    assert figures == {
        "episodes/cart_out_of_view/deterministic": 0.5,
        "episodes/cart_out_of_view/sampled": 0.5,
    }
    assert control_failures.out_of_view_figures("pendulum-swingup", [episode], [episode]) == {}
