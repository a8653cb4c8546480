"""A sweep runner: many HIEROS training runs, sequentially, in a local process pool, or as Ray tasks.

Two kinds of job:

* :class:`Run` (:func:`run_one`, :func:`run_sweep`): train one HIEROS model and record the collected reward of every
  finished training episode (SB3's ``Monitor``: return and the environment step at which the episode ended), which
  is what the thesis' ablation figures plot (used by :mod:`benchmarks.ablations`). Environments: a suite task
  (``Run(..., suite="dmc_vision")``, made by :func:`benchmarks.suites.make_env`); without a suite an Atari id
  (``ALE/<Game>-v5``) uses the Atari100k protocol of :func:`benchmarks.suites.make_atari_env` (RGB 64x64) and any
  other gymnasium id SB3's ``make_vec_env``.
* :class:`TrainJob` (:func:`grid_jobs`, :func:`run_grid`): one :func:`benchmarks.train.train` run (periodic and final
  evaluation, model, ``result.json``) per task and seed of a grid; the results go to
  :func:`benchmarks.aggregate.aggregate` (tables next to the thesis' and curve PNGs).

Execution (``workers``, ``ray_address``): ``workers=1`` runs the jobs one after the other in this process, ``workers>1``
in a local process pool (one torch thread each); ``ray_address`` runs one Ray task per job (1 CPU each) on a Ray
cluster: ``"auto"`` (an existing cluster, e.g. after ``ray start --head``), ``"local"`` (a fresh local instance unless
Ray is already initialised in this process) or ``"ray://host:10001"``/``"host:6379"``. Ray is the optional ``ray``
extra (``pip install 'sb3-hieros[ray]'``); the cluster's nodes need this repository importable (same path or
installed package). Results come back in the order of the jobs either way.

Command lines::

    # a grid of train.py runs, aggregated into <out>/aggregate (tables + curves)
    python -m benchmarks.sweep --grid atari100k --seeds 3 --preset paper --out runs --ray-address auto
    python -m benchmarks.sweep --grid dmc_proprio --tasks cartpole-balance walker-walk --seeds 2 --steps 20000 \\
        --preset small --workers 2 --out runs
    python -m benchmarks.sweep --grid CartPole-v1 --seeds 2 --steps 2000 --preset small --out runs
    # seeds of one configuration, episode returns only (no evaluation)
    python -m benchmarks.sweep --env CartPole-v1 --seeds 2 --steps 2000 --workers 2 --kwargs '{"preset": "small"}'
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field
from typing import Any, TypeVar

__all__ = ["Run", "TrainJob", "atari_id", "execute", "grid_jobs", "run_grid", "run_one", "run_sweep", "run_train_job"]

Job = TypeVar("Job")


@dataclass(frozen=True)
class Run:
    """One training run.

    :param variant: label of the configuration (e.g. ``"hieros"`` or an ablation name)
    :param env_id: gymnasium id (``ALE/...`` ids use the Atari100k wrappers), or the task of ``suite``
    :param seed: random seed of the model and the environment
    :param steps: environment steps to train
    :param kwargs: HIEROS keywords (``preset``, ``config_overrides``, ``learning_starts`` ...)
    :param threads: torch threads of the run
    :param suite: a suite of :data:`benchmarks.suites.SUITES` whose task ``env_id`` is; "" = infer from ``env_id``
    """

    variant: str
    env_id: str
    seed: int
    steps: int
    kwargs: dict[str, Any] = field(default_factory=dict)
    threads: int = 1
    suite: str = ""


@dataclass(frozen=True)
class TrainJob:
    """One :func:`benchmarks.train.train` run.

    :param suite: a suite of :data:`benchmarks.suites.SUITES`
    :param task: a task of the suite
    :param seed: seed of the run
    :param kwargs: further keywords of :func:`benchmarks.train.train` (``preset``, ``steps``, ``out`` ...)
    """

    suite: str
    task: str
    seed: int
    kwargs: dict[str, Any] = field(default_factory=dict)


def atari_id(game: str) -> str:
    """Gymnasium id of an Atari game name (``"Krull"`` -> ``"ALE/Krull-v5"``); ids pass unchanged."""
    return game if "/" in game or game.endswith(("-v0", "-v1", "-v4", "-v5")) else f"ALE/{game}-v5"


def _run_env(run: Run) -> tuple[Any, str]:
    """The vec env (with a ``Monitor``) and the policy name of a run."""
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.monitor import Monitor
    from stable_baselines3.common.preprocessing import is_image_space, is_image_space_channels_first
    from stable_baselines3.common.vec_env import DummyVecEnv, VecTransposeImage

    from benchmarks.suites import SUITE_POLICIES, make_atari_env, make_env

    if run.suite:
        env: Any = DummyVecEnv([lambda: Monitor(make_env(run.suite, run.env_id, seed=run.seed))])
        policy = SUITE_POLICIES[run.suite]
    elif run.env_id.startswith("ALE/"):
        game = run.env_id[len("ALE/") :].rsplit("-v", 1)[0]
        env = DummyVecEnv([lambda: Monitor(make_atari_env(game, seed=run.seed))])
        policy = "CnnPolicy"
    else:
        return make_vec_env(run.env_id, n_envs=1, seed=run.seed), "MlpPolicy"
    space = env.observation_space
    if is_image_space(space) and not is_image_space_channels_first(space):
        env = VecTransposeImage(env)
    return env, policy


def run_one(run: Run) -> dict[str, Any]:
    """Train one run and return its record.

    :param run: what to train
    :return: ``{"variant", "env_id", "seed", "steps", "threads", "suite", "episode_end_steps": [...],
        "episode_returns": [...], "wall_s", "updates": [per level]}``
    """
    import torch as th

    from sb3_hieros import HIEROS

    th.set_num_threads(max(1, run.threads))
    env, policy = _run_env(run)
    start = time.perf_counter()
    model = HIEROS(policy, env, seed=run.seed, **run.kwargs)
    model.learn(run.steps)
    monitor = env.envs[0] if not hasattr(env, "venv") else env.venv.envs[0]
    while not hasattr(monitor, "get_episode_rewards"):
        monitor = monitor.env
    lengths = monitor.get_episode_lengths()
    ends = [int(sum(lengths[: i + 1])) for i in range(len(lengths))]
    return {
        **{k: v for k, v in asdict(run).items() if k != "kwargs"},
        "episode_end_steps": ends,
        "episode_returns": [float(r) for r in monitor.get_episode_rewards()],
        "wall_s": round(time.perf_counter() - start, 1),
        "updates": model.level_updates(),
    }


def run_train_job(job: TrainJob) -> dict[str, Any]:
    """Run one :class:`TrainJob` (:func:`benchmarks.train.train`) and return its result record."""
    from benchmarks.train import train

    return train(job.suite, job.task, seed=job.seed, **job.kwargs)


def _ray(address: str) -> Any:
    """The ``ray`` module, connected to ``address`` (see the module docstring)."""
    try:
        import ray
    except ImportError as error:
        raise ImportError(
            f"--ray-address / ray_address needs the 'ray' extra: pip install 'sb3-hieros[ray]' ({error})"
        ) from error
    if not ray.is_initialized():
        if address == "local":
            ray.init(include_dashboard=False)
        else:
            ray.init(address=address)
    return ray


def _ray_runtime_env() -> dict[str, Any]:
    """Ray workers start in a fresh interpreter: put this repository (``benchmarks`` is not an installed package) on
    their ``PYTHONPATH``, so that they can import the task functions. Cluster nodes need the repository at the same
    path."""
    root = str(pathlib.Path(__file__).resolve().parent.parent)
    paths = [root, *filter(None, os.environ.get("PYTHONPATH", "").split(os.pathsep))]
    return {"env_vars": {"PYTHONPATH": os.pathsep.join(dict.fromkeys(paths))}}


def execute(
    fn: Callable[[Job], dict[str, Any]],
    jobs: Sequence[Job],
    workers: int = 1,
    ray_address: str | None = None,
    report: Callable[[dict[str, Any]], None] | None = None,
) -> list[dict[str, Any]]:
    """``[fn(job) for job in jobs]``, sequentially, in a process pool or as Ray tasks.

    :param fn: a picklable top-level function (:func:`run_one`, :func:`run_train_job`)
    :param jobs: its arguments, started in this order
    :param workers: processes of the local pool (1 = in this process); ignored with ``ray_address``
    :param ray_address: run one Ray task (1 CPU) per job on this cluster (``"auto"``, ``"local"``, an address)
    :param report: called with each result as it is collected (in job order)
    :return: the results in the order of ``jobs``
    """
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers must be an int >= 1, got {workers!r}")
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    report = report or (lambda record: None)
    results: list[dict[str, Any]] = []
    if ray_address is not None:
        ray = _ray(ray_address)
        task = ray.remote(num_cpus=1, runtime_env=_ray_runtime_env())(fn)
        refs = [task.remote(job) for job in jobs]
        for ref in refs:
            results.append(ray.get(ref))
            report(results[-1])
        return results
    if workers == 1:
        for job in jobs:
            results.append(fn(job))
            report(results[-1])
        return results
    with ProcessPoolExecutor(max_workers=workers) as pool:
        for future in [pool.submit(fn, job) for job in jobs]:
            results.append(future.result())
            report(results[-1])
    return results


def run_sweep(
    runs: Sequence[Run], workers: int = 1, verbose: bool = True, ray_address: str | None = None
) -> list[dict[str, Any]]:
    """Train every run, ``workers`` at a time (processes; 1 = sequentially in this process) or on Ray.

    :param runs: the runs, started in this order
    :param workers: number of worker processes
    :param verbose: print one line per finished run
    :param ray_address: run on Ray instead (see :func:`execute`)
    :return: the records of :func:`run_one`, in the order of ``runs``
    """

    def report(record: dict[str, Any]) -> None:
        if verbose:
            returns = record["episode_returns"]
            last = sum(returns[-10:]) / max(1, len(returns[-10:]))
            print(
                f"{record['variant']} {record['env_id']} seed {record['seed']}: {len(returns)} episodes, "
                f"last-10 return {last:.1f}, {record['wall_s']} s",
                flush=True,
            )

    return execute(run_one, runs, workers=workers, ray_address=ray_address, report=report)


def grid_jobs(
    grid: str, seeds: int, tasks: Sequence[str] | None = None, train_kwargs: dict[str, Any] | None = None
) -> list[TrainJob]:
    """The jobs of a grid: every task of a suite (or one gymnasium id, as the ``classic`` suite) times seeds.

    :param grid: ``"atari100k"``, ``"dmc_vision"``, ``"dmc_proprio"`` (their task lists) or a gymnasium id
    :param seeds: seeds 0..seeds-1 per task
    :param tasks: a subset of the suite's tasks (None = all)
    :param train_kwargs: keywords of :func:`benchmarks.train.train` shared by every job
    :return: the jobs, task-major
    """
    from benchmarks.suites import SUITES

    if isinstance(seeds, bool) or not isinstance(seeds, int) or seeds < 1:
        raise ValueError(f"seeds must be an int >= 1, got {seeds!r}")
    if grid in SUITES and grid != "classic":
        suite, names = grid, tuple(tasks) if tasks else SUITES[grid].tasks
    else:
        import gymnasium as gym

        if grid not in gym.registry:
            raise ValueError(
                f"unknown grid {grid!r}: expected one of {sorted(set(SUITES) - {'classic'})} or a gymnasium id"
            )
        if tasks:
            raise ValueError(f"tasks apply to suite grids only, got tasks={list(tasks)} for gymnasium id {grid!r}")
        suite, names = "classic", (grid,)
    return [TrainJob(suite, task, seed, dict(train_kwargs or {})) for task in names for seed in range(seeds)]


def run_grid(
    jobs: Sequence[TrainJob],
    workers: int = 1,
    ray_address: str | None = None,
    aggregate_out: str | pathlib.Path | None = None,
    verbose: bool = True,
) -> tuple[list[dict[str, Any]], str]:
    """Run the :class:`TrainJob` s and aggregate their results.

    :param jobs: from :func:`grid_jobs`
    :param workers: local processes (see :func:`execute`)
    :param ray_address: run on Ray instead (see :func:`execute`)
    :param aggregate_out: folder for :func:`benchmarks.aggregate.aggregate`'s files (None = none written)
    :param verbose: print one line per finished run and the tables
    :return: ``(records in job order, markdown tables)``
    """
    from benchmarks.aggregate import aggregate

    def report(record: dict[str, Any]) -> None:
        if verbose:
            print(
                f"{record['suite']} {record['task']} seed {record['seed']}: final {record['final_mean']:.2f} "
                f"+- {record['final_std']:.2f}, {record['wall_s']} s",
                flush=True,
            )

    records = execute(run_train_job, jobs, workers=workers, ray_address=ray_address, report=report)
    markdown, _ = aggregate(records, out=aggregate_out)
    if verbose:
        print(markdown)
    return records, markdown


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    """Command line (see the module docstring)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--grid", default=None, help="atari100k | dmc_vision | dmc_proprio | <gymnasium id>")
    parser.add_argument("--tasks", nargs="+", default=None, help="subset of the grid suite's tasks")
    parser.add_argument("--env", default="CartPole-v1", help="without --grid: the task of the Run sweep")
    parser.add_argument("--seeds", type=int, default=1)
    parser.add_argument("--steps", type=int, default=None, help="agent steps (grid default: the suite's budget)")
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--ray-address", default=None, help="run one Ray task per run: auto | local | ADDRESS")
    parser.add_argument("--kwargs", default=None, help="JSON dict of HIEROS keywords")
    parser.add_argument("--preset", default="paper", choices=["paper", "small"], help="grid runs' preset")
    parser.add_argument("--config-overrides", default=None, help="grid runs: JSON dict for config_overrides")
    parser.add_argument("--out", default="runs", help="grid runs' root folder (aggregate in <out>/aggregate)")
    parser.add_argument("--eval-freq", type=int, default=10_000)
    parser.add_argument("--eval-episodes", type=int, default=100)
    parser.add_argument("--periodic-eval-episodes", type=int, default=10)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    if args.grid is None:
        kwargs = json.loads(args.kwargs) if args.kwargs else {"preset": "small"}
        steps = 2000 if args.steps is None else args.steps
        runs = [Run("hieros", args.env, seed, steps, kwargs, args.threads) for seed in range(args.seeds)]
        return run_sweep(runs, args.workers, ray_address=args.ray_address)
    train_kwargs = {
        "preset": args.preset,
        "steps": args.steps,
        "eval_freq": args.eval_freq,
        "eval_episodes": args.eval_episodes,
        "periodic_eval_episodes": args.periodic_eval_episodes,
        "out": args.out,
        "threads": args.threads,
        "config_overrides": json.loads(args.config_overrides) if args.config_overrides else None,
        "hieros_kwargs": json.loads(args.kwargs) if args.kwargs else None,
    }
    jobs = grid_jobs(args.grid, args.seeds, args.tasks, train_kwargs)
    records, _ = run_grid(jobs, args.workers, args.ray_address, aggregate_out=pathlib.Path(args.out) / "aggregate")
    return records


if __name__ == "__main__":
    main()
