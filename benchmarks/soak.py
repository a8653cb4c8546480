"""Soak run: does a long HIEROS run leak memory, file descriptors or threads once its replay is full?

Trains the ``small`` preset on CartPole-v1 for ``--steps`` environment steps (default 30k) with a small replay
(``--buffer-size``, default 2000 steps at level 0, so every level's buffer is full after a few thousand steps), saving
a checkpoint with its replay every ``--checkpoint-every`` steps (into a temporary directory, removed at the end) to
exercise the file paths too. Every ``--sample-every`` steps it samples, from ``/proc/self``: the resident set size
(VmRSS), its peak so far (VmHWM), the open file descriptors and the thread count.

It prints a table of the samples and a summary: the step at which every level's replay is full, the RSS then, the
largest RSS sampled afterwards and its growth relative to the RSS at full (flat = growth within ``--tolerance``,
default 10%), and the descriptor and thread counts at full and at the end. Linux only (``/proc``).

Run from the repository root::

    python -m benchmarks.soak                                  # the full soak: 30k steps, preset train ratio
    python -m benchmarks.soak --steps 8000 --train-ratio 8     # a shorter run (minutes on a CPU)
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from dataclasses import dataclass

import torch as th
from stable_baselines3.common.callbacks import BaseCallback

from benchmarks._timing import environment_header
from sb3_hieros import HIEROS


@dataclass(frozen=True)
class Sample:
    """Process figures at one step."""

    step: int
    rss_mib: float
    hwm_mib: float
    fds: int
    threads: int
    full: bool
    updates: int


def process_status() -> tuple[float, float, int]:
    """VmRSS and VmHWM in MiB and the thread count of this process, from ``/proc/self/status``.

    :return: (rss, peak rss, threads)
    """
    values: dict[str, int] = {}
    with open("/proc/self/status") as f:
        for line in f:
            name, _, rest = line.partition(":")
            if name in ("VmRSS", "VmHWM", "Threads"):
                values[name] = int(rest.split()[0])
    return values["VmRSS"] / 1024, values["VmHWM"] / 1024, values["Threads"]


def open_fds() -> int:
    """Number of open file descriptors of this process (entries of ``/proc/self/fd``, minus the one listing it)."""
    return len(os.listdir("/proc/self/fd")) - 1


class SoakCallback(BaseCallback):
    """Samples the process figures every ``sample_every`` steps and saves a checkpoint every ``checkpoint_every``.

    :param sample_every: steps between samples
    :param checkpoint_every: steps between checkpoints (model + replay of every level), 0 for none
    :param checkpoint_dir: where the checkpoints go (overwritten each time)
    """

    def __init__(self, sample_every: int, checkpoint_every: int, checkpoint_dir: str) -> None:
        super().__init__()
        self.sample_every = sample_every
        self.checkpoint_every = checkpoint_every
        self.checkpoint_dir = checkpoint_dir
        self.samples: list[Sample] = []

    def all_full(self) -> bool:
        """Whether every env stream of every level's replay is full."""
        return all(bool(b.stream_full.all()) for b in self.model.level_buffers())  # type: ignore[attr-defined]

    def sample(self) -> None:
        rss, hwm, threads = process_status()
        updates = self.model.level_updates()[0]  # type: ignore[attr-defined]
        self.samples.append(Sample(self.num_timesteps, rss, hwm, open_fds(), threads, self.all_full(), updates))

    def _on_training_start(self) -> None:
        self.sample()

    def _on_step(self) -> bool:
        if self.checkpoint_every and self.num_timesteps % self.checkpoint_every == 0:
            self.model.save(os.path.join(self.checkpoint_dir, "model.zip"))
            self.model.save_replay_buffer(os.path.join(self.checkpoint_dir, "replay.pkl"))
        if self.num_timesteps % self.sample_every == 0:
            self.sample()
        return True


def summarize(samples: list[Sample], tolerance: float) -> list[str]:
    """Summary lines: when the replay filled, RSS growth after that, descriptors and threads.

    The reference point ("at full") is the first sample at which every level's replay is full and training has
    started (before the first update the optimiser states and autograd buffers do not exist yet). Besides the growth
    relative to it, the largest RSS of the second half of the later samples is compared with that of the first half:
    a leak keeps growing, a warm-up of the allocator levels off.

    :param samples: the samples in step order
    :param tolerance: allowed relative RSS growth after the replay is full
    :return: lines to print
    """
    full = [s for s in samples if s.full and s.updates > 0]
    first, last = samples[0], samples[-1]
    lines = []
    if not full:
        lines.append("replay never full while training: run longer or use a smaller --buffer-size")
        return lines
    at_full = full[0]
    peak = max(full, key=lambda s: s.rss_mib)
    growth = (peak.rss_mib - at_full.rss_mib) / at_full.rss_mib
    half = len(full) // 2
    late = ""
    if half >= 1:
        early_max = max(s.rss_mib for s in full[:half])
        late_max = max(s.rss_mib for s in full[half:])
        late = (
            f"; max RSS of the 2nd half after full (from step {full[half].step}) vs the 1st half: "
            f"{late_max:.1f} vs {early_max:.1f} MiB ({(late_max - early_max) / early_max:+.1%})"
        )
    lines.append(f"every level's replay full (and training) at step {at_full.step}")
    lines.append(
        f"RSS at full {at_full.rss_mib:.1f} MiB, max after full {peak.rss_mib:.1f} MiB (step {peak.step}, "
        f"{growth:+.1%}), last {last.rss_mib:.1f} MiB (step {last.step}); VmHWM at full {at_full.hwm_mib:.1f} MiB, "
        f"at the end {last.hwm_mib:.1f} MiB"
    )
    verdict = "yes" if growth <= tolerance else "NO"
    lines.append(f"RSS flat within {tolerance:.0%} after the replay is full: {verdict}{late}")
    lines.append(
        f"open fds: start {first.fds}, at full {at_full.fds}, end {last.fds}, max {max(s.fds for s in samples)}"
        f"; {'no growth after full' if max(s.fds for s in full) <= at_full.fds else 'GROWING'}"
    )
    lines.append(
        f"threads: start {first.threads}, at full {at_full.threads}, end {last.threads}, "
        f"max {max(s.threads for s in samples)}"
        f"; {'no growth after full' if max(s.threads for s in full) <= at_full.threads else 'GROWING'}"
    )
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=30_000, help="environment steps")
    parser.add_argument("--buffer-size", type=int, default=2000, help="level-0 replay capacity (level i: // k**i)")
    parser.add_argument("--train-ratio", type=float, default=None, help="replayed steps per env step (preset: 64)")
    parser.add_argument("--learning-starts", type=int, default=None, help="random steps first (preset: 500)")
    parser.add_argument("--sample-every", type=int, default=250, help="steps between samples")
    parser.add_argument("--checkpoint-every", type=int, default=2000, help="steps between checkpoints, 0: none")
    parser.add_argument("--tolerance", type=float, default=0.10, help="allowed RSS growth after the replay is full")
    parser.add_argument("--rows", type=int, default=20, help="table rows to print (evenly spaced samples)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    if args.steps < 1 or args.sample_every < 1 or args.buffer_size < 1:
        parser.error("--steps, --sample-every and --buffer-size must be >= 1")
    th.set_num_threads(args.threads)
    print(environment_header())
    print(
        f"soak: small preset, CartPole-v1, steps {args.steps}, buffer_size {args.buffer_size}, "
        f"train_ratio {args.train_ratio or 'preset'}, learning_starts {args.learning_starts or 'preset'}, "
        f"checkpoint every {args.checkpoint_every}, sample every {args.sample_every}, seed {args.seed}"
    )
    model = HIEROS(
        "MlpPolicy",
        "CartPole-v1",
        preset="small",
        buffer_size=args.buffer_size,
        config_overrides={} if args.train_ratio is None else {"train_ratio": args.train_ratio},
        learning_starts=args.learning_starts,
        seed=args.seed,
    )
    sizes = ", ".join(f"level {i}: {b.buffer_size * b.n_envs} rows" for i, b in enumerate(model.level_buffers()))
    print(f"replay capacities: {sizes}")
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as checkpoint_dir:
        callback = SoakCallback(args.sample_every, args.checkpoint_every, checkpoint_dir)
        model.learn(args.steps, callback=callback)
        callback.sample()
    wall = time.perf_counter() - start
    samples = callback.samples
    print(f"{'step':>7} {'RSS MiB':>9} {'VmHWM MiB':>10} {'fds':>5} {'threads':>8} {'full':>5} {'updates':>8}")
    stride = max(1, len(samples) // args.rows)
    first_full = next((s for s in samples if s.full and s.updates > 0), None)
    for i, s in enumerate(samples):
        if i % stride == 0 or s is first_full or i == len(samples) - 1:
            row = f"{s.step:>7} {s.rss_mib:>9.1f} {s.hwm_mib:>10.1f} {s.fds:>5} {s.threads:>8} {s.full!s:>5}"
            print(f"{row} {s.updates:>8}")
    print(
        f"{model.num_timesteps} steps, {model.level_updates()[0]} level-0 updates, level updates "
        f"{model.level_updates()}, skipped {model.skipped_updates()}, wall {wall:.0f} s"
    )
    for line in summarize(samples, args.tolerance):
        print(line)


if __name__ == "__main__":
    main()
