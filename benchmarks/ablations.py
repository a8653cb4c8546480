"""HIEROS against its ablations (thesis 5.3): collected reward per environment step, red = HIEROS, blue = ablation.

For every task and seed the script trains HIEROS (``"hieros"``, the preset unchanged) and each requested ablation of
:data:`sb3_hieros.ablations.ABLATIONS` (``docs/ablations.md``) through the local sweep runner
(:mod:`benchmarks.sweep`, ``--workers`` processes), then

* plots, per ablation, the collected reward of the training episodes against the environment step for every task
  (mean over seeds as a line, min-max over seeds shaded; HIEROS red, the ablation blue, as the thesis' figures
  5.10-5.23) into ``<out>/<ablation>.png``;
* prints a markdown table (also ``<out>/table.md``): per task and variant the *final return* (mean return of the
  episodes that ended in the last 20 % of the steps, mean +- std over seeds), the *mean return* over the whole run
  (area under the curve), the difference of the final return to HIEROS and the wall time per run;
* writes every run's episodes to ``<out>/results.json``.

``--ablation all`` runs one ablation per thesis section 5.3.1-5.3.12 (depth: ``levels_1``; replay: ``uniform_replay``)
against one shared HIEROS baseline per task and seed; ``--ablation every`` runs every registered name.

Examples::

    # the thesis grid (GPU): four Atari games, three seeds, 100k agent steps, the paper preset
    python -m benchmarks.ablations --ablation rssm --games Krull Breakout BattleZone Freeway --seeds 3 \\
        --steps 100000 --preset paper
    # a small CPU budget on CartPole
    python -m benchmarks.ablations --ablation all --env CartPole-v1 --seeds 2 --steps 10000 --workers 2
    # table and figures again from a finished run's results.json (no training)
    python -m benchmarks.ablations --ablation all --from-results results/ablations/results.json
"""

from __future__ import annotations

import argparse
import json
import pathlib
import warnings
from typing import Any

import numpy as np

from benchmarks._cli import json_object
from benchmarks.sweep import Run, atari_id, run_sweep
from sb3_hieros.ablations import ABLATIONS, ablation_changes_preset, ablation_overrides

#: One ablation per thesis section (what ``--ablation all`` runs; of ``no_novelty`` / ``with_novelty`` only the one
#: that changes the preset).
THESIS_SET = (
    "shared_world_model",
    "rssm",
    "uniform_replay",
    "levels_1",
    "deter_from_output",
    "last_state_only",
    "small_s5",
    "decoded_subgoals",
    "update_subgoals",
    "extrinsic_top_only",
    "no_actor_extras",
    "no_novelty",
    "with_novelty",
)
BASELINE = "hieros"
FINAL_FRACTION = 0.2


def ablation_names(requested: list[str], preset: str = "paper", base: dict[str, Any] | None = None) -> list[str]:
    """Expand ``all`` / ``every`` and check the names.

    Ablations that leave the preset unchanged (e.g. ``no_novelty`` on the small preset, which has no novelty reward)
    are left out of ``all`` / ``every``; asked for by name they raise ``ValueError``, as they would only train the
    baseline twice.

    :param requested: names from the command line
    :param preset: the preset the ablations apply to
    :param base: ``config_overrides`` applied before each ablation
    :return: ablation names, in order, without duplicates
    """
    names: list[str] = []
    for name in requested:
        expanded = list(THESIS_SET) if name == "all" else list(ABLATIONS) if name == "every" else [name]
        for item in expanded:
            if item not in ABLATIONS:
                raise ValueError(f"unknown ablation {item!r}; expected 'all', 'every' or one of {sorted(ABLATIONS)}")
            if not ablation_changes_preset(item, preset, base):
                if item == name:
                    raise ValueError(
                        f"ablation {item!r} does not change preset {preset!r} (with the given config_overrides): "
                        "it would train the baseline again"
                    )
                continue
            if item not in names:
                names.append(item)
    return names


def plan(
    names: list[str], envs: list[str], seeds: int, steps: int, preset: str, extra: dict[str, Any], threads: int
) -> list[Run]:
    """The runs: HIEROS and every ablation on every task with seeds 0..seeds-1 (baselines first)."""
    runs = []
    for variant in [BASELINE, *names]:
        overrides = ablation_overrides(variant, preset, extra.get("config_overrides"))
        kwargs = {**extra, "preset": preset, "config_overrides": overrides}
        runs += [Run(variant, env, seed, steps, kwargs, threads) for env in envs for seed in range(seeds)]
    return runs


def binned_curve(record: dict[str, Any], steps: int, bins: int) -> np.ndarray:
    """Collected reward per step of one run: the mean return of the episodes that ended in each of ``bins`` equal
    step intervals, carried forward through intervals without an episode end (NaN before the first).

    :param record: a :func:`benchmarks.sweep.run_one` record
    :param steps: total steps of the run
    :param bins: number of intervals
    :return: (bins,) returns
    """
    ends = np.asarray(record["episode_end_steps"], dtype=np.float64)
    returns = np.asarray(record["episode_returns"], dtype=np.float64)
    edges = np.linspace(0, steps, bins + 1)
    curve = np.full(bins, np.nan)
    last = np.nan
    for b in range(bins):
        inside = (ends > edges[b]) & (ends <= edges[b + 1])
        if inside.any():
            last = float(returns[inside].mean())
        curve[b] = last
    return curve


def final_return(record: dict[str, Any], steps: int) -> float:
    """Mean return of the episodes that ended in the last :data:`FINAL_FRACTION` of the steps (else the last one)."""
    ends = np.asarray(record["episode_end_steps"])
    returns = np.asarray(record["episode_returns"], dtype=np.float64)
    if returns.size == 0:
        return float("nan")
    late = ends > (1.0 - FINAL_FRACTION) * steps
    return float(returns[late].mean() if late.any() else returns[-1])


def summarise(records: list[dict[str, Any]], steps: int, bins: int = 20) -> dict[tuple[str, str], dict[str, float]]:
    """(task, variant) -> final return mean / std over seeds, mean return, wall seconds per run, seeds.

    The mean return is the area under the collected-reward curve divided by the steps: the mean of
    :func:`binned_curve` over its ``bins`` step intervals (intervals before the first episode end left out), so that
    it weighs every part of the run alike, however many episodes ended in it.
    """
    table: dict[tuple[str, str], dict[str, float]] = {}
    keys = dict.fromkeys((r["env_id"], r["variant"]) for r in records)
    for env, variant in keys:
        group = [r for r in records if r["env_id"] == env and r["variant"] == variant]
        finals = [final_return(r, steps) for r in group]
        means = []
        for r in group:
            curve = binned_curve(r, steps, bins)
            means.append(float(np.nanmean(curve)) if np.isfinite(curve).any() else float("nan"))
        table[(env, variant)] = {
            "final_mean": float(np.mean(finals)),
            "final_std": float(np.std(finals)),
            "mean_return": float(np.mean(means)),
            "wall_s": float(np.mean([r["wall_s"] for r in group])),
            "seeds": float(len(group)),
        }
    return table


def markdown_table(table: dict[tuple[str, str], dict[str, float]]) -> str:
    """The summary as a markdown table (one row per task and variant, HIEROS first)."""
    lines = [
        "| task | variant | thesis | final return | mean return | final - HIEROS | wall s / run | seeds |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for (env, variant), row in table.items():
        base = table.get((env, BASELINE))
        delta = "-" if base is None or variant == BASELINE else f"{row['final_mean'] - base['final_mean']:+.1f}"
        section = ABLATIONS[variant].section if variant in ABLATIONS else "-"
        lines.append(
            f"| {env} | {variant} | {section} | {row['final_mean']:.1f} +- {row['final_std']:.1f} | "
            f"{row['mean_return']:.1f} | {delta} | {row['wall_s']:.0f} | {int(row['seeds'])} |"
        )
    return "\n".join(lines)


def plot(records: list[dict[str, Any]], ablation: str, envs: list[str], steps: int, bins: int, path: pathlib.Path):
    """One panel per task: HIEROS (red) and ``ablation`` (blue), mean over seeds with the min-max range shaded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(envs), figsize=(4.5 * len(envs), 3.4), squeeze=False)
    x = (np.arange(bins) + 1) * steps / bins
    for ax, env in zip(axes[0], envs, strict=True):
        for variant, color, label in ((BASELINE, "red", "HIEROS"), (ablation, "blue", ablation)):
            curves = np.stack(
                [binned_curve(r, steps, bins) for r in records if r["env_id"] == env and r["variant"] == variant]
            )
            with warnings.catch_warnings():  # all-NaN columns before the first episode end
                warnings.simplefilter("ignore", RuntimeWarning)
                mean, low, high = np.nanmean(curves, 0), np.nanmin(curves, 0), np.nanmax(curves, 0)
            ax.plot(x, mean, color=color, lw=2, label=label)
            ax.fill_between(x, low, high, color=color, alpha=0.2, lw=0)
        ax.set_title(env)
        ax.set_xlabel("environment steps")
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("collected reward per episode")
    axes[0][0].legend()
    section = ABLATIONS[ablation].section
    fig.suptitle(f"HIEROS (red) vs {ablation} (blue), thesis {section}\n{ABLATIONS[ablation].description}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> dict[tuple[str, str], dict[str, float]]:
    """Run, plot and tabulate (see the module docstring).

    :param argv: command-line arguments (default: ``sys.argv``)
    :return: the summary table
    """
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ablation", nargs="+", required=True, help="names, 'all' (thesis 5.3.1-12) or 'every'")
    parser.add_argument("--env", nargs="+", default=["CartPole-v1"], help="gymnasium ids")
    parser.add_argument("--games", nargs="+", default=None, help="Atari games (ALE/<Game>-v5); replaces --env")
    parser.add_argument("--seeds", type=int, default=3, help="seeds 0..N-1")
    parser.add_argument("--steps", type=int, default=10_000, help="environment steps per run")
    parser.add_argument("--preset", default="small")
    parser.add_argument("--workers", type=int, default=1, help="parallel processes")
    parser.add_argument("--threads", type=int, default=1, help="torch threads per run")
    parser.add_argument("--bins", type=int, default=20, help="points of the reward curves")
    parser.add_argument(
        "--hieros-kwargs", type=json_object, default={}, help="JSON dict of extra HIEROS keywords for every run"
    )
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("results/ablations"))
    parser.add_argument(
        "--from-results",
        type=pathlib.Path,
        default=None,
        help="a results.json of an earlier run: tabulate, no training",
    )
    args = parser.parse_args(argv)
    if args.from_results is not None:
        return tabulate_results(args.from_results, args.out, args.bins)
    if args.seeds < 1 or args.steps < 1 or args.bins < 1:
        raise ValueError(f"--seeds, --steps and --bins must be >= 1, got {args.seeds}, {args.steps}, {args.bins}")
    extra = args.hieros_kwargs
    names = ablation_names(args.ablation, args.preset, extra.get("config_overrides"))
    envs = [atari_id(g) for g in args.games] if args.games else list(args.env)
    from benchmarks._timing import environment_header

    print(environment_header())
    runs = plan(names, envs, args.seeds, args.steps, args.preset, extra, args.threads)
    variants = ", ".join([BASELINE, *names])
    print(f"{len(runs)} runs: {variants} on {', '.join(envs)}, {args.seeds} seeds, {args.steps} steps each")
    records = run_sweep(runs, args.workers)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(
        json.dumps({"args": {k: str(v) for k, v in vars(args).items()}, "runs": records}, indent=1) + "\n"
    )
    return report(records, names, envs, args.steps, args.bins, args.out)


def report(
    records: list[dict[str, Any]], names: list[str], envs: list[str], steps: int, bins: int, out: pathlib.Path
) -> dict[tuple[str, str], dict[str, float]]:
    """Write the per-ablation PNGs and ``table.md`` into ``out`` and print the table.

    :return: the summary table
    """
    out.mkdir(parents=True, exist_ok=True)
    for name in names:
        plot(records, name, envs, steps, bins, out / f"{name}.png")
    table = summarise(records, steps, bins)
    text = markdown_table(table)
    (out / "table.md").write_text(text + "\n")
    print(text)
    for (env, variant), row in table.items():
        print(f"{env}/{variant}_final_return: {row['final_mean']:.1f}")
    return table


def tabulate_results(path: pathlib.Path, out: pathlib.Path, bins: int) -> dict[tuple[str, str], dict[str, float]]:
    """Table and PNGs from the ``results.json`` of an earlier run (``--from-results``), without training.

    :param path: the ``results.json``
    :param out: output directory
    :param bins: points of the reward curves
    :return: the summary table
    """
    data = json.loads(pathlib.Path(path).read_text())
    records = data["runs"]
    steps = int(data["args"]["steps"])
    names = [v for v in dict.fromkeys(r["variant"] for r in records) if v != BASELINE]
    envs = list(dict.fromkeys(r["env_id"] for r in records))
    return report(records, names, envs, steps, bins, out)


if __name__ == "__main__":
    main()
