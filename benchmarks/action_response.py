"""World models alone: how strongly a trained level-0 world model responds to its actions, in about two minutes.

A screen for world-model changes that :mod:`benchmarks.control_failures` would otherwise need a whole 10k-step agent
run per seed to show. On DMC cartpole-balance (action repeat 2, :mod:`benchmarks.suites`) from proprioception, or
with ``--suite dmc_vision`` from 64x64 pixels (2400 updates take about 20 minutes on one core beside another
run); the data policies act on the simulator state (:func:`benchmarks.control_failures.physical_state`, the
proprio observation itself) in both:

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
  several counts (``--updates 2400,4800,9600``) measure the same model after each;
* **action response**: on 3 held-out episodes (smooth, small and uniform random actions), from every 25th step a
  copy of the environment and the world model (open loop from the posterior state) are driven 5 steps with the
  action held at +1 and at -1. Per observation entry the regression slope of the model's difference (+1 minus -1)
  onto the environment's (as in :mod:`benchmarks.control_failures`) and the correlation; the same for the reward;
  for prior modes (``mode``) and for the mean of 32 sampled rollouts (``sampled``). The observation entries are the
  cart position, the pole angle's cosine and sine, the cart velocity and the pole's angular velocity; from pixels
  these are the simulator state's entries (the same five), read from the model's state by the state probe below;
* **state probe**: a linear map from the posterior's world-state features to the simulator state
  (:func:`benchmarks.control_failures.fit_state_probe`), fitted on the training episodes; ``{entry}_probe_r2`` is
  the share of each entry's variance it explains on the held-out episodes (their own states, not the training
  policy's): how much of the state the model holds, linearly, in the same units from proprioception and pixels;
* **state resolution**: per observation entry, the root-mean-square error of the observation decoded from the
  posterior mode on the training episodes (``{entry}_recon_rmse``; the actor acts on the same state) against the
  typical change one held action makes to that entry in one agent step on the held-out episodes
  (``{entry}_step_effect``: half the mean absolute +1 minus -1 difference after the first driven step). Their ratio,
  ``{entry}_resolution``, above 1 means the world state does not resolve what one action does. The same error over
  the states a balancing policy keeps (``{entry}_recon_rmse_upright``: pole within about 25 degrees of upright,
  ``cos > 0.9``, turning slower than 2 rad/s) and the spread of the entry there (``{entry}_std_upright``). From
  pixels the state probe stands in for the decoder (its error on the episodes it was fitted on).

Run from the repo root: ``python -m benchmarks.action_response [--suite dmc_proprio|dmc_vision] [--kinds s5,rssm]
[--seeds 0,1] [--updates N[,N...]] [--data feedback|one-policy|balancing|uniform] [--wm-overrides JSON]``. The last
lines print every figure as ``kind/seed/name: value`` (``kind/seed/N_updates/name`` with several update counts).
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import time
from collections.abc import Callable, Iterator, Sequence
from types import SimpleNamespace
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.preprocessing import is_image_space
from stable_baselines3.common.vec_env import VecTransposeImage

from benchmarks._cli import json_object
from benchmarks._timing import environment_header
from benchmarks.control_failures import (
    _corr,
    _slope,
    cart_out_of_view,
    fit_state_probe,
    physical_state,
    r2_per_entry,
)
from benchmarks.suites import make_env
from sb3_hieros.agent.world_model import (
    LatentState,
    WorldModel,
    make_world_model,
    world_model_lr_scheduler,
    world_model_optimizer,
)
from sb3_hieros.config import get_preset

TASK = "cartpole-balance"
#: Suites of :data:`TASK`: its state vector, or its 64x64 RGB render (the state probe reads the state from pixels).
SUITES = ("dmc_proprio", "dmc_vision")
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


def world_model_space(suite: str) -> spaces.Space:
    """The observation space a level-0 world model sees on :data:`TASK`: images channel-first, as SB3's
    ``VecTransposeImage`` gives them to the agent."""
    env = make_env(suite, TASK)
    space = env.observation_space
    env.close()
    return VecTransposeImage.transpose_space(space) if is_image_space(space) else space


def collect(
    kinds: Sequence[str], seed: int, branch: bool, suite: str = "dmc_proprio"
) -> tuple[dict[str, th.Tensor], list[tuple[int, int, Any]]]:
    """One episode per entry of ``kinds``, stacked: ``"feedback"`` (:func:`feedback_at_bounds` with a new ``w`` per
    episode), ``"one_policy"`` (the same with one ``w`` for every episode of the call), ``"balancing"``
    (:func:`balancing_feedback`) or an :func:`open_loop_actions` kind. The policies act on the simulator state.

    :param kinds: the policy of each episode
    :param seed: base seed (episode ``e`` resets with ``seed * 1000 + e``)
    :param branch: keep a copy of the environment at every ``STRIDE``-th step (held-out episodes)
    :param suite: one of :data:`SUITES`
    :return: ``obs`` (E, T, 5) or (E, T, 3, 64, 64) uint8, ``state`` (E, T, 5) (the simulator state, float64),
        ``prev_action`` (E, T, 1), ``reward`` (E, T), ``is_first`` (E, T) and the copies as (episode, step, env)
        where ``state[e, step]`` is the copy's simulator state (and ``obs[e, step]`` its last vector observation)
    """
    rows: dict[str, list[np.ndarray]] = {"obs": [], "state": [], "prev_action": [], "reward": [], "is_first": []}
    copies = []
    for e, kind in enumerate(kinds):
        rng = np.random.default_rng(seed * 1000 + e)
        env = make_env(suite, TASK, seed=seed * 1000 + e)
        obs, _ = env.reset(seed=seed * 1000 + e)
        state = physical_state(env)
        # drawn for every kind, so an episode's noise is the same whichever w it uses
        w = rng.normal(size=state.shape[0])
        if kind == "one_policy":
            w = np.random.default_rng(seed).normal(size=state.shape[0])
        planned = None if kind in ("feedback", "one_policy", "balancing") else open_loop_actions(kind, 10_000, rng)
        o, s, pa, r = [obs], [state], [np.zeros(1, np.float32)], [0.0]
        t = 0
        while True:
            if branch and t % STRIDE == STRIDE // 2:
                copies.append((e, t, copy.deepcopy(env)))
            policy_input = state.astype(np.float32)  # the proprio observation itself
            if planned is not None:
                action = planned[t]
            elif kind == "balancing":
                action = balancing_feedback(policy_input, rng)
            else:
                action = feedback_at_bounds(policy_input, w, rng)
            obs, reward, terminated, truncated, _ = env.step(action)
            state = physical_state(env)
            o.append(obs)
            s.append(state)
            pa.append(action)
            r.append(float(reward))
            t += 1
            if terminated or truncated:
                break
        if not branch:
            # a copy of a pixel env renders through the original (gymnasium's AddRenderObservation keeps a closure
            # over its own wrapper, which deepcopy shares), so an env with copies stays open
            env.close()
        observations = np.stack(o)
        images = observations.ndim == 4  # (T, H, W, C) renders, stored channel-first as the agent sees them
        rows["obs"].append(observations.transpose(0, 3, 1, 2) if images else observations.astype(np.float32))
        rows["state"].append(np.stack(s))
        rows["prev_action"].append(np.asarray(pa, np.float32))
        rows["reward"].append(np.asarray(r, np.float32))
        rows["is_first"].append(np.arange(len(o)) == 0)
    data = {k: th.as_tensor(np.ascontiguousarray(np.stack(v))) for k, v in rows.items()}
    # a branch must leave room for its driven steps inside the recorded episode
    copies = [(e, t, env) for e, t, env in copies if t + RESPONSE_STEPS < data["obs"].shape[1]]
    return data, copies


def train(
    model: WorldModel, data: dict[str, th.Tensor], updates: Sequence[int], seed: int
) -> Iterator[tuple[int, dict[str, float]]]:
    """Updates on uniformly sampled chunks, each from the posterior state before it, pausing after each count.

    :param updates: increasing update counts
    :return: yields the count and the last update's metrics at each of ``updates``
    """
    preset = get_preset("small")
    batch, length = preset.batch_size, preset.batch_length
    optimizer = world_model_optimizer(model)
    scheduler = world_model_lr_scheduler(optimizer, model.config.warmup)
    n_episodes, n_steps = data["obs"].shape[:2]
    rng = np.random.default_rng(seed)
    metrics: dict[str, float] = {}
    contexts: LatentState | None = None
    for i in range(max(updates)):
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
        if i + 1 in updates:
            yield i + 1, metrics


#: A read-out of the simulator state from world states: (N,) batch -> (N, 5).
Readout = Callable[[LatentState], np.ndarray]


@th.no_grad()
def posterior(model: WorldModel, data: dict[str, th.Tensor]) -> LatentState:
    """The posterior modes of every step of ``data``, batch (E, T)."""
    post, _ = model.observe(data["obs"], data["prev_action"], data["is_first"], deterministic=True)
    return post


def features_of(model: WorldModel, post: LatentState) -> np.ndarray:
    """The world-state features of every state of ``post``, flattened over its batch, (N, P) float64."""
    return model.features(post.flatten_batch()).double().numpy()


def states_of(data: dict[str, th.Tensor]) -> np.ndarray:
    """The simulator states of every step of ``data``, (E * T, 5)."""
    return data["state"].reshape(-1, len(OBS_NAMES)).double().numpy()


def one_step_effect(copies: Sequence[tuple[int, int, Any]]) -> np.ndarray:
    """Half the mean absolute difference of the simulator state after one step at +1 and one at -1 (a property of
    the environment, the same for every model).

    :param copies: environment copies (:func:`collect` with ``branch=True``)
    :return: (5,) per state entry
    """
    effects = []
    for _, _, env in copies:
        first = []
        for sign in (1.0, -1.0):
            env_copy = copy.deepcopy(env)
            env_copy.step(np.array([sign], np.float32))
            first.append(physical_state(env_copy))
            env_copy.close()
        effects.append(np.abs(first[0] - first[1]) / 2)
    return np.mean(effects, 0)


@th.no_grad()
def state_resolution(
    post: LatentState, data: dict[str, th.Tensor], effect: np.ndarray, readout: Readout
) -> dict[str, float]:
    """How precisely the posterior state holds the simulator state, against what one action changes in one step.

    :param post: the posterior modes of ``data`` (:func:`posterior`)
    :param data: episodes whose states are read out from their posterior modes
    :param effect: (5,) :func:`one_step_effect`
    :param readout: the decoder (proprioception) or a state probe fitted on ``data`` (pixels)
    :return: ``{entry}_recon_rmse``, ``{entry}_step_effect`` and their ratio ``{entry}_resolution`` per state
        entry; ``{entry}_recon_rmse_upright`` and ``{entry}_std_upright`` over the upright states (NaN if none)
    """
    states = th.as_tensor(states_of(data))  # (E * T, 5)
    error = th.as_tensor(readout(post.flatten_batch())).double() - states
    rmse = error.pow(2).mean(0).sqrt().numpy()
    upright = (states[:, OBS_NAMES.index("pole_cos")] > UPRIGHT_COS) & (
        states[:, OBS_NAMES.index("pole_angular_velocity")].abs() < UPRIGHT_ANGULAR_VELOCITY
    )
    rmse_upright = error[upright].pow(2).mean(0).sqrt().numpy()
    std_upright = states[upright].std(0).numpy()
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
    model: WorldModel,
    post: LatentState,
    copies: Sequence[tuple[int, int, Any]],
    samples: int,
    readout: Readout,
) -> dict[str, float]:
    """Slopes and correlations of the model's +1 / -1 differences against the environment's.

    :param post: the posterior modes of the episodes of ``copies`` (:func:`posterior`)
    :param samples: 0 for prior modes, else the mean of that many sampled rollouts
    :param readout: the simulator state of the model's states (the decoder, or a state probe from pixels)
    :return: ``{name}_slope`` and ``{name}_corr`` for every state entry and the reward
    """
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
                _, reward, *_ = env_copy.step(np.array([sign], np.float32))
                state, _ = model.img_step(state, action, deterministic=samples == 0)
                ro.append(physical_state(env_copy))
                rr.append(float(reward))
                mo.append(np.asarray(readout(state), np.float64).mean(0))
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
        out[f"{name}_corr"] = _corr(model_diff, real_diff)
    return out


def measure(
    model: WorldModel,
    data: dict[str, th.Tensor],
    held_out: dict[str, th.Tensor],
    copies: Sequence[tuple[int, int, Any]],
    effect: np.ndarray,
) -> dict[str, float]:
    """Every figure of a trained model (see the module docstring); the decoder reads the state from
    proprioception, the state probe from pixels."""
    model.eval()
    post, held_out_post = posterior(model, data), posterior(model, held_out)
    probe = fit_state_probe(features_of(model, post), states_of(data))
    if data["obs"].dim() == 3:  # vector observations: the simulator state itself, decoded

        def readout(state: LatentState) -> np.ndarray:
            return model.decode(state).double().numpy()
    else:

        def readout(state: LatentState) -> np.ndarray:
            return probe(model.features(state).double().numpy())

    figures = {}
    for mode, samples in (("mode", 0), ("sampled", 32)):
        figures.update(
            {f"{mode}_{k}": v for k, v in action_response(model, held_out_post, copies, samples, readout).items()}
        )
    figures.update(state_resolution(post, data, effect, readout))
    held_out_r2 = r2_per_entry(probe(features_of(model, held_out_post)), states_of(held_out))
    figures.update({f"{name}_probe_r2": float(v) for name, v in zip(OBS_NAMES, held_out_r2, strict=True)})
    model.train()
    return figures


def run(
    kinds: Sequence[str],
    seeds: Sequence[int],
    updates: Sequence[int],
    episodes: int,
    data_kind: str,
    overrides: dict[str, Any],
    suite: str = "dmc_proprio",
) -> dict[str, float]:
    """Train and measure every kind for every seed, after each of ``updates``; prints a line per measurement and
    returns ``kind/seed/name`` figures (``kind/seed/N_updates/name`` with several counts) and
    ``data/seed/return_mean``, the mean return of the data policy's episodes; ``data/seed/cart_out_of_view`` and
    ``held_out/cart_out_of_view``, the share of steps whose cart is out of the pixel camera's view
    (:data:`~benchmarks.control_failures.CARTPOLE_OUT_OF_VIEW`)."""
    results: dict[str, float] = {}
    held_out, copies = collect(["smooth", "small", "uniform"], seed=99, branch=True, suite=suite)
    cart = OBS_NAMES.index("cart_position")
    results["held_out/cart_out_of_view"] = cart_out_of_view(held_out["state"][..., cart].numpy())
    effect = one_step_effect(copies)
    for seed in seeds:
        policies = ["uniform"] + [data_kind.replace("-", "_")] * (episodes - 1)
        data, _ = collect(policies, seed=1 + seed, branch=False, suite=suite)
        returns = data["reward"][1:].sum(1)  # the episodes of the data policy (the first is uniformly random)
        mean_return = float(returns.mean()) if len(returns) else float("nan")
        results[f"data/{seed}/return_mean"] = mean_return
        out_of_view = cart_out_of_view(data["state"][..., cart].numpy())
        results[f"data/{seed}/cart_out_of_view"] = out_of_view
        print(
            f"seed {seed}: {len(returns)} {data_kind} episodes, return {mean_return:.1f} on average; the cart out of "
            f"the pixel camera's view in {out_of_view:.0%} of the steps",
            flush=True,
        )
        for kind in kinds:
            th.manual_seed(seed)
            config = dataclasses.replace(get_preset("small").world_model, **{**overrides, "kind": kind})
            model = make_world_model(world_model_space(suite), 1, config)
            trained, resumed = 0.0, time.perf_counter()
            for count, metrics in train(model, data, updates, seed):
                trained += time.perf_counter() - resumed  # the measurements do not count as training
                figures = {"train_seconds": trained}
                figures.update(
                    {
                        name: metrics.get(name, float("nan"))
                        for name in ("obs_loss", "reward_loss", "kl", "post_entropy")
                    }
                )
                figures.update(measure(model, data, held_out, copies, effect))
                print(
                    f"{kind} seed {seed}: {count} updates in {trained:.0f} s; pole angular velocity "
                    f"slope {figures['mode_pole_angular_velocity_slope']:.2f} (corr "
                    f"{figures['mode_pole_angular_velocity_corr']:.2f}), cart velocity "
                    f"{figures['mode_cart_velocity_slope']:.2f}, reward {figures['mode_reward_slope']:.2f} "
                    f"(corr {figures['mode_reward_corr']:.2f}); resolution of the pole angular velocity "
                    f"{figures['pole_angular_velocity_resolution']:.2f}, cart velocity "
                    f"{figures['cart_velocity_resolution']:.2f}; upright, the pole angular velocity's error "
                    f"{figures['pole_angular_velocity_recon_rmse_upright']:.2f} against its spread "
                    f"{figures['pole_angular_velocity_std_upright']:.2f}; held-out probe R^2 of the pole sine "
                    f"{figures['pole_sin_probe_r2']:.2f}, angular velocity "
                    f"{figures['pole_angular_velocity_probe_r2']:.2f}",
                    flush=True,
                )
                label = f"{kind}/{seed}" if len(updates) == 1 else f"{kind}/{seed}/{count}_updates"
                results.update({f"{label}/{k}": v for k, v in figures.items()})
                resumed = time.perf_counter()
    return results


def main(argv: Sequence[str] | None = None) -> dict[str, float]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--suite", default="dmc_proprio", choices=SUITES, help="observations: state or pixels")
    parser.add_argument("--kinds", default="s5,rssm", help="comma-separated world models: s5, rssm")
    parser.add_argument("--seeds", default="0", help="comma-separated seeds (data and initialisation)")
    parser.add_argument(
        "--updates", default="2400", help="world-model updates per model; comma-separated counts measure after each"
    )
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
    try:
        updates = [int(u) for u in args.updates.split(",") if u.strip()]
    except ValueError:
        raise ValueError(f"--updates must be comma-separated integers, got {args.updates!r}") from None
    if not updates or min(updates) < 1 or updates != sorted(set(updates)):
        raise ValueError(f"--updates must be increasing counts >= 1, got {args.updates!r}")
    if args.episodes < 1:
        raise ValueError(f"--episodes must be >= 1, got {args.episodes}")
    overrides = args.wm_overrides
    if "kind" in overrides:
        raise ValueError(f"--wm-overrides must not set 'kind' (use --kinds), got {overrides!r}")
    th.set_num_threads(args.threads)
    print(environment_header())
    results = run(kinds, seeds, updates, args.episodes, args.data, overrides, args.suite)
    for name, value in results.items():
        print(f"{name}: {value:.3f}")
    return results


if __name__ == "__main__":
    main()
