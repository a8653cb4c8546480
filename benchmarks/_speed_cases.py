"""The timed parts of ``python -m benchmarks.speed compare``, run once per call in a fresh interpreter.

``benchmarks/speed.py`` runs this file with :func:`benchmarks._gitref.run_script` for the working tree and for a git
ref, so ``import sb3_hieros`` here loads the package of the tree it is run for. Only the public API is used
(``HIEROS(..., preset=, seed=, learning_starts=, config_overrides=)``, ``learn``, ``predict``), so any revision with
that API can be timed. The Atari environment comes from this file's own ``suites.py`` and the JSON options are read
by its own ``_cli.py`` (both loaded by path), the same on both sides.

Parts (``--part``), each on ``--threads`` torch threads:

* ``learn``: wall time of ``model.learn(steps)`` of a new small-preset ``MlpPolicy`` model on ``--learn-env``
  (a Gymnasium id with vector observations, CartPole-v1 by default);
* ``predict``: latency of ``model.predict(obs, state, episode_start, deterministic=True)`` on one CartPole env, the
  recurrent state threaded from call to call (an untrained small-preset model; the env is stepped with the actions);
* ``pong``: env steps per second of ``learn`` on ALE Pong 64x64 with the small preset, after ``learning_starts``
  random steps and one untimed warm-up segment, over one timed segment in which every level trains.

``--policy-kwargs`` (JSON) are passed to every model as ``policy_kwargs`` (e.g. ``{"bf16": true}``), and
``--config-overrides`` (JSON) as ``config_overrides`` (e.g. ``{"world_model_updates": 2}``; left out when empty, so
that revisions before that keyword can still be timed). The result is written as JSON to ``--out``.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import pathlib
import statistics
import sys
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

PARTS = ("learn", "predict", "pong")


def _level_updates(model: Any) -> list[int]:
    """Updates per level so far (revisions without ``level_updates()`` keep the counts in ``_level_updates``)."""
    counts = model.level_updates() if hasattr(model, "level_updates") else model._level_updates
    return list(counts or [])


def _config_keywords(config_overrides: dict[str, Any] | None) -> dict[str, Any]:
    """``config_overrides=`` where there are any, nothing otherwise (revisions before the keyword take no such key)."""
    return {"config_overrides": config_overrides} if config_overrides else {}


def time_learn(
    steps: int,
    learning_starts: int,
    seed: int,
    policy_kwargs: dict[str, Any] | None = None,
    env_id: str = "CartPole-v1",
    config_overrides: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Seconds of ``learn(steps)`` on ``env_id``, small preset (construction not timed).

    :param steps: environment steps
    :param learning_starts: random steps before training
    :param seed: seed of the model and its env
    :param policy_kwargs: the model's ``policy_kwargs`` (None: none)
    :param env_id: Gymnasium id of an env with vector observations
    :param config_overrides: the model's ``config_overrides`` (None or empty: none)
    :return: ``seconds`` and ``level_updates``
    """
    from sb3_hieros import HIEROS

    model = HIEROS(
        "MlpPolicy",
        env_id,
        preset="small",
        seed=seed,
        learning_starts=learning_starts,
        policy_kwargs=policy_kwargs,
        **_config_keywords(config_overrides),
    )
    start = time.perf_counter()
    model.learn(steps)
    seconds = time.perf_counter() - start
    return {"seconds": seconds, "level_updates": _level_updates(model)}


def time_predict(
    calls: int,
    warmup: int,
    seed: int,
    policy_kwargs: dict[str, Any] | None = None,
    config_overrides: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Per-call latency of deterministic ``predict`` on one CartPole env with the state threaded.

    :param calls: timed calls
    :param warmup: untimed calls first
    :param seed: seed of the model and of the env
    :param policy_kwargs: the model's ``policy_kwargs`` (None: none)
    :param config_overrides: the model's ``config_overrides`` (None or empty: none)
    :return: ``median_ms``, ``mean_ms`` and ``calls``
    """
    import gymnasium as gym

    from sb3_hieros import HIEROS

    model = HIEROS(
        "MlpPolicy",
        "CartPole-v1",
        preset="small",
        seed=seed,
        policy_kwargs=policy_kwargs,
        **_config_keywords(config_overrides),
    )
    env = gym.make("CartPole-v1")
    obs, _ = env.reset(seed=seed)
    state, start = None, True
    samples = []
    for call in range(warmup + calls):
        begin = time.perf_counter()
        action, state = model.predict(obs, state=state, episode_start=np.array([start]), deterministic=True)
        elapsed = time.perf_counter() - begin
        if call >= warmup:
            samples.append(elapsed)
        obs, _, terminated, truncated, _ = env.step(int(action))
        start = terminated or truncated
        if start:
            obs, _ = env.reset()
    return {
        "median_ms": statistics.median(samples) * 1e3,
        "mean_ms": statistics.fmean(samples) * 1e3,
        "calls": calls,
    }


def _sibling(name: str) -> Any:
    """The module ``name`` next to this file (e.g. ``suites``), loaded by path (``benchmarks`` on sys.path may be
    another tree's)."""
    path = pathlib.Path(__file__).resolve().parent / f"{name}.py"
    spec = importlib.util.spec_from_file_location(f"_speed_{name}", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def time_pong(
    steps: int,
    warmup: int,
    learning_starts: int,
    seed: int,
    policy_kwargs: dict[str, Any] | None = None,
    config_overrides: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Env steps per second of ``learn`` on ALE Pong 64x64, small preset, over one timed segment.

    :param steps: env steps of the timed segment
    :param warmup: env steps of the untimed segment before it (after the random ``learning_starts`` steps)
    :param learning_starts: untimed random steps first
    :param seed: seed of the model and of the env
    :param policy_kwargs: the model's ``policy_kwargs`` (None: none)
    :param config_overrides: the model's ``config_overrides`` (None or empty: none)
    :return: ``steps_per_s`` and ``level_updates`` (updates per level in the timed segment)
    """
    from sb3_hieros import HIEROS

    env = _sibling("suites").make_atari_env("Pong", seed=seed)
    model = HIEROS(
        "CnnPolicy",
        env,
        preset="small",
        seed=seed,
        learning_starts=learning_starts,
        policy_kwargs=policy_kwargs,
        **_config_keywords(config_overrides),
    )
    model.learn(learning_starts + warmup)
    before = _level_updates(model)
    start = time.perf_counter()
    model.learn(steps, reset_num_timesteps=False)
    seconds = time.perf_counter() - start
    updates = [now - then for now, then in zip(_level_updates(model), before, strict=True)]
    return {"steps_per_s": steps / seconds, "seconds": seconds, "level_updates": updates}


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--part", choices=PARTS, required=True)
    parser.add_argument("--out", type=pathlib.Path, required=True)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--learn-steps", type=int, default=3000)
    parser.add_argument("--learn-env", default="CartPole-v1")
    parser.add_argument("--learning-starts", type=int, default=500)
    parser.add_argument("--predict-calls", type=int, default=500)
    parser.add_argument("--predict-warmup", type=int, default=20)
    parser.add_argument("--pong-steps", type=int, default=128)
    parser.add_argument("--pong-warmup", type=int, default=32)
    parser.add_argument("--pong-learning-starts", type=int, default=256)
    json_object = _sibling("_cli").json_object
    parser.add_argument("--policy-kwargs", type=json_object, default={}, help="policy_kwargs of the models, as JSON")
    parser.add_argument(
        "--config-overrides", type=json_object, default={}, help="config_overrides of the models, as JSON"
    )
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    kwargs, overrides = args.policy_kwargs, args.config_overrides
    if args.part == "learn":
        result = time_learn(args.learn_steps, args.learning_starts, args.seed, kwargs, args.learn_env, overrides)
    elif args.part == "predict":
        result = time_predict(args.predict_calls, args.predict_warmup, args.seed, kwargs, overrides)
    else:
        result = time_pong(args.pong_steps, args.pong_warmup, args.pong_learning_starts, args.seed, kwargs, overrides)
    import sb3_hieros

    result["sb3_hieros"] = str(pathlib.Path(sb3_hieros.__file__).resolve().parent)
    result["threads"] = torch.get_num_threads()
    args.out.write_text(json.dumps(result))


if __name__ == "__main__":
    main(sys.argv[1:])
