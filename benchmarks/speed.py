"""Speed benchmarks, one argparse subcommand per table.

``python -m benchmarks.speed s5`` times forward+backward of the resettable S5 layer (thesis 4.4.2) against
recurrent baselines, and its scan against the same scan differentiated by autograd (instead of its hand-written
backward) and against the scan style of the public HIEROS reference implementation, following the
timing protocol of ``benchmarks/_timing.py``: all variants of one
sequence length run interleaved round-robin in one process after warm-ups; min and median are reported.
The last lines print each speed ratio (baseline median / ours median) as ``name: value``.

``python -m benchmarks.speed agent`` measures whole-agent training speed: environment steps per second
of ``HIEROS.learn`` on ALE Pong 64x64 (``benchmarks/suites.py``) with the small preset, which includes acting and
the updates of every level at the preset's train ratio. Two builds with the same seed, S5WM (default) and RSSM
(``world_model.kind="rssm"``), are first filled with ``learning_starts`` random steps (untimed), then timed in
alternating segments of ``--segment`` environment steps (``learn(segment, reset_num_timesteps=False)``), one untimed
warm-up segment each first. The thesis reports S5WM 1.59x as fast as RSSM on a GPU; the goal here is >= 1.5x.
During the timed segments a :class:`PhaseClock` splits each build's wall time into acting, world-model updates,
imagination, actor-critic + autoencoder updates, replay sampling and the rest (environment, buffer writes), so the
table shows which parts the sequence model can speed up at all.

``python -m benchmarks.speed compare --ref <git ref>`` times the same public-API parts for the working tree and for the
ref (checked out into a temporary git worktree, removed afterwards), each part in a fresh interpreter per repetition
(``benchmarks/_speed_cases.py``), the two sides alternated in the order A B B A ... so that a drift of the machine's
load falls on both: ``learn`` (seconds of ``model.learn(3000)`` on CartPole-v1, small preset, learning_starts 500),
``predict`` (latency of deterministic ``predict`` on one env with the recurrent state threaded) and ``pong`` (env steps
per second of ``learn`` on ALE Pong 64x64, small preset, every level training). It prints each side's median and range
over the repetitions and the speed-ups (ref time / our time, our steps/s / ref steps/s) as ``name: value`` last.
``--policy-kwargs`` and ``--ref-policy-kwargs`` (JSON) set the models' ``policy_kwargs`` of each side, e.g.
``--ref HEAD --policy-kwargs '{"bf16": true}' --ref-policy-kwargs '{"bf16": false}'`` times bf16 losses against
float32 in the same code (the default, ``"auto"``, is bf16 on CPUs with native bf16 and float32 elsewhere).
``--config-overrides`` and ``--ref-config-overrides`` (JSON) set each side's ``config_overrides`` in the same way, and
``--learn-env`` times ``learn`` on another Gymnasium env with vector observations: ``--ref HEAD --parts learn
--learn-env Pendulum-v1 --config-overrides '{"world_model_updates": 2}'`` times what a configuration change costs on a
continuous-control task.

``python -m benchmarks.speed profile`` asks where the time of one update and of one ``predict`` goes, with
``torch.profiler``: a small-preset ``MlpPolicy`` model on CartPole-v1 learns past ``learning_starts``, then
``--updates`` level-0 updates (``Subactor.train_step`` on replay batches, as ``learn`` runs them) and
``--predict-calls`` deterministic ``predict`` calls are timed, then profiled. For each it prints the wall time, the
aten operator calls, the share of the operators' time spent in matrix products (``mm``, ``addmm``, ``bmm``,
``baddbmm``) and the rate they reached (floating-point operations from their shapes), and the bound that follows: the
time if everything but the matrix products took no time at all, i.e. the largest speed-up that removing overhead alone
(fusion, compilation, fewer operators) could give at this preset on this CPU.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import pathlib
import statistics
import tempfile
import time
from collections import defaultdict
from collections.abc import Callable, Sequence
from typing import Any

import torch
from torch import nn

from benchmarks import _gitref
from benchmarks._cli import json_object
from benchmarks._timing import Timing, environment_header, format_ms, time_interleaved
from sb3_hieros.nn.s5 import S5Layer, S5Stack, associative_scan_resettable, compile_s5, resettable_scan
from sb3_hieros.nn.scan import _interleave

Elements = tuple[torch.Tensor, torch.Tensor, torch.Tensor]


def _reference_style_combine(earlier: Elements, later: Elements) -> Elements:
    """Resettable S5 combine as the reference implementation does it (three ``torch.where`` per combine).

    Elements are (transition A, input Bu, reset flag d). If the later segment contains a reset, it is returned
    unchanged; otherwise the usual (A_j A_i, A_j b_i + b_j) with the earlier flag. Three ``torch.where``.
    """
    a_i, b_i, d_i = earlier
    a_j, b_j, d_j = later
    has_reset = d_j > 0
    return (
        torch.where(has_reset, a_j, a_j * a_i),
        torch.where(has_reset, b_j, a_j * b_i + b_j),
        torch.where(has_reset, d_j, d_i),
    )


def reference_style_scan(elements: Elements) -> Elements:
    """Generic odd/even associative scan over (A, Bu, d) triples along dim 1, every component combined.

    Written for this benchmark from the description of the reference's scan (a port of the
    ``jax.lax.associative_scan`` recursion that scans the full triples, with a full-size ``(B, T, P)`` transition
    tensor); it is the baseline, not the implementation we use.

    :param elements: A ``(B, T, P)`` complex, Bu ``(B, T, P)`` complex, d ``(B, T, 1)`` float
    :return: inclusive prefix combination of the triples; its second component holds the states
    """
    length = elements[0].shape[1]
    if length < 2:
        return elements
    reduced = _reference_style_combine(
        tuple(e[:, 0:-1:2] for e in elements),  # type: ignore[arg-type]
        tuple(e[:, 1::2] for e in elements),  # type: ignore[arg-type]
    )
    odd = reference_style_scan(reduced)
    left = odd if length % 2 == 1 else tuple(o[:, :-1] for o in odd)
    even_rest = _reference_style_combine(left, tuple(e[:, 2::2] for e in elements))  # type: ignore[arg-type]
    even = tuple(torch.cat((e[:, :1], r), dim=1) for e, r in zip(elements, even_rest, strict=True))
    return tuple(_interleave(e, o, length) for e, o in zip(even, odd, strict=True))  # type: ignore[return-value]


def _fwd_bwd(fn: Callable[[], torch.Tensor]) -> Callable[[], None]:
    def run() -> None:
        out = fn()
        if out.is_complex():
            out = torch.view_as_real(out)
        out.sum().backward()

    return run


def s5_variants(
    length: int,
    batch: int,
    d_model: int,
    d_state: int,
    n_blocks: int,
    n_stack: int,
    seed: int,
    compile_layer: bool = False,
) -> dict[str, Callable[[], None]]:
    """Forward+backward callables of every variant for one sequence length.

    :param compile_layer: also time an ``S5Layer`` under ``compile_s5`` (compiles once here, tens of seconds)
    :return: name -> zero-argument callable
    """
    torch.manual_seed(seed)
    x = torch.randn(batch, length, d_model, requires_grad=True)
    reset = torch.rand(batch, length) < 0.02
    reset[:, length // 2] = True  # at least one episode border per sequence

    layer = S5Layer(d_model, d_state, n_blocks)
    stack = S5Stack(n_stack, d_model, d_state, n_blocks)
    cell = nn.GRUCell(d_model, d_model)
    gru = nn.GRU(d_model, d_model, batch_first=True)

    def gru_cell_loop() -> torch.Tensor:
        h = x.new_zeros(batch, d_model)
        outs = []
        for x_t in x.unbind(1):
            h = cell(x_t, h)
            outs.append(h)
        return torch.stack(outs, dim=1)

    # Scan kernel only, same inputs for both: x_t = (1 - reset_t) Lambda_bar x_{t-1} + Bu_t.
    with torch.no_grad():
        lambda_bar0, _ = layer.discretize()
    lambda_bar_param = torch.view_as_real(lambda_bar0).clone().requires_grad_(True)
    bu_param = torch.randn(batch, length, d_state, 2, requires_grad=True)
    keep = (~reset).float().unsqueeze(-1)
    flag = reset.float().unsqueeze(-1)

    def ours_scan() -> torch.Tensor:
        return resettable_scan(torch.view_as_complex(lambda_bar_param), keep, torch.view_as_complex(bu_param))

    def ours_scan_autograd() -> torch.Tensor:
        return associative_scan_resettable(
            torch.view_as_complex(lambda_bar_param), keep, torch.view_as_complex(bu_param)
        )

    def reference_scan() -> torch.Tensor:
        bu = torch.view_as_complex(bu_param)
        transition = torch.view_as_complex(lambda_bar_param).expand(batch, length, d_state)
        return reference_style_scan((transition, bu, flag))[1]

    variants = {
        "S5Layer": _fwd_bwd(lambda: layer(x, reset)[0]),
        "GRUCell loop": _fwd_bwd(gru_cell_loop),
        "nn.GRU (fused)": _fwd_bwd(lambda: gru(x)[0]),
        "scan (ours)": _fwd_bwd(ours_scan),
        "scan (ours, autograd bwd)": _fwd_bwd(ours_scan_autograd),
        "scan (reference style)": _fwd_bwd(reference_scan),
        f"S5Stack ({n_stack} layers)": _fwd_bwd(lambda: stack(x, reset)[0]),
    }
    if compile_layer:
        compiled = S5Layer(d_model, d_state, n_blocks)
        compiled.load_state_dict(layer.state_dict())
        compile_s5(compiled)
        start = time.perf_counter()
        _fwd_bwd(lambda: compiled(x, reset)[0])()
        print(f"  (T={length}: torch.compile of S5Layer took {time.perf_counter() - start:.0f} s)")
        variants["S5Layer (compile_s5)"] = _fwd_bwd(lambda: compiled(x, reset)[0])
    return variants


def run_s5(args: argparse.Namespace) -> None:
    """``s5`` subcommand: S5 layer, scan and stack timings; prints ratios last."""
    print(environment_header())
    print(
        f"fwd+bwd, B={args.batch}, H={args.d_model}, P={args.d_state}, J={args.n_blocks}, "
        f"warmup={args.warmup}, reps={args.reps} (interleaved), times min / median"
    )
    ratios: dict[str, float] = {}
    for length in args.lengths:
        variants = s5_variants(
            length,
            args.batch,
            args.d_model,
            args.d_state,
            args.n_blocks,
            args.stack_layers,
            args.seed,
            compile_layer=args.compile,
        )
        timings: dict[str, Timing] = time_interleaved(variants, warmup=args.warmup, reps=args.reps)
        print(f"\nT={length}")
        for name, timing in timings.items():
            print(f"  {name:<26} {format_ms(timing)}")
        s5 = timings["S5Layer"].median
        ratios[f"s5_vs_grucell_T{length}"] = timings["GRUCell loop"].median / s5
        ratios[f"s5_vs_gru_fused_T{length}"] = timings["nn.GRU (fused)"].median / s5
        ratios[f"scan_vs_reference_scan_T{length}"] = (
            timings["scan (reference style)"].median / timings["scan (ours)"].median
        )
        ratios[f"scan_vs_autograd_backward_T{length}"] = (
            timings["scan (ours, autograd bwd)"].median / timings["scan (ours)"].median
        )
        if args.compile:
            ratios[f"s5_compiled_vs_eager_T{length}"] = s5 / timings["S5Layer (compile_s5)"].median
        stack_name = f"S5Stack ({args.stack_layers} layers)"
        ratios[f"s5stack{args.stack_layers}_ms_T{length}"] = timings[stack_name].median * 1e3
    print("\nratios (baseline median / ours median; s5stack*_ms is the stack's median in ms):")
    for name, value in ratios.items():
        print(f"{name}: {value:.2f}")


def build_agent(game: str, world_model: str, seed: int, learning_starts: int | None, n_levels: int | None) -> Any:
    """A small-preset ``HIEROS("CnnPolicy")`` on one Atari100k game (64x64 RGB, action repeat 4).

    :param game: Atari game name (``benchmarks.suites.make_atari_env``)
    :param world_model: ``"s5"`` or ``"rssm"``
    :param seed: seed of the agent and of the environment
    :param learning_starts: random steps before training; None = the preset's
    :param n_levels: hierarchy depth; None = the preset's
    :return: the model (not trained)
    """
    from benchmarks.suites import make_atari_env
    from sb3_hieros import HIEROS

    return HIEROS(
        "CnnPolicy",
        make_atari_env(game, seed=seed),
        preset="small",
        seed=seed,
        learning_starts=learning_starts,
        config_overrides={"world_model": {"kind": world_model}, **({} if n_levels is None else {"n_levels": n_levels})},
    )


class PhaseClock:
    """Wall time of the parts of ``HIEROS.learn``, measured by wrapping methods of one model's instances.

    Wrapped (instance attributes shadowing the methods; benchmark use only, the model is not saved): the hierarchy's
    ``step`` (acting: every level's observation step and actor) and ``train_step`` (one update of every level that is
    due), the model's ``train`` (replay sampling, replay context and logging around it), each level's
    ``world_model_step`` and each world model's ``rollout`` (imagination). :meth:`phases` derives disjoint parts of
    the wall time from them; the shared-world-model ablation is measured the same way.

    :param model: a ``HIEROS`` model
    """

    PHASES = ("acting", "world_model", "imagination", "actor_critic_ae", "replay_and_rest", "env_and_rest")

    def __init__(self, model: Any) -> None:
        self.seconds: defaultdict[str, float] = defaultdict(float)
        self._in_train_step = False
        hierarchy = model.policy.hierarchy
        self._wrap(hierarchy, "step", "acting")
        self._wrap(model, "train", "train")
        self._wrap(hierarchy, "train_step", "train_step")
        for level in hierarchy.levels:
            if hasattr(level, "world_model"):  # the shared-world-model ablation's upper levels have none
                self._wrap(level, "world_model_step", "world_model")
                self._wrap(level.world_model, "rollout", "imagination")

    def _wrap(self, owner: Any, name: str, key: str) -> None:
        method = getattr(owner, name)

        @functools.wraps(method)
        def timed(*args: Any, **kwargs: Any) -> Any:
            outer = self._in_train_step
            self._in_train_step = outer or key == "train_step"
            start = time.perf_counter()
            try:
                return method(*args, **kwargs)
            finally:
                elapsed = time.perf_counter() - start
                self._in_train_step = outer
                self.seconds[key] += elapsed
                if outer and key != "train_step":
                    self.seconds[f"{key} in train_step"] += elapsed

        object.__setattr__(owner, name, timed)

    def reset(self) -> None:
        """Forget the time measured so far."""
        self.seconds.clear()

    def phases(self, wall: float) -> dict[str, float]:
        """Disjoint parts of ``wall`` seconds of ``learn``, in seconds.

        :param wall: wall time of the ``learn`` calls measured since the last :meth:`reset`
        :return: :data:`PHASES` -> seconds: ``actor_critic_ae`` = the hierarchy's ``train_step`` less the world-model
            steps and imaginations inside it; ``replay_and_rest`` = ``train`` less ``train_step`` and less any
            world-model step or imagination outside it (replay sampling, replay context, logging);
            ``env_and_rest`` = ``wall`` less acting and ``train`` (environment steps, replay writes, callbacks)
        """
        t = self.seconds
        inner = t["world_model in train_step"] + t["imagination in train_step"]
        return {
            "acting": t["acting"],
            "world_model": t["world_model"],
            "imagination": t["imagination"],
            "actor_critic_ae": t["train_step"] - inner,
            "replay_and_rest": t["train"] - t["train_step"] - (t["world_model"] + t["imagination"] - inner),
            "env_and_rest": wall - t["acting"] - t["train"],
        }


def run_agent(args: argparse.Namespace) -> None:
    """``agent`` subcommand: env steps/s of ``learn`` for S5WM and RSSM builds; prints the speed-up last."""
    if args.segment < 1 or args.rounds < 1 or args.warmup < 0:
        raise ValueError(
            f"need --segment >= 1, --rounds >= 1, --warmup >= 0, got {args.segment}, {args.rounds}, {args.warmup}"
        )
    print(environment_header())
    load, cpus = os.getloadavg()[0], os.cpu_count() or 1
    if torch.get_num_threads() > 1 and load + torch.get_num_threads() > cpus:
        print(
            f"warning: {torch.get_num_threads()} threads on {cpus} CPUs with load {load:.1f}: intra-op threads then "
            "wait on each other and single-sample acting slows down many-fold; --threads 1 is faster on a busy machine"
        )
    builds = {"S5WM": "s5", "RSSM": "rssm"}
    models: dict[str, Any] = {}
    for name, kind in builds.items():
        start = time.perf_counter()
        model = build_agent(args.game, kind, args.seed, args.learning_starts, args.n_levels)
        built = time.perf_counter() - start
        start = time.perf_counter()
        model.learn(model.learning_starts)
        filled = time.perf_counter() - start
        models[name] = model
        n_params = sum(p.numel() for p in model.policy.parameters())
        print(
            f"  {name}: {n_params / 1e6:.2f}M parameters, built in {built:.1f} s, "
            f"{model.learning_starts} random steps (untimed) in {filled:.1f} s"
        )
    cfg = models["S5WM"].config
    per_step = cfg.train_ratio / (cfg.batch_size * cfg.batch_length)
    print(
        f"ALE {args.game} 64x64 RGB, action repeat 4, small preset, n_levels={cfg.n_levels}, "
        f"train_ratio={cfg.train_ratio:g}, batch {cfg.batch_size}x{cfg.batch_length}: "
        f"{per_step:g} level-0 updates per env step (level i every {cfg.subgoal_interval}**i of them)"
    )
    print(
        f"segments of {args.segment} env steps = learn({args.segment}, reset_num_timesteps=False), "
        f"{args.warmup} untimed + {args.rounds} timed per build, interleaved"
    )
    for model in models.values():
        for _ in range(args.warmup):
            model.learn(args.segment, reset_num_timesteps=False)
    clocks = {name: PhaseClock(model) for name, model in models.items()}
    before = {name: model.level_updates() for name, model in models.items()}
    variants = {
        name: (lambda model=model: model.learn(args.segment, reset_num_timesteps=False))
        for name, model in models.items()
    }
    timings: dict[str, Timing] = time_interleaved(variants, warmup=0, reps=args.rounds)
    for name, timing in timings.items():
        updates = [
            (now - then) / args.rounds for now, then in zip(models[name].level_updates(), before[name], strict=True)
        ]
        print(
            f"  {name:<5} segment {timing.min:7.2f} / {timing.median:7.2f} s (min / median), env steps/s "
            f"{args.segment / timing.min:6.2f} / {args.segment / timing.median:6.2f} (best / median), "
            f"updates per segment by level {[f'{u:g}' for u in updates]}"
        )
    print(agent_phase_table(clocks, timings, args.segment * args.rounds))
    steps_per_s = {name: args.segment / timing.median for name, timing in timings.items()}
    speedup = timings["RSSM"].median / timings["S5WM"].median
    speedup_best = timings["RSSM"].min / timings["S5WM"].min
    print("\nenv steps per second (median segment) and S5WM / RSSM speed-up (goal >= 1.5x; thesis 1.59x on a GPU):")
    print(f"s5wm_env_steps_per_s: {steps_per_s['S5WM']:.3f}")
    print(f"rssm_env_steps_per_s: {steps_per_s['RSSM']:.3f}")
    print(f"s5wm_vs_rssm_speedup_best: {speedup_best:.2f}")
    print(f"s5wm_vs_rssm_speedup: {speedup:.2f}")
    print(f"goal_speedup_1.5x: {'met' if speedup >= 1.5 else 'not met'}")


def agent_phase_table(clocks: dict[str, PhaseClock], timings: dict[str, Timing], env_steps: int) -> str:
    """Where each build's time goes: seconds per 1000 env steps of every :data:`PhaseClock.PHASES` part, its share
    of the build's wall time, and, with exactly the builds ``S5WM`` and ``RSSM``, RSSM time / S5WM time per part
    (> 1: S5WM is faster there). Last lines ``<build>_<part>_share: value`` and ``<part>_speedup: value``.

    :param clocks: build name -> its clock, measured over the timed segments only
    :param timings: build name -> timing of those segments (``total`` is the wall time the clock splits)
    :param env_steps: env steps per build over the timed segments
    :return: the table as text
    """
    parts = {name: clock.phases(timings[name].total) for name, clock in clocks.items()}
    names = list(parts)
    paired = set(names) == {"S5WM", "RSSM"}
    header = f"{'part (s per 1000 env steps, share)':<36}" + "".join(f"{n:>20}" for n in names)
    lines = ["", header + (f"{'RSSM / S5WM':>13}" if paired else "")]
    for phase in (*PhaseClock.PHASES, "total"):
        row = f"{phase:<36}"
        for name in names:
            seconds = timings[name].total if phase == "total" else parts[name][phase]
            row += f"{seconds * 1000 / env_steps:12.2f} ({seconds / timings[name].total:5.1%})"
        if paired:
            rssm = timings["RSSM"].total if phase == "total" else parts["RSSM"][phase]
            s5 = timings["S5WM"].total if phase == "total" else parts["S5WM"][phase]
            row += f"{rssm / s5:13.2f}" if s5 > 0 else f"{'-':>13}"
        lines.append(row)
    lines.append("")
    for name in names:
        for phase in PhaseClock.PHASES:
            lines.append(f"{name.lower()}_{phase}_share: {parts[name][phase] / timings[name].total:.3f}")
    if paired:
        for phase in PhaseClock.PHASES:
            if parts["S5WM"][phase] > 0:
                lines.append(f"{phase}_speedup: {parts['RSSM'][phase] / parts['S5WM'][phase]:.2f}")
        rssm_total = timings["RSSM"].total
        for free in ((), ("imagination", "acting")):
            needed = world_model_speedup_needed(parts["S5WM"], parts["RSSM"]["world_model"], rssm_total, 1.5, free)
            name = "world_model_speedup_needed_for_1.5x" + ("_with_imagination_and_acting_free" if free else "")
            lines.append(f"{name}: {needed:.2f}")
    return "\n".join(lines)


def world_model_speedup_needed(
    s5wm: dict[str, float], rssm_world_model: float, rssm_total: float, goal: float, free: Sequence[str] = ()
) -> float:
    """How much faster than RSSM's the S5WM world-model step would have to be for the whole agent to reach ``goal``
    times RSSM's speed, every other part of S5WM as measured (or, for the parts named in ``free``, costing nothing).

    :param s5wm: S5WM's :data:`PhaseClock.PHASES` parts in seconds
    :param rssm_world_model: RSSM's world-model step time over the same env steps
    :param rssm_total: RSSM's wall time over the same env steps
    :param goal: whole-agent speed-up sought
    :param free: parts of S5WM taken to cost nothing
    :return: RSSM world-model time / allowed S5WM world-model time; ``inf`` when the other parts alone exceed the
        time the goal allows
    """
    others = sum(seconds for phase, seconds in s5wm.items() if phase != "world_model" and phase not in free)
    allowed = rssm_total / goal - others
    return rssm_world_model / allowed if allowed > 0 else float("inf")


CASES_SCRIPT = pathlib.Path(__file__).resolve().parent / "_speed_cases.py"
#: part -> (figure in its result, unit, True when larger is faster)
COMPARED = {
    "learn": ("seconds", "s", False),
    "predict": ("median_ms", "ms per call", False),
    "pong": ("steps_per_s", "env steps/s", True),
}


def time_part(root: pathlib.Path, part: str, options: Sequence[str], timeout: float | None = None) -> dict[str, Any]:
    """One timing of ``part`` with the ``sb3_hieros`` of the tree at ``root``, in a fresh interpreter.

    :param root: the working tree or a temporary checkout of a ref
    :param part: one of :data:`COMPARED`
    :param options: further arguments of ``benchmarks/_speed_cases.py`` (sizes, threads, seed)
    :param timeout: seconds before the run is killed, or None
    :return: the part's result (``benchmarks/_speed_cases.py``)
    """
    with tempfile.TemporaryDirectory(prefix="sb3-hieros-speed-") as tmp:
        out = pathlib.Path(tmp) / "result.json"
        result = _gitref.run_script(root, CASES_SCRIPT, ["--part", part, "--out", str(out), *options], timeout)
        if result.returncode != 0 or not out.exists():
            raise RuntimeError(f"the {part} timing failed with {root}/sb3_hieros:\n{result.stderr[-4000:]}")
        found = json.loads(out.read_text())
    if not pathlib.Path(found["sb3_hieros"]).is_relative_to(root.resolve()):
        raise RuntimeError(f"the {part} timing imported sb3_hieros from {found['sb3_hieros']}, not from {root}")
    return found


def compare_table(samples: dict[str, dict[str, list[float]]]) -> str:
    """Medians and ranges of both sides and the speed-ups, from paired repetitions.

    :param samples: part -> {"here": figures, "ref": figures}, one figure per repetition in the same order
        (:data:`COMPARED` says which figure and whether larger is faster)
    :return: a table, then ``<part>_speedup: value`` lines (median of the paired per-repetition speed-ups; > 1: the
        working tree is faster) and ``<part>_speedup_of_medians: value``
    """

    def spread(values: Sequence[float]) -> str:
        return f"{statistics.median(values):10.3f} [{min(values):.3f}, {max(values):.3f}]"

    lines = [f"{'part':<8}{'unit':<14}{'here median [min, max]':>32}{'ref median [min, max]':>32}{'speed-up':>30}"]
    summary = []
    for part, sides in samples.items():
        _, unit, larger_is_faster = COMPARED[part]
        here, ref = sides["here"], sides["ref"]
        paired = [(h / r if larger_is_faster else r / h) for h, r in zip(here, ref, strict=True)]
        medians = statistics.median(here), statistics.median(ref)
        of_medians = medians[0] / medians[1] if larger_is_faster else medians[1] / medians[0]
        lines.append(f"{part:<8}{unit:<14}{spread(here):>32}{spread(ref):>32}{spread(paired):>30}")
        summary.append(f"{part}_speedup: {statistics.median(paired):.2f}")
        summary.append(f"{part}_speedup_of_medians: {of_medians:.2f}")
        if part == "pong":
            summary.append(f"pong_env_steps_per_s: {medians[0]:.2f}")
            summary.append(f"pong_env_steps_per_s_ref: {medians[1]:.2f}")
    return "\n".join([*lines, "", *summary])


#: the model settings each side of ``compare`` has: option (the ref's is ``--ref-<option>``), HIEROS keyword, example
SIDE_SETTINGS = (
    ("policy-kwargs", "policy_kwargs", '{"bf16": true}'),
    ("config-overrides", "config_overrides", '{"world_model_updates": 2}'),
)


def run_compare(args: argparse.Namespace) -> None:
    """``compare`` subcommand: the working tree against ``--ref``, parts alternated; prints the speed-ups last."""
    if args.reps < 1:
        raise ValueError(f"--reps must be >= 1, got {args.reps}")
    root = _gitref.repo_root()
    commit = _gitref.resolve(args.ref, root)
    options = [
        f"--threads={args.threads}",
        f"--seed={args.seed}",
        f"--learn-steps={args.learn_steps}",
        f"--learn-env={args.learn_env}",
        f"--learning-starts={args.learning_starts}",
        f"--predict-calls={args.predict_calls}",
        f"--pong-steps={args.pong_steps}",
        f"--pong-warmup={args.pong_warmup}",
        f"--pong-learning-starts={args.pong_learning_starts}",
    ]
    side_options = {
        side: [*options, *(f"--{name}={json.dumps(getattr(args, prefix + dest))}" for name, dest, _ in SIDE_SETTINGS)]
        for side, prefix in (("here", ""), ("ref", "ref_"))
    }
    print(environment_header())
    print(
        f"working tree {root} against {args.ref} ({commit[:12]}): parts {' '.join(args.parts)}, {args.reps} "
        f"repetitions, sides alternated A B B A, {args.threads} torch thread(s), fresh interpreter per timing"
    )
    print(
        f"learn: {args.learn_env} learn({args.learn_steps}), learning_starts {args.learning_starts}; predict: "
        f"{args.predict_calls} calls; pong: {args.pong_steps} timed env steps after {args.pong_learning_starts} "
        f"random + {args.pong_warmup} warm-up steps; policy_kwargs here {args.policy_kwargs}, ref "
        f"{args.ref_policy_kwargs}; config_overrides here {args.config_overrides}, ref {args.ref_config_overrides}"
    )
    samples: dict[str, dict[str, list[float]]] = {part: {"here": [], "ref": []} for part in args.parts}
    with _gitref.checkout(commit, root) as tree:
        trees = {"here": root, "ref": tree}
        for rep in range(args.reps):
            order = ("here", "ref") if rep % 2 == 0 else ("ref", "here")
            for part in args.parts:
                figure, unit, _ = COMPARED[part]
                for side in order:
                    result = time_part(trees[side], part, side_options[side], args.timeout)
                    samples[part][side].append(result[figure])
                    extra = f", level updates {result['level_updates']}" if "level_updates" in result else ""
                    print(f"  rep {rep + 1} {part:<8} {side:<4} {result[figure]:10.3f} {unit}{extra}", flush=True)
    print()
    print(compare_table(samples))


#: matrix-product operators and their floating-point operations from the profiler's input shapes
MATMUL_OPERATORS = ("aten::mm", "aten::addmm", "aten::bmm", "aten::baddbmm")


def matmul_flops(name: str, shapes: Sequence[Sequence[int]]) -> int:
    """Floating-point operations (2 per multiply-add) of one call of a matrix-product operator.

    :param name: one of :data:`MATMUL_OPERATORS`
    :param shapes: the call's input shapes as the profiler records them (``addmm``/``baddbmm``: the added tensor first)
    :return: ``2 * M * K * N`` (times the batch for ``bmm``/``baddbmm``)
    """
    if name not in MATMUL_OPERATORS:
        raise ValueError(f"not a matrix-product operator: {name!r}, expected one of {MATMUL_OPERATORS}")
    left, right = (shapes[0], shapes[1]) if name in ("aten::mm", "aten::bmm") else (shapes[1], shapes[2])
    if len(left) != len(right) or len(left) not in (2, 3) or left[-1] != right[-2]:
        raise ValueError(f"{name} with input shapes {list(shapes)}: not a (batched) matrix product")
    batch = left[0] if len(left) == 3 else 1
    return 2 * batch * left[-2] * left[-1] * right[-1]


def operator_summary(events: Any, wall_seconds: float, calls: int) -> dict[str, float]:
    """What a profile of ``calls`` repetitions of one thing says about it.

    :param events: ``prof.key_averages(group_by_input_shape=True)`` of a ``torch.profiler`` run with ``record_shapes``
    :param wall_seconds: wall time of the same repetitions without the profiler (which slows every operator call)
    :param calls: number of repetitions
    :return: per call ``wall_ms``, ``operator_ms`` (operators' self time under the profiler), ``aten_calls`` and
        ``matmul_ms``; ``matmul_share`` (of the operators' time), ``matmul_gflops`` (rate of the matrix products) and
        ``overhead_free_speedup`` (wall time / matrix-product time)
    """
    op_us = matmul_us = flops = 0.0
    aten_calls = 0
    for event in events:
        if not event.key.startswith("aten::"):
            continue
        aten_calls += event.count
        op_us += event.self_cpu_time_total
        if event.key in MATMUL_OPERATORS and event.input_shapes:
            matmul_us += event.self_cpu_time_total
            flops += event.count * matmul_flops(event.key, event.input_shapes)
    wall_ms = 1000.0 * wall_seconds / calls
    matmul_ms = matmul_us / 1000.0 / calls
    return {
        "wall_ms": wall_ms,
        "operator_ms": op_us / 1000.0 / calls,
        "aten_calls": aten_calls / calls,
        "matmul_ms": matmul_ms,
        "matmul_share": matmul_us / op_us if op_us else 0.0,
        "matmul_gflops": flops / (matmul_us * 1e3) if matmul_us else 0.0,
        "overhead_free_speedup": wall_ms / matmul_ms if matmul_ms else float("inf"),
    }


def profile_parts(
    steps: int, learning_starts: int, updates: int, predict_calls: int, seed: int, policy_kwargs: dict[str, Any]
) -> dict[str, dict[str, float]]:
    """Profiles of level-0 updates and of ``predict`` for a small-preset model on CartPole-v1 (see the module doc).

    :param steps: env steps the model learns first (must pass ``learning_starts``)
    :param learning_starts: random steps before training
    :param updates: profiled level-0 updates
    :param predict_calls: profiled predict calls
    :param seed: seed of the model
    :param policy_kwargs: the model's ``policy_kwargs``
    :return: ``"update"`` and ``"predict"`` -> :func:`operator_summary`
    """
    import gymnasium as gym
    import numpy as np
    from torch.profiler import ProfilerActivity, profile

    from sb3_hieros import HIEROS

    if steps <= learning_starts:
        raise ValueError(f"steps ({steps}) must exceed learning_starts ({learning_starts}) so that replay can sample")
    model = HIEROS(
        "MlpPolicy",
        "CartPole-v1",
        preset="small",
        seed=seed,
        learning_starts=learning_starts,
        policy_kwargs=policy_kwargs,
    )
    model.learn(steps)
    level, replay = model.policy.hierarchy.levels[0], model.level_buffers()[0]
    batches = [replay.sample(model.config.batch_size) for _ in range(updates + 1)]
    model.policy.set_training_mode(True)
    level.train_step(batches[0])  # untimed: first-call allocations
    start = time.perf_counter()
    for batch in batches[1:]:
        level.train_step(batch)
    wall = time.perf_counter() - start
    with profile(activities=[ProfilerActivity.CPU], record_shapes=True) as prof:
        for batch in batches[1:]:
            level.train_step(batch)
    results = {"update": operator_summary(prof.key_averages(group_by_input_shape=True), wall, updates)}
    model.policy.set_training_mode(False)
    env = gym.make("CartPole-v1")
    obs, _ = env.reset(seed=seed)
    state, first = None, np.array([True])

    def act() -> None:
        nonlocal obs, state, first
        action, state = model.predict(obs, state, first, deterministic=True)
        obs, _, terminated, truncated, _ = env.step(int(action))
        first = np.array([terminated or truncated])
        if terminated or truncated:
            obs, _ = env.reset()

    for _ in range(20):
        act()
    start = time.perf_counter()
    for _ in range(predict_calls):
        act()
    wall = time.perf_counter() - start
    with profile(activities=[ProfilerActivity.CPU], record_shapes=True) as prof:
        for _ in range(predict_calls):
            act()
    results["predict"] = operator_summary(prof.key_averages(group_by_input_shape=True), wall, predict_calls)
    return results


def run_profile(args: argparse.Namespace) -> None:
    """``profile`` subcommand: where an update's and a predict call's time goes; prints the figures last."""
    for name in ("updates", "predict_calls"):
        if getattr(args, name) < 1:
            raise ValueError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    print(environment_header())
    print(
        f"CartPole-v1, small preset, learn({args.steps}) with learning_starts {args.learning_starts}, then "
        f"{args.updates} level-0 updates and {args.predict_calls} predict calls under torch.profiler; "
        f"{torch.get_num_threads()} torch thread(s); policy_kwargs {args.policy_kwargs}; wall times without the "
        "profiler, operator times with it (it slows every call)"
    )
    results = profile_parts(
        args.steps, args.learning_starts, args.updates, args.predict_calls, args.seed, args.policy_kwargs
    )
    for part, figures in results.items():
        for key, value in figures.items():
            print(f"{part}/{key}: {value:.3f}")


def build_parser() -> argparse.ArgumentParser:
    """Argument parser with one subcommand per benchmark table."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.speed", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)

    s5 = sub.add_parser("s5", help="S5 layer vs GRU baselines, our scan vs the reference scan style, S5 stack")
    s5.add_argument("--reps", type=int, default=20, help="timed repetitions per variant (default 20)")
    s5.add_argument("--warmup", type=int, default=3, help="untimed warm-up calls per variant (default 3)")
    s5.add_argument("--threads", type=int, default=2, help="torch intra-op threads (default 2)")
    s5.add_argument("--lengths", type=int, nargs="+", default=[64, 256], help="sequence lengths T")
    s5.add_argument("--batch", type=int, default=16)
    s5.add_argument("--d-model", type=int, default=256)
    s5.add_argument("--d-state", type=int, default=128)
    s5.add_argument("--n-blocks", type=int, default=4)
    s5.add_argument("--stack-layers", type=int, default=8)
    s5.add_argument("--seed", type=int, default=0)
    s5.add_argument("--compile", action="store_true", help="also time S5Layer under compile_s5 (slow to compile)")
    s5.set_defaults(func=run_s5)

    agent = sub.add_parser("agent", help="HIEROS training env steps/s on Pong 64x64, S5WM vs RSSM, small preset")
    agent.add_argument(
        "--threads",
        type=int,
        default=2,
        help="torch intra-op threads (default 2; use 1 when other jobs share the CPUs)",
    )
    agent.add_argument(
        "--learning-starts", type=int, default=None, help="untimed random steps first (default: the preset's)"
    )
    agent.add_argument(
        "--segment", type=int, default=64, help="env steps per timed segment (default 64: 8 level-0 updates)"
    )
    agent.add_argument("--rounds", type=int, default=5, help="timed segments per build (default 5)")
    agent.add_argument("--warmup", type=int, default=1, help="untimed segments per build first (default 1)")
    agent.add_argument("--n-levels", type=int, default=None, help="hierarchy depth (default: the preset's)")
    agent.add_argument("--game", default="Pong", help="Atari game (default Pong)")
    agent.add_argument("--seed", type=int, default=0)
    agent.set_defaults(func=run_agent)

    compare = sub.add_parser(
        "compare", help="learn / predict / Pong timings of the working tree against a git ref, alternated; ratios"
    )
    compare.add_argument("--ref", required=True, help="git revision to compare with (branch, tag or commit)")
    compare.add_argument(
        "--parts", nargs="+", choices=tuple(COMPARED), default=list(COMPARED), help="parts to time (default: all)"
    )
    compare.add_argument("--reps", type=int, default=3, help="repetitions of every part and side (default 3)")
    compare.add_argument("--threads", type=int, default=1, help="torch threads of the timed runs (default 1)")
    compare.add_argument("--learn-steps", type=int, default=3000, help="env steps of the learn part (default 3000)")
    compare.add_argument(
        "--learn-env",
        default="CartPole-v1",
        help="Gymnasium env of the learn part, vector observations (default CartPole-v1)",
    )
    compare.add_argument("--learning-starts", type=int, default=500, help="of the learn part (default 500)")
    compare.add_argument("--predict-calls", type=int, default=500, help="timed predict calls (default 500)")
    compare.add_argument("--pong-steps", type=int, default=128, help="timed Pong env steps (default 128)")
    compare.add_argument("--pong-warmup", type=int, default=32, help="untimed Pong training steps first (default 32)")
    compare.add_argument(
        "--pong-learning-starts", type=int, default=256, help="random Pong steps before those (default 256)"
    )
    compare.add_argument("--seed", type=int, default=0)
    compare.add_argument("--timeout", type=float, default=3600.0, help="seconds per timing (default 3600)")
    for name, dest, example in SIDE_SETTINGS:
        compare.add_argument(
            f"--{name}",
            type=json_object,
            default={},
            help=f"{dest} of the working tree's models, JSON (e.g. '{example}')",
        )
        compare.add_argument(f"--ref-{name}", type=json_object, default={}, help=f"{dest} of the ref's models, JSON")
    compare.set_defaults(func=run_compare)

    prof = sub.add_parser("profile", help="where one update's and one predict call's time goes (torch.profiler)")
    prof.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    prof.add_argument("--steps", type=int, default=700, help="env steps learned first (default 700)")
    prof.add_argument("--learning-starts", type=int, default=500, help="random steps before training (default 500)")
    prof.add_argument("--updates", type=int, default=20, help="profiled level-0 updates (default 20)")
    prof.add_argument("--predict-calls", type=int, default=300, help="profiled predict calls (default 300)")
    prof.add_argument("--seed", type=int, default=0)
    prof.add_argument("--policy-kwargs", type=json_object, default={}, help="the model's policy_kwargs, JSON")
    prof.set_defaults(func=run_profile)
    return parser


def main(argv: Sequence[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    if getattr(args, "threads", None) is not None:
        if args.threads < 1:
            raise ValueError(f"--threads must be >= 1, got {args.threads}")
        if args.command != "compare":  # compare sets them in the interpreters it starts
            torch.set_num_threads(args.threads)
    args.func(args)


if __name__ == "__main__":
    main()
