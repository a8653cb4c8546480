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

Fault mode (``--faults N``): does a run survive ``kill -9`` at random moments? A training process (the same small
preset on CartPole-v1, checkpointing model and replay every ``--checkpoint-every`` steps with ``model.save`` and
``model.save_replay_buffer``) is killed with SIGKILL ``N`` times, each time at a random point: during an update
(right after the loop hands over to ``train()``) or during a checkpoint save (a random delay after the save began,
up to the duration of the saves so far). After every kill a new process checks the checksums of every checkpoint
file, resumes from the newest complete pair with ``HIEROS.load(..., safe=True)`` and ``load_replay_buffer``, and
trains on. Checkpoints are taken at the start of a vec-env step, after the previous step's transition was stored and
its updates made, so a resumed run makes the same updates as one that never stopped. The report gives the lost steps
(progress at the kill minus the step resumed from), failed resumes, corrupt files, temporary files left by killed
saves and whether the final ``num_timesteps``, ``_n_updates``, ``_level_updates`` and ``_update_budget`` equal those
of an uninterrupted run with the same settings (run afterwards, also in a child process)::

    python -m benchmarks.soak --faults 20 --steps 6000 --train-ratio 8 --checkpoint-every 200
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import queue
import signal
import subprocess
import sys
import tempfile
import threading
import time
import zipfile
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env

from benchmarks._checkpoint import PeriodicCheckpoint, checkpoint_paths, checkpoint_steps, load_checkpoint
from benchmarks._timing import environment_header
from sb3_hieros import HIEROS
from sb3_hieros.save_util import verify_archive


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


# ------------------------------------------------------------------------------------------------ fault mode

#: counters a resumed run must share with an uninterrupted one
COUNTERS = ("num_timesteps", "_n_updates", "_level_updates", "_update_budget")


def _say(*parts: Any) -> None:
    """One protocol line from the training process to the orchestrator."""
    print(*parts, flush=True)


def corrupt_files(directory: pathlib.Path) -> list[str]:
    """Checkpoint files (temporary files of killed saves excluded) that are not intact zips matching their checksums."""
    bad = []
    for path in sorted(directory.glob("*.zip")):
        try:
            with zipfile.ZipFile(path) as archive:
                if verify_archive(archive, str(path)) is None:
                    bad.append(f"{path.name} (no manifest)")
        except (ValueError, zipfile.BadZipFile, OSError) as err:
            bad.append(f"{path.name} ({err})")
    return bad


class FaultCheckpoint(PeriodicCheckpoint):
    """Checkpoints at the start of every ``every``-th vec-env step and protocol lines for the orchestrator.

    ``STEP n`` after every step, ``TRAIN n`` when the loop is about to make an update, ``SAVE_BEGIN n`` /
    ``SAVE_END n seconds`` around a checkpoint. The two newest checkpoints are kept.

    :param directory: where the checkpoints go
    :param every: steps between checkpoints
    """

    def _save(self, step: int) -> None:
        start = time.perf_counter()
        _say("SAVE_BEGIN", step)
        super()._save(step)
        _say("SAVE_END", step, f"{time.perf_counter() - start:.4f}")
        for old in checkpoint_steps(self.directory)[2:]:
            for path in checkpoint_paths(self.directory, old):
                path.unlink(missing_ok=True)

    def _on_step(self) -> bool:
        _say("STEP", self.model.num_timesteps)
        return True

    def _on_rollout_end(self) -> None:
        model = self.model
        cfg = model.config  # type: ignore[attr-defined]
        due = model.update_budget + model.n_envs * cfg.train_ratio / (cfg.batch_size * cfg.batch_length)  # type: ignore[attr-defined]
        if model.num_timesteps > model.learning_starts and due >= 1.0:  # type: ignore[attr-defined]
            _say("TRAIN", model.num_timesteps)


def fault_worker(args: argparse.Namespace) -> None:
    """One training process of the fault soak: resume from the newest intact checkpoint (or start), train to
    ``--steps``, report the counters."""
    th.set_num_threads(args.threads)
    directory = pathlib.Path(args.worker)
    directory.mkdir(parents=True, exist_ok=True)
    for bad in corrupt_files(directory):
        _say("CORRUPT", bad)
    env = make_vec_env("CartPole-v1", n_envs=1, seed=args.seed)
    steps = checkpoint_steps(directory)
    if steps:
        model = load_checkpoint(directory, steps[0], env, safe=True)
        _say("RESUMED", steps[0], int(all(b.can_sample() for b in model.level_buffers())))
    else:
        model = HIEROS(
            "MlpPolicy",
            env,
            preset="small",
            buffer_size=args.buffer_size,
            config_overrides={"train_ratio": args.train_ratio},
            learning_starts=args.learning_starts,
            seed=args.seed,
        )
        _say("FRESH")
    left = args.steps - model.num_timesteps
    if left > 0:
        callback = FaultCheckpoint(directory, args.checkpoint_every)
        model.learn(left, callback=callback, reset_num_timesteps=not steps)
    counters = {name: getattr(model, name) for name in COUNTERS}
    counters["replay_sizes"] = [b.size() for b in model.level_buffers()]
    _say("DONE", json.dumps(counters))


@dataclass
class Kill:
    """One SIGKILL of the fault soak."""

    kind: str  #: "update" or "save"
    progress: int  #: last step the process reported before it died
    during_save: bool = False  #: the save it aimed at had not finished
    during_update: bool = False  #: no step followed the update it aimed at
    resumed_from: int | None = None


@dataclass
class FaultReport:
    """Result of :func:`run_fault_soak`."""

    kills: list[Kill] = field(default_factory=list)
    failed_resumes: int = 0
    corrupt: list[str] = field(default_factory=list)
    temp_files_left: set[str] = field(default_factory=set)  #: temporary files found right after the kills
    temp_files_at_end: int = 0
    resumes_all_sampling: bool = True  #: every resume point had every level able to sample
    counters: dict[str, Any] = field(default_factory=dict)
    uninterrupted: dict[str, Any] = field(default_factory=dict)
    wall_faulty: float = 0.0
    wall_uninterrupted: float = 0.0

    @property
    def lost_steps(self) -> list[int]:
        return [k.progress - k.resumed_from for k in self.kills if k.resumed_from is not None]

    @property
    def counters_equal(self) -> bool:
        return all(self.counters.get(n) == self.uninterrupted.get(n) for n in COUNTERS) and bool(self.counters)

    def lines(self) -> list[str]:
        """The summary to print."""
        kinds = [k.kind for k in self.kills]
        lost = self.lost_steps
        out = [
            f"kill {i + 1}: during {'an update' if k.kind == 'update' else 'a checkpoint save'} at step {k.progress}"
            + (" (the save had not finished)" if k.during_save else "")
            + (" (inside the update)" if k.during_update else "")
            + f", resumed from {k.resumed_from}"
            for i, k in enumerate(self.kills)
        ]
        out.append(
            f"kills: {len(self.kills)} ({kinds.count('update')} during updates, {kinds.count('save')} aimed at saves, "
            f"{sum(k.during_save for k in self.kills)} of them before the save finished; "
            f"{sum(k.during_update for k in self.kills)} of the update kills before the next step began)"
        )
        out.append(f"failed resumes: {self.failed_resumes}; corrupt files: {len(self.corrupt)} {self.corrupt or ''}")
        out.append(
            f"temporary files left by killed saves: {len(self.temp_files_left)}, of them left at the end: "
            f"{self.temp_files_at_end} (the next save to the same path removes them)"
        )
        if lost:
            out.append(f"lost steps: total {sum(lost)}, mean {np.mean(lost):.1f}, max {max(lost)} per kill")
        out.append(f"every level could sample at every resume point: {'yes' if self.resumes_all_sampling else 'no'}")
        shown = {n: self.counters.get(n) for n in (*COUNTERS, "replay_sizes")}
        out.append(f"final counters: {shown}")
        out.append(f"uninterrupted:  { {n: self.uninterrupted.get(n) for n in (*COUNTERS, 'replay_sizes')} }")
        out.append(f"counters equal to the uninterrupted run: {'yes' if self.counters_equal else 'NO'}")
        out.append(f"wall: faulty run {self.wall_faulty:.0f} s, uninterrupted run {self.wall_uninterrupted:.0f} s")
        return out


def _worker_command(args: argparse.Namespace, directory: pathlib.Path) -> list[str]:
    return [
        sys.executable,
        "-m",
        "benchmarks.soak",
        "--worker",
        str(directory),
        "--steps",
        str(args.steps),
        "--buffer-size",
        str(args.buffer_size),
        "--train-ratio",
        str(args.train_ratio),
        "--learning-starts",
        str(args.learning_starts),
        "--checkpoint-every",
        str(args.checkpoint_every),
        "--threads",
        str(args.threads),
        "--seed",
        str(args.seed),
    ]


class _Child:
    """A worker process whose protocol lines arrive on a queue (read by a thread, so waits can time out)."""

    def __init__(self, command: list[str]) -> None:
        env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
        root = pathlib.Path(__file__).resolve().parent.parent
        self.process = subprocess.Popen(
            command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=root, env=env
        )
        self.lines: queue.Queue[str | None] = queue.Queue()
        self.stderr: list[str] = []
        threading.Thread(target=self._pump, daemon=True).start()
        threading.Thread(target=lambda: self.stderr.extend(self.process.stderr), daemon=True).start()  # type: ignore[arg-type]

    def _pump(self) -> None:
        for line in self.process.stdout:  # type: ignore[union-attr]
            self.lines.put(line.strip())
        self.lines.put(None)

    def next_line(self, timeout: float) -> str | None:
        """The next line, None at the end of output; raises ``TimeoutError`` when none comes in ``timeout`` s."""
        try:
            return self.lines.get(timeout=timeout)
        except queue.Empty:
            raise TimeoutError(f"no output from the training process for {timeout:.0f} s") from None

    def kill(self) -> None:
        self.process.send_signal(signal.SIGKILL)
        self.process.wait()


def _run_segment(
    args: argparse.Namespace, directory: pathlib.Path, plan: dict[str, Any] | None, report: FaultReport
) -> tuple[Kill | None, dict[str, Any] | None, list[float]]:
    """Run one training process; kill it as ``plan`` says (None: let it finish).

    :return: the kill (or None), the DONE counters (or None), the durations of the saves it reported
    """
    child = _Child(_worker_command(args, directory))
    progress, saves_seen, durations = 0, 0, []
    done: dict[str, Any] | None = None
    kill: Kill | None = None
    aimed_at: int | None = None
    finished_saves: set[int] = set()
    while True:
        line = child.next_line(args.timeout)
        if line is None:
            break
        word, *rest = line.split(" ", 1) if line else [""]
        if word == "STEP":
            progress = int(rest[0])
        elif word == "CORRUPT":
            report.corrupt.append(rest[0])
        elif word == "RESUMED":
            step, sampling = rest[0].split()
            report.resumes_all_sampling &= sampling == "1"
        elif word == "SAVE_END":
            step, seconds = rest[0].split()
            finished_saves.add(int(step))
            durations.append(float(seconds))
        elif word == "DONE":
            done = json.loads(rest[0])
        if plan is None or kill is not None:
            continue
        if plan["kind"] == "update" and word == "TRAIN" and int(rest[0]) >= plan["after"]:
            child.kill()
            kill = Kill("update", progress)
            aimed_at = int(rest[0])
        elif plan["kind"] == "save" and word == "SAVE_BEGIN":
            saves_seen += 1
            if saves_seen == plan["nth_save"]:
                time.sleep(plan["delay"])
                child.kill()
                aimed_at = int(rest[0])
                kill = Kill("save", progress)
    child.process.wait()
    if kill is not None and aimed_at is not None:
        kill.progress = progress
        kill.during_save = kill.kind == "save" and aimed_at not in finished_saves
        kill.during_update = kill.kind == "update" and progress == aimed_at
    if kill is None and child.process.returncode != 0:
        report.failed_resumes += 1
        print("training process failed:\n" + "".join(child.stderr[-20:]), file=sys.stderr)
    return kill, done, durations


def run_fault_soak(args: argparse.Namespace) -> FaultReport:
    """Kill and resume a training process ``args.faults`` times, then run it once without kills (module docstring).

    :param args: the parsed command line (``faults``, ``steps``, ``checkpoint_every``, ``kill_after``, ...)
    :return: the report
    """
    rng = np.random.default_rng(args.seed)
    report = FaultReport()
    save_seconds = [0.2]
    with tempfile.TemporaryDirectory() as tmp:
        faulty, straight = pathlib.Path(tmp) / "faulty", pathlib.Path(tmp) / "uninterrupted"
        start = time.perf_counter()
        while True:
            steps = checkpoint_steps(faulty) if faulty.exists() else []
            resume = steps[0] if steps else 0
            if report.kills and report.kills[-1].resumed_from is None:
                report.kills[-1].resumed_from = resume
            plan = None
            if len(report.kills) < args.faults:
                every = args.checkpoint_every
                saves_left = (args.steps - 1) // every - resume // every  # before the run ends
                first = 1 if resume >= args.kill_after else 1 + (args.kill_after - resume) // every
                nth_save = min(int(first + rng.integers(0, 2)), saves_left)
                if rng.random() < 0.5 or nth_save < 1:
                    low = max(resume, args.kill_after) + 1
                    after = min(int(rng.integers(low, low + 2 * every)), args.steps - every)  # an update comes later
                    plan = {"kind": "update", "after": after}
                else:
                    delay = float(rng.uniform(0.0, 1.0) * np.median(save_seconds))
                    plan = {"kind": "save", "nth_save": nth_save, "delay": delay}
            kill, done, durations = _run_segment(args, faulty, plan, report)
            save_seconds += durations
            if kill is not None:
                report.kills.append(kill)
                report.temp_files_left.update(p.name for p in faulty.glob(".*.tmp"))
                continue
            if done is None:  # the process died by itself: resume once more, but not forever
                if report.failed_resumes > args.faults:
                    break
                continue
            report.counters = done
            break
        report.temp_files_at_end = len(list(faulty.glob(".*.tmp")))
        report.wall_faulty = time.perf_counter() - start
        start = time.perf_counter()
        _, done, _ = _run_segment(args, straight, None, report)
        report.uninterrupted = done or {}
        report.wall_uninterrupted = time.perf_counter() - start
    return report


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
    parser.add_argument("--faults", type=int, default=0, help="fault mode: SIGKILL and resume this many times")
    parser.add_argument("--kill-after", type=int, default=1000, help="fault mode: no kill before this step")
    parser.add_argument("--timeout", type=float, default=600.0, help="fault mode: max seconds without output")
    parser.add_argument("--worker", default=None, help=argparse.SUPPRESS)  # a training process of the fault mode
    args = parser.parse_args()
    if args.worker is not None:
        fault_worker(args)
        return
    if args.faults:
        if args.train_ratio is None or args.learning_starts is None:
            parser.error("fault mode needs --train-ratio and --learning-starts")
        if args.checkpoint_every < 1 or args.kill_after + 2 * args.checkpoint_every > args.steps:
            parser.error(
                "fault mode needs --checkpoint-every >= 1 and --kill-after + 2 * --checkpoint-every <= --steps"
            )
        print(environment_header())
        print(
            f"fault soak: small preset, CartPole-v1, steps {args.steps}, buffer_size {args.buffer_size}, "
            f"train_ratio {args.train_ratio}, learning_starts {args.learning_starts}, checkpoint every "
            f"{args.checkpoint_every}, {args.faults} SIGKILLs after step {args.kill_after}, seed {args.seed}, "
            f"{args.threads} torch thread(s)"
        )
        for line in run_fault_soak(args).lines():
            print(line)
        return
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
