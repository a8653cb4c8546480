"""A small local sweep runner: HIEROS training runs (variant x task x seed) sequentially or in a process pool.

Each :class:`Run` trains one HIEROS model on one task and records the collected reward of every finished training
episode (SB3's ``Monitor``: return and the environment step at which the episode ended), which is what the thesis'
ablation figures plot ("collected reward per step"). :func:`run_sweep` runs a list of them with ``workers`` processes
(one torch thread each; ``workers=1`` runs them in this process) and returns the records in the order given.

Tasks: a gymnasium id (``CartPole-v1``, ``Pendulum-v1`` ...) is made with SB3's ``make_vec_env`` and trained with
``MlpPolicy``; an Atari id (``ALE/<Game>-v5``, needs ``ale-py``) with ``make_atari_env`` (SB3's Atari wrappers, 84x84
grey frames, frame skip 4) + ``VecTransposeImage`` and ``CnnPolicy``.

Command line (one variant, for a quick check)::

    python -m benchmarks.sweep --env CartPole-v1 --seeds 2 --steps 2000 --workers 2 --kwargs '{"preset": "small"}'
"""

from __future__ import annotations

import argparse
import json
import os
import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field
from typing import Any

__all__ = ["Run", "atari_id", "run_one", "run_sweep"]


@dataclass(frozen=True)
class Run:
    """One training run.

    :param variant: label of the configuration (e.g. ``"hieros"`` or an ablation name)
    :param env_id: gymnasium id (``ALE/...`` ids use the Atari wrappers)
    :param seed: random seed of the model and the environment
    :param steps: environment steps to train
    :param kwargs: HIEROS keywords (``preset``, ``config_overrides``, ``learning_starts`` ...)
    :param threads: torch threads of the run
    """

    variant: str
    env_id: str
    seed: int
    steps: int
    kwargs: dict[str, Any] = field(default_factory=dict)
    threads: int = 1


def atari_id(game: str) -> str:
    """Gymnasium id of an Atari game name (``"Krull"`` -> ``"ALE/Krull-v5"``); ids pass unchanged."""
    return game if "/" in game or game.endswith(("-v0", "-v1", "-v4", "-v5")) else f"ALE/{game}-v5"


def run_one(run: Run) -> dict[str, Any]:
    """Train one run and return its record.

    :param run: what to train
    :return: ``{"variant", "env_id", "seed", "steps", "episode_end_steps": [...], "episode_returns": [...],
        "wall_s", "updates": [per level]}``
    """
    import torch as th
    from stable_baselines3.common.env_util import make_atari_env, make_vec_env
    from stable_baselines3.common.vec_env import VecTransposeImage

    from sb3_hieros import HIEROS

    th.set_num_threads(max(1, run.threads))
    if run.env_id.startswith("ALE/"):
        env: Any = VecTransposeImage(make_atari_env(run.env_id, n_envs=1, seed=run.seed))
        policy = "CnnPolicy"
    else:
        env = make_vec_env(run.env_id, n_envs=1, seed=run.seed)
        policy = "MlpPolicy"
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
        "updates": list(model._level_updates or []),
    }


def run_sweep(runs: Sequence[Run], workers: int = 1, verbose: bool = True) -> list[dict[str, Any]]:
    """Train every run, ``workers`` at a time (processes; 1 = sequentially in this process).

    :param runs: the runs, started in this order
    :param workers: number of worker processes
    :param verbose: print one line per finished run
    :return: the records of :func:`run_one`, in the order of ``runs``
    """
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    os.environ.setdefault("OMP_NUM_THREADS", "1")

    def report(record: dict[str, Any]) -> None:
        if verbose:
            returns = record["episode_returns"]
            last = sum(returns[-10:]) / max(1, len(returns[-10:]))
            print(
                f"{record['variant']} {record['env_id']} seed {record['seed']}: {len(returns)} episodes, "
                f"last-10 return {last:.1f}, {record['wall_s']} s",
                flush=True,
            )

    records = []
    if workers == 1:
        for run in runs:
            records.append(run_one(run))
            report(records[-1])
        return records
    with ProcessPoolExecutor(max_workers=workers) as pool:
        for future in [pool.submit(run_one, run) for run in runs]:
            records.append(future.result())
            report(records[-1])
    return records


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    """Command line: seeds 0..N-1 of one HIEROS configuration on one task (see the module docstring)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="CartPole-v1")
    parser.add_argument("--seeds", type=int, default=1)
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--kwargs", default='{"preset": "small"}', help="JSON dict of HIEROS keywords")
    args = parser.parse_args(argv)
    kwargs = json.loads(args.kwargs)
    runs = [Run("hieros", args.env, seed, args.steps, kwargs) for seed in range(args.seeds)]
    return run_sweep(runs, args.workers)


if __name__ == "__main__":
    main()
