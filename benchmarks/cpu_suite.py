"""What a CPU can show: HIEROS (small preset) against SB3's PPO, DQN and SAC with rl-zoo hyperparameters and DreamerV3.

Every (task, algorithm, seed) run trains ``--steps`` agent steps (the same for every algorithm; on DMC each agent
step is 2 control steps, the same for all), is evaluated ``--n-evals`` times, evenly spaced, the last at the end
(``--eval-episodes`` episodes on a separate env seeded ``seed + 10000``, deterministic policy). Tasks:

============================  ===============================================  ==============================
task                          environment                                       algorithms
============================  ===============================================  ==============================
``CartPole-v1``               gymnasium                                         hieros, dreamerv3, ppo, dqn
``Pendulum-v1``               gymnasium                                         hieros, dreamerv3, ppo, sac
``cartpole-balance-proprio``  ``suites.make_env("dmc_proprio", ...)``           hieros, dreamerv3, ppo, sac
``cartpole-balance-pixels``   ``suites.make_env("dmc_vision", ...)``, 64x64      hieros, dreamerv3, ppo, sac
============================  ===============================================  ==============================

Baseline hyperparameters are read from rl_zoo3's installed ``hyperparams/<algo>.yml`` (the ``zoo`` extra), as
``python -m rl_zoo3.train --algo <algo> --env <id> -n <steps>`` would use them: ``n_envs``, ``policy_kwargs`` and
``lin_<x>`` schedules included, schedules and exploration decay running over the ``--steps`` budget. The zoo has no
dm_control entries, so the DMC tasks use the zoo's ``Pendulum-v1`` entry of the same algorithm (the other
one-dimensional continuous-control task here), with ``CnnPolicy`` on pixels and SAC's replay capped at the budget.
HIEROS uses ``preset="small"`` plus ``--hieros-kwargs``. ``dreamerv3`` is sheeprl's DreamerV3 XS, run by
:mod:`benchmarks.peers` (the ``peers`` extra; without it, runs of it stop the suite before anything trains).
SB3's PPO trains whole rollouts (``n_steps * n_envs``: 256 on CartPole, 4096 with the Pendulum entry), so below
that budget it trains more steps than the others; the table then names the steps it trained.

Outputs in ``--out``: ``runs.jsonl`` (one line per finished run, written as it finishes), ``results.json`` (the runs
of this invocation, in order), ``table.md`` (final return mean +- std over seeds, side by side,
and wall time per run) and ``cpu_suite.png`` (evaluation return against agent steps, one panel per task). The
script ends by printing the table.

``--resume`` skips every run whose settings (task, algorithm, seed, steps, evaluation settings, HIEROS keywords)
already have a line in ``runs.jsonl`` and takes its record from there, so a suite of several hours can be run task by
task, or continued after an interruption, into one table. Each record names the git commit it ran at
(``"commit"``); a resumed suite mixes commits only if the code changed in between, and the table does not hide that:
check the commits in ``runs.jsonl``. A HIEROS run can also be continued from within: with ``--checkpoint-freq N`` it
saves its model, replay and evaluations so far into ``<out>/checkpoints/`` every N agent steps, and ``--resume`` goes
on from there (the folder is removed once the run is recorded; without ``--resume`` every run starts afresh), so a run
of several hours (pixels) can be spread over several sessions; ``--first-seed`` splits a task's seeds over processes.
``--report`` trains nothing: it remakes ``table.md`` and the PNG from the records in ``runs.jsonl`` of the runs asked
for, whatever their evaluation settings (so a pixel task evaluated on fewer episodes, each 500 rendered steps, joins
the table; its "Final eval" cell says how many).

Example (long: about 20 minutes per HIEROS run of 10k steps on one core; run it task by task, then make the table)::

    python -m benchmarks.cpu_suite --seeds 3 --steps 10000 --out docs/cpu_suite --resume --tasks Pendulum-v1
    python -m benchmarks.cpu_suite --seeds 3 --steps 10000 --out docs/cpu_suite --resume --eval-episodes 3
        --tasks cartpole-balance-pixels   # (one line)
    python -m benchmarks.cpu_suite --seeds 3 --steps 10000 --out docs/cpu_suite --report

``docs/cpu_suite/`` holds the runs made so far and the table the README shows.
"""

from __future__ import annotations

import argparse
import functools
import hashlib
import json
import os
import pathlib
import shutil
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import asdict, astuple, dataclass, field, fields
from typing import Any

import numpy as np

from benchmarks._cli import json_object

os.environ.setdefault("MUJOCO_GL", "egl")

__all__ = [
    "ALGOS",
    "CHECKPOINT_DIR",
    "LABELS",
    "TASKS",
    "SuiteRun",
    "TaskSpec",
    "append_record",
    "finished_runs",
    "recorded_runs",
    "run_checkpoint_dir",
    "run_key",
    "run_suite_run",
    "suite_runs",
    "table",
    "task_vec_env",
    "zoo_hyperparams",
]


@dataclass(frozen=True)
class TaskSpec:
    """One task of the CPU suite.

    :param suite: suite of :func:`benchmarks.suites.make_env`
    :param task: task of that suite
    :param zoo_key: the rl-zoo hyperparameter entry the baselines use
    :param algos: algorithms run on it
    """

    suite: str
    task: str
    zoo_key: str
    algos: tuple[str, ...]


TASKS: dict[str, TaskSpec] = {
    "CartPole-v1": TaskSpec("classic", "CartPole-v1", "CartPole-v1", ("hieros", "dreamerv3", "ppo", "dqn")),
    "Pendulum-v1": TaskSpec("classic", "Pendulum-v1", "Pendulum-v1", ("hieros", "dreamerv3", "ppo", "sac")),
    "cartpole-balance-proprio": TaskSpec(
        "dmc_proprio", "cartpole-balance", "Pendulum-v1", ("hieros", "dreamerv3", "ppo", "sac")
    ),
    "cartpole-balance-pixels": TaskSpec(
        "dmc_vision", "cartpole-balance", "Pendulum-v1", ("hieros", "dreamerv3", "ppo", "sac")
    ),
}
ALGOS = ("hieros", "dreamerv3", "ppo", "dqn", "sac")
#: Column titles of the table.
LABELS = {"hieros": "HIEROS small", "dreamerv3": "DreamerV3 XS (sheeprl)", "ppo": "PPO", "dqn": "DQN", "sac": "SAC"}
EVAL_SEED_OFFSET = 10_000
#: Sub-folder of ``--out`` with the checkpoints of unfinished HIEROS runs (``--checkpoint-freq``).
CHECKPOINT_DIR = "checkpoints"


@dataclass(frozen=True)
class SuiteRun:
    """One (task, algorithm, seed) run.

    :param task: a key of :data:`TASKS`
    :param algo: one of :data:`ALGOS`
    :param seed: seed of the model and the training env
    :param steps: agent steps to train
    :param eval_episodes: episodes per evaluation
    :param n_evals: evaluations, evenly spaced, the last one (``eval_episodes`` episodes) at the end
    :param hieros_kwargs: HIEROS keywords on top of ``preset="small"``
    """

    task: str
    algo: str
    seed: int
    steps: int
    eval_episodes: int = 10
    n_evals: int = 5
    hieros_kwargs: dict[str, Any] = field(default_factory=dict)


def _linear(initial: float) -> Any:
    def schedule(progress_remaining: float) -> float:
        return progress_remaining * initial

    return schedule


def zoo_hyperparams(algo: str, key: str) -> tuple[int, dict[str, Any]]:
    """An entry of rl_zoo3's installed ``hyperparams/<algo>.yml`` as constructor keywords.

    Converted as rl_zoo3 does: ``lin_<x>`` strings become linear schedules, a ``policy_kwargs`` string is evaluated,
    ``n_timesteps`` is dropped (the budget is ``--steps``) and ``policy`` is left to the caller.

    :param algo: ``"ppo"``, ``"dqn"`` or ``"sac"``
    :param key: the entry, e.g. ``"CartPole-v1"``
    :return: ``(n_envs, keywords)``
    """
    try:
        import rl_zoo3
    except ImportError as error:
        raise ImportError(f"the baselines' hyperparameters need the 'zoo' extra (rl_zoo3): {error}") from error
    import torch.nn as nn
    import yaml

    path = pathlib.Path(rl_zoo3.__file__).parent / "hyperparams" / f"{algo}.yml"
    if not path.is_file():
        raise ValueError(f"rl_zoo3 has no hyperparameter file for algo {algo!r} ({path})")
    entries = yaml.safe_load(path.read_text())
    if key not in entries:
        raise ValueError(f"rl_zoo3's {algo}.yml has no entry {key!r}")
    entry = dict(entries[key])
    unsupported = {"normalize", "frame_stack", "env_wrapper", "callback", "vec_env_wrapper"} & set(entry)
    if unsupported:
        raise ValueError(f"zoo entry {algo}/{key} uses {sorted(unsupported)}, which cpu_suite does not apply")
    n_envs = int(entry.pop("n_envs", 1))
    entry.pop("n_timesteps", None)
    entry.pop("policy", None)
    for name, value in entry.items():
        if isinstance(value, str) and value.startswith("lin_"):
            entry[name] = _linear(float(value[len("lin_") :]))
    if isinstance(entry.get("policy_kwargs"), str):
        entry["policy_kwargs"] = eval(entry["policy_kwargs"], {"dict": dict, "nn": nn})  # as rl_zoo3 does
    if isinstance(entry.get("train_freq"), list):
        entry["train_freq"] = tuple(entry["train_freq"])
    return n_envs, entry


def task_vec_env(spec: TaskSpec, n_envs: int, seed: int) -> Any:
    """The training env of a task: ``n_envs`` monitored envs of :func:`benchmarks.suites.make_env` (seeds ``seed``,
    ``seed + 1``, ...) in a ``DummyVecEnv``, image observations channel-first."""
    from stable_baselines3.common.monitor import Monitor
    from stable_baselines3.common.preprocessing import is_image_space, is_image_space_channels_first
    from stable_baselines3.common.vec_env import DummyVecEnv, VecTransposeImage

    from benchmarks.suites import make_env

    def maker(rank: int) -> Any:
        return lambda: Monitor(make_env(spec.suite, spec.task, seed=seed + rank))

    venv: Any = DummyVecEnv([maker(rank) for rank in range(n_envs)])
    if is_image_space(venv.observation_space) and not is_image_space_channels_first(venv.observation_space):
        venv = VecTransposeImage(venv)
    return venv


def run_suite_run(
    run: SuiteRun, checkpoint_dir: pathlib.Path | None = None, checkpoint_freq: int = 0
) -> dict[str, Any]:
    """Train and evaluate one run.

    A HIEROS run with ``checkpoint_dir`` and ``checkpoint_freq`` saves its model, replay and evaluations so far into
    ``checkpoint_dir`` every ``checkpoint_freq`` agent steps (the files of :class:`benchmarks.train.RunCheckpoint`),
    and goes on from the checkpoint it finds there (``docs/resume.md``: the same updates per level as a run that never
    stopped; the random streams are seeded with ``seed + step``, and the evaluation env starts its episodes afresh).
    The folder is removed when the run has finished. Other algorithms ignore both.

    :param run: what to run
    :param checkpoint_dir: the run's checkpoint folder (:func:`run_checkpoint_dir`); None: no checkpoints
    :param checkpoint_freq: agent steps between two checkpoints (0: none)
    :return: ``{**run fields, "eval_steps": [...], "eval_returns": [...], "trained_steps", "final_mean", "final_std",
        "wall_s"}``, and ``"resumed_at"`` (the steps it went on from) for a run continued from a checkpoint
    :raises ValueError: a checkpoint in ``checkpoint_dir`` that belongs to a run with other settings
    """
    import torch as th
    from stable_baselines3 import DQN, PPO, SAC
    from stable_baselines3.common.callbacks import BaseCallback, CallbackList
    from stable_baselines3.common.evaluation import evaluate_policy

    from benchmarks._checkpoint import check_same_options, load_checkpoint
    from benchmarks.suites import SUITE_POLICIES
    from benchmarks.train import RunCheckpoint
    from sb3_hieros import HIEROS

    if run.task not in TASKS:
        raise ValueError(f"unknown task {run.task!r}; expected one of {sorted(TASKS)}")
    spec = TASKS[run.task]
    if run.algo not in spec.algos:
        raise ValueError(f"algo {run.algo!r} is not run on {run.task!r}; expected one of {spec.algos}")
    if isinstance(checkpoint_freq, bool) or not isinstance(checkpoint_freq, int) or checkpoint_freq < 0:
        raise ValueError(f"checkpoint_freq must be an int >= 0 (0: no checkpoints), got {checkpoint_freq!r}")
    if run.algo == "dreamerv3":
        from benchmarks.peers import run_dreamerv3

        return run_dreamerv3(run)
    th.set_num_threads(1)
    policy = SUITE_POLICIES[spec.suite]
    if run.algo == "hieros":
        n_envs, kwargs = 1, {"preset": "small", **run.hieros_kwargs}
    else:
        n_envs, kwargs = zoo_hyperparams(run.algo, spec.zoo_key)
        if run.algo == "sac":
            kwargs["buffer_size"] = min(int(kwargs.get("buffer_size", 1_000_000)), run.steps)
    env = task_vec_env(spec, n_envs, run.seed)
    eval_env = task_vec_env(spec, 1, run.seed + EVAL_SEED_OFFSET)
    algo_class: Any = {"hieros": HIEROS, "ppo": PPO, "dqn": DQN, "sac": SAC}[run.algo]
    checkpointing = run.algo == "hieros" and checkpoint_dir is not None and checkpoint_freq > 0
    saved = None
    if checkpointing and (checkpoint_dir / "progress.json").is_file():
        saved = json.loads((checkpoint_dir / "progress.json").read_text())
        check_same_options(saved["run"], json.loads(json.dumps(asdict(run))), checkpoint_dir / "progress.json")
    start = time.perf_counter()
    evaluations: list[tuple[int, float]] = []
    if saved is None:
        model = algo_class(policy, env, seed=run.seed, **kwargs)
        earlier_s, resumed_at = 0.0, []
    else:
        step = int(saved["step"])
        model = load_checkpoint(checkpoint_dir, step, env)
        model.set_random_seed(run.seed + step)
        evaluations = [(int(t), float(r)) for t, r in saved["evaluations"]]
        earlier_s, resumed_at = float(saved["wall_s"]), [*saved["resumed_at"], step]
    milestones = [m for m in (run.steps * i // run.n_evals for i in range(1, run.n_evals)) if m > model.num_timesteps]

    class EvaluateAtMilestones(BaseCallback):
        def _on_step(self) -> bool:
            while milestones and self.num_timesteps >= milestones[0]:
                milestones.pop(0)
                mean, _ = evaluate_policy(model, eval_env, n_eval_episodes=run.eval_episodes, deterministic=True)
                evaluations.append((int(self.num_timesteps), float(mean)))
            return True

    callbacks: list[BaseCallback] = [EvaluateAtMilestones()]
    if checkpointing:

        def progress() -> dict[str, Any]:
            return {
                "run": asdict(run),
                "wall_s": earlier_s + time.perf_counter() - start,
                "resumed_at": resumed_at,
                "evaluations": evaluations,
            }

        callbacks.append(RunCheckpoint(checkpoint_dir, checkpoint_freq, progress))
    model.learn(run.steps - model.num_timesteps, callback=CallbackList(callbacks), reset_num_timesteps=saved is None)
    returns, _ = evaluate_policy(
        model, eval_env, n_eval_episodes=run.eval_episodes, deterministic=True, return_episode_rewards=True
    )
    evaluations.append((int(model.num_timesteps), float(np.mean(returns))))
    wall = earlier_s + time.perf_counter() - start
    env.close()
    eval_env.close()
    if checkpointing:
        shutil.rmtree(checkpoint_dir, ignore_errors=True)
    resumed = {"resumed_at": resumed_at} if resumed_at else {}
    return {
        **asdict(run),
        "eval_steps": [t for t, _ in evaluations],
        "eval_returns": [m for _, m in evaluations],
        "trained_steps": int(model.num_timesteps),
        "final_mean": float(np.mean(returns)),
        "final_std": float(np.std(returns)),
        "wall_s": round(wall, 1),
        "commit": _git_commit(),
        **resumed,
    }


def _run_with_checkpoints(run: SuiteRun, out: pathlib.Path, checkpoint_freq: int) -> dict[str, Any]:
    """:func:`run_suite_run` with the run's checkpoint folder under ``out`` (a top-level function, for the pool)."""
    return run_suite_run(run, run_checkpoint_dir(out, run), checkpoint_freq)


def _git_commit() -> str | None:
    """The commit of the checkout this file lies in (with ``+dirty`` for uncommitted changes), None outside git."""
    import subprocess

    root = pathlib.Path(__file__).resolve().parent.parent
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"], cwd=root, capture_output=True, text=True
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None
    return commit + ("+dirty" if dirty else "")


def finished_runs(path: str | pathlib.Path) -> dict[tuple[Any, ...], dict[str, Any]]:
    """The records of ``runs.jsonl`` (see ``--resume``) by :func:`run_key`; the last line of a run wins.

    :param path: the ``runs.jsonl`` file; a missing file means no finished runs
    :return: run key -> record
    :raises ValueError: a line that is not a JSON record of a run, naming the file and the line number (a last line
        without its newline, an append cut short by a crash, is left out with a warning: that run is done again)
    """
    path = pathlib.Path(path)
    if not path.is_file():
        return {}
    names = [f.name for f in fields(SuiteRun)]
    done: dict[tuple[Any, ...], dict[str, Any]] = {}
    text = path.read_text()
    lines = text.splitlines()
    for number, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            record = json.loads(line)
            run = SuiteRun(**{name: record[name] for name in names})
        except (json.JSONDecodeError, KeyError, TypeError) as error:
            if number == len(lines) and not text.endswith("\n"):
                warnings.warn(
                    f"{path}:{number} is an unfinished record (cut short by a crash?); left out", stacklevel=2
                )
                continue
            raise ValueError(f"{path}:{number} is not a cpu_suite run record ({error}): {line[:80]!r}") from error
        done[run_key(run)] = record
    return done


def drop_unfinished_line(path: pathlib.Path) -> None:
    """Cut a last line without its newline (an append that a crash cut short) from ``runs.jsonl`` before appending."""
    if not path.is_file():
        return
    data = path.read_bytes()
    if data and not data.endswith(b"\n"):
        with path.open("r+b") as handle:
            handle.truncate(data.rfind(b"\n") + 1)


def append_record(path: pathlib.Path, record: dict[str, Any]) -> None:
    """Append one run's record to ``runs.jsonl`` as a line, on disk before this returns.

    :param path: the ``runs.jsonl`` file (a last line cut short by a crash is cut off first)
    :param record: the record of :func:`run_suite_run`
    """
    drop_unfinished_line(path)
    with path.open("a") as handle:
        handle.write(json.dumps(record) + "\n")
        handle.flush()
        os.fsync(handle.fileno())


def run_key(run: SuiteRun) -> tuple[Any, ...]:
    """The settings of ``run`` as a hashable tuple (HIEROS keywords as sorted JSON): the keys of :func:`finished_runs`.

    :param run: a run
    :return: its key
    """
    return tuple(json.dumps(v, sort_keys=True) if isinstance(v, dict) else v for v in astuple(run))


def run_checkpoint_dir(out: str | pathlib.Path, run: SuiteRun) -> pathlib.Path:
    """The checkpoint folder of ``run`` under ``out`` (``--checkpoint-freq``), named by its task, algorithm and seed
    and a digest of all its settings, so that runs with other settings never share one.

    :param out: the suite's ``--out``
    :param run: a run
    :return: ``<out>/checkpoints/<task>_<algo>_seed<seed>_<digest>``
    """
    digest = hashlib.sha256(repr(run_key(run)).encode()).hexdigest()[:12]
    return pathlib.Path(out) / CHECKPOINT_DIR / f"{run.task}_{run.algo}_seed{run.seed}_{digest}"


def recorded_runs(path: str | pathlib.Path, runs: Sequence[SuiteRun]) -> list[dict[str, Any]]:
    """The records of ``runs.jsonl`` for ``runs`` (see ``--report``), matched on task, algorithm, seed, steps and
    HIEROS keywords but not on the evaluation settings, so tasks evaluated differently (fewer episodes on pixels) can
    share one table. Runs without a record are left out.

    :param path: the ``runs.jsonl`` file
    :param runs: the runs wanted, in table order
    :return: the records found, in the order of ``runs``
    :raises ValueError: two records of one run that differ only in their evaluation settings
    """

    def settings(run: SuiteRun | dict[str, Any]) -> tuple[Any, ...]:
        fields_ = asdict(run) if isinstance(run, SuiteRun) else run
        names = ("task", "algo", "seed", "steps")
        return (*(fields_[n] for n in names), json.dumps(fields_["hieros_kwargs"], sort_keys=True))

    found: dict[tuple[Any, ...], dict[str, Any]] = {}
    for record in finished_runs(path).values():
        key = settings(record)
        if key in found:
            evals = [(r["n_evals"], r["eval_episodes"]) for r in (found[key], record)]
            raise ValueError(
                f"{path} has two records of {key[:4]} with different evaluation settings (n_evals, eval_episodes) "
                f"{evals[0]} and {evals[1]}; expected one per run: remove the line you do not want in the table"
            )
        found[key] = record
    return [found[settings(run)] for run in runs if settings(run) in found]


def suite_runs(
    tasks: Sequence[str],
    algos: Sequence[str],
    seeds: Sequence[int],
    steps: int,
    eval_episodes: int = 10,
    n_evals: int = 5,
    hieros_kwargs: dict[str, Any] | None = None,
) -> list[SuiteRun]:
    """Every (task, algorithm, seed) combination, skipping algorithms a task does not run (e.g. DQN on Pendulum).

    :param tasks: keys of :data:`TASKS`
    :param algos: algorithms of :data:`ALGOS`
    :param seeds: seeds
    :param steps: agent steps per run (>= 1)
    :param eval_episodes: episodes per evaluation
    :param n_evals: evaluations per run, the last at the end
    :param hieros_kwargs: HIEROS keywords, given to the HIEROS runs only (every other run has none, so that a report
        with HIEROS keywords still finds the peers' records)
    :return: the runs, task-major, then algorithm, then seed
    """
    for task in tasks:
        if task not in TASKS:
            raise ValueError(f"unknown task {task!r}; expected some of {sorted(TASKS)}")
    for algo in algos:
        if algo not in ALGOS:
            raise ValueError(f"unknown algo {algo!r}; expected some of {ALGOS}")
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise ValueError(f"steps must be an int >= 1, got {steps!r}")
    if isinstance(n_evals, bool) or not isinstance(n_evals, int) or n_evals < 1:
        raise ValueError(f"n_evals must be an int >= 1, got {n_evals!r}")
    return [
        SuiteRun(task, algo, seed, steps, eval_episodes, n_evals, dict(hieros_kwargs or {}) if algo == "hieros" else {})
        for task in tasks
        for algo in TASKS[task].algos
        if algo in algos
        for seed in seeds
    ]


def table(records: Sequence[dict[str, Any]]) -> str:
    """Markdown table: one row per task with the episodes of its final evaluation, per algorithm the final return
    (mean +- std over seeds) and wall time, and the steps actually trained where they exceed the budget (PPO trains
    whole rollouts of ``n_steps * n_envs``).

    :param records: results of :func:`run_suite_run`
    :return: the table
    """
    algos = [a for a in ALGOS if any(r["algo"] == a for r in records)]
    lines = [
        "| Task | Steps | Final eval | " + " | ".join(LABELS[a] for a in algos) + " |",
        "|---|---:|---:|" + "---:|" * len(algos),
    ]
    for task in dict.fromkeys(r["task"] for r in records):
        cells = []
        for algo in algos:
            runs = [r for r in records if r["task"] == task and r["algo"] == algo]
            if not runs:
                cells.append("")
                continue
            finals = np.array([r["final_mean"] for r in runs])
            wall = np.mean([r["wall_s"] for r in runs])
            trained = max(r["trained_steps"] for r in runs)
            extra = f", {trained:,} steps" if trained != runs[0]["steps"] else ""
            seeds = f"{len(runs)} seed" + ("s" if len(runs) != 1 else "")
            cells.append(f"{finals.mean():.1f} +- {finals.std():.1f} ({seeds}, {wall:.0f} s/run{extra})")
        steps = max(r["steps"] for r in records if r["task"] == task)
        episodes = "/".join(str(e) for e in sorted({r["eval_episodes"] for r in records if r["task"] == task}))
        lines.append(f"| {task} | {steps:,} | {episodes} episodes | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot(records: Sequence[dict[str, Any]], path: str | pathlib.Path) -> None:
    """Evaluation return against agent steps, one panel per task, mean over seeds per algorithm (min-max shaded).

    :param records: results of :func:`run_suite_run`
    :param path: PNG file
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tasks = list(dict.fromkeys(r["task"] for r in records))
    colors = {
        "hieros": "tab:red",
        "dreamerv3": "tab:orange",
        "ppo": "tab:blue",
        "dqn": "tab:green",
        "sac": "tab:purple",
    }
    fig, axes = plt.subplots(1, len(tasks), figsize=(4 * len(tasks), 3.2), squeeze=False)
    for ax, task in zip(axes[0], tasks, strict=True):
        for algo in ALGOS:
            runs = [r for r in records if r["task"] == task and r["algo"] == algo]
            if not runs:
                continue
            length = min(len(r["eval_returns"]) for r in runs)
            curves = np.array([r["eval_returns"][:length] for r in runs])
            x = runs[0]["eval_steps"][:length]
            ax.plot(x, curves.mean(0), color=colors[algo], label=LABELS[algo], marker=".")
            ax.fill_between(x, curves.min(0), curves.max(0), color=colors[algo], alpha=0.15)
        ax.set_title(task, fontsize=10)
        ax.set_xlabel("agent steps")
        ax.legend(fontsize=8)  # one per panel: the algorithms differ between tasks
    axes[0][0].set_ylabel("evaluation return")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _check_peers_extra() -> None:
    """Fail before training anything when ``dreamerv3`` runs are asked for without sheeprl."""
    import importlib.util

    if importlib.util.find_spec("sheeprl") is None:
        raise ImportError(
            "the dreamerv3 runs need the 'peers' extra (pip install 'sb3-hieros[peers]'); "
            "leave them out with --algos hieros ppo dqn sac"
        )


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    """Command line (see the module docstring)."""
    from benchmarks.sweep import execute

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=list(TASKS), choices=list(TASKS))
    parser.add_argument("--algos", nargs="+", default=list(ALGOS), choices=list(ALGOS))
    parser.add_argument("--seeds", type=int, default=3, help="how many seeds: S..S+N-1 with --first-seed S (default 0)")
    parser.add_argument(
        "--first-seed",
        type=int,
        default=0,
        help="the first seed S (to split the seeds of a suite over processes)",
    )
    parser.add_argument("--steps", type=int, default=20_000, help="agent steps per run, every algorithm")
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument(
        "--n-evals", type=int, default=5, help="evaluations per run, evenly spaced, the last at the end"
    )
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--hieros-kwargs", type=json_object, default={}, help="JSON dict of HIEROS keywords")
    parser.add_argument("--out", default="cpu_suite")
    parser.add_argument(
        "--resume", action="store_true", help="reuse the runs already recorded in <out>/runs.jsonl (same settings)"
    )
    parser.add_argument(
        "--checkpoint-freq",
        type=int,
        default=0,
        help="HIEROS runs: save a checkpoint into <out>/checkpoints/ every N agent steps; with --resume an unfinished "
        "run goes on from its checkpoint (0: none)",
    )
    parser.add_argument(
        "--report",
        action="store_true",
        help="train nothing: remake table.md and the PNG from <out>/runs.jsonl for --tasks/--algos/--seeds/--steps, "
        "whatever their evaluation settings",
    )
    args = parser.parse_args(argv)
    if args.first_seed < 0:
        parser.error(f"--first-seed must be >= 0, got {args.first_seed}")
    if args.checkpoint_freq < 0:
        parser.error(f"--checkpoint-freq must be >= 0 (0: no checkpoints), got {args.checkpoint_freq}")
    runs = suite_runs(
        args.tasks,
        args.algos,
        range(args.first_seed, args.first_seed + args.seeds),
        args.steps,
        args.eval_episodes,
        args.n_evals,
        args.hieros_kwargs,
    )

    def report(record: dict[str, Any]) -> None:
        print(
            f"{record['task']} {record['algo']} seed {record['seed']}: final {record['final_mean']:.1f} "
            f"+- {record['final_std']:.1f}, {record['wall_s']} s",
            flush=True,
        )

    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    log = out / "runs.jsonl"
    if args.report:
        records = recorded_runs(log, runs)
        if not records:
            raise ValueError(f"{log} records none of the {len(runs)} runs asked for; expected at least one")
        if len(records) < len(runs):
            print(f"--report: {len(runs) - len(records)} of {len(runs)} runs not in {log}, left out", flush=True)
    else:
        done = finished_runs(log) if args.resume else {}
        drop_unfinished_line(log)
        todo = [run for run in runs if run_key(run) not in done]
        if done:
            print(f"--resume: {len(runs) - len(todo)} of {len(runs)} runs already in {log}", flush=True)

        if any(run.algo == "dreamerv3" for run in todo):
            _check_peers_extra()

        def record_run(record: dict[str, Any]) -> None:
            append_record(log, record)  # one line per run, on disk before the next run starts
            report(record)

        if not args.resume:  # every run starts afresh: an earlier run's checkpoint is not gone on from
            for run in todo:
                shutil.rmtree(run_checkpoint_dir(out, run), ignore_errors=True)
        runner: Callable[[SuiteRun], dict[str, Any]] = run_suite_run
        if args.checkpoint_freq:
            runner = functools.partial(_run_with_checkpoints, out=out, checkpoint_freq=args.checkpoint_freq)
        fresh = iter(execute(runner, todo, workers=args.workers, report=record_run))
        records = [done.get(run_key(run)) or next(fresh) for run in runs]
        (out / "results.json").write_text(json.dumps(records, indent=1))
    markdown = table(records)
    (out / "table.md").write_text(markdown + "\n")
    plot(records, out / "cpu_suite.png")
    print(markdown)
    return records


if __name__ == "__main__":
    main()
