"""Why a trained HIEROS agent does (or does not) learn a task: what each level does and believes, measured.

The continuous-control counterpart of :mod:`benchmarks.cartpole_failures`, for any task of
:mod:`benchmarks.suites`. It loads one or more saved models (``NAME=PATH`` to name them in the tables), plays
``--episodes`` held-out episodes with the deterministic policy (the evaluation protocol) and as many with sampled
actions (the training behaviour), and reports per model:

* **returns** of both kinds of episodes; on DMC cartpole tasks the share of their steps whose cart is out of the
  pixel camera's view (:data:`CARTPOLE_OUT_OF_VIEW`);
* **actions, per level**: level 0 (the environment action, in [-1, 1] for Box spaces): the mean and mean absolute
  value of the deterministic action, the share of action entries at the bounds (``|a| > 0.95``), the policy's mean
  std and the mean distance between the deterministic action and a sample at the same state. Levels above: how
  often the subgoal changes when the level acts, and the entropy of its policy;
* **state feedback** (level 0, Box actions and vector observations, deterministic episodes): the least-squares fit
  of the deterministic action on the observation entries and a constant, ``a ~ K o + c``: the gain of every
  (action entry, observation entry) pair in the observation's own units (for at most :data:`MAX_FEEDBACK_GAINS`
  pairs), the constant, and the share of the action's variance the fit explains (R^2). A policy that reacts to the
  state as a controller would has a high R^2 and gains on the entries that matter (on cartpole both the pole angle
  and its angular velocity), a biased one a large constant; with the mean absolute value of every observation entry
  over the episodes (where the state drifts to);
* **world model** (level 0, on the held-out episodes): open-loop predictions over ``--horizon`` steps from the
  posterior state at every ``--stride``-th step with the actions the agent actually took: mean absolute reward error
  and the observation error relative to a repeat-the-last-observation baseline (vector observations);
* **state probe** (level 0, tasks whose simulator state :func:`physical_state` reads: DMC and gymnasium's classic
  control, from pixels too): a ridge regression from the world-state features of the posterior to the simulator
  state, fitted and scored on alternating blocks of steps: the share of each state entry's variance the filtered
  latent holds (R^2), and, open loop over ``--horizon`` steps with the actions taken, the probed prediction's error
  against a repeat-the-start-state baseline. Once on the held-out episodes (``state_probe/agent``: the states the
  policy visits; a policy that balances well visits few, which makes single entries' R^2 unstable), once on as many
  episodes with uniformly random actions (``state_probe/random``: the same states for every model, so models from
  pixels and from proprioception, or from different points of training, are compared on one distribution). It says
  whether the world model has recovered the state (on cartpole the pole's angle and angular velocity) and predicts
  its motion; beside it, the same probe from the last two observations themselves (the read-out without a world
  model);
* **action response** (level 0, Box actions, on the held-out episodes): from every ``--stride``-th state the real
  environment (a copy of it) and the world model (open loop from the posterior state) are driven for
  ``--response-steps`` steps with the action held at +1 and at -1; the regression slope of the model's difference
  (+1 minus -1) onto the environment's, per observation entry (vector observations) and for the reward, with the
  correlation of the reward differences. A slope of 1 is a model that responds to actions as the environment does,
  0 one that ignores them: the actor learns by back-propagating through these differences;
* **critic** (level 0, extrinsic term): its value at each visited state against the realised discounted return
  (bootstrapped with the critic's value where an episode is cut by its time limit): means, bias and correlation;
* **imagination** (level 0): from the posterior state at every ``--stride``-th step of the sampled episodes, an
  imagined rollout as in training (the actor sampling actions in the world model); its extrinsic rewards at steps
  1..H against the rewards the episode received over the same steps (mean per step, and the bias at the first and
  the last imagined step): whether the policy's imagined future is worse or better than its real one;
* **return normalisers**: the scale ``max(1, P95 - P5)`` of every reward term of every level;
* **actor objective** (every level, from the posterior states of the sampled episodes, imagined as training does):
  per reward term the spread of its normalised advantage and the gradient norm it puts on the actor's parameters,
  and the share of each term (and of the entropy bonus) in the sum of those norms. For a level trained by dynamics
  backpropagation also the norm of the gradient that reaches each imagined action, per imagined step, and at level 0
  the correlation of the first imagined action's ascent direction with each observation entry at the start state
  (the state feedback the objective asks for; Box actions, vector observations); and whether that pull is sampling
  noise or a consistent function of the state: each of 128 start states imagined 16 times, the per-sample
  signal-to-noise ratio, the split-half reliability of the per-start mean and the share of it the observation
  explains linearly;
* for a model with an ``evaluations.npz`` or ``result.json`` beside it, nothing more: train with
  :mod:`benchmarks.train` or :mod:`benchmarks.cpu_suite` and point this script at the saved models.

Example (three models of one task, e.g. one level, two levels, two levels without the subgoal reward)::

    python -m benchmarks.control_failures --suite dmc_proprio --task cartpole-balance --episodes 3 \\
        one_level=runs/l1/model.zip two_levels=runs/l2/model.zip no_subgoal=runs/sg0/model.zip

The last lines print each figure as ``model/name: value``.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import pathlib
from collections import defaultdict
from collections.abc import Callable, Iterator, Sequence
from copy import deepcopy
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces

from benchmarks._timing import environment_header
from benchmarks.suites import SUITES, make_env
from sb3_hieros import HIEROS
from sb3_hieros.agent.returns import cumulative_discount, lambda_returns
from sb3_hieros.agent.world_model import LatentState, WorldModel, stack_states

os.environ.setdefault("MUJOCO_GL", "egl")

__all__ = [
    "Episode",
    "action_figures",
    "action_response_figures",
    "actor_objective_figures",
    "ascent_figures",
    "critic_figures",
    "feedback_figures",
    "open_loop_figures",
    "physical_state",
    "play",
    "pull_figures",
    "state_probe_figures",
]

#: An action entry counts as "at the bound" when its magnitude (in [-1, 1] units) exceeds this.
AT_BOUND = 0.95
#: :func:`feedback_figures` reports single gains only up to this many (action entry, observation entry) pairs.
MAX_FEEDBACK_GAINS = 32


@dataclass
class Episode:
    """What one played episode left behind (time-major lists, one entry per agent step)."""

    observations: list[np.ndarray] = field(default_factory=list)
    rewards: list[float] = field(default_factory=list)
    #: level-0 action vectors actually taken ([-1, 1] for Box, one-hot for Discrete), each (A,)
    actions: list[np.ndarray] = field(default_factory=list)
    #: per level, the posterior state after each observation (levels with a world model of their own)
    latents: dict[int, list[LatentState]] = field(default_factory=lambda: defaultdict(list))
    #: per level i >= 1, the subgoal code in force after each step, each (S,)
    codes: dict[int, list[th.Tensor]] = field(default_factory=lambda: defaultdict(list))
    #: per level i >= 1, whether the level acted at each step
    updated: dict[int, list[bool]] = field(default_factory=lambda: defaultdict(list))
    #: level-0 deterministic action, a fresh sample and the policy std at each visited state, each (A,)
    mode: list[np.ndarray] = field(default_factory=list)
    sample: list[np.ndarray] = field(default_factory=list)
    std: list[np.ndarray] = field(default_factory=list)
    #: level-0 extrinsic value at each visited state
    values: list[float] = field(default_factory=list)
    #: the simulator's state behind each observation (:func:`physical_state`), None where the env does not expose it
    states: list[np.ndarray | None] = field(default_factory=list)
    truncated: bool = False

    @property
    def total(self) -> float:
        """The episode's return."""
        return float(np.sum(self.rewards))


def _level_goal(hierarchy: Any, level: int, codes: Sequence[th.Tensor]) -> th.Tensor | None:
    """The subgoal level ``level`` sees (its feature form), or None at the top level."""
    if level == hierarchy.n_levels - 1:
        return None
    return hierarchy.levels[level].goal_features(codes[level + 1])


def physical_state(env: Any) -> np.ndarray | None:
    """The simulator's state behind the env's current observation, as one float64 vector, where the env exposes it.

    dm_control tasks (through shimmy, whose env forwards ``task`` and ``physics``): the task's own observation of
    the physics, the entries ``dmc_proprio`` observes, in the task's order, also behind a pixel env (cartpole: cart
    position, pole cosine and sine, cart and pole velocities). gymnasium's classic-control envs: their ``state``.

    :param env: a gymnasium env (wrappers included)
    :return: (S,) state, or None for envs without one of the two
    """
    base = env.unwrapped
    task, physics = getattr(base, "task", None), getattr(base, "physics", None)
    if task is not None and physics is not None and hasattr(task, "get_observation"):
        return np.concatenate(
            [np.asarray(v, dtype=np.float64).reshape(-1) for v in task.get_observation(physics).values()]
        )
    state = getattr(base, "state", None)
    if state is None:
        return None
    try:
        return np.asarray(state, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        return None


def _random_action(space: spaces.Space, rng: np.random.Generator, like: th.Tensor) -> th.Tensor:
    """A level-0 action vector drawn uniformly: in [-1, 1] per entry (Box), a one-hot of a random index (Discrete).

    :param space: the env's action space
    :param rng: the draws' generator
    :param like: (1, A) the policy's action, for size, dtype and device
    :return: (1, A) action
    """
    size = int(like.shape[-1])
    if isinstance(space, spaces.Discrete):
        action = np.eye(size)[rng.integers(size)]
    else:
        action = rng.uniform(-1.0, 1.0, size=size)
    return th.as_tensor(action, dtype=like.dtype, device=like.device)[None]


@th.no_grad()
def play(model: HIEROS, env: Any, seed: int, deterministic: bool, random_actions: bool = False) -> Episode:
    """One episode with the hierarchy's recurrent state threaded (the acting path of ``predict``).

    :param model: the agent
    :param env: a gymnasium env of the task the model was trained on
    :param seed: seed of ``env.reset`` (and of the random actions)
    :param deterministic: policy modes instead of samples
    :param random_actions: take uniformly random actions (:func:`_random_action`) instead of the policy's; the
        hierarchy filters them as its own, so every model sees the same episodes
    :return: the episode's record
    """
    policy = model.policy
    hierarchy = policy.hierarchy
    level0 = hierarchy.levels[0]
    ac0 = level0.actor_critic
    obs, _ = env.reset(seed=seed)
    state = hierarchy.initial_state(1)
    first = np.ones(1, dtype=bool)
    episode = Episode()
    rng = np.random.default_rng(seed)
    while True:
        batch = obs[None] if isinstance(obs, np.ndarray) else {k: v[None] for k, v in obs.items()}
        tensor, _ = policy.obs_to_tensor(batch)
        state, step = hierarchy.step(state, tensor, first, deterministic)
        if random_actions:  # the action in force is the one taken and the one the world model steps with next
            drawn = _random_action(model.action_space, rng, state.actions[0])
            state = state._replace(actions=(drawn, *state.actions[1:]))
        first = np.zeros(1, dtype=bool)
        for i, latent in enumerate(state.latents):
            episode.latents[i].append(latent)
        for i in range(1, hierarchy.n_levels):
            episode.codes[i].append(state.actions[i][0])
            episode.updated[i].append(bool(step.updated[i][0]))
        goal = _level_goal(hierarchy, 0, state.actions)
        feat, _, _ = level0.features(state.latents[0], goal)
        dist = ac0.actor(feat)
        episode.mode.append(dist.mode()[0].float().numpy().reshape(-1))
        episode.sample.append(dist.sample()[0].float().numpy().reshape(-1))
        if hasattr(dist, "std"):
            episode.std.append(dist.std[0].float().numpy())
        episode.values.append(float(ac0.critics["extrinsic"].value(feat)[0]) if "extrinsic" in ac0.critics else 0.0)
        episode.observations.append(np.asarray(obs, dtype=np.float64) if isinstance(obs, np.ndarray) else obs)
        episode.states.append(physical_state(env))
        episode.actions.append(state.actions[0][0].float().numpy())
        action = policy.env_actions(state.actions[0])[0]
        obs, reward, terminated, truncated, _ = env.step(action)
        episode.rewards.append(float(reward))
        if terminated or truncated:
            episode.truncated = bool(truncated and not terminated)
            return episode


#: DMC cartpole: from this cart position on (either side) the cart's body lies outside the 64x64 frame of camera 0,
#: the camera of the pixel suite (rendered: its last pixels leave the frame between 1.75 and 1.8 at any pole angle;
#: the rail ends near 2), so from pixels the state is seen at most through a tilted pole.
CARTPOLE_OUT_OF_VIEW = 1.8


def out_of_view_figures(task: str, greedy: Sequence[Episode], sampled: Sequence[Episode]) -> dict[str, float]:
    """On DMC cartpole tasks, the share of steps whose cart is out of the pixel camera's view
    (:data:`CARTPOLE_OUT_OF_VIEW`), from the simulator state, whatever the observations.

    :return: ``episodes/cart_out_of_view/deterministic`` and ``.../sampled``; nothing on other tasks
    """
    if not task.startswith("cartpole-"):
        return {}
    out = {}
    for name, episodes in (("deterministic", greedy), ("sampled", sampled)):
        cart = np.array([s[0] for e in episodes for s in e.states if s is not None])
        if len(cart):
            out[f"episodes/cart_out_of_view/{name}"] = cart_out_of_view(cart)
    return out


def cart_out_of_view(cart_positions: np.ndarray) -> float:
    """The share of DMC cartpole cart positions (any shape) out of the pixel camera's view
    (:data:`CARTPOLE_OUT_OF_VIEW`)."""
    return float((np.abs(cart_positions) >= CARTPOLE_OUT_OF_VIEW).mean())


def action_figures(model: HIEROS, episodes: Sequence[Episode]) -> dict[str, float]:
    """Level-0 action statistics and, per level above, how often the subgoal changes.

    :param model: the agent that played ``episodes``
    :param episodes: episodes played by :func:`play`
    :return: figures
    """
    out: dict[str, float] = {}
    mode = np.concatenate([np.stack(e.mode) for e in episodes])
    sample = np.concatenate([np.stack(e.sample) for e in episodes])
    if isinstance(model.action_space, spaces.Box):
        out["level0/mode_mean"] = float(mode.mean())
        out["level0/mode_abs_mean"] = float(np.abs(mode).mean())
        out["level0/at_bounds"] = float((np.abs(mode) > AT_BOUND).mean())
        out["level0/policy_std"] = float(np.concatenate([np.stack(e.std) for e in episodes]).mean())
        out["level0/mode_sample_distance"] = float(np.abs(mode - sample).mean())
    else:
        out["level0/mode_sample_disagree"] = float((mode.argmax(-1) != sample.argmax(-1)).mean())
    for i in range(1, model.policy.hierarchy.n_levels):
        changes, acts = 0, 0
        for e in episodes:
            codes = e.codes[i]
            for t in range(1, len(codes)):
                if e.updated[i][t]:
                    acts += 1
                    changes += int(not th.equal(codes[t], codes[t - 1]))
        out[f"level{i}/subgoal_change_rate"] = changes / max(acts, 1)
    return out


def feedback_figures(model: HIEROS, episodes: Sequence[Episode]) -> dict[str, float]:
    """How the level-0 deterministic action depends on the observation: the linear state-feedback fit ``a ~ K o + c``.

    :param model: the agent that played ``episodes`` (Box actions and a flat vector observation, else no figures)
    :param episodes: deterministic episodes played by :func:`play`
    :return: ``level0/feedback_r2``, ``level0/feedback_bias_a{j}``, ``level0/feedback_gain_a{j}_obs{k}`` (for at most
        :data:`MAX_FEEDBACK_GAINS` pairs) and ``state/abs_mean_obs{k}``
    """
    if not _box_and_vector(model):
        return {}
    obs = _stacked_observations(episodes)  # (N, D)
    mode = np.concatenate([np.stack(e.mode) for e in episodes])  # (N, A)
    coef, r2 = _linear_fit(obs, mode)  # (D + 1, A)
    out = {"level0/feedback_r2": r2}
    n_obs, n_act = obs.shape[1], mode.shape[1]
    for j in range(n_act):
        out[f"level0/feedback_bias_a{j}"] = float(coef[-1, j])
        if n_obs * n_act <= MAX_FEEDBACK_GAINS:
            for k in range(n_obs):
                out[f"level0/feedback_gain_a{j}_obs{k}"] = float(coef[k, j])
    for k in range(n_obs):
        out[f"state/abs_mean_obs{k}"] = float(np.abs(obs[:, k]).mean())
    return out


@th.no_grad()
def open_loop(wm: WorldModel, starts: Sequence[tuple[Episode, int]], horizon: int) -> Iterator[tuple[int, LatentState]]:
    """Level 0's world model driven open loop, deterministic, from the posterior states of ``starts`` with the
    actions the agent took, all starts as one batch.

    :param wm: level 0's world model
    :param starts: (episode, step t) pairs with at least ``horizon`` actions after t
    :param horizon: open-loop steps H
    :return: yields j and the imagined states s_{t+j+1} (batch (N,)) for j = 0 .. H-1
    """
    state = stack_states([e.latents[0][t] for e, t in starts], 0).flatten_batch()
    for j in range(horizon):
        actions = th.as_tensor(np.stack([e.actions[t + j] for e, t in starts]), dtype=th.float32)  # (N, A)
        state, _ = wm.img_step(state, actions, deterministic=True)
        yield j, state


@th.no_grad()
def open_loop_figures(model: HIEROS, episodes: Sequence[Episode], horizon: int, stride: int) -> dict[str, float]:
    """Level 0's open-loop reward and observation errors with the actions actually taken.

    From the posterior state s_t the world model imagines s_{t+1} .. s_{t+H} with the actions a_t .. a_{t+H-1}
    (:func:`open_loop`); the reward head at s_{t+j} predicts the reward of arriving at o_{t+j}, the decoder o_{t+j}.

    :param model: the agent
    :param episodes: held-out episodes
    :param horizon: open-loop steps H
    :param stride: a start every ``stride`` steps
    :return: ``world_model/reward_mae``, ``world_model/reward_abs_mean`` (the scale of the rewards) and, for vector
        observations, ``world_model/obs_error_vs_repeat_last``
    """
    wm = model.policy.hierarchy.levels[0].world_model
    starts = [(e, t) for e in episodes for t in range(0, len(e.rewards) - horizon, stride)]
    if not starts:  # every episode ended within the horizon
        return {"world_model/reward_mae": float("nan"), "world_model/reward_abs_mean": float("nan")}
    reward_err, reward_abs, obs_err, base_err = [], [], [], []
    vector = isinstance(model.observation_space, spaces.Box) and len(model.observation_space.shape) == 1
    for j, state in open_loop(wm, starts, horizon):
        rewards = np.array([e.rewards[t + j] for e, t in starts])  # (N,)
        reward_err.append(np.abs(wm.reward(state).double().numpy() - rewards))
        reward_abs.append(np.abs(rewards))
        inside = [i for i, (e, t) in enumerate(starts) if t + j + 1 < len(e.observations)] if vector else []
        if inside:
            predicted = wm.decode(state).double().numpy()[inside]  # (n, D)
            target = np.stack([starts[i][0].observations[starts[i][1] + j + 1] for i in inside])
            repeat = np.stack([starts[i][0].observations[starts[i][1]] for i in inside])
            obs_err.append(((predicted - target) ** 2).mean(1))
            base_err.append(((repeat - target) ** 2).mean(1))
    out = {
        "world_model/reward_mae": float(np.concatenate(reward_err).mean()),
        "world_model/reward_abs_mean": float(np.concatenate(reward_abs).mean()),
    }
    if obs_err:
        out["world_model/obs_error_vs_repeat_last"] = float(
            np.concatenate(obs_err).mean() / max(np.concatenate(base_err).mean(), 1e-12)
        )
    return out


#: Ridge penalties (on standardised features) :func:`fit_state_probe` chooses from.
PROBE_PENALTIES = tuple(10.0**k for k in range(-2, 6))
#: Steps of the blocks :func:`state_probe_figures` splits episodes into (at least twice the open-loop horizon): a
#: probe is fitted on every other block and scored on the blocks between, so neighbouring steps never sit on both sides.
PROBE_BLOCK = 50


def r2_per_entry(predicted: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """The share of each column's variance over ``truth`` (N, S) that ``predicted`` explains, (S,)."""
    return 1.0 - ((predicted - truth) ** 2).mean(0) / np.maximum(truth.std(0), 1e-12) ** 2


def _ridge_path(x: np.ndarray, y: np.ndarray, penalties: Sequence[float]) -> list[np.ndarray]:
    """Ridge coefficients of ``y`` on ``x`` (both centred), (P, S), for each penalty (one SVD for all)."""
    u, s, vt = np.linalg.svd(x, full_matrices=False)
    uy = u.T @ y
    return [vt.T @ ((s / (s**2 + penalty))[:, None] * uy) for penalty in penalties]


def fit_state_probe(
    features: np.ndarray, states: np.ndarray, block: int = PROBE_BLOCK
) -> Callable[[np.ndarray], np.ndarray]:
    """A linear map from world-state features to simulator states, by ridge regression on standardised features,
    for each state entry with the penalty of :data:`PROBE_PENALTIES` that predicts it best from alternating blocks
    of ``block`` rows (fitted on the even blocks, scored on the odd ones), then refitted on all rows.

    :param features: (N, P) features, in time order
    :param states: (N, S) states
    :param block: rows per block of the penalty's choice
    :return: a function from (M, P) features to (M, S) predicted states
    """
    mean, scale = features.mean(0), np.maximum(features.std(0), 1e-6)
    x = (features - mean) / scale
    y_mean = states.mean(0)
    y = states - y_mean
    even = (np.arange(len(x)) // block) % 2 == 0
    best = np.full(y.shape[1], len(PROBE_PENALTIES) - 1)  # (S,) index of each state entry's penalty
    if even.any() and (~even).any():
        xe, ye = x[even], y[even]
        coefs = _ridge_path(xe - xe.mean(0), ye - ye.mean(0), PROBE_PENALTIES)
        errors = [(((x[~even] - xe.mean(0)) @ c + ye.mean(0) - y[~even]) ** 2).sum(0) for c in coefs]  # each (S,)
        best = np.argmin(np.stack(errors), axis=0)
    path = _ridge_path(x, y, PROBE_PENALTIES)
    coef = np.stack([path[i][:, d] for d, i in enumerate(best)], axis=1)  # (P, S)
    return lambda f: ((f - mean) / scale) @ coef + y_mean


@th.no_grad()
def state_probe_figures(
    model: HIEROS, episodes: Sequence[Episode], horizon: int, stride: int, name: str = "state_probe"
) -> dict[str, float]:
    """How much of the simulator's state level 0's world model holds, filtered and predicted open loop.

    Every episode is cut into blocks of ``max(PROBE_BLOCK, 2 * horizon)`` steps; the blocks alternate between two
    folds. A linear probe (:func:`fit_state_probe`) from the world-state features of the posterior to the simulator
    state (:func:`physical_state`) is fitted on each fold and scored on the other: on the posterior states, and on
    the states imagined from every ``stride``-th posterior state over ``horizon`` steps with the actions the agent
    took (starts whose ``horizon`` steps stay inside their block, so no target was fitted on).

    :param model: the agent that played the episodes
    :param episodes: episodes of any behaviour (deterministic and sampled together cover more states)
    :param horizon: open-loop steps
    :param stride: a start every ``stride`` steps
    :param name: the figures' prefix
    :return: per state entry d, ``<name>/posterior_r2/s{d}`` (the share of its variance the probe of the
        posterior explains), ``<name>/observation_r2/s{d}`` (the same from the last two observations themselves,
        flattened: the linear read-out without a world model; array observations) and
        ``<name>/open_loop_vs_repeat/s{d}`` (the open-loop prediction's mean squared error over steps 1..H against
        that of repeating the start state; below 1: the model predicts the motion), and each over all entries
        (``posterior_r2`` and ``observation_r2`` their mean, ``open_loop_vs_repeat`` the ratio of the summed
        errors, each entry in units of its spread); nothing where a state is missing
    """
    if not episodes or any(s is None for e in episodes for s in e.states):
        return {}
    wm = model.policy.hierarchy.levels[0].world_model
    block = max(PROBE_BLOCK, 2 * horizon)
    features = np.concatenate(
        [wm.features(stack_states(e.latents[0], 0).flatten_batch()).double().numpy() for e in episodes]
    )  # (T, P)
    states = np.concatenate([np.stack(e.states) for e in episodes])  # (T, S)
    fold = np.concatenate([(np.arange(len(e.states)) // block) % 2 for e in episodes])
    if fold.all() or not fold.any():
        return {}
    probes = [fit_state_probe(features[fold == k], states[fold == k], block) for k in (0, 1)]
    spread = np.maximum(states.std(0), 1e-12)

    def out_of_fold_r2(inputs: np.ndarray, fitted: Sequence[Callable[[np.ndarray], np.ndarray]]) -> np.ndarray:
        predicted = np.empty_like(states)
        for k in (0, 1):
            predicted[fold == k] = fitted[1 - k](inputs[fold == k])
        return r2_per_entry(predicted, states)

    r2 = out_of_fold_r2(features, probes)
    out = {f"{name}/posterior_r2/s{d}": float(v) for d, v in enumerate(r2)}
    out[f"{name}/posterior_r2"] = float(r2.mean())
    if all(isinstance(o, np.ndarray) for e in episodes for o in e.observations):
        # the same probe from the last two observations themselves: what a linear read-out gets without a world model
        pairs = np.concatenate(
            [
                np.concatenate([flat, np.concatenate([flat[:1], flat[:-1]])], axis=1)
                for flat in (np.stack(e.observations).reshape(len(e.observations), -1) for e in episodes)
            ]
        )  # (T, 2 * prod(obs_shape))
        raw = out_of_fold_r2(pairs, [fit_state_probe(pairs[fold == k], states[fold == k], block) for k in (0, 1)])
        out.update({f"{name}/observation_r2/s{d}": float(v) for d, v in enumerate(raw)})
        out[f"{name}/observation_r2"] = float(raw.mean())
    error, repeat = np.zeros(len(spread)), np.zeros(len(spread))
    for k in (0, 1):
        starts = [
            (e, t)
            for e in episodes
            for t in range(0, len(e.states) - horizon, stride)
            if (t // block) % 2 == k and t % block + horizon < block
        ]
        if not starts:
            continue
        start_states = np.stack([e.states[t] for e, t in starts])  # (N, S)
        for j, state in open_loop(wm, starts, horizon):
            truth = np.stack([e.states[t + j + 1] for e, t in starts])  # (N, S)
            error += (((probes[1 - k](wm.features(state).double().numpy()) - truth) / spread) ** 2).sum(0)
            repeat += (((start_states - truth) / spread) ** 2).sum(0)
    if repeat.any():
        ratio = error / np.maximum(repeat, 1e-12)
        out.update({f"{name}/open_loop_vs_repeat/s{d}": float(v) for d, v in enumerate(ratio)})
        out[f"{name}/open_loop_vs_repeat"] = float(error.sum() / repeat.sum())
    return out


def _corr(x: np.ndarray, y: np.ndarray) -> float:
    """Pearson correlation of two series; NaN where either is constant."""
    return float(np.corrcoef(x, y)[0, 1]) if np.std(x) > 0 and np.std(y) > 0 else float("nan")


def _slope(model_diff: np.ndarray, env_diff: np.ndarray) -> float:
    """Least-squares slope of the model's differences onto the environment's (through the origin)."""
    denominator = float((env_diff**2).sum())
    return float((model_diff * env_diff).sum() / denominator) if denominator > 0 else float("nan")


@th.no_grad()
def action_response_figures(
    model: HIEROS, suite: str, task: str, seeds: Sequence[int], episodes: Sequence[Episode], steps: int, stride: int
) -> dict[str, float]:
    """How strongly level 0's world model responds to its actions, against the real environment.

    Each episode is replayed in a fresh environment (same seed, the recorded actions); at every ``stride``-th step a
    copy of the environment and the world model (from the posterior state, open loop, deterministic) are driven
    ``steps`` steps with the action held at +1 and at -1 (the bounds of a Box action space).

    :param model: the agent that played ``episodes``
    :param suite: suite of the task (for :func:`benchmarks.suites.make_env`)
    :param task: the task
    :param seeds: the reset seed of each episode
    :param episodes: episodes played by :func:`play`
    :param steps: steps of each driven branch
    :param stride: a start every ``stride`` steps
    :return: ``world_model/action_slope_obs{d}`` per entry of a vector observation, ``world_model/action_slope_reward``
        and ``world_model/action_corr_reward``; nothing for other action spaces
    """
    if not isinstance(model.action_space, spaces.Box):
        return {}
    policy = model.policy
    wm = policy.hierarchy.levels[0].world_model
    vector = isinstance(model.observation_space, spaces.Box) and len(model.observation_space.shape) == 1
    n_act = int(np.prod(model.action_space.shape))
    held = {sign: th.full((1, n_act), float(sign)) for sign in (1, -1)}
    env_obs, wm_obs, env_rew, wm_rew = [], [], [], []
    for seed, e in zip(seeds, episodes, strict=True):
        env = make_env(suite, task, seed=seed)
        env.reset(seed=seed)
        for t, action in enumerate(e.actions[: len(e.rewards) - steps]):
            if t % stride == 0:
                branches = {}
                for sign, act in held.items():
                    # a pixel env's copy renders the original's frame (gymnasium's AddRenderObservation keeps a
                    # closure over its own wrapper); only its rewards and vector observations are read
                    copy, state = deepcopy(env), e.latents[0][t]
                    real_o, real_r, model_o, model_r = [], [], [], []
                    for _ in range(steps):
                        obs, reward, *_ = copy.step(policy.env_actions(act)[0])
                        state, _ = wm.img_step(state, act, deterministic=True)
                        real_r.append(float(reward))
                        model_r.append(float(wm.reward(state)[0]))
                        if vector:
                            real_o.append(np.asarray(obs, dtype=np.float64))
                            model_o.append(wm.decode(state)[0].double().numpy())
                    copy.close()
                    branches[sign] = (real_o, real_r, model_o, model_r)
                plus, minus = branches[1], branches[-1]
                env_rew += list(np.subtract(plus[1], minus[1]))
                wm_rew += list(np.subtract(plus[3], minus[3]))
                if vector:
                    env_obs += list(np.subtract(plus[0], minus[0]))
                    wm_obs += list(np.subtract(plus[2], minus[2]))
            _, reward, *_ = env.step(policy.env_actions(th.as_tensor(action, dtype=th.float32)[None])[0])
            if not math.isclose(float(reward), e.rewards[t], rel_tol=1e-6, abs_tol=1e-9):
                raise RuntimeError(
                    f"{task}: replaying the episode of seed {seed} gave reward {float(reward)!r} at step {t} where it "
                    f"gave {e.rewards[t]!r}; the action response needs an environment that replays deterministically"
                )
        env.close()
    real_r, model_r = np.array(env_rew), np.array(wm_rew)
    out = {"world_model/action_slope_reward": _slope(model_r, real_r)}
    out["world_model/action_corr_reward"] = _corr(model_r, real_r)
    if env_obs:
        real_o, model_o = np.stack(env_obs), np.stack(wm_obs)  # (starts * steps, D)
        for d in range(real_o.shape[1]):
            out[f"world_model/action_slope_obs{d}"] = _slope(model_o[:, d], real_o[:, d])
    return out


def critic_figures(model: HIEROS, episodes: Sequence[Episode]) -> dict[str, float]:
    """Level 0's extrinsic value at each visited state against the realised discounted return.

    :param model: the agent
    :param episodes: held-out episodes
    :return: mean value, mean return, bias (value - return) and their correlation
    """
    gamma = model.policy.hierarchy.levels[0].actor_critic.discount
    values, returns = [], []
    for e in episodes:
        g = e.values[-1] if e.truncated else 0.0
        realised = []
        for r in reversed(e.rewards):
            g = r + gamma * g
            realised.append(g)
        values += e.values
        returns += realised[::-1]
    v, r = np.array(values), np.array(returns)
    corr = _corr(v, r)
    return {
        "critic/value_mean": float(v.mean()),
        "critic/return_mean": float(r.mean()),
        "critic/bias": float((v - r).mean()),
        "critic/correlation": corr,
    }


def normaliser_figures(model: HIEROS) -> dict[str, float]:
    """The return scale of every reward term of every level."""
    out = {}
    hierarchy = model.policy.hierarchy
    for i in range(hierarchy.n_levels):
        ac = hierarchy.levels[i].actor_critic
        for name in ac.active_terms:
            out[f"level{i}/return_scale/{name}"] = float(ac.return_scale(name))
    return out


@contextlib.contextmanager
def _recorded_samples(actor: th.nn.Module) -> Iterator[list[th.Tensor]]:
    """Within the block, every action sampled from ``actor``'s distributions is appended to the yielded list (the
    per-step tensors the imagined rollout is built from, so gradients can be taken with respect to them)."""
    drawn: list[th.Tensor] = []
    forward = actor.forward

    def recording(*args: Any, **kwargs: Any) -> Any:
        dist = forward(*args, **kwargs)
        sample = dist.sample

        def sample_and_record(*a: Any, **k: Any) -> th.Tensor:
            x = sample(*a, **k)
            drawn.append(x)
            return x

        dist.sample = sample_and_record
        return dist

    actor.forward = recording
    try:
        yield drawn
    finally:
        del actor.forward


def _grad_norm(loss: th.Tensor, params: Sequence[th.Tensor]) -> float:
    grads = th.autograd.grad(loss, params, retain_graph=True, allow_unused=True)
    return math.sqrt(sum(float((g.float() ** 2).sum()) for g in grads if g is not None))


def _imagined_advantages(
    ac: Any, imagined: Any, rewards: dict[str, th.Tensor], dynamics: bool, value_gradient: str | None = None
) -> tuple[th.Tensor, dict[str, th.Tensor]]:
    """The discount weights of an imagined rollout and each reward term's normalised advantage
    ``alpha_k (R^k - v^k) / S_k`` as the actor loss has them (eq. 4.3, 4.9).

    :param ac: the level's actor-critic
    :param imagined: the level's imagined trajectory (``features``, ``continues``), (H + 1, N, ...)
    :param rewards: per term the imagined rewards, (H + 1, N)
    :param dynamics: the critics' values keep the graph to the features (dynamics backpropagation) instead of being
        detached (REINFORCE)
    :param value_gradient: with ``dynamics``, the values that keep the graph (``ActorCriticConfig.value_gradient``:
        ``"all"``, ``"returns"``, ``"none"``); None: the actor-critic's own setting
    :return: weights (H, N) and per term advantages (H, N)
    """
    chosen = ac.value_gradient if value_gradient is None else value_gradient
    differentiable = dynamics and chosen != "none"
    feats, cont = imagined.features, imagined.continues
    continues = th.cat([th.ones_like(cont[:1]), cont[1:].detach()], 0)
    weight = cumulative_discount(continues, ac.discount)[:-1]
    advantages = {}
    for name, alpha in ac.reward_weights.items():
        critic = ac.critics[name]
        values = critic.value(feats, detach_params=True) if differentiable else critic.value(feats.detach()).detach()
        returns = lambda_returns(rewards[name][1:], values[:-1], continues[1:], values[-1], ac.discount, ac.lambda_)
        baseline = values[:-1] if chosen == "all" else values[:-1].detach()
        advantages[name] = alpha * (returns - baseline) / ac.return_scale(name)
    return weight, advantages


def _box_and_vector(model: HIEROS) -> bool:
    """Box actions and a flat vector observation: the spaces the state-feedback figures are defined for."""
    space = model.observation_space
    return isinstance(model.action_space, spaces.Box) and isinstance(space, spaces.Box) and len(space.shape) == 1


def _stacked_observations(episodes: Sequence[Episode]) -> np.ndarray:
    """The episodes' observations, concatenated in play order: (N, D)."""
    return np.concatenate([np.stack(e.observations) for e in episodes])


def _linear_fit(obs: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares fit ``target ~ K obs + c`` and the share of the target's variance it explains.

    :param obs: (N, D)
    :param target: (N,) or (N, A)
    :return: coefficients (D + 1[, A]) with the constant last, and R^2 (NaN for a constant target)
    """
    design = np.concatenate([obs, np.ones((len(obs), 1))], 1)  # (N, D + 1)
    coef, *_ = np.linalg.lstsq(design, target, rcond=None)
    residual = ((target - design @ coef) ** 2).sum()
    spread = ((target - target.mean(0)) ** 2).sum()
    varies = np.ptp(target, axis=0).max() > 0  # a constant target has no variance to explain
    return coef, float(1.0 - residual / spread) if varies else math.nan


def ascent_figures(
    model: HIEROS, episodes: Sequence[Episode], chosen: th.Tensor, ascent: th.Tensor
) -> dict[str, float]:
    """Which way the imagined objective pulls the first action, against the observation at its start state.

    ``ascent`` is minus the actor loss's gradient on the first imagined action of each rollout: the direction in
    which the world model and the critics say the action should move. Its correlation with each observation entry
    (over the start states) is the state feedback the objective asks for, to be read beside the feedback the policy
    has (``level0/feedback_gain_*``): a correlation the policy's gains do not show is a change the actor is asked to
    make and has not made.

    :param model: the agent (Box actions and a flat vector observation, else no figures)
    :param episodes: the episodes whose level-0 states started the rollouts, in the order the starts were stacked
    :param chosen: (N,) indices of the start states used, into that stacking
    :param ascent: (N, A) ascent directions of the first imagined action
    :return: ``level0/ascent_corr_a{j}_obs{k}`` for at most :data:`MAX_FEEDBACK_GAINS` pairs
    """
    if not _box_and_vector(model):
        return {}
    obs = _stacked_observations(episodes)[chosen.numpy()]  # (N, D)
    pull = ascent.detach().float().reshape(ascent.shape[0], -1).numpy()  # (N, A)
    if obs.shape[1] * pull.shape[1] > MAX_FEEDBACK_GAINS:
        return {}
    out = {}
    for j in range(pull.shape[1]):
        for k in range(obs.shape[1]):
            out[f"level0/ascent_corr_a{j}_obs{k}"] = _corr(pull[:, j], obs[:, k])
    return out


def actor_objective_figures(model: HIEROS, episodes: Sequence[Episode], max_starts: int = 512) -> dict[str, float]:
    """Per level, how much each reward term (and the entropy bonus) pulls on the actor (eq. 4.3, 4.9).

    The posterior states of ``episodes`` start imagined rollouts of ``imag_horizon`` steps as in training, with the
    subgoal in force at each state held fixed. Each active term k contributes ``alpha_k (R^k - v^k) / S_k`` to the
    advantage; the figure ``grad_share/<k>`` is the norm of the gradient of its weighted mean on the actor's
    parameters, divided by the sum of those norms over the terms and the entropy bonus.

    :param model: the agent
    :param episodes: episodes whose states start the rollouts (sampled actions, as in training)
    :param max_starts: at most this many start states (drawn without replacement)
    :return: figures
    """
    policy = model.policy
    hierarchy = policy.hierarchy
    out: dict[str, float] = {}
    generator = th.Generator().manual_seed(0)
    for i in range(len(episodes[0].latents)):
        level = hierarchy.levels[i]
        ac = level.actor_critic
        latents = [
            s
            for e in episodes
            for s, up in zip(e.latents[i], e.updated[i] if i else [True] * len(e.latents[i]), strict=True)
            if up
        ]
        codes = None
        if i < hierarchy.n_levels - 1:
            codes = th.stack(
                [
                    c
                    for e in episodes
                    for c, up in zip(e.codes[i + 1], e.updated[i] if i else [True] * len(e.codes[i + 1]), strict=True)
                    if up
                ]
            )
        start = stack_states(latents, 0).flatten_batch()
        n = int(start.batch_shape[0])
        chosen = th.randperm(n, generator=generator)[:max_starts]
        start = start.select(chosen).detach()
        if codes is not None:
            codes = codes[chosen]
        dynamics = level.imag_gradient == "dynamics"
        policy.set_training_mode(True)
        with th.enable_grad(), _recorded_samples(ac.actor) as drawn:
            imagined = level.imagine(start, codes)
            rewards = level.imagined_rewards(imagined)
            w, advantages = _imagined_advantages(ac, imagined, rewards, dynamics)
            params = list(ac.actor_parameters())
            dist = ac.actor(imagined.features.detach()[:-1])
            norms, total = {}, 0.0
            for name, advantage in advantages.items():
                objective = advantage if dynamics else dist.log_prob(imagined.actions.detach()) * advantage.detach()
                term = -(w * objective).mean()
                total = total + term
                norms[name] = _grad_norm(term, params)
                out[f"level{i}/advantage_std/{name}"] = float(advantage.detach().std())
            entropy_term = -(w * ac.entropy_coef * dist.entropy()).mean()
            norms["entropy"] = _grad_norm(entropy_term, params)
            if dynamics:
                grads = th.autograd.grad(total + entropy_term, drawn)  # per imagined step, (N, A)
                per_step = [float(g.reshape(g.shape[0], -1).norm(dim=-1).mean()) for g in grads]
                out[f"level{i}/action_grad_first"] = float(per_step[0])
                out[f"level{i}/action_grad_last"] = float(per_step[-1])
                if i == 0:
                    out.update(ascent_figures(model, episodes, chosen, -grads[0]))
        policy.set_training_mode(False)
        norm_sum = sum(norms.values()) or 1.0
        for name, value in norms.items():
            out[f"level{i}/grad_norm/{name}"] = value
            out[f"level{i}/grad_share/{name}"] = value / norm_sum
    return out


def pull_figures(model: HIEROS, episodes: Sequence[Episode], starts: int = 128, samples: int = 16) -> dict[str, float]:
    """Is the imagined objective's pull on the first action noise, or a consistent function of the state?

    ``starts`` level-0 posterior states of ``episodes`` are each imagined ``samples`` times as training does (dynamics
    backpropagation), and the pull on the first imagined action (minus the actor loss's gradient on it, every reward
    term) is taken per rollout. Reported for the first action entry: the per-sample signal-to-noise ratio
    ``mean^2 / var`` over a start's samples (median over starts), the split-half reliability (correlation over starts
    of the means of the two halves of the samples) and the share of the variance of the per-start mean that a linear
    function of the observation explains (R^2). A reliable pull that the observation does not explain comes from
    something other than the physical state (the latent's memory, the subgoal, model error).

    The pull is also split by its path: through the imagined rewards alone (the critics' values detached from the
    features) and through the critics' values (the rest). ``pull_critic_share`` is the critic path's share of the sum
    of both paths' squared pulls; each path has its split-half reliability and observation R^2, and
    ``pull_paths_corr`` correlates the two paths' per-start means.

    :param model: the agent (Box actions, a flat vector observation and dynamics backpropagation at level 0, else no
        figures)
    :param episodes: episodes whose level-0 states start the rollouts
    :param starts: start states (drawn without replacement)
    :param samples: rollouts per start (>= 4)
    :return: ``level0/pull_snr``, ``level0/pull_split_half``, ``level0/pull_obs_r2``, and per path
        ``level0/pull_{reward,critic}_split_half`` and ``_obs_r2``, ``level0/pull_critic_share``,
        ``level0/pull_paths_corr``
    """
    level = model.policy.hierarchy.levels[0]
    if level.imag_gradient != "dynamics" or not _box_and_vector(model) or samples < 4:
        return {}
    hierarchy, ac = model.policy.hierarchy, level.actor_critic
    latents = [s for e in episodes for s in e.latents[0]]
    chosen = th.randperm(len(latents), generator=th.Generator().manual_seed(0))[:starts]
    repeated = chosen.repeat_interleave(samples)
    start = stack_states(latents, 0).flatten_batch().select(repeated).detach()
    codes = th.stack([c for e in episodes for c in e.codes[1]])[repeated] if hierarchy.n_levels > 1 else None
    model.policy.set_training_mode(True)
    with th.enable_grad(), _recorded_samples(ac.actor) as drawn:
        imagined = level.imagine(start, codes)
        rewards = level.imagined_rewards(imagined)
        pulls = []
        for value_gradient in (None, "none"):
            weight, advantages = _imagined_advantages(ac, imagined, rewards, True, value_gradient)
            loss = th.zeros(())
            for advantage in advantages.values():
                loss = loss - (weight * advantage).mean()
            pull = -th.autograd.grad(loss, drawn[0], retain_graph=value_gradient is None)[0]
            pulls.append(pull.detach().float().reshape(len(chosen), samples, -1)[..., 0].numpy())  # (starts, samples)
    model.policy.set_training_mode(False)
    pull_np, reward_np = pulls
    critic_np = pull_np - reward_np
    obs = _stacked_observations(episodes)[chosen.numpy()]
    half = samples // 2

    def split_half(x: np.ndarray) -> float:
        return _corr(x[:, :half].mean(1), x[:, half:].mean(1))

    mean, var = pull_np.mean(1), pull_np.var(1, ddof=1)
    out = {
        "level0/pull_snr": float(np.median(mean**2 / np.maximum(var, 1e-30))),
        "level0/pull_split_half": split_half(pull_np),
        "level0/pull_obs_r2": _linear_fit(obs, mean)[1],
        "level0/pull_critic_share": float(
            (critic_np**2).sum() / max((critic_np**2).sum() + (reward_np**2).sum(), 1e-30)
        ),
        "level0/pull_paths_corr": _corr(reward_np.mean(1), critic_np.mean(1)),
    }
    for name, path in (("reward", reward_np), ("critic", critic_np)):
        out[f"level0/pull_{name}_split_half"] = split_half(path)
        out[f"level0/pull_{name}_obs_r2"] = _linear_fit(obs, path.mean(1))[1]
    return out


@th.no_grad()
def imagination_figures(model: HIEROS, episodes: Sequence[Episode], stride: int) -> dict[str, float]:
    """Closed-loop imagination against what followed: level 0's imagined extrinsic rewards against the real ones.

    From the posterior state at every ``stride``-th step ``t`` of each episode with ``imag_horizon`` steps left, level
    0 imagines as training does (its actor sampling actions in the world model, the subgoal in force held fixed);
    its imagined rewards at steps 1..H are set beside the rewards the episode received at t..t+H-1, which came from
    the same policy (sampled actions) in the real environment. A world model whose closed-loop imagination drifts to
    worse (better) states than the policy reaches shows a negative (positive) reward bias growing with the step.

    :param model: the agent
    :param episodes: episodes played with sampled actions (the behaviour imagination imitates)
    :param stride: start every this many steps
    :return: ``imagination/reward_imagined`` and ``reward_real`` (mean per step), ``reward_bias_first`` and
        ``reward_bias_last`` (imagined minus real at the first and the last imagined step), ``starts``
    """
    hierarchy = model.policy.hierarchy
    level = hierarchy.levels[0]
    horizon = level.config.imag_horizon
    latents, codes, real = [], [], []
    for e in episodes:
        for t in range(0, len(e.rewards) - horizon + 1, stride):
            latents.append(e.latents[0][t])
            if hierarchy.n_levels > 1:
                codes.append(e.codes[1][t])
            real.append(e.rewards[t : t + horizon])
    if not latents:
        return {}
    start = stack_states(latents, 0).flatten_batch().detach()
    imagined = level.imagine(start, th.stack(codes) if codes else None)
    rewards = imagined.rewards[1:].float().numpy().T  # (N, H): the reward of imagined steps 1..H
    real_np = np.array(real)  # (N, H)
    bias = (rewards - real_np).mean(0)  # (H,)
    return {
        "imagination/reward_imagined": float(rewards.mean()),
        "imagination/reward_real": float(real_np.mean()),
        "imagination/reward_bias_first": float(bias[0]),
        "imagination/reward_bias_last": float(bias[-1]),
        "imagination/starts": float(len(latents)),
    }


def analyse(
    model: HIEROS, suite: str, task: str, episodes: int, seed: int, horizon: int, stride: int, response_steps: int
) -> dict[str, float]:
    """Every figure of the module docstring for one model.

    :return: name -> value
    """
    env = make_env(suite, task, seed=seed)
    th.manual_seed(seed)
    greedy = [play(model, env, seed + j, True) for j in range(episodes)]
    sampled = [play(model, env, seed + episodes + j, False) for j in range(episodes)]
    randomly = [play(model, env, seed + 2 * episodes + j, False, random_actions=True) for j in range(episodes)]
    env.close()
    out = {
        "return/deterministic": float(np.mean([e.total for e in greedy])),
        "return/sampled": float(np.mean([e.total for e in sampled])),
    }
    out.update(out_of_view_figures(task, greedy, sampled))
    out.update(action_figures(model, greedy))
    out.update(feedback_figures(model, greedy))
    out.update(open_loop_figures(model, greedy, horizon, stride))
    out.update(state_probe_figures(model, [*greedy, *sampled], horizon, stride, "state_probe/agent"))
    out.update(state_probe_figures(model, randomly, horizon, stride, "state_probe/random"))
    seeds = [seed + j for j in range(episodes)]
    out.update(action_response_figures(model, suite, task, seeds, greedy, response_steps, stride))
    out.update(critic_figures(model, greedy))
    out.update(imagination_figures(model, sampled, stride))
    out.update(normaliser_figures(model))
    out.update(actor_objective_figures(model, sampled))
    out.update(pull_figures(model, sampled))
    return out


def _named_models(items: Sequence[str]) -> list[tuple[str, pathlib.Path]]:
    named = []
    for item in items:
        name, _, path = item.rpartition("=") if "=" in item else (pathlib.Path(item).parent.name, "", item)
        if not pathlib.Path(path).exists():
            raise ValueError(f"model file {path!r} does not exist (argument {item!r}; expected PATH or NAME=PATH)")
        named.append((name or path, pathlib.Path(path)))
    if len({n for n, _ in named}) != len(named):
        raise ValueError(f"model names must be distinct, got {[n for n, _ in named]}")
    return named


def main(argv: Sequence[str] | None = None) -> dict[str, dict[str, float]]:
    """Analyse every model given and print one table with a column per model, then ``model/name: value`` lines.

    :return: model name -> figures
    """
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("models", nargs="+", help="HIEROS saves, as PATH or NAME=PATH")
    parser.add_argument("--suite", required=True, choices=sorted(SUITES))
    parser.add_argument("--task", required=True)
    parser.add_argument("--episodes", type=int, default=3, help="deterministic and sampled episodes each")
    parser.add_argument("--seed", type=int, default=20_000, help="seed of the first held-out episode")
    parser.add_argument("--horizon", type=int, default=15, help="open-loop steps of the world-model check")
    parser.add_argument("--stride", type=int, default=10, help="steps between two open-loop starts")
    parser.add_argument("--response-steps", type=int, default=5, help="steps of each action-response branch")
    args = parser.parse_args(argv)
    for name in ("episodes", "horizon", "stride", "response_steps"):
        if getattr(args, name) < 1:
            raise ValueError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    models = _named_models(args.models)
    print(environment_header())
    th.set_num_threads(1)
    results = {}
    for name, path in models:
        model = HIEROS.load(path, device="cpu")
        results[name] = analyse(
            model, args.suite, args.task, args.episodes, args.seed, args.horizon, args.stride, args.response_steps
        )
    keys = sorted({k for r in results.values() for k in r})
    print("\n| figure | " + " | ".join(results) + " |\n|---|" + "---:|" * len(results))
    for key in keys:
        cells = [f"{r[key]:.4g}" if key in r else "-" for r in results.values()]
        print(f"| {key} | " + " | ".join(cells) + " |")
    print()
    for name, figures in results.items():
        for key, value in figures.items():
            print(f"{name}/{key}: {value:g}")
    return results


if __name__ == "__main__":
    main()
