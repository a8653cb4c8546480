"""One HIEROS training run on one task of a benchmark suite (:mod:`benchmarks.suites`), with the thesis' protocol.

The run trains ``--steps`` agent steps (default: the suite's budget, e.g. 100k for Atari100k), evaluates every
``--eval-freq`` steps with SB3's ``EvalCallback`` (``--periodic-eval-episodes`` episodes) and at the end over
``--eval-episodes`` episodes (100 in the thesis), and writes into ``<out>/<suite>/<task>/seed<seed>/``:

* ``train.monitor.csv`` / ``eval.monitor.csv``: SB3 ``Monitor`` logs of the training and evaluation episodes;
* ``evaluations.npz``: the periodic evaluations (``EvalCallback``'s ``timesteps``, ``results``, ``ep_lengths``);
* ``model.zip``: the trained model (``HIEROS.load`` reads it);
* ``replay_buffer.pkl`` with ``--save-replay-buffer``: its replay (``load_replay_buffer`` reads it);
* ``result.json``: suite, task, seed, preset, steps, final mean/std return, the final returns, the periodic
  evaluation curve, wall time and the keywords of the run (:func:`benchmarks.aggregate.load_results` reads it);
* ``checkpoint/`` with ``--checkpoint-freq N`` while the run goes on: every N agent steps the model, its replay
  (every level) and ``progress.json`` (the step, the training time so far, the periodic evaluations and the run's
  options). ``--resume`` continues a run from its checkpoint (a run without one starts afresh; a finished run, one
  with ``result.json``, is not run again; either is refused, naming the options, when it was written with other
  options); the folder is removed when the run finishes.

A resumed run loads the model with ``HIEROS.load`` and its replay with ``load_replay_buffer`` and goes on with
``reset_num_timesteps=False`` (see ``docs/resume.md``): the same updates per level as a run that never stopped, the
periodic evaluations at the same steps, the training monitor appended to. The random generators are reseeded
with ``seed + step`` of the checkpoint, so a resumed run does not repeat the actions an uninterrupted one would
have drawn. ``train_s`` / ``wall_s`` add the time of every earlier part up to its last checkpoint to the last
part's (``resumed_at`` lists the steps the run was resumed at); the monitors are appended to (their time
column starts again at each resume).

Evaluation uses a separate environment seeded with ``seed + 10000`` and the deterministic policy unless
``--stochastic-eval``.

Examples::

    python -m benchmarks.train --suite atari100k --task Pong --seed 0 --preset paper --out runs
    python -m benchmarks.train --suite atari100k --task Pong --preset small --checkpoint-freq 5000 --resume \\
        --out runs  # run again after an interruption to go on from the last checkpoint
    python -m benchmarks.train --suite classic --task CartPole-v1 --preset small --steps 5000 --eval-freq 1000 \\
        --eval-episodes 10 --out runs --config-overrides '{"n_levels": 1}'
"""

from __future__ import annotations

import argparse
import json
import pathlib
import shutil
import time
from typing import Any

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback, EvalCallback

from benchmarks._checkpoint import PeriodicCheckpoint, check_same_options, checkpoint_paths, load_checkpoint
from benchmarks._cli import json_object
from benchmarks.suites import SUITE_POLICIES, SUITES, make_env
from sb3_hieros.save_util import atomic_path

__all__ = ["CHECKPOINT_DIR", "EVAL_SEED_OFFSET", "RunCheckpoint", "run_dir", "train"]

#: The evaluation env of a run with seed s is seeded with s + EVAL_SEED_OFFSET.
EVAL_SEED_OFFSET = 10_000

#: Sub-folder of a run folder that holds its checkpoint while the run goes on.
CHECKPOINT_DIR = "checkpoint"


def run_dir(out: str | pathlib.Path, suite: str, task: str, seed: int) -> pathlib.Path:
    """Folder of one run: ``<out>/<suite>/<task with "/" as "_">/seed<seed>``."""
    return pathlib.Path(out) / suite / task.replace("/", "_") / f"seed{seed}"


def _vec_env(
    suite: str, task: str, seed: int, monitor_file: pathlib.Path, env_kwargs: dict[str, Any], append: bool = False
) -> Any:
    """A one-env ``DummyVecEnv`` with a ``Monitor`` writing ``monitor_file`` (appending to it with ``append``);
    image observations channel-first."""
    from stable_baselines3.common.monitor import Monitor
    from stable_baselines3.common.preprocessing import is_image_space, is_image_space_channels_first
    from stable_baselines3.common.vec_env import DummyVecEnv, VecTransposeImage

    def monitored() -> Any:
        env = make_env(suite, task, seed=seed, **env_kwargs)
        return Monitor(env, str(monitor_file), override_existing=not append)

    venv: Any = DummyVecEnv([monitored])
    space = venv.observation_space
    if is_image_space(space) and not is_image_space_channels_first(space):
        venv = VecTransposeImage(venv)
    return venv


def check_counts(**counts: Any) -> None:
    """Raise ``ValueError`` naming the first value that is not an int >= 1 (bools are refused).

    :param counts: name -> value
    """
    for name, value in counts.items():
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"{name} must be an int >= 1, got {value!r}")


class RunCheckpoint(PeriodicCheckpoint):
    """Saves a run's checkpoint into ``directory`` at the start of every ``every``-th vec-env step.

    The files are ``model_<step>.zip``, ``replay_<step>.zip`` and, written last and atomically, ``progress.json``
    naming the step: a save interrupted at any point leaves the previous checkpoint usable. Older model and replay
    files are removed once ``progress.json`` names the new ones.

    :param directory: the checkpoint folder (created on the first save)
    :param every: agent steps between checkpoints
    :param progress: returns the run's progress besides the step (training time, evaluations, options)
    """

    def __init__(self, directory: pathlib.Path, every: int, progress: Any) -> None:
        super().__init__(directory, every)
        self.progress = progress

    def _save(self, step: int) -> None:
        super()._save(step)
        with atomic_path(self.directory / "progress.json") as tmp:
            tmp.write_text(json.dumps({"step": step, **self.progress()}, indent=1))
        kept = checkpoint_paths(self.directory, step)
        for old in (*self.directory.glob("model_*.zip"), *self.directory.glob("replay_*.zip")):
            if old not in kept:
                old.unlink(missing_ok=True)


def _restore_evaluations(callback: EvalCallback, saved: dict[str, Any], step: int) -> None:
    """Give a fresh ``EvalCallback`` the evaluations of the checkpoint and its step count, so that it writes the
    whole curve and evaluates at the same steps as a run that never stopped (one env: calls = agent steps)."""
    callback.evaluations_timesteps = list(saved["timesteps"])
    callback.evaluations_results = [list(r) for r in saved["results"]]
    callback.evaluations_length = [list(n) for n in saved["ep_lengths"]]
    callback.n_calls = step


def train(
    suite: str,
    task: str,
    seed: int = 0,
    preset: str = "paper",
    steps: int | None = None,
    eval_freq: int = 10_000,
    eval_episodes: int = 100,
    periodic_eval_episodes: int = 10,
    out: str | pathlib.Path = "runs",
    threads: int = 1,
    config_overrides: dict[str, Any] | None = None,
    hieros_kwargs: dict[str, Any] | None = None,
    env_kwargs: dict[str, Any] | None = None,
    deterministic: bool = True,
    device: str = "auto",
    verbose: int = 0,
    save_replay_buffer: bool = False,
    checkpoint_freq: int = 0,
    resume: bool = False,
) -> dict[str, Any]:
    """Train HIEROS on one task of a suite, evaluate it and write the run's files (see the module docstring).

    :param suite: a suite of :data:`benchmarks.suites.SUITES`
    :param task: a task of that suite (game, ``"<domain>-<task>"`` or gymnasium id)
    :param seed: seed of the model and the training env (the evaluation env gets ``seed + EVAL_SEED_OFFSET``)
    :param preset: HIEROS preset (``"paper"`` or ``"small"``)
    :param steps: agent steps to train; None = the suite's budget (:attr:`SuiteSpec.agent_steps`)
    :param eval_freq: periodic evaluation every this many agent steps (<= 0: none)
    :param eval_episodes: episodes of the final evaluation (>= 1)
    :param periodic_eval_episodes: episodes of each periodic evaluation (>= 1)
    :param out: root folder of the runs
    :param threads: torch threads
    :param config_overrides: HIEROS ``config_overrides``
    :param hieros_kwargs: further HIEROS keywords (``learning_starts``, ``train_ratio`` ...)
    :param env_kwargs: further keywords of :func:`benchmarks.suites.make_env` (e.g. ``{"sticky": True}``)
    :param deterministic: evaluate with the deterministic policy
    :param device: torch device
    :param verbose: HIEROS verbosity
    :param save_replay_buffer: also save the replay buffer as ``replay_buffer.pkl`` (to continue the run later with
        ``HIEROS.load`` and ``load_replay_buffer``)
    :param checkpoint_freq: save a checkpoint into ``<run>/checkpoint/`` every this many agent steps (0: none)
    :param resume: go on from the run's checkpoint if it has one; return the record of a finished run
        (``result.json`` exists) without training; either must have been written with these options
    :return: the record written to ``result.json``
    """
    import torch as th
    from stable_baselines3.common.callbacks import CallbackList
    from stable_baselines3.common.evaluation import evaluate_policy

    from sb3_hieros import HIEROS

    if suite not in SUITES:
        raise ValueError(f"unknown suite {suite!r}; expected one of {sorted(SUITES)}")
    steps = SUITES[suite].agent_steps if steps is None else steps
    check_counts(
        steps=steps, eval_episodes=eval_episodes, threads=threads, periodic_eval_episodes=periodic_eval_episodes
    )
    if isinstance(checkpoint_freq, bool) or not isinstance(checkpoint_freq, int) or checkpoint_freq < 0:
        raise ValueError(f"checkpoint_freq must be an int >= 0 (0: no checkpoints), got {checkpoint_freq!r}")
    hieros_kwargs = dict(hieros_kwargs or {})
    for reserved in ("preset", "config_overrides", "seed", "env", "policy"):
        if reserved in hieros_kwargs:
            raise ValueError(f"hieros_kwargs must not contain {reserved!r} (it has its own argument)")
    env_kwargs = dict(env_kwargs or {})
    options = {
        "suite": suite,
        "task": task,
        "seed": seed,
        "preset": preset,
        "steps": steps,
        "eval_freq": eval_freq,
        "periodic_eval_episodes": periodic_eval_episodes,
        "deterministic_eval": deterministic,
        "config_overrides": config_overrides or {},
        "hieros_kwargs": hieros_kwargs,
        "env_kwargs": env_kwargs,
    }

    th.set_num_threads(threads)
    folder = run_dir(out, suite, task, seed)
    checkpoint_dir = folder / CHECKPOINT_DIR
    if resume and (folder / "result.json").is_file():
        record = json.loads((folder / "result.json").read_text())
        check_same_options(record, options, folder / "result.json")
        return record
    saved = None
    if resume and (checkpoint_dir / "progress.json").is_file():
        saved = json.loads((checkpoint_dir / "progress.json").read_text())
        check_same_options(saved["options"], options, checkpoint_dir / "progress.json")
    folder.mkdir(parents=True, exist_ok=True)
    env = _vec_env(suite, task, seed, folder / "train", env_kwargs, append=saved is not None)
    eval_env = _vec_env(suite, task, seed + EVAL_SEED_OFFSET, folder / "eval", env_kwargs, append=saved is not None)
    start = time.perf_counter()
    earlier_s = 0.0 if saved is None else float(saved["train_s"])
    resumed_at = [] if saved is None else [*saved["resumed_at"], int(saved["step"])]
    if saved is None:
        model = HIEROS(
            SUITE_POLICIES[suite],
            env,
            preset=preset,
            config_overrides=config_overrides,
            seed=seed,
            device=device,
            verbose=verbose,
            **hieros_kwargs,
        )
    else:
        step = int(saved["step"])
        model = load_checkpoint(checkpoint_dir, step, env, device=device, verbose=verbose)
        model.set_random_seed(seed + step)
    callbacks: list[BaseCallback] = []
    evaluation = None
    if eval_freq > 0:
        evaluation = EvalCallback(
            eval_env,
            n_eval_episodes=periodic_eval_episodes,
            eval_freq=eval_freq,
            log_path=str(folder),
            deterministic=deterministic,
            verbose=0,
        )
        if saved is not None:
            _restore_evaluations(evaluation, saved["evaluations"], int(saved["step"]))
        callbacks.append(evaluation)
    if checkpoint_freq > 0:

        def progress() -> dict[str, Any]:
            return {
                "train_s": earlier_s + time.perf_counter() - start,
                "resumed_at": resumed_at,
                "evaluations": {
                    "timesteps": [int(t) for t in evaluation.evaluations_timesteps] if evaluation else [],
                    "results": [[float(r) for r in rs] for rs in evaluation.evaluations_results] if evaluation else [],
                    "ep_lengths": [[int(n) for n in ns] for ns in evaluation.evaluations_length] if evaluation else [],
                },
                "options": options,
            }

        callbacks.append(RunCheckpoint(checkpoint_dir, checkpoint_freq, progress))
    model.learn(steps - model.num_timesteps, callback=CallbackList(callbacks), reset_num_timesteps=saved is None)
    train_s = earlier_s + time.perf_counter() - start
    returns, _ = evaluate_policy(
        model, eval_env, n_eval_episodes=eval_episodes, deterministic=deterministic, return_episode_rewards=True
    )
    model.save(folder / "model.zip")
    if save_replay_buffer:
        model.save_replay_buffer(folder / "replay_buffer.pkl")
    record = {
        "suite": suite,
        "task": task,
        "seed": seed,
        "preset": preset,
        "steps": int(model.num_timesteps),
        "env_steps": int(model.num_timesteps) * SUITES[suite].action_repeat,
        "final_mean": float(np.mean(returns)),
        "final_std": float(np.std(returns)),
        "final_episodes": len(returns),
        "final_returns": [float(r) for r in returns],
        "eval_timesteps": [int(t) for t in evaluation.evaluations_timesteps] if evaluation else [],
        "eval_means": [float(np.mean(r)) for r in evaluation.evaluations_results] if evaluation else [],
        "deterministic_eval": deterministic,
        "train_s": round(train_s, 1),
        "wall_s": round(earlier_s + time.perf_counter() - start, 1),
        "config_overrides": config_overrides or {},
        "hieros_kwargs": hieros_kwargs,
        "env_kwargs": env_kwargs,
    }
    if resumed_at:
        record["resumed_at"] = resumed_at
    (folder / "result.json").write_text(json.dumps(record, indent=1))
    shutil.rmtree(checkpoint_dir, ignore_errors=True)
    env.close()
    eval_env.close()
    return record


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Command line (see the module docstring)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--suite", required=True, choices=sorted(SUITES))
    parser.add_argument("--task", required=True)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--preset", default="paper", choices=["paper", "small"])
    parser.add_argument("--steps", type=int, default=None, help="agent steps (default: the suite's budget)")
    parser.add_argument("--eval-freq", type=int, default=10_000, help="periodic evaluation every N steps (<=0: off)")
    parser.add_argument("--eval-episodes", type=int, default=100, help="episodes of the final evaluation")
    parser.add_argument("--periodic-eval-episodes", type=int, default=10)
    parser.add_argument("--out", default="runs")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--config-overrides", type=json_object, default=None, help="JSON dict for config_overrides")
    parser.add_argument("--hieros-kwargs", type=json_object, default=None, help="JSON dict of HIEROS keywords")
    parser.add_argument("--env-kwargs", type=json_object, default=None, help="JSON dict for suites.make_env")
    parser.add_argument("--stochastic-eval", action="store_true", help="evaluate with sampled actions")
    parser.add_argument("--device", default="auto")
    parser.add_argument("--verbose", type=int, default=0)
    parser.add_argument("--save-replay-buffer", action="store_true", help="also save replay_buffer.pkl")
    parser.add_argument(
        "--checkpoint-freq", type=int, default=0, help="save a checkpoint every N agent steps (0: none)"
    )
    parser.add_argument(
        "--resume", action="store_true", help="go on from the run's checkpoint; skip a run that has result.json"
    )
    args = parser.parse_args(argv)
    record = train(
        args.suite,
        args.task,
        seed=args.seed,
        preset=args.preset,
        steps=args.steps,
        eval_freq=args.eval_freq,
        eval_episodes=args.eval_episodes,
        periodic_eval_episodes=args.periodic_eval_episodes,
        out=args.out,
        threads=args.threads,
        config_overrides=args.config_overrides,
        hieros_kwargs=args.hieros_kwargs,
        env_kwargs=args.env_kwargs,
        deterministic=not args.stochastic_eval,
        device=args.device,
        verbose=args.verbose,
        save_replay_buffer=args.save_replay_buffer,
        checkpoint_freq=args.checkpoint_freq,
        resume=args.resume,
    )
    print(
        f"{record['suite']} {record['task']} seed {record['seed']}: final return {record['final_mean']:.2f} "
        f"+- {record['final_std']:.2f} over {record['final_episodes']} episodes after {record['steps']} steps, "
        f"{record['wall_s']} s -> {run_dir(args.out, args.suite, args.task, args.seed)}",
        flush=True,
    )
    return record


if __name__ == "__main__":
    main()
