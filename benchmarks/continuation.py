"""Continue a saved run, with its world models frozen or learning, and evaluate as it goes.

Does a trained agent's policy get better in the real environment when it is optimised further against what its own
world model and critics imagine? With ``--freeze-world-model`` the world models of every level stop learning
(learning rate 0, as rl-zoo's ``enjoy`` loads a model) while the actors and critics go on training on imagination
from the run's replay and from the data the continuing agent collects; without it everything goes on learning. A
higher ``--train-ratio`` than the run's gives more updates per environment step. If a frozen world model's
imagination were a faithful stand-in for the environment, more optimisation against it would not make the real
return worse.

Input: a folder of :mod:`benchmarks.train` run with ``--save-replay-buffer`` (``model.zip`` and
``replay_buffer.pkl``). The continuation trains on a fresh env seeded ``--seed`` and evaluates deterministic
episodes (reset with seeds ``--seed`` + 10,000, + 10,001, ...; the same episodes at every evaluation) before it starts
and every ``--eval-every`` agent steps: their return, and level 0's extrinsic value at the visited states against the
discounted return that followed them (as :func:`benchmarks.control_failures.critic_figures`). An imagination that
the policy exploits shows as a value that rises while the real return falls.

Run from the repo root: ``python -m benchmarks.continuation --run <folder> --suite dmc_proprio --task
cartpole-balance [--steps 2000] [--train-ratio 512] [--freeze-world-model] [--eval-every 250] [--eval-episodes 5]``.
The last lines print every figure as ``continuation/<name>: value``.
"""

from __future__ import annotations

import argparse
import pathlib
import time
from collections.abc import Sequence

import numpy as np

from benchmarks._timing import environment_header
from benchmarks.control_failures import critic_figures, play
from benchmarks.suites import SUITES, make_env
from benchmarks.train import EVAL_SEED_OFFSET, check_counts


def continue_run(
    run: str | pathlib.Path,
    suite: str,
    task: str,
    steps: int = 2000,
    train_ratio: float | None = None,
    freeze_world_model: bool = False,
    eval_every: int = 250,
    eval_episodes: int = 5,
    seed: int = 7,
    save: str | pathlib.Path | None = None,
) -> dict[str, float]:
    """Load ``run``'s model and replay, train ``steps`` more agent steps, evaluate every ``eval_every`` steps.

    :param run: folder holding ``model.zip`` and ``replay_buffer.pkl``
    :param suite: suite of :data:`benchmarks.suites.SUITES`
    :param task: task of that suite
    :param steps: further agent steps (>= 1)
    :param train_ratio: replayed steps per environment step from now on; None keeps the run's
    :param freeze_world_model: world-model learning rate 0 at every level
    :param eval_every: agent steps between evaluations (>= 1)
    :param eval_episodes: deterministic episodes per evaluation (>= 1)
    :param seed: seed of the training env (the evaluation episodes are reset with ``seed + EVAL_SEED_OFFSET + j``)
    :param save: where to save the continued model, or None
    :return: for 0 and every evaluation's steps: ``return_at_{steps}`` (mean of the evaluation's episodes),
        ``return_std_at_{steps}``, ``value_at_{steps}`` and ``discounted_return_at_{steps}`` (level 0's mean extrinsic
        value at the visited states and the realised discounted return from them); ``seconds``; ``level{i}_updates``
        made during the continuation
    """
    from stable_baselines3.common.monitor import Monitor

    from sb3_hieros import HIEROS

    if suite not in SUITES:
        raise ValueError(f"unknown suite {suite!r}; expected one of {sorted(SUITES)}")
    check_counts(steps=steps, eval_every=eval_every, eval_episodes=eval_episodes)
    folder = pathlib.Path(run)
    for name in ("model.zip", "replay_buffer.pkl"):
        if not (folder / name).is_file():
            raise ValueError(f"{folder} has no {name} (train the run with --save-replay-buffer)")
    env = Monitor(make_env(suite, task, seed=seed))
    eval_env = make_env(suite, task)
    custom = {"learning_rate": 0.0, "lr_schedule": lambda _: 0.0} if freeze_world_model else None
    overrides = {} if train_ratio is None else {"train_ratio": float(train_ratio)}
    model = HIEROS.load(folder / "model.zip", env=env, custom_objects=custom, config_overrides=overrides)
    model.load_replay_buffer(folder / "replay_buffer.pkl")
    updates_before = model.level_updates()
    print(
        f"{folder}: world-model learning rate {model.config.world_model.lr}, train ratio {model.config.train_ratio}, "
        f"replay {[buffer.size() for buffer in model.level_buffers()]}, level updates so far {updates_before}",
        flush=True,
    )
    figures: dict[str, float] = {}

    def evaluate(done: int) -> None:
        model.policy.set_training_mode(False)
        episodes = [play(model, eval_env, seed + EVAL_SEED_OFFSET + j, True) for j in range(eval_episodes)]
        returns = [e.total for e in episodes]
        critic = critic_figures(model, episodes)
        figures[f"return_at_{done}"] = float(np.mean(returns))
        figures[f"return_std_at_{done}"] = float(np.std(returns))
        figures[f"value_at_{done}"] = critic["critic/value_mean"]
        figures[f"discounted_return_at_{done}"] = critic["critic/return_mean"]
        print(
            f"after {done} steps: return {np.mean(returns):.1f} +- {np.std(returns):.1f}; level-0 extrinsic value "
            f"{critic['critic/value_mean']:.2f} at the visited states, realised discounted return "
            f"{critic['critic/return_mean']:.2f}",
            flush=True,
        )

    evaluate(0)
    start, done = time.perf_counter(), 0
    while done < steps:
        chunk = min(eval_every, steps - done)
        model.learn(chunk, reset_num_timesteps=False)
        done += chunk
        evaluate(done)
    figures["seconds"] = time.perf_counter() - start
    for i, (after, before) in enumerate(zip(model.level_updates(), updates_before, strict=True)):
        figures[f"level{i}_updates"] = float(after - before)
    if save is not None:
        model.save(save)
    env.close()
    eval_env.close()
    return figures


def main(argv: Sequence[str] | None = None) -> dict[str, float]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", required=True, help="folder with model.zip and replay_buffer.pkl")
    parser.add_argument("--suite", required=True, choices=sorted(SUITES))
    parser.add_argument("--task", required=True)
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--train-ratio", type=float, default=None, help="default: the run's")
    parser.add_argument("--freeze-world-model", action="store_true")
    parser.add_argument("--eval-every", type=int, default=250)
    parser.add_argument("--eval-episodes", type=int, default=5)
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--save", default=None, help="save the continued model here")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    import torch as th

    th.set_num_threads(args.threads)
    print(environment_header(), flush=True)
    figures = continue_run(
        args.run,
        args.suite,
        args.task,
        steps=args.steps,
        train_ratio=args.train_ratio,
        freeze_world_model=args.freeze_world_model,
        eval_every=args.eval_every,
        eval_episodes=args.eval_episodes,
        seed=args.seed,
        save=args.save,
    )
    for name, value in figures.items():
        print(f"continuation/{name}: {value:.4g}")
    return figures


if __name__ == "__main__":
    main()
