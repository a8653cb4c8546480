"""Sample efficiency on CartPole-v1: HIEROS (small preset) against SB3's PPO and DQN with rl-zoo hyperparameters.

Every (algorithm, seed) run trains on CartPole-v1 and is evaluated with the deterministic policy when it passes each
step milestone (default 5k / 10k / 20k environment steps, ``--eval-episodes`` episodes on a separate env); the run
stops after the last milestone. Runs go side by side in one invocation (``--workers`` processes), and the script
prints a markdown table (mean +- std over seeds per milestone), writes ``results.json`` and ``sample_efficiency.png``
into ``--out`` and ends with ``name: value`` lines.

PPO and DQN use the rl-zoo3 2.9.2 hyperparameters for CartPole-v1 (``hyperparams/ppo.yml`` and ``dqn.yml``) and are
trained with the zoo's total budget (``n_timesteps``), so their linear schedules and exploration decay match a zoo
run; the milestones only decide when to evaluate and stop. HIEROS takes ``--hieros-kwargs`` (JSON) on top of
``preset="small"``.

``--report FILE ...`` trains nothing: it merges the runs of earlier ``results.json`` files and writes the table
(``table.md``) and figure of them into ``--out``; HIEROS runs of a file with ``hieros_kwargs`` are labelled with them.

Examples::

    python -m benchmarks.sample_efficiency --seeds 0 1 2 --workers 2
    python -m benchmarks.sample_efficiency --report docs/sample_efficiency/small_preset.json \
        docs/sample_efficiency/ppo_dqn.json --out docs/sample_efficiency
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import time
from concurrent.futures import ProcessPoolExecutor
from typing import Any

import numpy as np

from benchmarks._cli import json_object

#: rl-zoo3 2.9.2 ``hyperparams/ppo.yml`` entry for CartPole-v1 (``lin_x`` = linear schedule from x to 0).
ZOO_PPO = {
    "n_envs": 8,
    "n_timesteps": 100_000,
    "n_steps": 32,
    "batch_size": 256,
    "gae_lambda": 0.8,
    "gamma": 0.98,
    "n_epochs": 20,
    "ent_coef": 0.0,
    "learning_rate": "lin_0.001",
    "clip_range": "lin_0.2",
}
#: rl-zoo3 2.9.2 ``hyperparams/dqn.yml`` entry for CartPole-v1.
ZOO_DQN = {
    "n_envs": 1,
    "n_timesteps": 50_000,
    "learning_rate": 2.3e-3,
    "batch_size": 64,
    "buffer_size": 100_000,
    "learning_starts": 1000,
    "gamma": 0.99,
    "target_update_interval": 10,
    "train_freq": 256,
    "gradient_steps": 128,
    "exploration_fraction": 0.16,
    "exploration_final_eps": 0.04,
    "policy_kwargs": {"net_arch": [256, 256]},
}
ALGOS = ("hieros", "ppo", "dqn")
ENV_ID = "CartPole-v1"


def _linear(initial: float):
    def schedule(progress_remaining: float) -> float:
        return progress_remaining * initial

    return schedule


def _zoo_kwargs(entry: dict[str, Any]) -> tuple[int, int, dict[str, Any]]:
    """(n_envs, n_timesteps, constructor keywords) of a zoo entry, with ``lin_x`` strings made into schedules."""
    kwargs = {k: v for k, v in entry.items() if k not in ("n_envs", "n_timesteps")}
    for key, value in kwargs.items():
        if isinstance(value, str) and value.startswith("lin_"):
            kwargs[key] = _linear(float(value[4:]))
    return int(entry["n_envs"]), int(entry["n_timesteps"]), kwargs


def run_one(algo: str, seed: int, milestones: list[int], eval_episodes: int, hieros_kwargs: dict[str, Any]) -> dict:
    """Train one algorithm with one seed and evaluate it at every milestone.

    :param algo: ``"hieros"``, ``"ppo"`` or ``"dqn"``
    :param seed: random seed (training env ``seed``, evaluation env ``seed + 1000``)
    :param milestones: increasing environment-step counts at which to evaluate; training stops after the last
    :param eval_episodes: evaluation episodes per milestone
    :param hieros_kwargs: extra HIEROS keywords
    :return: ``{"algo", "seed", "steps": [...], "returns": [...], "wall_s"}``
    """
    import torch as th
    from stable_baselines3 import DQN, PPO
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.evaluation import evaluate_policy

    from sb3_hieros import HIEROS

    th.set_num_threads(1)
    eval_env = make_vec_env(ENV_ID, n_envs=1, seed=seed + 1000)

    class EvalAtMilestones(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self.pending = list(milestones)
            self.steps: list[int] = []
            self.returns: list[float] = []

        def _on_step(self) -> bool:
            while self.pending and self.num_timesteps >= self.pending[0]:
                mean, _ = evaluate_policy(self.model, eval_env, n_eval_episodes=eval_episodes, deterministic=True)
                self.steps.append(self.pending.pop(0))
                self.returns.append(float(mean))
            return bool(self.pending)

    if algo == "hieros":
        env = make_vec_env(ENV_ID, n_envs=1, seed=seed)
        model: Any = HIEROS("MlpPolicy", env, preset="small", seed=seed, **hieros_kwargs)
        total = milestones[-1]
    elif algo in ("ppo", "dqn"):
        n_envs, total, kwargs = _zoo_kwargs(ZOO_PPO if algo == "ppo" else ZOO_DQN)
        env = make_vec_env(ENV_ID, n_envs=n_envs, seed=seed)
        model = (PPO if algo == "ppo" else DQN)("MlpPolicy", env, seed=seed, **kwargs)
        total = max(total, milestones[-1])
    else:
        raise ValueError(f"algo must be one of {ALGOS}, got {algo!r}")
    callback = EvalAtMilestones()
    start = time.perf_counter()
    model.learn(total, callback=callback)
    return {
        "algo": algo,
        "seed": seed,
        "steps": callback.steps,
        "returns": callback.returns,
        "wall_s": round(time.perf_counter() - start, 1),
    }


def summarise(runs: list[dict], milestones: list[int]) -> dict[str, dict[int, tuple[float, float, int]]]:
    """algo -> milestone -> (mean, std, number of seeds) of the evaluation returns."""
    table: dict[str, dict[int, tuple[float, float, int]]] = {}
    for algo in dict.fromkeys(r["algo"] for r in runs):
        table[algo] = {}
        for m in milestones:
            values = [r["returns"][r["steps"].index(m)] for r in runs if r["algo"] == algo and m in r["steps"]]
            if values:
                table[algo][m] = (float(np.mean(values)), float(np.std(values)), len(values))
    return table


def plot(runs: list[dict], table: dict, path: pathlib.Path) -> None:
    """Mean evaluation return against steps per algorithm (seeds as thin lines) into ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for i, (algo, rows) in enumerate(table.items()):
        color = f"C{i}"
        for r in runs:
            if r["algo"] == algo:
                ax.plot(r["steps"], r["returns"], color=color, alpha=0.3, lw=1)
        steps = sorted(rows)
        ax.plot(steps, [rows[s][0] for s in steps], color=color, marker="o", lw=2, label=algo)
    ax.set_xlabel("environment steps")
    ax.set_ylabel("evaluation return (deterministic)")
    ax.set_title(f"{ENV_ID}: HIEROS small vs rl-zoo PPO / DQN")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def markdown_table(runs: list[dict], milestones: list[int]) -> str:
    """Markdown table: per algorithm and milestone the mean +- std over seeds (and every seed's value), and the mean
    wall time of a run.

    :param runs: records of :func:`run_one`
    :param milestones: the step counts of the columns
    :return: the table
    """
    table = summarise(runs, milestones)
    lines = ["| algorithm | seeds | " + " | ".join(f"{m // 1000}k steps" for m in milestones) + " | wall s / run |"]
    lines.append("|---|---:|" + "---:|" * (len(milestones) + 1))
    for algo, rows in table.items():
        mine = [r for r in runs if r["algo"] == algo]
        cells = []
        for m in milestones:
            seeds = ", ".join(f"{r['returns'][r['steps'].index(m)]:.1f}" for r in mine if m in r["steps"])
            cells.append(f"{rows[m][0]:.1f} +- {rows[m][1]:.1f} ({seeds})" if m in rows else "-")
        wall = np.mean([r["wall_s"] for r in mine])
        lines.append(f"| {algo} | {len(mine)} | " + " | ".join(cells) + f" | {wall:.0f} |")
    return "\n".join(lines)


def load_runs(paths: list[pathlib.Path]) -> tuple[list[dict], list[int]]:
    """The runs of several ``results.json`` files and the union of their milestones.

    HIEROS runs of a file whose ``hieros_kwargs`` are not empty get the algorithm label ``hieros <kwargs as JSON>``.

    :param paths: ``results.json`` files of this script
    :return: ``(runs, milestones)``
    """
    runs: list[dict] = []
    milestones: set[int] = set()
    for path in paths:
        data = json.loads(pathlib.Path(path).read_text())
        if not isinstance(data, dict) or not {"runs", "milestones"} <= set(data):
            raise ValueError(f"{path} is not a results.json of benchmarks.sample_efficiency (no 'runs'/'milestones')")
        kwargs = data.get("hieros_kwargs") or {}
        for run in data["runs"]:
            label = run["algo"]
            if label == "hieros" and kwargs:
                label = f"hieros {json.dumps(kwargs, separators=(', ', ': '))}"
            runs.append({**run, "algo": label})
        milestones.update(int(m) for m in data["milestones"])
    return runs, sorted(milestones)


def report(paths: list[pathlib.Path], out: pathlib.Path) -> str:
    """Table and figure of recorded runs, without training (``--report``).

    :param paths: ``results.json`` files
    :param out: folder for ``table.md`` and ``sample_efficiency.png``
    :return: the table
    """
    runs, milestones = load_runs(paths)
    markdown = markdown_table(runs, milestones)
    out.mkdir(parents=True, exist_ok=True)
    (out / "table.md").write_text(markdown + "\n")
    plot(runs, summarise(runs, milestones), out / "sample_efficiency.png")
    return markdown


def main(argv: list[str] | None = None) -> dict:
    """Run the grid, print the table, write the files (see the module docstring).

    :param argv: command-line arguments (default: ``sys.argv``)
    :return: the summary table
    """
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--algos", nargs="+", default=list(ALGOS), choices=ALGOS)
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--milestones", nargs="+", type=int, default=[5_000, 10_000, 20_000])
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--workers", type=int, default=1, help="parallel processes (one torch thread each)")
    parser.add_argument("--hieros-kwargs", type=json_object, default={}, help="JSON dict of extra HIEROS keywords")
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("results/sample_efficiency"))
    parser.add_argument(
        "--report", nargs="+", type=pathlib.Path, default=None, help="results.json files: table and figure only"
    )
    args = parser.parse_args(argv)
    if args.report:
        print(report(args.report, args.out))
        return summarise(*load_runs(args.report))
    milestones = sorted(set(args.milestones))
    if not milestones or milestones[0] <= 0:
        raise ValueError(f"--milestones must be positive step counts, got {args.milestones}")
    hieros_kwargs = args.hieros_kwargs
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    from benchmarks._timing import environment_header

    print(environment_header())
    args.out.mkdir(parents=True, exist_ok=True)
    jobs = [(a, s) for a in args.algos for s in args.seeds]  # the slowest runs (HIEROS) first
    with ProcessPoolExecutor(max_workers=max(1, args.workers)) as pool:
        futures = [pool.submit(run_one, a, s, milestones, args.eval_episodes, hieros_kwargs) for a, s in jobs]
        runs = []
        for future in futures:
            run = future.result()
            runs.append(run)
            evals = dict(zip(run["steps"], run["returns"], strict=True))
            print(f"{run['algo']} seed {run['seed']}: {evals} ({run['wall_s']} s)")
    table = summarise(runs, milestones)
    print(markdown_table(runs, milestones))
    (args.out / "results.json").write_text(
        json.dumps({"runs": runs, "hieros_kwargs": hieros_kwargs, "milestones": milestones}, indent=2) + "\n"
    )
    plot(runs, table, args.out / "sample_efficiency.png")
    for algo, rows in table.items():
        for m, (mean, _, _) in rows.items():
            print(f"{algo}_return_{m // 1000}k: {mean:.1f}")
    if "hieros" in table and 10_000 in table["hieros"]:
        mean = table["hieros"][10_000][0]
        print(f"goal hieros >= 450 at 10k: {'met' if mean >= 450 else 'missed'} ({mean:.1f})")
    return table


if __name__ == "__main__":
    main()
