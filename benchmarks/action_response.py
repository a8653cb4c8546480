"""World models alone: how strongly a trained level-0 world model responds to its actions, in about two minutes.

A screen for world-model changes that :mod:`benchmarks.control_failures` would otherwise need a whole 10k-step agent
run per seed to show. On DMC cartpole-balance from proprioception (action repeat 2, :mod:`benchmarks.suites`):

* **training data**: ``--episodes`` episodes, the first with uniformly random actions, the others with a
  state-feedback policy at the bounds, ``clip(sign(w . o_t) + 0.7 eps, -1, 1)`` with a random ``w`` per episode and
  ``eps ~ N(0, 1)``: the kind of data an agent whose deterministic action sits at the bounds collects, where the
  action is largely predictable from the state; ``--data one-policy`` uses one ``w`` for every episode, as an agent's
  data comes from one policy, so the action is predictable from the state alone and not only from the episode's
  history; ``--data balancing`` uses a linear state feedback that balances the pole (:func:`balancing_feedback`,
  with noise), so that most states are near upright, as late in a run that learns the task; ``--data uniform``
  gives random-action episodes only;
* **training**: each world model (the ``small`` preset's, ``--kinds`` ``s5`` and/or ``rssm``, with
  ``--wm-overrides`` applied) makes ``--updates`` updates on 16 x 16 chunks sampled uniformly from the episodes,
  each chunk starting from the posterior state before it (recomputed every 100 updates, as the replay context does);
  the default 2400 is about the level-0 updates of a 10k-step ``small`` run (9500 training steps x 64 / 256);
* **action response**: on 3 held-out episodes (smooth, small and uniform random actions), from every 25th step a
  copy of the environment and the world model (open loop from the posterior state) are driven 5 steps with the
  action held at +1 and at -1. Per observation entry the regression slope of the model's difference (+1 minus -1)
  onto the environment's (as in :mod:`benchmarks.control_failures`) and the correlation; the same for the reward;
  for prior modes (``mode``) and for the mean of 32 sampled rollouts (``sampled``). The observation entries are the
  cart position, the pole angle's cosine and sine, the cart velocity and the pole's angular velocity;
* **state resolution**: per observation entry, the root-mean-square error of the observation decoded from the
  posterior mode on the training episodes (``{entry}_recon_rmse``; the actor acts on the same state) against the
  typical change one held action makes to that entry in one agent step on the held-out episodes
  (``{entry}_step_effect``: half the mean absolute +1 minus -1 difference after the first driven step). Their ratio,
  ``{entry}_resolution``, above 1 means the world state does not resolve what one action does. The same error over
  the states a balancing policy keeps (``{entry}_recon_rmse_upright``: pole within about 25 degrees of upright,
  ``cos > 0.9``, turning slower than 2 rad/s) and the spread of the entry there (``{entry}_std_upright``).

Run from the repo root: ``python -m benchmarks.action_response [--kinds s5,rssm] [--seeds 0,1] [--updates N]
[--data feedback|one-policy|balancing|uniform] [--wm-overrides JSON]``. The last lines print every figure as
``kind/seed/name: value``.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import time
from collections.abc import Sequence
from types import SimpleNamespace
from typing import Any

import numpy as np
import torch as th

from benchmarks._cli import json_object
from benchmarks._timing import environment_header
from benchmarks.control_failures import _slope
from benchmarks.suites import make_env
from sb3_hieros.agent.world_model import (
    LatentState,
    WorldModel,
    make_world_model,
    world_model_lr_scheduler,
    world_model_optimizer,
)
from sb3_hieros.config import get_preset

TASK = ("dmc_proprio", "cartpole-balance")
OBS_NAMES = ("cart_position", "pole_cos", "pole_sin", "cart_velocity", "pole_angular_velocity")
KINDS = ("s5", "rssm")
RESPONSE_STEPS = 5
STRIDE = 25
CONTEXT_EVERY = 100
#: The states a balancing policy keeps: pole cosine above this and angular velocity below the next (rad/s).
UPRIGHT_COS = 0.9
UPRIGHT_ANGULAR_VELOCITY = 2.0
#: Gains of :func:`balancing_feedback` on (cart position, pole cos, pole sin, cart velocity, pole angular velocity):
#: with its noise it keeps the pole upright (the run prints the return of its episodes).
BALANCING_GAINS = np.array([0.3, 0.0, 3.0, 0.3, 1.0])


def feedback_at_bounds(obs: np.ndarray, w: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The training policy: ``clip(sign(w . o) + 0.7 eps, -1, 1)``, shape (1,)."""
    return np.clip(np.sign(obs @ w) + 0.7 * rng.normal(size=1), -1.0, 1.0).astype(np.float32)


def balancing_feedback(obs: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A policy that balances the pole: ``clip(K . o_t + 0.5 eps, -1, 1)`` with :data:`BALANCING_GAINS`, shape (1,)."""
    return np.clip(obs @ BALANCING_GAINS + 0.5 * rng.normal(size=1), -1.0, 1.0).astype(np.float32)


def open_loop_actions(kind: str, n: int, rng: np.random.Generator) -> np.ndarray:
    """State-independent action sequences ``(n, 1)``: ``"uniform"``, ``"smooth"`` (AR(1), clipped) or ``"small"``."""
    if kind == "uniform":
        return rng.uniform(-1.0, 1.0, (n, 1)).astype(np.float32)
    if kind == "small":
        return np.clip(0.3 * rng.normal(size=(n, 1)), -1.0, 1.0).astype(np.float32)
    if kind == "smooth":
        noise, out, a = rng.normal(size=n), np.empty((n, 1), np.float32), 0.0
        for t in range(n):
            a = 0.8 * a + 0.6 * noise[t]
            out[t] = np.clip(a, -1.0, 1.0)
        return out
    raise ValueError(f"unknown action kind {kind!r}; expected uniform, smooth or small")


def collect(kinds: Sequence[str], seed: int, branch: bool) -> tuple[dict[str, th.Tensor], list[tuple[int, int, Any]]]:
    """One episode per entry of ``kinds``, stacked: ``"feedback"`` (:func:`feedback_at_bounds` with a new ``w`` per
    episode), ``"one_policy"`` (the same with one ``w`` for every episode of the call), ``"balancing"``
    (:func:`balancing_feedback`) or an :func:`open_loop_actions` kind.

    :param kinds: the policy of each episode
    :param seed: base seed (episode ``e`` resets with ``seed * 1000 + e``)
    :param branch: keep a copy of the environment at every ``STRIDE``-th step (held-out episodes)
    :return: ``obs`` (E, T, 5), ``prev_action`` (E, T, 1), ``reward`` (E, T), ``is_first`` (E, T) and the copies as
        (episode, step, env) where ``obs[e, step]`` is the copy's last observation
    """
    rows: dict[str, list[np.ndarray]] = {"obs": [], "prev_action": [], "reward": [], "is_first": []}
    copies = []
    for e, kind in enumerate(kinds):
        rng = np.random.default_rng(seed * 1000 + e)
        env = make_env(*TASK, seed=seed * 1000 + e)
        obs, _ = env.reset(seed=seed * 1000 + e)
        w = rng.normal(size=obs.shape[0])  # drawn for every kind, so an episode's noise is the same whichever w it uses
        if kind == "one_policy":
            w = np.random.default_rng(seed).normal(size=obs.shape[0])
        planned = None if kind in ("feedback", "one_policy", "balancing") else open_loop_actions(kind, 10_000, rng)
        o, pa, r = [obs], [np.zeros(1, np.float32)], [0.0]
        t = 0
        while True:
            if branch and t % STRIDE == STRIDE // 2:
                copies.append((e, t, copy.deepcopy(env)))
            if planned is not None:
                action = planned[t]
            elif kind == "balancing":
                action = balancing_feedback(obs, rng)
            else:
                action = feedback_at_bounds(obs, w, rng)
            obs, reward, terminated, truncated, _ = env.step(action)
            o.append(obs)
            pa.append(action)
            r.append(float(reward))
            t += 1
            if terminated or truncated:
                break
        env.close()
        rows["obs"].append(np.asarray(o, np.float32))
        rows["prev_action"].append(np.asarray(pa, np.float32))
        rows["reward"].append(np.asarray(r, np.float32))
        rows["is_first"].append(np.arange(len(o)) == 0)
    data = {k: th.as_tensor(np.stack(v)) for k, v in rows.items()}
    # a branch must leave room for its driven steps inside the recorded episode
    copies = [(e, t, env) for e, t, env in copies if t + RESPONSE_STEPS < data["obs"].shape[1]]
    return data, copies


def train(model: WorldModel, data: dict[str, th.Tensor], updates: int, seed: int) -> dict[str, float]:
    """``updates`` updates on uniformly sampled chunks, each from the posterior state before it."""
    preset = get_preset("small")
    batch, length = preset.batch_size, preset.batch_length
    optimizer = world_model_optimizer(model)
    scheduler = world_model_lr_scheduler(optimizer, model.config.warmup)
    n_episodes, n_steps = data["obs"].shape[:2]
    rng = np.random.default_rng(seed)
    metrics: dict[str, float] = {}
    contexts: LatentState | None = None
    for i in range(updates):
        if i % CONTEXT_EVERY == 0:
            with th.no_grad():
                contexts, _ = model.observe(data["obs"], data["prev_action"], data["is_first"])  # (E, T)
        episode = rng.integers(0, n_episodes, batch)
        start = rng.integers(0, n_steps - length, batch)
        rows = (episode[:, None], start[:, None] + np.arange(length)[None])
        chunk = SimpleNamespace(
            observations=data["obs"][rows],
            actions=data["prev_action"][rows],
            rewards=data["reward"][rows],
            is_first=data["is_first"][rows],
            is_terminal=th.zeros(batch, length, dtype=th.bool),
        )
        # the state after row start - 1 (a chunk at row 0 starts an episode: is_first resets it)
        before = contexts.select((th.as_tensor(episode), th.as_tensor(np.maximum(start - 1, 0))))
        metrics, _ = model.train_step(chunk, optimizer, scheduler, before)
    return metrics


def one_step_effect(copies: Sequence[tuple[int, int, Any]]) -> np.ndarray:
    """Half the mean absolute difference of the observation after one step at +1 and one at -1 (a property of the
    environment, the same for every model).

    :param copies: environment copies (:func:`collect` with ``branch=True``)
    :return: (5,) per observation entry
    """
    effects = []
    for _, _, env in copies:
        first = []
        for sign in (1.0, -1.0):
            env_copy = copy.deepcopy(env)
            first.append(env_copy.step(np.array([sign], np.float32))[0])
            env_copy.close()
        effects.append(np.abs(first[0] - first[1]) / 2)
    return np.mean(effects, 0)


@th.no_grad()
def state_resolution(model: WorldModel, data: dict[str, th.Tensor], effect: np.ndarray) -> dict[str, float]:
    """How precisely the posterior state holds the observation, against what one action changes in one step.

    :param data: episodes whose observations are decoded from their posterior modes
    :param effect: (5,) :func:`one_step_effect`
    :return: ``{entry}_recon_rmse``, ``{entry}_step_effect`` and their ratio ``{entry}_resolution`` per observation
        entry; ``{entry}_recon_rmse_upright`` and ``{entry}_std_upright`` over the upright states (NaN if none)
    """
    post, _ = model.observe(data["obs"], data["prev_action"], data["is_first"], deterministic=True)
    obs = data["obs"].double().reshape(-1, len(OBS_NAMES))  # (E * T, 5)
    error = model.decode(post).double().reshape(-1, len(OBS_NAMES)) - obs
    rmse = error.pow(2).mean(0).sqrt().numpy()
    upright = (obs[:, OBS_NAMES.index("pole_cos")] > UPRIGHT_COS) & (
        obs[:, OBS_NAMES.index("pole_angular_velocity")].abs() < UPRIGHT_ANGULAR_VELOCITY
    )
    rmse_upright = error[upright].pow(2).mean(0).sqrt().numpy()
    std_upright = obs[upright].std(0).numpy()
    out = {}
    for d, name in enumerate(OBS_NAMES):
        out[f"{name}_recon_rmse"] = float(rmse[d])
        out[f"{name}_step_effect"] = float(effect[d])
        out[f"{name}_resolution"] = float(rmse[d] / effect[d]) if effect[d] > 0 else float("nan")
        out[f"{name}_recon_rmse_upright"] = float(rmse_upright[d])
        out[f"{name}_std_upright"] = float(std_upright[d])
    return out


@th.no_grad()
def action_response(
    model: WorldModel, data: dict[str, th.Tensor], copies: Sequence[tuple[int, int, Any]], samples: int
) -> dict[str, float]:
    """Slopes and correlations of the model's +1 / -1 differences against the environment's.

    :param samples: 0 for prior modes, else the mean of that many sampled rollouts
    :return: ``{name}_slope`` and ``{name}_corr`` for every observation entry and the reward
    """
    post, _ = model.observe(data["obs"], data["prev_action"], data["is_first"], deterministic=True)
    rollouts = max(1, samples)
    real_obs, model_obs, real_rew, model_rew = [], [], [], []
    for episode, step, env in copies:
        branch = {}
        for sign in (1.0, -1.0):
            env_copy = copy.deepcopy(env)
            state = post.select((slice(episode, episode + 1), step)).map_fields(
                lambda x: x.expand(rollouts, *x.shape[1:]).contiguous()
            )
            action = th.full((rollouts, 1), sign)
            ro, rr, mo, mr = [], [], [], []
            for _ in range(RESPONSE_STEPS):
                obs, reward, *_ = env_copy.step(np.array([sign], np.float32))
                state, _ = model.img_step(state, action, deterministic=samples == 0)
                ro.append(obs)
                rr.append(float(reward))
                mo.append(model.decode(state).mean(0).double().numpy())
                mr.append(float(model.reward(state).mean()))
            env_copy.close()
            branch[sign] = (np.array(ro), np.array(rr), np.array(mo), np.array(mr))
        real_obs.append(branch[1.0][0] - branch[-1.0][0])
        real_rew.append(branch[1.0][1] - branch[-1.0][1])
        model_obs.append(branch[1.0][2] - branch[-1.0][2])
        model_rew.append(branch[1.0][3] - branch[-1.0][3])
    out = {}
    pairs = [
        (name, np.concatenate(model_obs)[:, d], np.concatenate(real_obs)[:, d]) for d, name in enumerate(OBS_NAMES)
    ]
    pairs.append(("reward", np.concatenate(model_rew), np.concatenate(real_rew)))
    for name, model_diff, real_diff in pairs:
        out[f"{name}_slope"] = _slope(model_diff, real_diff)
        spread = model_diff.std() > 0 and real_diff.std() > 0
        out[f"{name}_corr"] = float(np.corrcoef(model_diff, real_diff)[0, 1]) if spread else float("nan")
    return out


def run(
    kinds: Sequence[str], seeds: Sequence[int], updates: int, episodes: int, data_kind: str, overrides: dict[str, Any]
) -> dict[str, float]:
    """Train and measure every kind for every seed; prints a line per model and returns ``kind/seed/name`` figures
    and ``data/seed/return_mean``, the mean return of the data policy's episodes."""
    results: dict[str, float] = {}
    held_out, copies = collect(["smooth", "small", "uniform"], seed=99, branch=True)
    effect = one_step_effect(copies)
    for seed in seeds:
        policies = ["uniform"] + [data_kind.replace("-", "_")] * (episodes - 1)
        data, _ = collect(policies, seed=1 + seed, branch=False)
        returns = data["reward"][1:].sum(1)  # the episodes of the data policy (the first is uniformly random)
        mean_return = float(returns.mean()) if len(returns) else float("nan")
        results[f"data/{seed}/return_mean"] = mean_return
        print(f"seed {seed}: {len(returns)} {data_kind} episodes, return {mean_return:.1f} on average", flush=True)
        for kind in kinds:
            th.manual_seed(seed)
            config = dataclasses.replace(get_preset("small").world_model, **{**overrides, "kind": kind})
            model = make_world_model(make_env(*TASK).observation_space, 1, config)
            start = time.perf_counter()
            metrics = train(model, data, updates, seed)
            seconds = time.perf_counter() - start
            model.eval()
            figures = {"train_seconds": seconds}
            figures.update({name: metrics.get(name, float("nan")) for name in ("obs_loss", "kl", "post_entropy")})
            for mode, samples in (("mode", 0), ("sampled", 32)):
                figures.update({f"{mode}_{k}": v for k, v in action_response(model, held_out, copies, samples).items()})
            figures.update(state_resolution(model, data, effect))
            print(
                f"{kind} seed {seed}: {updates} updates in {seconds:.0f} s; pole angular velocity slope "
                f"{figures['mode_pole_angular_velocity_slope']:.2f} (corr "
                f"{figures['mode_pole_angular_velocity_corr']:.2f}), cart velocity "
                f"{figures['mode_cart_velocity_slope']:.2f}, reward {figures['mode_reward_slope']:.2f} "
                f"(corr {figures['mode_reward_corr']:.2f}); resolution of the pole angular velocity "
                f"{figures['pole_angular_velocity_resolution']:.2f}, cart velocity "
                f"{figures['cart_velocity_resolution']:.2f}; upright, the pole angular velocity's error "
                f"{figures['pole_angular_velocity_recon_rmse_upright']:.2f} against its spread "
                f"{figures['pole_angular_velocity_std_upright']:.2f}",
                flush=True,
            )
            results.update({f"{kind}/{seed}/{k}": v for k, v in figures.items()})
    return results


def main(argv: Sequence[str] | None = None) -> dict[str, float]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--kinds", default="s5,rssm", help="comma-separated world models: s5, rssm")
    parser.add_argument("--seeds", default="0", help="comma-separated seeds (data and initialisation)")
    parser.add_argument("--updates", type=int, default=2400, help="world-model updates per model")
    parser.add_argument("--episodes", type=int, default=16, help="training episodes (500 agent steps each)")
    parser.add_argument(
        "--data",
        default="feedback",
        choices=("feedback", "one-policy", "balancing", "uniform"),
        help="training policy",
    )
    parser.add_argument("--wm-overrides", type=json_object, default={}, help="JSON dict of WorldModelConfig fields")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    args = parser.parse_args(argv)
    kinds = [k.strip() for k in args.kinds.split(",") if k.strip()]
    if not kinds or set(kinds) - set(KINDS):
        raise ValueError(f"--kinds must be a non-empty subset of {','.join(KINDS)}, got {args.kinds!r}")
    seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    if not seeds:
        raise ValueError(f"--seeds needs at least one seed, got {args.seeds!r}")
    if args.updates < 1 or args.episodes < 1:
        raise ValueError(f"--updates and --episodes must be >= 1, got {args.updates} and {args.episodes}")
    overrides = args.wm_overrides
    if "kind" in overrides:
        raise ValueError(f"--wm-overrides must not set 'kind' (use --kinds), got {overrides!r}")
    th.set_num_threads(args.threads)
    print(environment_header())
    results = run(kinds, seeds, args.updates, args.episodes, args.data, overrides)
    for name, value in results.items():
        print(f"{name}: {value:.3f}")
    return results


if __name__ == "__main__":
    main()
