"""benchmarks/demo.py (the ``make demo`` job): log lines reach a redirected output while the run goes on."""

from __future__ import annotations

import os
import pathlib
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_demo_log_lines_are_not_held_back_when_redirected(tmp_path):
    # a long run whose stdout is a pipe: the first evaluation's line must arrive while it still trains
    command = [sys.executable, "-m", "benchmarks.demo", "--steps", "100000", "--eval-freq", "20"]
    command += ["--eval-episodes", "1", "--subgoal-every", "100000", "--threads", "1", "--no-progress-bar"]
    command += ["--out", str(tmp_path)]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    env.pop("PYTHONUNBUFFERED", None)
    process = subprocess.Popen(command, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    lines: list[str] = []
    try:
        deadline = time.monotonic() + 240
        assert process.stdout is not None
        while time.monotonic() < deadline:
            line = process.stdout.readline()
            if not line:
                break
            lines.append(line)
            if line.startswith("Eval num_timesteps=20"):
                break
        assert lines and lines[-1].startswith("Eval num_timesteps=20"), lines
        assert process.poll() is None  # still training
        assert any("random actions for the first 500 steps" in line for line in lines), lines
        # the evaluation log written just before each "Eval" line: the first line came right after the first
        # evaluation, not with a block of later ones once a pipe buffer filled up
        evaluations = _paused_read(process, tmp_path / "evaluations.npz")
        assert evaluations[0] == 20 and len(evaluations) <= 3, evaluations
    finally:
        process.kill()
        process.wait()


def _paused_read(process: subprocess.Popen, path: pathlib.Path) -> np.ndarray:
    """``timesteps`` of an ``evaluations.npz`` that a running process writes, read while the process is paused."""
    for _ in range(20):
        process.send_signal(signal.SIGSTOP)
        try:
            with np.load(path) as data:
                return data["timesteps"]
        except (OSError, ValueError, KeyError, EOFError):
            process.send_signal(signal.SIGCONT)  # caught in the middle of a write
            time.sleep(0.05)
    raise AssertionError(f"{path} could not be read")


def test_threads_follow_the_free_cpus():
    from benchmarks.demo import auto_threads

    assert auto_threads(2, 0.1)[0] == 2  # a quiet 2-core machine
    assert auto_threads(2, 0.4)[0] == 2
    assert auto_threads(2, 1.0)[0] == 1  # one core busy: a second thread would wait on it
    assert auto_threads(2, 5.0)[0] == 1  # busier than the machine: still one thread
    assert auto_threads(16, 0.0)[0] == 2  # never more than ``most``
    assert auto_threads(16, 0.0, most=4)[0] == 4
    assert auto_threads(16, 13.2, most=4)[0] == 3
    assert auto_threads(1, 0.0)[0] == 1
    threads, why = auto_threads(2, 1.2)
    assert threads == 1 and "2 CPUs available, load 1.2, so 0.8 free" in why


def test_thread_choice_checks_its_inputs():
    from benchmarks.demo import auto_threads, free_cpus

    with pytest.raises(ValueError, match="cpus must be a positive int, got 0"):
        auto_threads(0, 0.0)
    with pytest.raises(ValueError, match=r"load must be a finite number >= 0, got -1\.0"):
        auto_threads(2, -1.0)
    with pytest.raises(ValueError, match="load must be a finite number >= 0, got nan"):
        auto_threads(2, float("nan"))
    cpus, load = free_cpus()
    assert cpus >= 1 and load >= 0.0
