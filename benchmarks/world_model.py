"""World-model benchmark: learning (a) and speed (b, c, d) of S5WM against DreamerV3's RSSM.

Parts (``--parts a,b,c,d``):

(a) open-loop prediction: a level-0 world model of the ``small`` preset is trained for a fixed number of updates on
    random-policy CartPole-v1 data; on held-out episodes it observes 5 steps and then imagines 15 steps with the
    recorded actions. Reported: the mean squared observation error (each dim divided by its variance in the training
    data) relative to "repeat the last observed observation". Goal < 0.5.
(b) world-model fwd+bwd per update (``loss`` + ``backward``), S5WM vs RSSM at equal widths with the same encoder and
    heads, timed interleaved: ``small`` preset at batch 16 x 64 with CartPole-sized vector observations (goal >= 2x),
    and ``paper`` preset at T=64 with 64x64x3 images and 18 actions: fp32 eager, fp32 + compile, and bf16 eager /
    bf16 + compile where the CPU has native bf16 (goal >= 1.3x).
(c) imagination of 1024 starts x 16 steps (no_grad, a 2-layer MLP actor included), S5 step vs RSSM step, for both
    presets, fp32 and (with native bf16) both world models under bf16 autocast. Goal: S5 at most 1.2x slower.
(d) achieved GFLOP/s of one ``paper``-size level-0 S5WM update (FLOPs counted with ``FlopCounterMode``, matmul and
    convolution only), against this machine's matmul peak measured in the same run (4096x1024 @ 1024x1024 fp32).
    Goal >= 40 % of the fp32 peak.

Run from the repo root: ``python -m benchmarks.world_model [--parts a,b,c,d] [--presets small,paper] [--quick]``
(``--presets`` limits parts b and c). The last lines print every figure as ``name: value``. Part (b) also prints the
minor page faults per call of each model (memory the allocator handed back to the OS and the next update touches
again).
"""

from __future__ import annotations

import argparse
import dataclasses
import resource
import time
from collections.abc import Callable
from types import SimpleNamespace

import gymnasium as gym
import numpy as np
import torch as th
from gymnasium import spaces
from torch.utils.flop_counter import FlopCounterMode

from benchmarks._timing import environment_header, format_ms, time_interleaved
from sb3_hieros.agent.world_model import (
    LatentState,
    WorldModel,
    make_world_model,
    stack_states,
    world_model_lr_scheduler,
    world_model_optimizer,
)
from sb3_hieros.config import WorldModelConfig, get_preset
from sb3_hieros.nn.distributions import OneHotCategoricalST
from sb3_hieros.nn.networks import MLP, native_bf16

RESULTS: dict[str, str] = {}


def record(name: str, value: float | str, fmt: str = "{:.3f}") -> None:
    RESULTS[name] = fmt.format(value) if isinstance(value, float) else str(value)


# ----------------------------------------------------------------------------------------------------------------------
# data
# ----------------------------------------------------------------------------------------------------------------------


def collect_cartpole(steps: int, seed: int) -> dict[str, np.ndarray]:
    """Random-policy CartPole-v1 stream in the buffer's row layout (o_t, a_{t-1}, r_t, is_first_t, is_terminal_t)."""
    env = gym.make("CartPole-v1")
    rng = np.random.default_rng(seed)
    obs, _ = env.reset(seed=seed)
    rows = {k: [] for k in ("obs", "prev_action", "reward", "is_first", "is_terminal")}

    def add(o, a, r, first, term):
        rows["obs"].append(o)
        rows["prev_action"].append(a)
        rows["reward"].append(r)
        rows["is_first"].append(first)
        rows["is_terminal"].append(term)

    add(obs, np.zeros(2, np.float32), 0.0, True, False)
    while len(rows["obs"]) < steps:
        action = int(rng.integers(2))
        obs, reward, terminated, truncated, _ = env.step(action)
        add(obs, np.eye(2, dtype=np.float32)[action], float(reward), False, bool(terminated))
        if terminated or truncated:
            obs, _ = env.reset()
            add(obs, np.zeros(2, np.float32), 0.0, True, False)
    env.close()
    return {
        "obs": np.asarray(rows["obs"], np.float32),
        "prev_action": np.asarray(rows["prev_action"], np.float32),
        "reward": np.asarray(rows["reward"], np.float32),
        "is_first": np.asarray(rows["is_first"], bool),
        "is_terminal": np.asarray(rows["is_terminal"], bool),
    }


def sample_chunks(data: dict[str, np.ndarray], batch: int, length: int, rng: np.random.Generator) -> SimpleNamespace:
    """Uniform windows of the stream (they may span episode borders: the resets handle that)."""
    starts = rng.integers(0, len(data["obs"]) - length, batch)
    idx = starts[:, None] + np.arange(length)[None]
    return SimpleNamespace(
        observations=th.as_tensor(data["obs"][idx]),
        actions=th.as_tensor(data["prev_action"][idx]),
        rewards=th.as_tensor(data["reward"][idx]),
        is_first=th.as_tensor(data["is_first"][idx]),
        is_terminal=th.as_tensor(data["is_terminal"][idx]),
    )


def synthetic_batch(
    batch: int, length: int, obs_shape: tuple[int, ...], n_actions: int, image: bool
) -> SimpleNamespace:
    """A random batch of the right shapes and dtypes (for speed measurements)."""
    gen = th.Generator().manual_seed(0)
    if image:
        obs = th.randint(0, 256, (batch, length, *obs_shape), dtype=th.uint8, generator=gen)
    else:
        obs = th.randn(batch, length, *obs_shape, generator=gen)
    actions = th.nn.functional.one_hot(th.randint(0, n_actions, (batch, length), generator=gen), n_actions).float()
    is_first = th.zeros(batch, length, dtype=th.bool)
    is_first[:, 0] = True
    is_first[::3, length // 2] = True
    actions[is_first] = 0.0
    return SimpleNamespace(
        observations=obs,
        actions=actions,
        rewards=th.randn(batch, length, generator=gen),
        is_first=is_first,
        is_terminal=th.zeros(batch, length, dtype=th.bool),
    )


# ----------------------------------------------------------------------------------------------------------------------
# (a) open-loop prediction on CartPole
# ----------------------------------------------------------------------------------------------------------------------


def open_loop_error(
    model: WorldModel,
    data: dict[str, np.ndarray],
    scale: np.ndarray,
    context: int,
    horizon: int,
    samples: int = 0,
) -> tuple[float, float, np.ndarray]:
    """Normalised MSE of open-loop predictions and of "repeat the last observation", over all long-enough episodes.

    The model observes ``context`` steps from the episode start (posterior modes), then imagines ``horizon`` steps with
    the recorded actions. ``samples == 0``: one rollout with prior modes; ``samples > 0``: the mean decoded observation
    of that many sampled rollouts (the MSE-optimal point prediction).
    """
    starts = np.flatnonzero(data["is_first"])
    ends = np.append(starts[1:], len(data["obs"]))
    window = context + horizon
    chosen = starts[(ends - starts) >= window]
    idx = chosen[:, None] + np.arange(window)[None]
    obs = th.as_tensor(data["obs"][idx])
    actions = th.as_tensor(data["prev_action"][idx])
    is_first = th.as_tensor(data["is_first"][idx])
    n, copies = len(chosen), max(1, samples)
    with th.no_grad():
        post, _ = model.observe(obs[:, :context], actions[:, :context], is_first[:, :context], deterministic=True)
        start = stack_states([post.select((slice(None), -1))] * copies, 0).flatten_batch()  # (copies * N,)
        step = iter(range(context, window + 1))

        def recorded_actions(state: LatentState) -> th.Tensor:
            t = next(step)
            action = actions[:, t] if t < window else th.zeros(n, actions.shape[-1])
            return action.repeat(copies, 1)

        states, _, _ = model.imagine(start, recorded_actions, horizon, deterministic=samples == 0)
        pred = model.decode(states.select(slice(1, None)))  # (horizon, copies * N, 4)
        pred = pred.reshape(horizon, copies, n, -1).mean(1).transpose(0, 1)  # (N, horizon, 4)
    truth = obs[:, context:]
    inv_var = th.as_tensor(1.0 / scale)
    model_err = ((pred - truth).pow(2) * inv_var).mean(-1)  # (N, horizon)
    repeat_err = ((obs[:, context - 1 : context] - truth).pow(2) * inv_var).mean(-1)
    per_step = (model_err.mean(0) / repeat_err.mean(0)).numpy()
    return float(model_err.mean()), float(repeat_err.mean()), per_step


def part_a(args: argparse.Namespace) -> None:
    preset = get_preset("small")
    config = preset.world_model
    batch, length = preset.batch_size, preset.batch_length
    updates = args.updates if args.updates is not None else (300 if args.quick else 4000)
    print(
        f"\n(a) open-loop prediction, small preset S5WM, CartPole-v1 random policy; budget {updates} updates of "
        f"{batch} x {length}, lr {config.lr}, warm-up {config.warmup}"
    )
    train = collect_cartpole(50_000, seed=0)
    test = collect_cartpole(5_000, seed=1)
    scale = train["obs"].var(0)
    th.manual_seed(0)
    space = gym.make("CartPole-v1").observation_space
    model = make_world_model(space, 2, config)
    optimizer = world_model_optimizer(model)
    scheduler = world_model_lr_scheduler(optimizer, config.warmup)
    rng = np.random.default_rng(0)
    start = time.perf_counter()
    context, horizon = 5, 15
    for i in range(1, updates + 1):
        metrics, _ = model.train_step(sample_chunks(train, batch, length, rng), optimizer, scheduler)
        if i % max(1, updates // 5) == 0 or i == updates:
            model_err, repeat_err, _ = open_loop_error(model, test, scale, context, horizon)
            print(
                f"  update {i:5d}  {time.perf_counter() - start:6.1f} s  loss {metrics['loss']:7.3f}  "
                f"obs {metrics['obs_loss']:.4f}  kl {metrics['kl']:.3f}  open-loop ratio (modes) "
                f"{model_err / repeat_err:.3f}"
            )
    train_s = time.perf_counter() - start
    record("a_updates", updates, "{}")
    record("a_train_seconds", train_s, "{:.1f}")
    for name, samples in (("modes", 0), ("mean_of_8_samples", 8)):
        model_err, repeat_err, per_step = open_loop_error(model, test, scale, context, horizon, samples)
        steps = ", ".join(f"{k + 1}: {per_step[k]:.3f}" for k in (0, 4, 9, 14))
        print(
            f"  {name}: model error {model_err:.4f}, repeat-last error {repeat_err:.4f}, ratio "
            f"{model_err / repeat_err:.3f}; ratio at step ({steps})"
        )
        record(f"a_open_loop_15_ratio_s5_{name}", model_err / repeat_err)


# ----------------------------------------------------------------------------------------------------------------------
# (b) fwd+bwd of one update
# ----------------------------------------------------------------------------------------------------------------------


def build(
    kind: str, config: WorldModelConfig, space: spaces.Space, n_actions: int, bf16: bool = False, compile: bool = False
) -> WorldModel:
    th.manual_seed(0)
    return make_world_model(space, n_actions, dataclasses.replace(config, kind=kind), bf16=bf16, compile=compile)


def fwd_bwd(model: WorldModel, batch: SimpleNamespace) -> Callable[[], None]:
    def run() -> None:
        model.zero_grad(set_to_none=True)
        loss, _, _ = model.loss(batch)
        loss.backward()

    return run


def faults_per_call(fn: Callable[[], None], calls: int = 3) -> float:
    """Minor page faults of this process per call of ``fn`` (after the timing, so the heap has grown already)."""
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(calls):
        fn()
    return (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / calls


def part_b(args: argparse.Namespace) -> None:
    if "small" in args.presets:
        part_b_small(args)
    if "paper" in args.presets:
        part_b_paper(args)


def part_b_small(args: argparse.Namespace) -> None:
    reps = 5 if args.quick else 15
    config = get_preset("small").world_model
    space = spaces.Box(-np.inf, np.inf, (4,), np.float32)
    batch = synthetic_batch(16, 64, (4,), 2, image=False)
    print(f"\n(b) world-model fwd+bwd per update, small preset, batch 16 x 64, vector obs (4,), 2 actions, {reps} reps")
    variants = {kind: fwd_bwd(build(kind, config, space, 2), batch) for kind in ("s5", "rssm")}
    timing = time_interleaved(variants, warmup=3, reps=reps)
    for name, t in timing.items():
        print(f"  {name:6s} {format_ms(t)}  (min / median), {faults_per_call(variants[name]):.0f} page faults per call")
    record("b_small_rssm_over_s5", timing["rssm"].median / timing["s5"].median)


def part_b_paper(args: argparse.Namespace) -> None:
    config = get_preset("paper").world_model
    space = spaces.Box(0, 255, (3, 64, 64), np.uint8)
    batch = synthetic_batch(16, 64, (3, 64, 64), 18, image=True)
    reps = 2 if args.quick else 4
    modes = [("fp32", False, False)]
    if not args.no_compile:
        modes.append(("fp32_compile", False, True))
    if native_bf16("cpu") or args.force_bf16:
        modes.append(("bf16", True, False))
        if not args.no_compile:
            modes.append(("bf16_compile", True, True))
    else:
        print("  bf16 modes skipped: this CPU has no avx512_bf16 / amx_bf16 (bf16 would be emulated, far slower)")
        record("b_paper_bf16_rssm_over_s5", "skipped (no bf16 hardware)")
    print(f"\n(b) paper preset, batch 16 x 64, images (3, 64, 64), 18 actions, {reps} reps per mode")
    for mode, bf16, compile in modes:
        models = {kind: build(kind, config, space, 18, bf16=bf16, compile=compile) for kind in ("s5", "rssm")}
        variants = {kind: fwd_bwd(m, batch) for kind, m in models.items()}
        start = time.perf_counter()
        try:
            for fn in variants.values():
                fn()  # first call: includes compilation when compile is on
        except Exception as exc:
            print(f"  {mode}: failed: {type(exc).__name__}: {str(exc).splitlines()[0][:200]}")
            record(f"b_paper_{mode}_rssm_over_s5", "failed")
            continue
        first_s = time.perf_counter() - start
        timing = time_interleaved(variants, warmup=1, reps=reps)
        print(f"  {mode}: first calls {first_s:.1f} s")
        for name, t in timing.items():
            print(f"    {name:6s} {format_ms(t)}")
        record(f"b_paper_{mode}_rssm_over_s5", timing["rssm"].median / timing["s5"].median)
        record(f"b_paper_{mode}_s5_ms", timing["s5"].median * 1e3, "{:.0f}")
        del models, variants


# ----------------------------------------------------------------------------------------------------------------------
# (c) imagination
# ----------------------------------------------------------------------------------------------------------------------


def imagination(model: WorldModel, n_actions: int, units: int, starts: int, horizon: int) -> Callable[[], None]:
    th.manual_seed(1)
    actor = MLP(model.feat_dim, n_actions, units, 2)
    start = model.initial_state(starts).map_fields(lambda x: x + 0.01 * th.randn_like(x) if not x.is_complex() else x)

    def policy(state: LatentState) -> th.Tensor:
        return OneHotCategoricalST(actor(model.features(state)), 0.01).sample()

    def run() -> None:
        with th.no_grad():
            model.imagine(start, policy, horizon)

    return run


def part_c(args: argparse.Namespace) -> None:
    reps = 5 if args.quick else 10
    precisions = ("fp32", "bf16") if native_bf16("cpu") or args.force_bf16 else ("fp32",)
    for preset, obs_shape, image, n_actions in (("small", (4,), False, 2), ("paper", (3, 64, 64), True, 18)):
        if preset not in args.presets:
            continue
        cfg = get_preset(preset)
        space = spaces.Box(0, 255, obs_shape, np.uint8) if image else spaces.Box(-np.inf, np.inf, obs_shape)
        for precision in precisions:
            print(
                f"\n(c) imagination 1024 starts x 16 steps, {preset} preset, {precision}, no_grad, "
                f"actor MLP 2x{cfg.actor_critic.units}"
            )
            bf16 = precision == "bf16"
            variants = {
                kind: imagination(
                    build(kind, cfg.world_model, space, n_actions, bf16=bf16),
                    n_actions,
                    cfg.actor_critic.units,
                    1024,
                    16,
                )
                for kind in ("s5", "rssm")
            }
            timing = time_interleaved(variants, warmup=2, reps=reps)
            for name, t in timing.items():
                print(f"  {name:6s} {format_ms(t)}")
            suffix = "" if precision == "fp32" else "_bf16"
            record(f"c_{preset}{suffix}_s5_over_rssm", timing["s5"].median / timing["rssm"].median)
            record(f"c_{preset}{suffix}_s5_ms", timing["s5"].median * 1e3, "{:.0f}")


# ----------------------------------------------------------------------------------------------------------------------
# (d) achieved GFLOP/s
# ----------------------------------------------------------------------------------------------------------------------


def matmul_peak(reps: int = 10) -> float:
    a, b = th.randn(4096, 1024), th.randn(1024, 1024)
    for _ in range(3):
        a @ b
    best = min(_timed(lambda: a @ b) for _ in range(reps))
    return 2 * 4096 * 1024 * 1024 / best / 1e9


def _timed(fn: Callable[[], object]) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def part_d(args: argparse.Namespace) -> None:
    reps = 2 if args.quick else 4
    config = get_preset("paper").world_model
    space = spaces.Box(0, 255, (3, 64, 64), np.uint8)
    batch = synthetic_batch(16, 64, (3, 64, 64), 18, image=True)
    print("\n(d) achieved GFLOP/s of one paper-size S5WM update (loss, backward, AdamW; batch 16 x 64, images 64x64x3)")
    peak_before = matmul_peak()
    achieved_by_mode: dict[str, float] = {}
    modes = [("fp32", False, False)]
    if not args.no_compile:
        modes.append(("fp32_compile", False, True))
    if native_bf16("cpu") or args.force_bf16:
        modes.append(("bf16", True, False))
    for mode, bf16, compile in modes:
        model = build("s5", config, space, 18, bf16=bf16, compile=compile)
        optimizer = world_model_optimizer(model)

        def update(model: WorldModel = model, optimizer: th.optim.Optimizer = optimizer) -> None:
            model.train_step(batch, optimizer)

        if compile:
            update()  # compilation, not counted
        counter = FlopCounterMode(display=False)
        with counter:
            update()
        flops = counter.get_total_flops()
        best = min(_timed(update) for _ in range(reps))
        achieved = flops / best / 1e9
        print(
            f"  {mode}: {flops / 1e9:.1f} GFLOP per update (matmul + conv), best {best * 1e3:.0f} ms "
            f"-> {achieved:.1f} GFLOP/s"
        )
        record(f"d_{mode}_gflop_per_update", flops / 1e9, "{:.1f}")
        record(f"d_{mode}_achieved_gflops", achieved, "{:.1f}")
        achieved_by_mode[mode] = achieved
        del model, optimizer
    peak = max(peak_before, matmul_peak())
    print(f"  matmul peak (4096x1024 @ 1024x1024 fp32, best of 2 x 10): {peak:.1f} GFLOP/s")
    record("d_matmul_peak_gflops", peak, "{:.1f}")
    for mode, achieved in achieved_by_mode.items():
        record(f"d_{mode}_fraction_of_fp32_peak", achieved / peak)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--parts", default="a,b,c,d", help="comma-separated subset of a,b,c,d")
    parser.add_argument("--quick", action="store_true", help="fewer updates and repetitions")
    parser.add_argument("--presets", default="small,paper", help="presets timed by parts (b) and (c): small, paper")
    parser.add_argument("--updates", type=int, default=None, help="training updates of part (a)")
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    parser.add_argument("--no-compile", action="store_true", help="skip the torch.compile variants of part (b)")
    parser.add_argument("--force-bf16", action="store_true", help="run bf16 variants even without bf16 hardware")
    args = parser.parse_args()
    if args.threads is not None:
        th.set_num_threads(args.threads)
    parts = [p.strip() for p in args.parts.split(",") if p.strip()]
    unknown = set(parts) - set("abcd")
    if unknown:
        raise ValueError(f"--parts must be a subset of a,b,c,d, got {sorted(unknown)}")
    args.presets = [p.strip() for p in args.presets.split(",") if p.strip()]
    unknown = set(args.presets) - {"small", "paper"}
    if unknown or not args.presets:
        raise ValueError(f"--presets must be a non-empty subset of small,paper, got {args.presets}")
    print(environment_header())
    for part in parts:
        {"a": part_a, "b": part_b, "c": part_c, "d": part_d}[part](args)
    print(f"\n{environment_header()}")
    for name, value in RESULTS.items():
        print(f"{name}: {value}")


if __name__ == "__main__":
    main()
