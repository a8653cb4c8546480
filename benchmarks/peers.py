"""A DreamerV3 peer for the CPU suite: sheeprl's DreamerV3 (XS) trained and evaluated as ``benchmarks.cpu_suite`` runs.

Each run trains sheeprl's DreamerV3 with its command line (``python -m sheeprl``, in a subprocess with one torch thread)
on a CPU-suite task for ``--steps`` agent steps, saving a checkpoint at every evaluation point; then each checkpoint is
evaluated as ``cpu_suite`` evaluates: ``--eval-episodes`` episodes of the greedy policy (the mode of the actor) on a
separate env seeded ``seed + 10000``, one env for all evaluations of the run. The environments are those of the suite
(:func:`benchmarks.suites.make_env` through :func:`sheeprl_env`, so the action repeat of DMC, the pixel size and the
time limits are the same), wrapped by sheeprl's own ``make_env`` as its training does.

The settings are sheeprl's ``exp=dreamer_v3 env=gym algo=dreamer_v3_XS`` with the overrides of
:func:`sheeprl_overrides`: one env, ``--steps`` steps, 16-step training sequences with
``algo.replay_ratio=0.25`` gradient steps per agent step (16 x 16 = 256 replayed steps per gradient step, so 64
replayed steps per agent step: the ``train_ratio=64`` of HIEROS' ``small`` preset), encoder and decoder keys of the
observation (``state`` for vectors, ``rgb`` for pixels), no video, no tensorboard log, no test episode of sheeprl's own.
Everything else (learning rates, ``learning_starts=1024``, model sizes) is sheeprl's XS configuration. Each record
names the exact command line in ``"sheeprl"``.

The records are the rows of ``cpu_suite`` (algo ``"dreamerv3"``), appended to ``<out>/runs.jsonl`` as each run
finishes; ``python -m benchmarks.cpu_suite ... --report`` puts them into the table and the figure. Needs the ``peers``
extra (``pip install 'sb3-hieros[peers]'``, which pins sheeprl 0.8.4). Example::

    python -m benchmarks.peers --tasks CartPole-v1 --seeds 3 --steps 10000 --out docs/cpu_suite --resume
    python -m benchmarks.cpu_suite --seeds 3 --steps 10000 --out docs/cpu_suite --report
"""

from __future__ import annotations

import argparse
import os
import pathlib
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import asdict
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from benchmarks.cpu_suite import SuiteRun

os.environ.setdefault("MUJOCO_GL", "egl")

__all__ = [
    "ALGO",
    "SHEEPRL_VERSION",
    "checkpoint_steps",
    "run_dreamerv3",
    "sheeprl_command",
    "sheeprl_env",
    "sheeprl_overrides",
]

#: The algorithm name of the peer's records in ``runs.jsonl``.
ALGO = "dreamerv3"
#: The sheeprl release the ``peers`` extra pins and the records were made with.
SHEEPRL_VERSION = "0.8.4"
#: sheeprl's experiment, environment family and model size.
BASE_OVERRIDES = ("exp=dreamer_v3", "env=gym", "algo=dreamer_v3_XS")
#: Training sequence length and gradient steps per agent step (the replay of HIEROS' ``small`` preset, see the module
#: docstring).
REPLAY_OVERRIDES = ("algo.per_rank_sequence_length=16", "algo.replay_ratio=0.25")
ROOT = pathlib.Path(__file__).resolve().parent.parent


def sheeprl_env(id: str, seed: int = 0) -> Any:
    """The env of a CPU-suite task for sheeprl's ``env.wrapper`` (sheeprl passes its ``seed``).

    :param id: a key of :data:`benchmarks.cpu_suite.TASKS`, e.g. ``"cartpole-balance-proprio"``
    :param seed: seed of the first reset and of the action space
    :return: :func:`benchmarks.suites.make_env` of the task
    """
    from benchmarks.cpu_suite import TASKS
    from benchmarks.suites import make_env

    if id not in TASKS:
        raise ValueError(f"unknown CPU-suite task {id!r}; expected one of {sorted(TASKS)}")
    spec = TASKS[id]
    return make_env(spec.suite, spec.task, seed=seed)


def sheeprl_overrides(
    task: str, seed: int, steps: int, n_evals: int, log_root: str | pathlib.Path, extra: Sequence[str] = ()
) -> list[str]:
    """The Hydra overrides of one training run of sheeprl's DreamerV3 on a CPU-suite task.

    :param task: a key of :data:`benchmarks.cpu_suite.TASKS`
    :param seed: seed of sheeprl and of the training env
    :param steps: agent steps to train (>= ``n_evals``)
    :param n_evals: checkpoints, every ``steps // n_evals`` steps, the last at the end
    :param log_root: folder of sheeprl's logs and checkpoints
    :param extra: more overrides, appended (they win)
    :return: the overrides, in order
    """
    from benchmarks.cpu_suite import TASKS

    if task not in TASKS:
        raise ValueError(f"unknown task {task!r}; expected one of {sorted(TASKS)}")
    for name, value, least in (("steps", steps, 1), ("n_evals", n_evals, 1), ("seed", seed, 0)):
        if isinstance(value, bool) or not isinstance(value, int) or value < least:
            raise ValueError(f"{name} must be an int >= {least}, got {value!r}")
    if steps < n_evals:
        raise ValueError(f"steps must be >= n_evals (one checkpoint per evaluation), got {steps} < {n_evals}")
    pixels = TASKS[task].suite == "dmc_vision"
    keys = (
        ["algo.cnn_keys.encoder=[rgb]", "algo.cnn_keys.decoder=[rgb]", "algo.mlp_keys.encoder=[]"]
        if pixels
        else [
            "algo.cnn_keys.encoder=[]",
            "algo.cnn_keys.decoder=[]",
            "algo.mlp_keys.encoder=[state]",
            "algo.mlp_keys.decoder=[state]",
        ]
    )
    log_root = pathlib.Path(log_root).resolve()
    return [
        *BASE_OVERRIDES,
        f"env.id={task}",
        "env.wrapper._target_=benchmarks.peers.sheeprl_env",
        "~env.wrapper.render_mode",
        f"+env.wrapper.seed={seed}",
        "env.num_envs=1",
        "env.sync_env=True",
        "env.capture_video=False",
        f"algo.total_steps={steps}",
        *REPLAY_OVERRIDES,
        *keys,
        "algo.run_test=False",
        f"buffer.size={steps}",
        "buffer.checkpoint=False",
        f"checkpoint.every={steps // n_evals}",
        f"checkpoint.keep_last={n_evals + 1}",
        "metric.log_level=0",
        "model_manager.disabled=True",
        "fabric.accelerator=cpu",
        "num_threads=1",
        f"seed={seed}",
        f"log_root={log_root}",
        f"run_name=seed_{seed}",
        f"hydra.run.dir={log_root / 'hydra'}",
        *extra,
    ]


def sheeprl_command(overrides: Sequence[str]) -> list[str]:
    """The command line of a sheeprl run with ``overrides``, in this Python.

    :param overrides: Hydra overrides (:func:`sheeprl_overrides`)
    :return: the command
    """
    return [sys.executable, "-m", "sheeprl", *overrides]


def checkpoint_steps(steps: int, n_evals: int, saved: Sequence[int]) -> list[int]:
    """The checkpoints to evaluate: for each of the ``n_evals`` evenly spaced evaluation points of ``cpu_suite``
    (``steps * i // n_evals``, the last at ``steps``), the first saved checkpoint at or after it.

    :param steps: agent steps of the run
    :param n_evals: evaluations
    :param saved: policy steps of the saved checkpoints
    :return: the policy steps of the checkpoints to evaluate, one per evaluation point
    :raises RuntimeError: an evaluation point without a checkpoint at or after it
    """
    chosen = []
    for i in range(1, n_evals + 1):
        point = steps * i // n_evals
        later = [s for s in saved if s >= point]
        if not later:
            raise RuntimeError(f"no checkpoint at or after step {point} among the saved ones {sorted(saved)}")
        chosen.append(min(later))
    return chosen


def _checkpoints(log_root: pathlib.Path) -> dict[int, pathlib.Path]:
    """``ckpt_<step>_<rank>.ckpt`` files under ``log_root`` by their policy step."""
    return {int(path.name.split("_")[1]): path for path in log_root.rglob("checkpoint/ckpt_*_0.ckpt")}


def _evaluate_checkpoints(paths: Sequence[pathlib.Path], seed: int, episodes: int) -> list[tuple[float, float]]:
    """Mean and std of the greedy return of each checkpoint, on one env seeded ``seed`` that continues between them."""
    import gymnasium as gym
    import torch as th
    from lightning import Fabric
    from omegaconf import OmegaConf
    from sheeprl.algos.dreamer_v3.agent import build_agent
    from sheeprl.algos.dreamer_v3.utils import prepare_obs
    from sheeprl.utils import fs
    from sheeprl.utils.env import make_env
    from sheeprl.utils.utils import dotdict

    fabric = Fabric(accelerator="cpu", devices=1, precision="32-true")
    cfg = dotdict(OmegaConf.to_container(fs.load_yaml(fs.run_config(paths[0])), resolve=True))
    env = make_env(cfg, seed, 0)()
    space = env.action_space
    continuous = isinstance(space, gym.spaces.Box)
    actions_dim = tuple(space.shape if continuous else [space.n])
    results = []
    for path in paths:
        state = fs.load_checkpoint(fabric, path, weights_only=False)
        *_, player = build_agent(
            fabric, actions_dim, continuous, cfg, env.observation_space, state["world_model"], state["actor"]
        )
        player.num_envs = 1
        returns = []
        for _ in range(episodes):
            obs, _ = env.reset()
            player.init_states()
            done, total = False, 0.0
            while not done:
                with th.inference_mode():
                    torch_obs = prepare_obs(fabric, obs, cnn_keys=cfg.algo.cnn_keys.encoder)
                    actions = player.get_actions(torch_obs, greedy=True)
                if continuous:
                    action = th.stack(actions, -1).cpu().numpy().reshape(space.shape)
                else:
                    action = int(actions[0].argmax(-1).item())
                obs, reward, terminated, truncated, _ = env.step(action)
                total += float(reward)
                done = terminated or truncated
            returns.append(total)
        results.append((float(np.mean(returns)), float(np.std(returns))))
    env.close()
    return results


def run_dreamerv3(
    run: SuiteRun, extra_overrides: Sequence[str] = (), work_dir: str | pathlib.Path | None = None
) -> dict[str, Any]:
    """Train sheeprl's DreamerV3 on one CPU-suite run and evaluate it as ``cpu_suite`` does.

    :param run: a :class:`benchmarks.cpu_suite.SuiteRun` with ``algo="dreamerv3"`` and no HIEROS keywords
    :param extra_overrides: Hydra overrides after those of :func:`sheeprl_overrides`
    :param work_dir: folder of sheeprl's logs and checkpoints, kept; None: a temporary folder, removed at the end
    :return: the ``cpu_suite`` record, with ``"sheeprl"``: version, command line, training and evaluation seconds
    """
    import torch as th

    from benchmarks.cpu_suite import EVAL_SEED_OFFSET, _git_commit

    if run.algo != ALGO:
        raise ValueError(f"run_dreamerv3 runs algo {ALGO!r}, got {run.algo!r}")
    if run.hieros_kwargs:
        raise ValueError(f"a {ALGO} run takes no HIEROS keywords, got {run.hieros_kwargs!r}")
    try:
        import sheeprl
    except ImportError as error:
        raise ImportError(f"{ALGO} runs need the 'peers' extra (pip install 'sb3-hieros[peers]'): {error}") from error
    if sheeprl.__version__ != SHEEPRL_VERSION:
        raise ImportError(f"{ALGO} runs need sheeprl {SHEEPRL_VERSION}, found {sheeprl.__version__}")
    root = pathlib.Path(work_dir) if work_dir is not None else pathlib.Path(tempfile.mkdtemp(prefix="peers_"))
    log_root = root / f"{run.task}_seed{run.seed}"
    overrides = sheeprl_overrides(run.task, run.seed, run.steps, run.n_evals, log_root, extra_overrides)
    command = sheeprl_command(overrides)
    environment = {
        **os.environ,
        "OMP_NUM_THREADS": "1",
        "MKL_NUM_THREADS": "1",
        "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
    }
    log_root.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    with (log_root / "sheeprl.log").open("w") as log:
        finished = subprocess.run(command, cwd=ROOT, env=environment, stdout=log, stderr=subprocess.STDOUT)
    train_s = time.perf_counter() - start
    if finished.returncode != 0:
        tail = (log_root / "sheeprl.log").read_text()[-3000:]
        raise RuntimeError(f"sheeprl exited with {finished.returncode}: {' '.join(command)}\n{tail}")
    saved = _checkpoints(log_root)
    chosen = checkpoint_steps(run.steps, run.n_evals, list(saved))
    threads = th.get_num_threads()
    th.set_num_threads(1)
    try:
        evaluations = _evaluate_checkpoints([saved[s] for s in chosen], run.seed + EVAL_SEED_OFFSET, run.eval_episodes)
    finally:
        th.set_num_threads(threads)
    wall = time.perf_counter() - start
    if work_dir is None:
        shutil.rmtree(root, ignore_errors=True)
    return {
        **asdict(run),
        "eval_steps": chosen,
        "eval_returns": [mean for mean, _ in evaluations],
        "trained_steps": max(saved),
        "final_mean": evaluations[-1][0],
        "final_std": evaluations[-1][1],
        "wall_s": round(wall, 1),
        "commit": _git_commit(),
        "sheeprl": {
            "version": SHEEPRL_VERSION,
            "command": ["python", "-m", "sheeprl", *[o for o in overrides if not _is_path_override(o)]],
            "train_s": round(train_s, 1),
            "eval_s": round(wall - train_s, 1),
        },
    }


def _is_path_override(override: str) -> bool:
    """Overrides naming local folders (the log root), left out of the recorded command."""
    return override.startswith(("log_root=", "hydra.run.dir="))


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    """Command line (see the module docstring)."""
    from benchmarks.cpu_suite import TASKS, append_record, finished_runs, run_key, suite_runs

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=list(TASKS), choices=list(TASKS))
    parser.add_argument("--seeds", type=int, default=3, help="seeds 0..N-1")
    parser.add_argument("--steps", type=int, default=10_000, help="agent steps per run")
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument(
        "--n-evals", type=int, default=5, help="evaluations per run, evenly spaced, the last at the end"
    )
    parser.add_argument("--out", default="cpu_suite", help="folder of runs.jsonl")
    parser.add_argument(
        "--resume", action="store_true", help="skip the runs recorded in <out>/runs.jsonl with the same settings"
    )
    parser.add_argument(
        "--sheeprl-overrides", nargs="*", default=[], help="more Hydra overrides of sheeprl (recorded in each row)"
    )
    parser.add_argument("--work-dir", default=None, help="keep sheeprl's logs and checkpoints here")
    args = parser.parse_args(argv)
    runs = suite_runs(args.tasks, [ALGO], range(args.seeds), args.steps, args.eval_episodes, args.n_evals)
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    log = out / "runs.jsonl"
    done = finished_runs(log) if args.resume else {}
    records = []
    for run in runs:
        record = done.get(run_key(run))
        if record is not None and _recorded_extra(record) == list(args.sheeprl_overrides):
            print(f"--resume: {run.task} seed {run.seed} already in {log}", flush=True)
        else:
            record = run_dreamerv3(run, args.sheeprl_overrides, args.work_dir)
            append_record(log, record)
            print(
                f"{run.task} {ALGO} seed {run.seed}: final {record['final_mean']:.1f} +- {record['final_std']:.1f}, "
                f"evaluations {[round(r, 1) for r in record['eval_returns']]} at {record['eval_steps']}, "
                f"{record['wall_s']} s",
                flush=True,
            )
        records.append(record)
    return records


def _recorded_extra(record: dict[str, Any]) -> list[str] | None:
    """The overrides a record ran with beyond those :func:`sheeprl_overrides` gives its settings."""
    command = record.get("sheeprl", {}).get("command")
    if command is None:
        return None
    base = sheeprl_overrides(record["task"], record["seed"], record["steps"], record["n_evals"], ".")
    base = [o for o in base if not _is_path_override(o)]
    overrides = command[3:]
    return overrides[len(base) :] if overrides[: len(base)] == base else None


if __name__ == "__main__":
    main()
