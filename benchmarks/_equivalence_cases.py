"""The seeded tiny ``learn`` runs of ``python -m benchmarks.equivalence`` and the fingerprint of their outcome.

This file is run as a script by ``benchmarks/equivalence.py`` against the ``sb3_hieros`` of the working tree and of a
git revision (``benchmarks/_gitref.py``), so it imports nothing from ``benchmarks`` and builds every model through the
public constructor keywords both sides accept (``preset``, ``config_overrides``, SB3's standard keywords and
``policy_kwargs={"bf16": False}``). It writes one JSON object: per case, SHA-256 digests of every parameter and
buffer, of every optimiser state, of the replay of every level, of a prediction after training and of the global
random states, and the counters.

Usage: ``python benchmarks/_equivalence_cases.py --out result.json [--cases a b ...] [--steps N] [--save-dir D]`` or,
to fingerprint models saved with ``--save-dir`` (by any revision) after loading them, ``... --load-dir D``.
"""

from __future__ import annotations

import argparse
import copy
import hashlib
import json
import random
import sys
from collections.abc import Callable, Mapping
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from gymnasium import spaces

#: Tiny networks: every code path of the small preset at a fraction of the cost (the tests use them too).
TINY_NETWORKS: dict[str, Any] = {
    "world_model": {
        "s5_layers": 1,
        "s5_model_dim": 16,
        "s5_state_dim": 8,
        "s5_hippo_blocks": 2,
        "deter_dim": 16,
        "stoch_groups": 4,
        "stoch_classes": 4,
        "hidden": 16,
        "cnn_depth": 2,
        "mlp_units": 16,
        "mlp_layers": 1,
        "head_units": 16,
        "head_layers": 1,
        "warmup": 2,
    },
    "actor_critic": {"units": 16, "layers": 1, "novelty_weight": 0.1},  # keeps the novelty critic in use
    "subgoal": {"units": 16, "layers": 1, "n_cat": 4, "n_classes": 4},
}
#: The cases' configuration: the tiny networks, 2 levels, k = 2, 8-step chunks, horizon 4.
TINY: dict[str, Any] = {
    **TINY_NETWORKS,
    "n_levels": 2,
    "subgoal_interval": 2,
    "batch_length": 8,
    "imag_horizon": 4,
    "train_ratio": 4.0,
}

REFERENCE_BEHAVIOUR = {"action_alignment": "current", "reinforce_advantage": "raw", "terminal_reward": "zeroed"}


class TinyImageEnv(gym.Env):
    """16x16x1 uint8 images (channel-last) from the env's seeded generator, Discrete(3) actions, 10-step episodes."""

    def __init__(self) -> None:
        self.observation_space = spaces.Box(0, 255, (16, 16, 1), np.uint8)
        self.action_space = spaces.Discrete(3)
        self.t = 0

    def _obs(self) -> np.ndarray:
        return self.np_random.integers(0, 256, (16, 16, 1), dtype=np.uint8)

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        self.t = 0
        return self._obs(), {}

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        self.t += 1
        return self._obs(), float(int(action) == self.t % 3), self.t >= 10, False, {}


class TinyDictEnv(gym.Env):
    """Dict observations (a 16x16x1 image and a 3-vector), Discrete(3) or Box(-2, 2, (2,)) actions, 12 steps."""

    def __init__(self, box: bool = False) -> None:
        self.observation_space = spaces.Dict(
            {"img": spaces.Box(0, 255, (16, 16, 1), np.uint8), "vec": spaces.Box(-1.0, 1.0, (3,), np.float32)}
        )
        self.action_space = spaces.Box(-2.0, 2.0, (2,), np.float32) if box else spaces.Discrete(3)
        self.t = 0

    def _obs(self) -> dict[str, np.ndarray]:
        return {
            "img": self.np_random.integers(0, 256, (16, 16, 1), dtype=np.uint8),
            "vec": self.np_random.uniform(-1.0, 1.0, 3).astype(np.float32),
        }

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        super().reset(seed=seed)
        self.t = 0
        return self._obs(), {}

    def step(self, action: Any) -> tuple[dict, float, bool, bool, dict]:
        self.t += 1
        return self._obs(), float(self.t % 3 == 0), self.t >= 12, False, {}


def _merge(base: Mapping[str, Any], changes: Mapping[str, Any]) -> dict[str, Any]:
    out = copy.deepcopy(dict(base))
    for key, value in changes.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
            out[key] = {**out[key], **value}
        else:
            out[key] = copy.deepcopy(value)
    return out


def _case(policy: str, env: str | Callable[[], gym.Env], n_envs: int = 1, **overrides: Any) -> dict[str, Any]:
    return {"policy": policy, "env": env, "n_envs": n_envs, "overrides": _merge(TINY, overrides)}


#: name -> (policy, env, number of envs, config_overrides)
CASES: dict[str, dict[str, Any]] = {
    "mlp_levels1": _case("MlpPolicy", "CartPole-v1", n_levels=1),
    "mlp_levels2": _case("MlpPolicy", "CartPole-v1"),
    "mlp_levels3": _case("MlpPolicy", "CartPole-v1", n_levels=3),
    "mlp_two_envs": _case("MlpPolicy", "CartPole-v1", n_envs=2, n_levels=3),
    "mlp_no_replay_context": _case("MlpPolicy", "CartPole-v1", replay_context=False),
    "cnn": _case("CnnPolicy", TinyImageEnv),
    "multi_input": _case("MultiInputPolicy", TinyDictEnv),
    "multi_input_box": _case("MultiInputPolicy", lambda: TinyDictEnv(box=True)),
    "box_pendulum": _case("MlpPolicy", "Pendulum-v1"),
    "shared_world_model": _case("MlpPolicy", "CartPole-v1", n_levels=3, hierarchical_world_models=False),
    "shared_world_model_box": _case("MlpPolicy", "Pendulum-v1", hierarchical_world_models=False),
    "update_subgoals_levels3": _case("MlpPolicy", "CartPole-v1", n_levels=3, update_subgoals_in_imagination=True),
    "update_subgoals_box": _case("MlpPolicy", "Pendulum-v1", update_subgoals_in_imagination=True),
    "switches": _case(
        "MlpPolicy",
        "CartPole-v1",
        n_levels=3,
        higher_level_input="last",
        decoded_subgoal_input=True,
        extrinsic_reward_levels="top",
        imag_start_fraction=1.0,
    ),
    "dropout_paper_heads": _case(
        "MlpPolicy", "CartPole-v1", world_model={"dropout": 0.1}, actor_critic={"units": 16, "layers": 2}
    ),
    "rssm_reference": _case(
        "MlpPolicy", "CartPole-v1", n_envs=2, world_model={"kind": "rssm"}, reference=REFERENCE_BEHAVIOUR
    ),
}


def _digest(*parts: Any) -> str:
    """SHA-256 of tensors, arrays and plain values (shape and dtype included)."""
    h = hashlib.sha256()

    def feed(x: Any) -> None:
        if isinstance(x, th.Tensor):
            x = th.view_as_real(x) if x.is_complex() else x
            x = x.detach().cpu().contiguous().numpy()
        if isinstance(x, np.ndarray):
            h.update(f"{x.dtype}{x.shape}".encode())
            h.update(np.ascontiguousarray(x).tobytes())
        elif isinstance(x, Mapping):
            for key in sorted(x, key=str):
                h.update(repr(key).encode())
                feed(x[key])
        elif isinstance(x, list | tuple):
            h.update(f"[{len(x)}".encode())
            for item in x:
                feed(item)
        else:
            h.update(repr(x).encode())

    for part in parts:
        feed(part)
    return h.hexdigest()


def _normalise(name: str) -> str:
    """A parameter or optimiser path without the segment that only says where the levels live."""
    return ".".join(part for part in name.split(".") if part != "hierarchy")


def _resolve(owner: Any, path: str) -> Any:
    for part in path.split("."):
        owner = getattr(owner, part)
    return owner


def _counters(model: Any) -> dict[str, Any]:
    level_updates = getattr(model, "level_updates", None)
    updates = level_updates() if callable(level_updates) else model._level_updates
    skipped = getattr(model, "skipped_updates", None)
    return {
        "num_timesteps": int(model.num_timesteps),
        "n_updates": int(model._n_updates),
        "level_updates": [int(u) for u in updates],
        "skipped_updates": [int(u) for u in (skipped() if callable(skipped) else model._skipped_updates)],
    }


def _replay(model: Any) -> list[str]:
    digests = []
    for buffer in [model.replay_buffer, *getattr(model.replay_buffer, "higher_levels", [])]:
        arrays = {
            name: getattr(buffer, name)
            for name in (
                "observations",
                "actions",
                "rewards",
                "is_first",
                "is_terminal",
                "subgoals",
                "context",
                "has_context",
                "stream_pos",
                "stream_full",
            )
            if getattr(buffer, name, None) is not None
        }
        digests.append(_digest(arrays))
    return digests


def _probe(space: spaces.Space) -> Any:
    """A fixed batch of two observations of ``space`` (from a generator of its own)."""
    rng = np.random.default_rng(0)
    if isinstance(space, spaces.Dict):
        return {key: _probe(sub) for key, sub in space.spaces.items()}
    if np.issubdtype(space.dtype, np.integer):
        return rng.integers(0, 256, (2, *space.shape)).astype(space.dtype)
    return rng.uniform(-1.0, 1.0, (2, *space.shape)).astype(space.dtype)


def _env(name: str) -> Any:
    from stable_baselines3.common.env_util import make_vec_env

    spec = CASES[name]
    return make_vec_env(spec["env"], n_envs=spec["n_envs"], seed=0)


def _fingerprint(model: Any) -> dict[str, Any]:
    import sb3_hieros

    params = {_normalise(key): _digest(value) for key, value in model.policy.state_dict().items()}
    optimizers = {}
    for path in model._get_torch_save_params()[0]:
        if path != "policy":
            optimizers[_normalise(path)] = _digest(_resolve(model, path).state_dict())
    rng = _digest(th.get_rng_state(), np.random.get_state()[1], random.getstate()[1])  # noqa: NPY002
    actions, state = model.predict(_probe(model.observation_space), deterministic=True)
    return {
        "sb3_hieros": sb3_hieros.__file__,
        "params": params,
        "optimizers": optimizers,
        "counters": _counters(model),
        "replay": _replay(model),
        "predict": _digest(actions, list(state)),
        "rng": rng,
    }


def run_case(name: str, steps: int, save_dir: str | None = None) -> dict[str, Any]:
    """Build the case's model (seed 0), learn ``steps`` steps and fingerprint the outcome.

    :param name: a key of :data:`CASES`
    :param steps: environment steps of ``learn``
    :param save_dir: also save the model as ``<save_dir>/<name>.zip``
    :return: the fingerprint (JSON-serialisable)
    """
    from sb3_hieros import HIEROS

    spec = CASES[name]
    model = HIEROS(
        spec["policy"],
        _env(name),
        preset="small",
        config_overrides=spec["overrides"],
        batch_size=2,
        learning_starts=20,
        buffer_size=500,
        # float32 pinned: the default bf16="auto" depends on the CPU, and older revisions default to float32
        policy_kwargs={"bf16": False},
        seed=0,
    )
    model.learn(steps)
    fingerprint = _fingerprint(model)
    if save_dir is not None:
        model.save(f"{save_dir}/{name}.zip")
    return fingerprint


def load_case(name: str, load_dir: str) -> dict[str, Any]:
    """Load ``<load_dir>/<name>.zip`` (saved by :func:`run_case`, possibly by another revision) and fingerprint it
    (the replay is not saved, so its part is left out).

    :param name: a key of :data:`CASES`
    :param load_dir: directory of the saves
    :return: the fingerprint without ``replay`` and ``rng``
    """
    from sb3_hieros import HIEROS

    model = HIEROS.load(f"{load_dir}/{name}.zip", env=_env(name))
    fingerprint = _fingerprint(model)
    del fingerprint["replay"], fingerprint["rng"]
    return fingerprint


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, help="JSON file for the fingerprints")
    parser.add_argument("--cases", nargs="+", default=sorted(CASES), help="cases to run (default: all)")
    parser.add_argument("--steps", type=int, default=64, help="environment steps of learn per case")
    parser.add_argument("--save-dir", default=None, help="also save each trained model as <dir>/<case>.zip")
    parser.add_argument("--load-dir", default=None, help="fingerprint the saves in this directory instead of learning")
    args = parser.parse_args(argv)
    th.set_num_threads(1)
    results: dict[str, Any] = {}
    for name in args.cases:
        try:
            if args.load_dir is None:
                results[name] = run_case(name, args.steps, args.save_dir)
            else:
                results[name] = load_case(name, args.load_dir)
        except Exception as error:  # reported per case, the other cases still run
            results[name] = {"error": f"{type(error).__name__}: {error}"}
    with open(args.out, "w") as handle:
        json.dump(results, handle, indent=1, sort_keys=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
