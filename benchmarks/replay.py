"""Replay selection: ETBS cost, the thesis' Fig. 4.9 redone, and sequence-buffer memory.

Run from the repository root::

    OMP_NUM_THREADS=1 python -m benchmarks.replay [--seeds 20] [--match-seeds 60] [--reps 15]

1. Cost of one batch of 16 chunk-start draws (what one training step needs) with ``etbs_indices`` at buffer
   sizes 1e3 and 5e7 (O(1): the ratio should stay <= 1.2), and against the O(n) count-based sampler
   (``CountBalancedSampler``, probabilities computed once per batch) at 1e4, 1e5, 1e6 (goal: ETBS >= 1000x
   faster at 1e6), and at 1e6 with the probabilities recomputed after each of the 16 draws. Interleaved timing
   (``benchmarks._timing``); a timed unit runs k batches and the figures are divided by k (per batch) and
   by 16 k (per draw).
2. Fig. 4.9 of the thesis: a buffer grows to 4000 items, one draw after each insert; the per-item draw
   counts (mean over seeds) for uniform, ETBS tau 0.3 and 1.0, the public code's capacity-scaled variant
   (capacity 1e6, its default replay size) and the count-based sampler. Summary: old/new ratio = mean count
   of the oldest 10% of items over the mean count of the newest 10% (1 = balanced).
3. Memory: array bytes of a ``SequenceReplayBuffer`` holding 100k steps of 64x64x3 uint8 observations over
   the raw observation bytes (100k * 64 * 64 * 3); SB3's ``ReplayBuffer`` for contrast.

Beyond the thesis: ``MeanFieldCountSampler`` (O(1) per draw) is timed and plotted next to the count-based
sampler at the same temperatures; ``meanfield_max_decile_deviation_*`` is the largest relative difference of
the per-decile mean counts between the two (goal: <= 0.10), measured on ``--match-seeds`` further seeds (the
newest decile holds about 0.1 draws per item, so fewer seeds leave several percent of noise there).
"""

from __future__ import annotations

import argparse
import pathlib
from collections.abc import Callable

import numpy as np
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer

from benchmarks._timing import environment_header, time_interleaved
from sb3_hieros.buffers import ETBSReplayBuffer, SequenceReplayBuffer
from sb3_hieros.etbs import CountBalancedSampler, MeanFieldCountSampler, etbs_indices

BATCH = 16
FIG_ITEMS = 4000
REFERENCE_CAPACITY = 1_000_000
COUNT_TEMPERATURES = (1.0, 0.1)


def _repeat(fn: Callable[[], object], k: int) -> Callable[[], None]:
    def unit() -> None:
        for _ in range(k):
            fn()

    return unit


def selection_cost(reps: int) -> tuple[dict[str, float], dict[str, float]]:
    """Per-batch seconds (median, min) of ETBS and count-based selection at several sizes."""
    rng = np.random.default_rng(0)
    variants: dict[str, Callable[[], None]] = {}
    batches: dict[str, int] = {}

    def add(name: str, fn: Callable[[], object], k: int) -> None:
        variants[name] = _repeat(fn, k)
        batches[name] = k

    for size in (1_000, 10_000, 100_000, 1_000_000, 50_000_000):
        add(f"etbs_{size:.0e}", lambda s=size: etbs_indices(s, BATCH, 0.3, rng), 200)
    meanfield = MeanFieldCountSampler(1.0)
    for size in (1_000_000, 50_000_000):
        add(f"mfield_{size:.0e}", lambda s=size: meanfield.sample(s, BATCH, rng), 200)
    for size, k in ((10_000, 20), (100_000, 2), (1_000_000, 1)):
        sampler = CountBalancedSampler(size, temperature=1.0)
        add(f"count_{size:.0e}", lambda s=size, c=sampler: c.sample(s, BATCH, rng), k)
    # counters updated after every draw (16 recomputations per batch), as the public code's TimeBalancedNaive does
    sequential = CountBalancedSampler(1_000_000, temperature=1.0)
    add("count_seq_1e+06", lambda: [sequential.sample(1_000_000, 1, rng) for _ in range(BATCH)], 1)
    timings = time_interleaved(variants, warmup=2, reps=reps)
    print(f"{'variant':<12} {'per batch of 16 (min / median)':>34} {'per draw (median)':>18}")
    per_batch, per_batch_min = {}, {}
    for name, t in timings.items():
        k = batches[name]
        per_batch[name], per_batch_min[name] = t.median / k, t.min / k
        print(
            f"{name:<12} {t.min / k * 1e6:14.2f} / {t.median / k * 1e6:10.2f} us {t.median / k / BATCH * 1e6:14.3f} us"
        )
    return per_batch, per_batch_min


def fig_4_9_counts(seeds: int) -> dict[str, np.ndarray]:
    """Mean per-item draw counts after growing to FIG_ITEMS items with one draw per insert."""
    samplers: dict[str, Callable[[int, np.random.Generator], np.ndarray]] = {
        "uniform": lambda size, rng: etbs_indices(size, 1, 0.0, rng, mode="uniform"),
        "etbs tau=0.3": lambda size, rng: etbs_indices(size, 1, 0.3, rng),
        "etbs tau=1.0": lambda size, rng: etbs_indices(size, 1, 1.0, rng),
        "reference tau=0.3": lambda size, rng: etbs_indices(
            size, 1, 0.3, rng, mode="reference", capacity=REFERENCE_CAPACITY
        ),
    }
    for temperature in COUNT_TEMPERATURES:
        meanfield = MeanFieldCountSampler(temperature)
        samplers[f"meanfield temp={temperature}"] = lambda size, rng, m=meanfield: m.sample(size, 1, rng)
    counts = {name: np.zeros(FIG_ITEMS) for name in [*samplers, *(f"count temp={t}" for t in COUNT_TEMPERATURES)]}
    for seed in range(seeds):
        for name, draw in samplers.items():
            rng = np.random.default_rng(seed)
            for size in range(1, FIG_ITEMS + 1):
                counts[name][draw(size, rng)] += 1
        for temperature in COUNT_TEMPERATURES:
            rng = np.random.default_rng(seed)
            sampler = CountBalancedSampler(FIG_ITEMS, temperature=temperature)
            for size in range(1, FIG_ITEMS + 1):
                sampler.sample(size, 1, rng)
            counts[f"count temp={temperature}"] += sampler.counts
    return {name: c / seeds for name, c in counts.items()}


def meanfield_deviation(temperature: float, seeds: int) -> np.ndarray:
    """Per-decile relative deviation of the meanfield sampler's mean counts from the count-based sampler's."""
    meanfield = MeanFieldCountSampler(temperature)
    count_total, meanfield_total = np.zeros(FIG_ITEMS), np.zeros(FIG_ITEMS)
    for seed in range(1000, 1000 + seeds):
        rng = np.random.default_rng(seed)
        counter = CountBalancedSampler(FIG_ITEMS, temperature=temperature)
        for size in range(1, FIG_ITEMS + 1):
            counter.sample(size, 1, rng)
            meanfield_total[meanfield.sample(size, 1, rng)] += 1
        count_total += counter.counts
    return meanfield_total.reshape(10, -1).mean(axis=1) / count_total.reshape(10, -1).mean(axis=1) - 1.0


def old_new_ratio(counts: np.ndarray) -> float:
    """Mean count of the oldest 10% of items over that of the newest 10%."""
    tenth = len(counts) // 10
    return float(counts[:tenth].mean() / counts[-tenth:].mean())


def save_figure(counts: dict[str, np.ndarray], seeds: int, path: pathlib.Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path.parent.mkdir(parents=True, exist_ok=True)
    window = 40
    kernel = np.ones(window) / window
    items = np.arange(FIG_ITEMS)
    fig, ax = plt.subplots(figsize=(9, 5))
    colors = {"uniform": "C0", "etbs tau=0.3": "C1", "etbs tau=1.0": "C2", "reference tau=0.3": "C3"}
    for i, temperature in enumerate(COUNT_TEMPERATURES):  # each meanfield curve dashed over its count curve
        colors[f"count temp={temperature}"] = colors[f"meanfield temp={temperature}"] = f"C{4 + i}"
    for name in sorted(counts, key=lambda n: n.startswith("meanfield")):
        smooth = np.convolve(counts[name], kernel, mode="valid")
        style = "--" if name.startswith("meanfield") else "-"
        ax.plot(items[: FIG_ITEMS - window + 1], smooth, style, color=colors[name], label=name, linewidth=1.2)
    harmonic = np.cumsum(1.0 / np.arange(1, FIG_ITEMS + 1))
    ax.plot(items, harmonic[-1] - np.concatenate([[0.0], harmonic[:-1]]), "k:", linewidth=1, label="uniform, expected")
    ax.set_xlabel("item i (insertion order, 0 = oldest)")
    ax.set_ylabel(f"times drawn (mean of {seeds} seeds, moving average of {window})")
    ax.set_title(f"Draw counts after growing to {FIG_ITEMS} items, one draw per insert (thesis Fig. 4.9)")
    ax.set_ylim(0, None)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def memory_ratios() -> dict[str, float]:
    """Array bytes over raw observation bytes for 100k steps of 64x64x3 uint8."""
    steps = 100_000
    obs_space = spaces.Box(0, 255, (64, 64, 3), np.uint8)
    action_space = spaces.Discrete(18)
    raw = steps * 64 * 64 * 3
    ratios = {}
    for name, cls in (("SequenceReplayBuffer", SequenceReplayBuffer), ("ETBSReplayBuffer", ETBSReplayBuffer)):
        buffer = cls(steps, obs_space, action_space, device="cpu", batch_length=64)
        arrays = [buffer.observations, buffer.actions, buffer.rewards, buffer.is_first, buffer.is_terminal]
        arrays += [buffer.stream_pos, buffer.stream_full]
        ratios[name] = sum(a.nbytes for a in arrays) / raw
        del buffer
    sb3 = ReplayBuffer(steps, obs_space, action_space, device="cpu", handle_timeout_termination=True)
    arrays = [sb3.observations, sb3.next_observations, sb3.actions, sb3.rewards, sb3.dones, sb3.timeouts]
    ratios["SB3 ReplayBuffer"] = sum(a.nbytes for a in arrays) / raw
    return ratios


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=20, help="seeds averaged in the Fig. 4.9 counts")
    parser.add_argument("--reps", type=int, default=15, help="timed repetitions per cost variant")
    parser.add_argument("--match-seeds", type=int, default=60, help="seeds of the meanfield vs count comparison")
    parser.add_argument("--figure", type=pathlib.Path, default=pathlib.Path("docs/images/etbs_fig4_9.png"))
    args = parser.parse_args()
    print(environment_header())

    print("\n1. selection cost")
    per_batch, per_batch_min = selection_cost(args.reps)

    print(f"\n2. Fig. 4.9: mean draw count per decile of items (oldest first), {args.seeds} seeds")
    counts = fig_4_9_counts(args.seeds)
    for name, c in counts.items():
        deciles = " ".join(f"{d:5.2f}" for d in c.reshape(10, -1).mean(axis=1))
        print(f"{name:<20} {deciles}")
    save_figure(counts, args.seeds, args.figure)

    print("\n3. memory (array bytes / raw observation bytes, 100k steps of 64x64x3 uint8)")
    memory = memory_ratios()
    for name, ratio in memory.items():
        print(f"{name:<22} {ratio:.4f}")

    print(f"\n4. meanfield vs count: relative deviation of the decile mean counts, {args.match_seeds} seeds")
    deviations = {t: meanfield_deviation(t, args.match_seeds) for t in COUNT_TEMPERATURES}
    for temperature, deviation in deviations.items():
        print(f"temp={temperature:<5} " + " ".join(f"{d:+6.3f}" for d in deviation))

    print()
    print(f"etbs_per_batch16_us_1e3: {per_batch['etbs_1e+03'] * 1e6:.2f}")
    print(f"etbs_per_draw_us_1e3: {per_batch['etbs_1e+03'] / BATCH * 1e6:.3f}")
    print(f"etbs_per_batch16_us_5e7: {per_batch['etbs_5e+07'] * 1e6:.2f}")
    print(f"etbs_per_draw_us_5e7: {per_batch['etbs_5e+07'] / BATCH * 1e6:.3f}")
    ratio, ratio_min = (t["etbs_5e+07"] / t["etbs_1e+03"] for t in (per_batch, per_batch_min))
    print(f"etbs_cost_ratio_5e7_over_1e3_median (goal <= 1.2): {ratio:.3f}")
    print(f"etbs_cost_ratio_5e7_over_1e3_min (goal <= 1.2): {ratio_min:.3f}")
    for size in ("1e+04", "1e+05", "1e+06"):
        count, etbs = per_batch[f"count_{size}"], per_batch[f"etbs_{size}"]
        print(f"count_per_batch16_us_{size}: {count * 1e6:.1f}")
        print(f"count_over_etbs_{size}{' (goal >= 1000)' if size == '1e+06' else ''}: {count / etbs:.0f}")
    print(f"count_over_etbs_1e+06_min: {per_batch_min['count_1e+06'] / per_batch_min['etbs_1e+06']:.0f}")
    print(f"count_sequential_per_batch16_us_1e+06: {per_batch['count_seq_1e+06'] * 1e6:.1f}")
    print(f"count_sequential_over_etbs_1e+06: {per_batch['count_seq_1e+06'] / per_batch['etbs_1e+06']:.0f}")
    for name, c in counts.items():
        print(f"old_new_ratio_{name.replace(' ', '_')}: {old_new_ratio(c):.2f}")
    print(f"meanfield_per_batch16_us_1e6: {per_batch['mfield_1e+06'] * 1e6:.2f}")
    print(f"meanfield_cost_ratio_5e7_over_1e6: {per_batch['mfield_5e+07'] / per_batch['mfield_1e+06']:.3f}")
    print(f"count_over_meanfield_1e+06: {per_batch['count_1e+06'] / per_batch['mfield_1e+06']:.0f}")
    for temperature, deviation in deviations.items():
        worst = np.abs(deviation).max()
        print(f"meanfield_max_decile_deviation_temp={temperature} (goal <= 0.10): {worst:.3f}")
    print(f"memory_ratio_SequenceReplayBuffer (goal <= 1.2): {memory['SequenceReplayBuffer']:.4f}")
    print(f"memory_ratio_SB3_ReplayBuffer: {memory['SB3 ReplayBuffer']:.4f}")
    print(f"figure: {args.figure}")


if __name__ == "__main__":
    main()
