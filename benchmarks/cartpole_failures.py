"""Why a trained HIEROS agent's CartPole-v1 episodes end, and what level 0 believes on the way.

Loads a saved model (e.g. ``results/demo/model.zip`` from ``make demo``), plays ``--episodes`` episodes on seeds
``--seed``, ``--seed + 1``, ... (deterministic policy unless ``--stochastic``) and reports:

* how each episode ended: the cart left the track (``|x| > x_threshold``), the pole fell
  (``|theta| > theta_threshold``), or the 500-step time limit;
* per bin of the cart position |x|, level 0's mean predicted continue probability and extrinsic value
  (:meth:`sb3_hieros.policies.HierosPolicy.state_estimates` at the posterior state after each observation, with
  the subgoal in force).

``--reset-every R`` restarts the agent's hierarchical recurrent state every R steps (the env goes on), as if a new
episode began: training sees chunks of ``batch_length`` steps from a fresh state, acting a whole episode, so this
tells whether late-episode failures come from recurrent states longer than training ever saw.

Example::

    python -m benchmarks.cartpole_failures results/demo/model.zip --episodes 10
    python -m benchmarks.cartpole_failures results/demo/model.zip --episodes 10 --reset-every 16

The last lines print each figure as ``name: value``.
"""

from __future__ import annotations

import argparse
import itertools
import pathlib
from collections import defaultdict
from collections.abc import Sequence

import gymnasium as gym
import numpy as np
import torch as th

from benchmarks._timing import environment_header
from sb3_hieros import HIEROS

X_BINS = (0.0, 0.5, 1.0, 1.5, 2.0, 2.4)


def end_cause(obs: np.ndarray, terminated: bool, env: gym.Env) -> str:
    """``"x"`` (cart off the track), ``"theta"`` (pole fell) or ``"time_limit"`` for the last observation of an
    episode.

    :param obs: last observation ``(x, x_dot, theta, theta_dot)``
    :param terminated: the env's ``terminated`` flag
    :param env: the CartPole env (its thresholds)
    :return: the cause
    """
    if not terminated:
        return "time_limit"
    return "x" if abs(obs[0]) > env.unwrapped.x_threshold else "theta"


def play(
    model: HIEROS, env: gym.Env, seed: int, deterministic: bool, reset_every: int = 0
) -> tuple[np.ndarray, dict[str, np.ndarray], str]:
    """One episode on ``env`` (a CartPole-v1 env, reset here with ``seed``).

    :param model: the agent
    :param env: a CartPole-v1 env
    :param seed: seed of ``env.reset``
    :param deterministic: policy modes instead of samples
    :param reset_every: restart the agent's recurrent state every ``reset_every`` steps (0: only at the start)
    :return: observations ``(T, 4)`` the agent acted on, level 0's :meth:`state_estimates` at each of them
        (each ``(T,)``) and the end cause
    """
    obs, _ = env.reset(seed=seed)
    state = None
    seen, estimates = [], defaultdict(list)
    while True:
        t = len(seen)
        start = np.array([t == 0 or (reset_every > 0 and t % reset_every == 0)])
        action, state = model.predict(obs[None], state=state, episode_start=start, deterministic=deterministic)
        for name, value in model.policy.state_estimates(state).items():
            estimates[name].append(float(value[0]))
        seen.append(obs)
        obs, _, terminated, truncated, _ = env.step(int(action[0]))
        if terminated or truncated:
            return np.array(seen), {k: np.array(v) for k, v in estimates.items()}, end_cause(obs, terminated, env)


def main(argv: Sequence[str] | None = None) -> dict[str, float]:
    """Play the episodes, print the per-episode lines, the |x| table and the ``name: value`` figures.

    :return: the figures
    """
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model", type=pathlib.Path, help="a HIEROS save trained on CartPole-v1")
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--seed", type=int, default=10_000, help="seed of the first episode")
    parser.add_argument("--stochastic", action="store_true", help="sample actions instead of the policy mode")
    parser.add_argument(
        "--reset-every", type=int, default=0, help="restart the agent's recurrent state every N steps (0: never)"
    )
    args = parser.parse_args(argv)
    if args.episodes < 1:
        raise ValueError(f"--episodes must be >= 1, got {args.episodes}")
    if args.reset_every < 0:
        raise ValueError(f"--reset-every must be >= 0 (0: never), got {args.reset_every}")
    print(environment_header())
    model = HIEROS.load(args.model, device="cpu")
    if model.observation_space.shape != (4,) or getattr(model.action_space, "n", None) != 2:
        raise ValueError(
            f"{args.model} was not trained on CartPole-v1: observation space {model.observation_space}, "
            f"action space {model.action_space}"
        )
    th.manual_seed(args.seed)
    causes = {"x": 0, "theta": 0, "time_limit": 0}
    lengths, xs, conts, values = [], [], [], []
    env = gym.make("CartPole-v1")
    for i in range(args.episodes):
        obs, est, cause = play(model, env, args.seed + i, not args.stochastic, args.reset_every)
        causes[cause] += 1
        lengths.append(len(obs))
        xs.append(np.abs(obs[:, 0]))
        conts.append(est["continue"])
        values.append(est["value/extrinsic"])
        print(
            f"episode {i}: length {len(obs)}, end {cause}, last x {obs[-1, 0]:+.2f}, last theta {obs[-1, 2]:+.3f}, "
            f"value {values[-1][0]:.1f} at the start, {values[-1][-1]:.1f} at the end"
        )
    env.close()
    x, cont, value = np.concatenate(xs), np.concatenate(conts), np.concatenate(values)
    print("\n| abs(x) | steps | mean continue | mean extrinsic value |\n|---|---:|---:|---:|")
    for lo, hi in itertools.pairwise(X_BINS):
        inside = (x >= lo) & (x < hi)
        if inside.any():
            print(f"| {lo:.1f}-{hi:.1f} | {inside.sum()} | {cont[inside].mean():.3f} | {value[inside].mean():.1f} |")
    figures = {
        "mean_length": float(np.mean(lengths)),
        "ended_cart_off_track": float(causes["x"]),
        "ended_pole_fell": float(causes["theta"]),
        "ended_time_limit": float(causes["time_limit"]),
    }
    for name, v in figures.items():
        print(f"{name}: {v:g}")
    return figures


if __name__ == "__main__":
    main()
