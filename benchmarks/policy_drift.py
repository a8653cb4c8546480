"""How the level-0 policy of a Box task moves while HIEROS learns: its action statistics per window of agent steps.

:mod:`benchmarks.control_failures` looks at saved models; this script watches one training run as
:mod:`benchmarks.cpu_suite` makes it (the same task names, env, ``preset="small"`` plus ``--hieros-kwargs`` and seed,
without the suite's evaluations) and reports, for every ``--window`` agent steps:

* ``taken_at_bounds``: the share of the actions taken (the buffer's action, in [-1, 1]) with ``|a| > 0.95``
  (:data:`AT_BOUNDS`); uniformly random actions, as in the warm-up, give 0.05;
* ``mode_mean``, ``mode_abs``, ``mode_at_bounds``: the mean, mean absolute value and share at the bounds of the
  deterministic action (the policy's mode) in the states the agent acted in, and ``std``, the policy's mean
  standard deviation there, also during the warm-up, where the untrained policy is computed but not followed;
* ``mode_spread`` and ``mode_state_r2``: how the mode depends on the state within the window: its standard deviation
  over the window's states, and the share of its variance that a linear fit on the simulator's state explains
  (:func:`benchmarks.control_failures.physical_state`, read before each action; tasks that expose it). A constant
  push has no spread; a controller that reacts to the state has spread and, where it is near linear, a high R^2;
* ``reward``: the mean reward per agent step;
* ``cart_out_of_view`` (DMC cartpole tasks): the share of steps whose cart is out of the pixel camera's view
  (:data:`benchmarks.control_failures.CARTPOLE_OUT_OF_VIEW`), from the simulator state;
* ``warmup``: the share of the window's steps with uniformly random actions (before
  :attr:`~sb3_hieros.HIEROS.actors_start`, the later of ``learning_starts`` and ``actor_learning_starts``);
* ``actor_grad_norm``: the level-0 actor's gradient norm logged last (``train/level0/actor/grad_norm``), where logged.

Example (the first 1300 steps of the RSSM setting with four world-model updates from proprioception)::

    python -m benchmarks.policy_drift --task cartpole-balance-proprio --seed 0 --steps 1300 --hieros-kwargs
        '{"config_overrides": {"world_model": {"kind": "rssm"}, "world_model_updates": 4}}'   # (one line)
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.callbacks import BaseCallback

from benchmarks._cli import json_object
from benchmarks._timing import environment_header
from benchmarks.control_failures import _level_goal, _linear_fit, cart_out_of_view, physical_state
from benchmarks.cpu_suite import TASKS, task_vec_env
from benchmarks.suites import SUITE_POLICIES
from sb3_hieros import HIEROS

os.environ.setdefault("MUJOCO_GL", "egl")

__all__ = ["AT_BOUNDS", "FIGURES", "PolicyDrift", "main", "run_drift", "window_figures"]

#: An action entry in [-1, 1] whose absolute value exceeds this is counted as at the bounds.
AT_BOUNDS = 0.95
#: The figures of a window, in the order of the printed table (``cart_out_of_view`` and ``actor_grad_norm`` only
#: where they apply, ``mode_state_r2`` where the task exposes its state).
FIGURES = (
    "warmup",
    "taken_at_bounds",
    "mode_mean",
    "mode_abs",
    "mode_at_bounds",
    "mode_spread",
    "mode_state_r2",
    "std",
    "reward",
    "cart_out_of_view",
    "actor_grad_norm",
)


def window_figures(
    taken: np.ndarray,
    mode: np.ndarray,
    std: np.ndarray,
    rewards: np.ndarray,
    warmup: np.ndarray,
    cart_positions: np.ndarray | None = None,
    states: np.ndarray | None = None,
) -> dict[str, float]:
    """The figures of one window of steps (see the module's docstring).

    :param taken: (N, A) actions taken, in [-1, 1]
    :param mode: (N, A) the policy's deterministic action in the same states
    :param std: (N, A) the policy's standard deviation there
    :param rewards: (N,) rewards received
    :param warmup: (N,) True for steps with uniformly random actions
    :param cart_positions: (N,) cart positions on DMC cartpole tasks, else None
    :param states: (N, S) the simulator's state each action was chosen in, where the task exposes it, else None
    :return: figure name -> value
    """
    figures = {
        "warmup": float(np.mean(warmup)),
        "taken_at_bounds": float(np.mean(np.abs(taken) > AT_BOUNDS)),
        "mode_mean": float(np.mean(mode)),
        "mode_abs": float(np.mean(np.abs(mode))),
        "mode_at_bounds": float(np.mean(np.abs(mode) > AT_BOUNDS)),
        "mode_spread": float(np.mean(np.std(mode, axis=0))),
        "std": float(np.mean(std)),
        "reward": float(np.mean(rewards)),
    }
    if states is not None:
        figures["mode_state_r2"] = _linear_fit(states, mode)[1]
    if cart_positions is not None:
        figures["cart_out_of_view"] = cart_out_of_view(cart_positions)
    return figures


class PolicyDrift(BaseCallback):
    """Records, at every step of a one-env HIEROS run on a Box task, the action taken and the level-0 policy in the
    state it was taken in, and summarises every ``window`` steps into :attr:`rows` (:func:`window_figures` plus the
    step, the model's ``num_timesteps`` at the window's end).

    The simulator's state is read once per step, after it (:func:`benchmarks.control_failures.physical_state`): the
    env resets at an episode's end, so that read is the state the next action is chosen in, and the cart's position
    in it is the one the step reached (or the reset's, at an episode's end).

    :param window: agent steps per row
    :param cartpole: count the steps with the cart out of the camera's view (DMC cartpole tasks)
    """

    def __init__(self, window: int, cartpole: bool = False) -> None:
        super().__init__()
        if isinstance(window, bool) or not isinstance(window, int) or window < 1:
            raise ValueError(f"window must be an int >= 1, got {window!r}")
        self.window = window
        self.cartpole = cartpole
        self.rows: list[dict[str, float]] = []
        self._steps: dict[str, list[Any]] = {}
        self._state: np.ndarray | None = None  # the simulator's state the next action is chosen in

    def _init_callback(self) -> None:
        model = self.model
        if not isinstance(model, HIEROS):
            raise TypeError(f"PolicyDrift watches a HIEROS run, got {type(model).__name__}")
        if not isinstance(model.action_space, spaces.Box):
            raise ValueError(f"PolicyDrift needs Box actions, got {model.action_space}")
        if model.n_envs != 1:
            raise ValueError(f"PolicyDrift watches one env, got n_envs={model.n_envs}")
        self._clear()

    def _on_training_start(self) -> None:
        self._state = physical_state(self.training_env.envs[0])

    def _clear(self) -> None:
        self._steps = {name: [] for name in ("taken", "mode", "std", "rewards", "warmup", "cart", "states")}

    @th.no_grad()
    def _on_step(self) -> bool:
        model: Any = self.model
        hierarchy = model.policy.hierarchy
        state = model._hier  # the hierarchy state the action was just chosen in
        level0 = hierarchy.levels[0]
        feat, _, _ = level0.features(state.latents[0], _level_goal(hierarchy, 0, state.actions))
        dist = level0.actor_critic.actor(feat)
        steps = self._steps
        steps["taken"].append(np.asarray(self.locals["buffer_actions"], dtype=np.float64)[0])
        steps["mode"].append(dist.mode()[0].float().numpy())
        steps["std"].append(dist.std[0].float().numpy())
        steps["rewards"].append(float(np.asarray(self.locals["rewards"])[0]))
        # num_timesteps counts this step already; its action was random if it was taken before the actors started
        steps["warmup"].append(self.num_timesteps - 1 < model.actors_start)
        if self._state is not None:
            steps["states"].append(self._state)
        self._state = physical_state(self.training_env.envs[0])
        if self.cartpole:
            steps["cart"].append(float(self._state[0]))
        if self.num_timesteps % self.window == 0:
            row = {"step": float(self.num_timesteps)}
            row.update(
                window_figures(
                    np.stack(steps["taken"]),
                    np.stack(steps["mode"]),
                    np.stack(steps["std"]),
                    np.asarray(steps["rewards"]),
                    np.asarray(steps["warmup"]),
                    np.asarray(steps["cart"]) if self.cartpole else None,
                    np.stack(steps["states"]) if len(steps["states"]) == len(steps["mode"]) else None,
                )
            )
            logged = model.logger.name_to_value.get("train/level0/actor/grad_norm")
            if logged is not None:
                row["actor_grad_norm"] = float(logged)
            self.rows.append(row)
            self._clear()
        return True


def run_drift(
    task: str, seed: int, steps: int, window: int, hieros_kwargs: dict[str, Any] | None = None
) -> list[dict[str, float]]:
    """Train HIEROS on a CPU-suite task as :mod:`benchmarks.cpu_suite` does (without its evaluations) and return the
    rows of :class:`PolicyDrift`.

    :param task: a key of :data:`benchmarks.cpu_suite.TASKS` with Box actions
    :param seed: seed of the model and the training env
    :param steps: agent steps to train
    :param window: agent steps per row
    :param hieros_kwargs: HIEROS keywords on top of ``preset="small"``
    :return: one row per window
    """
    if task not in TASKS:
        raise ValueError(f"unknown task {task!r}; expected one of {sorted(TASKS)}")
    spec = TASKS[task]
    drift = PolicyDrift(window, cartpole=spec.suite.startswith("dmc") and spec.task.startswith("cartpole-"))
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < window:
        raise ValueError(f"steps must be an int >= window ({window}), got {steps!r}")
    env = task_vec_env(spec, 1, seed)
    if not isinstance(env.action_space, spaces.Box):
        env.close()
        raise ValueError(f"task {task!r} has {env.action_space} actions; policy_drift needs Box actions")
    model = HIEROS(SUITE_POLICIES[spec.suite], env, seed=seed, **{"preset": "small", **(hieros_kwargs or {})})
    model.learn(steps, callback=drift)
    env.close()
    return drift.rows


def main(argv: Sequence[str] | None = None) -> list[dict[str, float]]:
    """Run one task and seed, print the table (a row per window) and write the rows to ``--out`` as JSON.

    :return: the rows
    """
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", required=True, choices=[name for name in TASKS if name != "CartPole-v1"])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--steps", type=int, default=3000, help="agent steps to train")
    parser.add_argument("--window", type=int, default=100, help="agent steps per row")
    parser.add_argument("--hieros-kwargs", type=json_object, default={}, help="JSON dict of HIEROS keywords")
    parser.add_argument("--out", default=None, help="JSON file for the rows")
    args = parser.parse_args(argv)
    print(environment_header())
    th.set_num_threads(1)
    rows = run_drift(args.task, args.seed, args.steps, args.window, args.hieros_kwargs)
    names = [name for name in FIGURES if any(name in row for row in rows)]
    print("\n| step | " + " | ".join(names) + " |\n|---:|" + "---:|" * len(names))
    for row in rows:
        cells = [f"{row[name]:.3g}" if name in row else "-" for name in names]
        print(f"| {int(row['step'])} | " + " | ".join(cells) + " |")
    if args.out:
        pathlib.Path(args.out).write_text(json.dumps(rows, indent=1) + "\n")
    return rows


if __name__ == "__main__":
    main()
