"""Demo: train HIEROS on CartPole-v1 and plot its learning curve (``make demo`` runs ``python -m benchmarks.demo``).

Trains the given preset (default ``small``) for ``--steps`` environment steps with SB3's progress bar
(``--no-progress-bar`` to hide it), evaluating the deterministic policy every ``--eval-freq`` steps on a separate
environment (SB3 ``EvalCallback``, ``--eval-episodes`` episodes). Its log lines are flushed as they are printed, so
output redirected to a file shows them at once. It writes to ``--out`` (default ``results/demo/``):

* ``learning_curve.png``: mean and standard deviation of the evaluation return over the training steps;
* ``evaluations.npz``: SB3's evaluation log (``timesteps``, ``results``, ``ep_lengths``);
* ``final_eval.json``: the last evaluation (mean/std return, episode returns), steps, wall time, settings;
* ``progress.csv``: the training log (``rollout/*``, ``time/*``, ``train/level{i}/*``);
* ``model.zip``: the trained model (``HIEROS.load``);
* ``subgoals/subgoals_<step>_env0.png``: every ``--subgoal-every`` steps (default 2000), the subgoal of every level
  above 0 decoded into the observation space, as bars per observation entry next to the real observation and, for
  classic-control tasks, as the frame the env draws for it (:class:`~sb3_hieros.SubgoalDecodeCallback`, added by
  :func:`extra_callbacks`).

``--report DIR`` trains nothing: it redraws ``DIR/learning_curve.png`` from the run's ``evaluations.npz`` and
``final_eval.json`` (``docs/demo/`` holds such a run).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import pathlib
import sys
import time

import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback, EvalCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.logger import configure

from benchmarks._timing import environment_header
from sb3_hieros import HIEROS, SubgoalDecodeCallback


def extra_callbacks(out: pathlib.Path, subgoal_every: int = 2_000) -> list[BaseCallback]:
    """Further callbacks of the demo: decoded-subgoal pictures written into ``out / "subgoals"``.

    :param out: output directory
    :param subgoal_every: environment steps between two pictures
    :return: callbacks to add to training
    """
    return [SubgoalDecodeCallback(every=subgoal_every, save_dir=out / "subgoals", tensorboard=False)]


def auto_threads(cpus: int, load: float, most: int = 2) -> tuple[int, str]:
    """Torch threads for a run, from the CPUs this process may use and the load on them.

    A core counts as free when the load leaves at least half of it; more threads than free cores wait on busy ones
    (intra-op threads synchronise at every operator), which slows the small preset's many small operators many-fold.
    At most ``most`` threads: the small preset's operators are too small for more to pay.

    :param cpus: CPUs this process may run on
    :param load: runnable processes on the machine (load average), this one not yet among them
    :param most: upper bound
    :return: the thread count and a sentence saying why
    """
    if isinstance(cpus, bool) or not isinstance(cpus, int) or cpus < 1:
        raise ValueError(f"cpus must be a positive int, got {cpus!r}")
    if not math.isfinite(load) or load < 0:
        raise ValueError(f"load must be a finite number >= 0, got {load!r}")
    if isinstance(most, bool) or not isinstance(most, int) or most < 1:
        raise ValueError(f"most must be a positive int, got {most!r}")
    free = max(0.0, cpus - load)
    threads = max(1, min(most, math.floor(free + 0.5)))
    why = f"{cpus} CPUs available, load {load:.1f}, so {free:.1f} free; at most {most}"
    return threads, why


def free_cpus() -> tuple[int, float]:
    """The CPUs this process may run on (its affinity) and the machine's load average over the last minute.

    :return: (cpus, load); load 0.0 where the system does not report one
    """
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else 0.0
    return cpus, load


def plot_learning_curve(evaluations: pathlib.Path, path: pathlib.Path, title: str) -> None:
    """Evaluation return (mean +- std over the evaluation episodes) against environment steps, as a PNG.

    :param evaluations: SB3's ``evaluations.npz``
    :param path: PNG to write
    :param title: plot title
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    data = np.load(evaluations)
    steps, results = data["timesteps"], data["results"]
    mean, std = results.mean(1), results.std(1)
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(steps, mean, marker="o", label="evaluation return (deterministic)")
    ax.fill_between(steps, mean - std, mean + std, alpha=0.25)
    ax.set_xlabel("environment steps")
    ax.set_ylabel("episode return")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def report(out: pathlib.Path) -> dict:
    """Redraw ``learning_curve.png`` of a finished demo run from its ``evaluations.npz`` and ``final_eval.json``.

    :param out: the run's output directory
    :return: the run's summary (``final_eval.json``)
    """
    summary = json.loads((out / "final_eval.json").read_text())
    title = f"HIEROS ({summary['preset']}) on {summary['env']}"
    plot_learning_curve(out / "evaluations.npz", out / "learning_curve.png", title)
    return summary


def main(argv: list[str] | None = None) -> dict:
    """Train, evaluate, plot and save (see the module docstring).

    :param argv: command-line arguments (default: ``sys.argv``)
    :return: the final evaluation summary written to ``final_eval.json``
    """
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=10_000, help="environment steps to train")
    parser.add_argument("--eval-freq", type=int, default=1_000, help="evaluate every N environment steps")
    parser.add_argument("--eval-episodes", type=int, default=5, help="episodes per evaluation")
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("results/demo"), help="output directory")
    parser.add_argument("--seed", type=int, default=0, help="random seed")
    parser.add_argument("--preset", default="small", choices=("small", "paper"), help="hyperparameter preset")
    parser.add_argument("--env", default="CartPole-v1", help="gymnasium environment id")
    parser.add_argument(
        "--subgoal-every", type=int, default=2_000, help="decoded-subgoal PNG every N environment steps"
    )
    parser.add_argument(
        "--threads",
        type=int,
        default=None,
        help="torch CPU threads (default: OMP_NUM_THREADS if set, else chosen from the free CPUs, at most 2)",
    )
    parser.add_argument(
        "--progress-bar", action=argparse.BooleanOptionalAction, default=True, help="show SB3's progress bar"
    )
    parser.add_argument(
        "--report", type=pathlib.Path, default=None, help="train nothing: redraw DIR/learning_curve.png from its run"
    )
    args = parser.parse_args(argv)
    if args.report is not None:
        return report(args.report)
    if hasattr(sys.stdout, "reconfigure"):
        sys.stdout.reconfigure(line_buffering=True)  # every log line reaches a redirected file at once
    if args.threads is not None:
        if args.threads < 1:
            raise ValueError(f"--threads must be >= 1, got {args.threads}")
        th.set_num_threads(args.threads)
        threads_line = f"torch threads: {args.threads} (--threads)"
    elif os.environ.get("OMP_NUM_THREADS"):
        threads_line = f"torch threads: {th.get_num_threads()} (OMP_NUM_THREADS={os.environ['OMP_NUM_THREADS']})"
    else:
        threads, why = auto_threads(*free_cpus())
        th.set_num_threads(threads)
        threads_line = f"torch threads: {threads} (chosen: {why}; --threads N to set)"

    out: pathlib.Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    print(environment_header())
    print(threads_line)
    print(f"demo: {args.preset} preset on {args.env}, {args.steps} steps, seed {args.seed}, output {out}")

    env = make_vec_env(args.env, n_envs=1, seed=args.seed)
    eval_env = make_vec_env(args.env, n_envs=1, seed=args.seed + 1000)
    model = HIEROS("MlpPolicy", env, preset=args.preset, seed=args.seed, verbose=0)
    model.set_logger(configure(str(out), ["csv"]))
    evaluation = EvalCallback(
        eval_env,
        eval_freq=args.eval_freq,
        n_eval_episodes=args.eval_episodes,
        deterministic=True,
        log_path=str(out),
        verbose=1,
    )
    start = time.perf_counter()
    n_params = sum(p.numel() for p in model.policy.parameters())
    print(
        f"{n_params / 1e6:.2f}M parameters; random actions for the first {model.learning_starts} steps, then training; "
        f"an evaluation every {args.eval_freq} steps",
        flush=True,
    )
    model.learn(
        args.steps,
        callback=[evaluation, *extra_callbacks(out, args.subgoal_every)],
        progress_bar=args.progress_bar,
    )
    wall = time.perf_counter() - start
    model.save(out / "model.zip")

    evaluations = out / "evaluations.npz"
    if not evaluations.exists():
        raise RuntimeError(f"no evaluation was run: --eval-freq {args.eval_freq} exceeds --steps {args.steps}")
    results = np.load(evaluations)["results"]
    plot_learning_curve(evaluations, out / "learning_curve.png", f"HIEROS ({args.preset}) on {args.env}")
    summary = {
        "env": args.env,
        "preset": args.preset,
        "seed": args.seed,
        "steps": int(model.num_timesteps),
        "level_updates": model.level_updates(),
        "wall_time_s": round(wall, 1),
        "seconds_per_env_step": round(wall / max(model.num_timesteps, 1), 4),
        "final_eval_mean_return": float(results[-1].mean()),
        "final_eval_std_return": float(results[-1].std()),
        "final_eval_returns": results[-1].tolist(),
        "eval_mean_returns": results.mean(1).tolist(),
    }
    (out / "final_eval.json").write_text(json.dumps(summary, indent=2) + "\n")
    print(
        f"wall time {wall:.1f} s ({summary['seconds_per_env_step']} s per env step), updates {summary['level_updates']}"
    )
    print("eval mean returns: " + ", ".join(f"{r:.1f}" for r in summary["eval_mean_returns"]))
    print(f"final_eval_mean_return: {summary['final_eval_mean_return']:.1f}")
    return summary


if __name__ == "__main__":
    main()
