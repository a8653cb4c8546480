"""Aggregate the result JSONs of :mod:`benchmarks.train` runs into tables next to the thesis' numbers.

* **Atari100k** (thesis Table 5.1): per game our final score (mean +- std over seeds) and its human-normalised score
  (HNS, :func:`human_normalized_score`, with the table's random and human scores) next to the thesis' HIEROS and
  DreamerV3 scores; below, the mean, median, interquartile mean (IQM) and optimality gap of the HNS (in %, as the
  thesis reports them) with 95 % stratified-bootstrap confidence intervals, next to the thesis' values where the runs
  cover all 25 games (over fewer games the two would aggregate different sets).
* **DMC vision** (thesis Table 5.2): raw scores per task next to the thesis' HIEROS and DreamerV3 columns, with
  mean and median rows.
* Other suites (``dmc_proprio``, ``classic``): our scores per task.
* Learning curves: ``<out>/<suite>_curves.png``, one panel per task, the periodic evaluations of every seed
  (thin) and their mean (thick).

The aggregate statistics follow Agarwal et al. (2021), as the thesis does: mean and median are taken over tasks of
the per-task mean over runs; IQM and optimality gap over all (run, task) scores; the confidence intervals come from a
stratified bootstrap (runs resampled with replacement within each task, percentile interval). For equal run counts
per task the statistics are those of rliable's ``aggregate_*`` functions (tested). The bootstrap is an own numpy
implementation (:func:`stratified_bootstrap_ci`) because rliable's (``rliable.library.get_interval_estimates``,
rliable 1.2) does not run with the current releases of its dependency ``arch``: arch 7.2 fails to import under
pandas 3, and arch 8 rejects the ``random_state`` keyword that rliable passes. With pandas 2.3 and arch 7.2, the two
gave the same 95 % intervals of the mean, median, IQM and optimality gap to within 0.003 (5 runs x 10 tasks, 20,000
replicates each); ours also takes tasks with different numbers of runs. Games without a thesis row (UpNDown) are
listed but left out of the aggregates, which, like the thesis', cover the 25 games of Table 5.1.

Command line::

    python -m benchmarks.aggregate runs --out runs/aggregate
"""

from __future__ import annotations

import argparse
import csv
import json
import pathlib
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from benchmarks.suites import ATARI100K_THESIS_LABELS, DATA_DIR, DMC_VISION_THESIS_LABELS

__all__ = [
    "THESIS_ATARI_AGGREGATES",
    "THESIS_DMC_AGGREGATES",
    "aggregate_iqm",
    "aggregate_mean",
    "aggregate_median",
    "aggregate_optimality_gap",
    "atari_table",
    "dmc_table",
    "human_normalized_score",
    "load_results",
    "plot_curves",
    "run_cost",
    "scores_by_task",
    "stratified_bootstrap_ci",
    "task_table",
    "thesis_table",
]

#: Aggregate rows of thesis Table 5.1 (human-normalised scores in %; None = not reported).
THESIS_ATARI_AGGREGATES: dict[str, dict[str, float | None]] = {
    "hieros": {"mean": 120.0, "median": 56.0, "iqm": 53.0, "optimality_gap": 49.0},
    "dreamerv3": {"mean": 112.0, "median": 49.0, "iqm": None, "optimality_gap": None},
}
#: Aggregate rows of thesis Table 5.2 (raw scores).
THESIS_DMC_AGGREGATES: dict[str, dict[str, float]] = {
    "hieros": {"mean": 652.56, "median": 785.8},
    "dreamerv3": {"mean": 739.6, "median": 808.5},
}
_TABLE_FILES = {"atari100k": "thesis_table_5_1_atari100k.csv", "dmc_vision": "thesis_table_5_2_dmc_vision.csv"}

TaskScores = Sequence[np.ndarray]  # one 1-D array of run scores per task (ragged allowed)


def thesis_table(suite: str) -> dict[str, dict[str, float]]:
    """A thesis table from ``benchmarks/data``: row label -> column -> value.

    :param suite: ``"atari100k"`` (Table 5.1) or ``"dmc_vision"`` (Table 5.2)
    :return: the rows
    """
    if suite not in _TABLE_FILES:
        raise ValueError(f"no thesis table for suite {suite!r}; expected one of {sorted(_TABLE_FILES)}")
    with open(DATA_DIR / _TABLE_FILES[suite]) as f:
        return {row.pop("task"): {k: float(v) for k, v in row.items()} for row in csv.DictReader(f)}


def human_normalized_score(score: float | np.ndarray, random: float, human: float) -> float | np.ndarray:
    """Human-normalised score ``(score - random) / (human - random)`` (thesis 5.1, Bellemare et al. 2013).

    :param score: agent score(s)
    :param random: score of the random policy
    :param human: score of the human tester
    :return: 0 at random, 1 at human level
    """
    if human == random:
        raise ValueError(f"human and random scores must differ, got both {human!r}")
    return (np.asarray(score, dtype=np.float64) - random) / (human - random)


def _check_scores(scores: TaskScores) -> list[np.ndarray]:
    tasks = [np.asarray(s, dtype=np.float64).reshape(-1) for s in scores]
    if not tasks or any(t.size == 0 for t in tasks):
        raise ValueError(f"scores must hold at least one score for every task, got sizes {[t.size for t in tasks]}")
    return tasks


def aggregate_mean(scores: TaskScores) -> float:
    """Mean over tasks of the per-task mean score.

    :param scores: one array of run scores per task
    :return: the mean
    """
    return float(np.mean([t.mean() for t in _check_scores(scores)]))


def aggregate_median(scores: TaskScores) -> float:
    """Median over tasks of the per-task mean score.

    :param scores: one array of run scores per task
    :return: the median
    """
    return float(np.median([t.mean() for t in _check_scores(scores)]))


def aggregate_iqm(scores: TaskScores) -> float:
    """Interquartile mean of all (run, task) scores: the mean of the middle 50 % after sorting, dropping
    ``floor(n / 4)`` scores at each end (``scipy.stats.trim_mean(x, 0.25)``; Agarwal et al. 2021).

    :param scores: one array of run scores per task
    :return: the IQM
    """
    flat = np.sort(np.concatenate(_check_scores(scores)))
    cut = int(0.25 * flat.size)
    return float(flat[cut : flat.size - cut].mean())


def aggregate_optimality_gap(scores: TaskScores, gamma: float = 1.0) -> float:
    """Optimality gap: mean of ``gamma - min(score, gamma)`` over all (run, task) scores (Agarwal et al. 2021).

    :param scores: one array of run scores per task
    :param gamma: the score counted as optimal (1 = human level for human-normalised scores)
    :return: the gap (0 = every run at least ``gamma``)
    """
    flat = np.concatenate(_check_scores(scores))
    return float(np.mean(gamma - np.minimum(flat, gamma)))


def stratified_bootstrap_ci(
    scores: TaskScores,
    statistic: Callable[[TaskScores], float],
    reps: int = 2000,
    confidence: float = 0.95,
    seed: int = 0,
) -> tuple[float, float]:
    """Percentile confidence interval of ``statistic`` under a stratified bootstrap: every replicate resamples the
    runs of each task with replacement (same count per task), keeping the tasks fixed (Agarwal et al. 2021).

    :param scores: one array of run scores per task
    :param statistic: aggregate of a list of per-task arrays (e.g. :func:`aggregate_iqm`)
    :param reps: bootstrap replicates (>= 1)
    :param confidence: coverage of the interval, in (0, 1)
    :param seed: seed of the resampling
    :return: ``(low, high)``
    """
    tasks = _check_scores(scores)
    if isinstance(reps, bool) or not isinstance(reps, int) or reps < 1:
        raise ValueError(f"reps must be an int >= 1, got {reps!r}")
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence!r}")
    rng = np.random.default_rng(seed)
    values = np.array(
        [statistic([t[rng.integers(0, t.size, t.size)] for t in tasks]) for _ in range(reps)], dtype=np.float64
    )
    tail = 100.0 * (1.0 - confidence) / 2.0
    low, high = np.percentile(values, [tail, 100.0 - tail])
    return float(low), float(high)


def load_results(root: str | pathlib.Path | Sequence[str | pathlib.Path]) -> list[dict[str, Any]]:
    """Every ``result.json`` of :mod:`benchmarks.train` under the given folder(s) (files are taken as they are).

    :param root: a folder (searched recursively), a result file, or a list of them
    :return: the records, sorted by suite, task and seed
    """
    roots = [root] if isinstance(root, str | pathlib.Path) else list(root)
    paths: list[pathlib.Path] = []
    for item in map(pathlib.Path, roots):
        if item.is_file():
            paths.append(item)
        elif item.is_dir():
            paths.extend(sorted(item.rglob("result.json")))
        else:
            raise ValueError(f"no such result file or folder: {item}")
    records = [json.loads(p.read_text()) for p in paths]
    for path, record in zip(paths, records, strict=True):
        missing = {"suite", "task", "seed", "final_mean"} - set(record)
        if missing:
            raise ValueError(f"{path} is not a benchmarks.train result: missing {sorted(missing)}")
    return sorted(records, key=lambda r: (r["suite"], r["task"], r["seed"]))


def scores_by_task(records: Sequence[dict[str, Any]], suite: str) -> dict[str, np.ndarray]:
    """Final mean scores of one suite's runs grouped by task (one entry per seed).

    :param records: results of :func:`load_results`
    :param suite: the suite to select
    :return: task -> array of per-seed final scores, tasks in first-seen order
    """
    grouped: dict[str, list[float]] = {}
    for record in records:
        if record["suite"] == suite:
            grouped.setdefault(record["task"], []).append(float(record["final_mean"]))
    return {task: np.array(values) for task, values in grouped.items()}


def _fmt(value: float | None, digits: int = 1) -> str:
    return "N/A" if value is None else f"{value:,.{digits}f}"


def _mean_std(values: np.ndarray) -> str:
    return f"{values.mean():,.1f} +- {values.std():,.1f} ({values.size})"


def run_cost(records: Sequence[dict[str, Any]], suite: str, task: str) -> str:
    """The preset(s) and the mean wall time per run of one task's runs, e.g. ``"small, 4.2 h"``.

    :param records: results of :func:`load_results`
    :param suite: the suite to select
    :param task: the task to select
    :return: the presets joined by ``/`` and the mean ``wall_s`` in hours (left out where no record has it)
    """
    runs = [r for r in records if r["suite"] == suite and r["task"] == task]
    presets = "/".join(dict.fromkeys(str(r.get("preset", "?")) for r in runs))
    hours = [float(r["wall_s"]) / 3600 for r in runs if "wall_s" in r]
    return f"{presets}, {np.mean(hours):.1f} h" if hours else presets


def _coverage(ours: int, thesis: int, noun: str) -> tuple[str, bool]:
    """How many of the thesis' tasks an aggregate row covers, and whether the thesis' aggregate compares with it.

    The thesis' aggregates are taken over all its tasks; over fewer they would compare different sets, so they are
    shown only where ours cover as many ("-" elsewhere).
    """
    complete = ours >= thesis
    return (f"{ours} {noun}s" if complete else f"{ours} of the thesis' {thesis} {noun}s"), complete


def atari_table(records: Sequence[dict[str, Any]], reps: int = 2000, seed: int = 0) -> tuple[str, dict[str, Any]]:
    """Markdown table of the Atari100k runs next to thesis Table 5.1, and the aggregate numbers.

    :param records: results of :func:`load_results` (other suites are ignored)
    :param reps: bootstrap replicates of the confidence intervals
    :param seed: seed of the bootstrap
    :return: ``(markdown, summary)``; summary: ``{"hns": {game: [per seed]}, "<statistic>": {"value", "ci"}}``
        with statistics in % of human
    """
    table = thesis_table("atari100k")
    scores = scores_by_task(records, "atari100k")
    lines = [
        "| Game | Random | Human | Ours (mean +- std (seeds)) | Ours HNS % | Ours: preset, wall time per run "
        "| HIEROS (thesis) | DreamerV3 (thesis) |",
        "|---|---:|---:|---:|---:|---|---:|---:|",
    ]
    hns: dict[str, np.ndarray] = {}
    for game, values in scores.items():
        label = ATARI100K_THESIS_LABELS.get(game)
        row = table.get(label) if label else None
        if row is None:
            lines.append(f"| {game} | | | {_mean_std(values)} | | {run_cost(records, 'atari100k', game)} | | |")
            continue
        hns[game] = np.asarray(human_normalized_score(values, row["random"], row["human"]))
        lines.append(
            f"| {label} | {_fmt(row['random'], 0)} | {_fmt(row['human'], 0)} | {_mean_std(values)} "
            f"| {100 * hns[game].mean():.1f} | {run_cost(records, 'atari100k', game)} | {_fmt(row['hieros'], 0)} "
            f"| {_fmt(row['dreamerv3'], 0)} |"
        )
    summary: dict[str, Any] = {"hns": {game: values.tolist() for game, values in hns.items()}}
    if hns:
        per_task = list(hns.values())
        statistics = {
            "mean": aggregate_mean,
            "median": aggregate_median,
            "iqm": aggregate_iqm,
            "optimality_gap": aggregate_optimality_gap,
        }
        names = {"mean": "Mean", "median": "Median", "iqm": "IQM", "optimality_gap": "Optimality Gap"}
        games, complete = _coverage(len(per_task), len(table), "game")
        for key, statistic in statistics.items():
            value = 100 * statistic(per_task)
            low, high = stratified_bootstrap_ci(per_task, statistic, reps=reps, seed=seed)
            summary[key] = {"value": value, "ci": [100 * low, 100 * high]}
            thesis = [_fmt(THESIS_ATARI_AGGREGATES[a][key], 0) if complete else "-" for a in ("hieros", "dreamerv3")]
            lines.append(
                f"| **{names[key]}** (HNS %, {games}) | | | | {value:.1f} [{100 * low:.1f}, {100 * high:.1f}] | "
                f"| {thesis[0]} | {thesis[1]} |"
            )
    return "\n".join(lines), summary


def dmc_table(records: Sequence[dict[str, Any]]) -> tuple[str, dict[str, Any]]:
    """Markdown table of the DMC vision runs next to thesis Table 5.2 (raw scores).

    :param records: results of :func:`load_results` (other suites are ignored)
    :return: ``(markdown, summary)``; summary: ``{"mean": ..., "median": ...}`` over our tasks
    """
    table = thesis_table("dmc_vision")
    scores = scores_by_task(records, "dmc_vision")
    lines = [
        "| Task | Ours (mean +- std (seeds)) | Ours: preset, wall time per run | HIEROS (thesis) "
        "| DreamerV3 (thesis) |",
        "|---|---:|---|---:|---:|",
    ]
    for task, values in scores.items():
        row = table.get(DMC_VISION_THESIS_LABELS.get(task, ""), {})
        lines.append(
            f"| {DMC_VISION_THESIS_LABELS.get(task, task)} | {_mean_std(values)} "
            f"| {run_cost(records, 'dmc_vision', task)} | {_fmt(row.get('hieros'))} | {_fmt(row.get('dreamerv3'))} |"
        )
    summary: dict[str, Any] = {}
    if scores:
        per_task = list(scores.values())
        summary = {"mean": aggregate_mean(per_task), "median": aggregate_median(per_task)}
        covered = sum(DMC_VISION_THESIS_LABELS.get(task) in table for task in scores)
        tasks, complete = _coverage(covered, len(table), "task")
        for key in ("mean", "median"):
            thesis = [_fmt(THESIS_DMC_AGGREGATES[a][key]) if complete else "-" for a in ("hieros", "dreamerv3")]
            lines.append(f"| **{key.capitalize()}** ({tasks}) | {summary[key]:,.1f} | | {thesis[0]} | {thesis[1]} |")
    return "\n".join(lines), summary


def task_table(records: Sequence[dict[str, Any]], suite: str) -> str:
    """Markdown table of one suite's final scores per task (no thesis reference).

    :param records: results of :func:`load_results`
    :param suite: the suite to select
    :return: the table
    """
    lines = ["| Task | Ours (mean +- std (seeds)) | Steps | Preset, wall time per run |", "|---|---:|---:|---|"]
    steps: dict[str, int] = {r["task"]: int(r.get("steps", 0)) for r in records if r["suite"] == suite}
    for task, values in scores_by_task(records, suite).items():
        lines.append(f"| {task} | {_mean_std(values)} | {steps[task]:,} | {run_cost(records, suite, task)} |")
    return "\n".join(lines)


def plot_curves(records: Sequence[dict[str, Any]], suite: str, path: str | pathlib.Path) -> pathlib.Path | None:
    """Learning curves of one suite: one panel per task, each seed's periodic evaluations and their mean.

    :param records: results of :func:`load_results`
    :param suite: the suite to plot
    :param path: PNG file to write
    :return: the path, or None when no run of the suite has periodic evaluations
    """
    runs = [r for r in records if r["suite"] == suite and r.get("eval_timesteps")]
    if not runs:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tasks = list(dict.fromkeys(r["task"] for r in runs))
    cols = min(5, len(tasks))
    rows = -(-len(tasks) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 2.6 * rows), squeeze=False)
    for ax, task in zip(axes.flat, tasks, strict=False):
        task_runs = [r for r in runs if r["task"] == task]
        for r in task_runs:
            ax.plot(r["eval_timesteps"], r["eval_means"], color="tab:red", alpha=0.3, lw=0.8)
        length = min(len(r["eval_means"]) for r in task_runs)
        mean = np.mean([r["eval_means"][:length] for r in task_runs], axis=0)
        ax.plot(task_runs[0]["eval_timesteps"][:length], mean, color="tab:red", lw=2)
        ax.set_title(task, fontsize=9)
        ax.tick_params(labelsize=7)
    for ax in list(axes.flat)[len(tasks) :]:
        ax.axis("off")
    fig.supxlabel("agent steps")
    fig.supylabel("evaluation return")
    fig.tight_layout()
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def aggregate(
    records: Sequence[dict[str, Any]], out: str | pathlib.Path | None = None, reps: int = 2000, seed: int = 0
) -> tuple[str, dict[str, Any]]:
    """All tables (and, with ``out``, the curve PNGs, ``aggregate.md`` and ``aggregate.json``) of some runs.

    :param records: results of :func:`load_results` or of :func:`benchmarks.train.train`
    :param out: folder for the files; None = write nothing
    :param reps: bootstrap replicates
    :param seed: seed of the bootstrap
    :return: ``(markdown, summary)`` with one section per suite
    """
    sections: list[str] = []
    summary: dict[str, Any] = {}
    for suite in dict.fromkeys(r["suite"] for r in records):
        if suite == "atari100k":
            text, summary[suite] = atari_table(records, reps=reps, seed=seed)
        elif suite == "dmc_vision":
            text, summary[suite] = dmc_table(records)
        else:
            text = task_table(records, suite)
        sections.append(f"### {suite}\n\n{text}")
        if out is not None:
            plot_curves(records, suite, pathlib.Path(out) / f"{suite}_curves.png")
    markdown = "\n\n".join(sections)
    if out is not None:
        out = pathlib.Path(out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "aggregate.md").write_text(markdown + "\n")
        (out / "aggregate.json").write_text(json.dumps(summary, indent=1))
    return markdown, summary


def main(argv: list[str] | None = None) -> tuple[str, dict[str, Any]]:
    """Command line (see the module docstring)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", help="folders with result.json files (searched recursively) or files")
    parser.add_argument("--out", default=None, help="folder for aggregate.md/.json and curve PNGs")
    parser.add_argument("--reps", type=int, default=2000, help="bootstrap replicates")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    markdown, summary = aggregate(load_results(args.runs), out=args.out, reps=args.reps, seed=args.seed)
    print(markdown)
    return markdown, summary


if __name__ == "__main__":
    main()
