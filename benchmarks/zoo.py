"""rl-baselines3-zoo (rl_zoo3) entry points with HIEROS registered as the algorithm ``hieros``.

rl_zoo3 2.9 has no plugin mechanism: its scripts look algorithms up in the dict ``rl_zoo3.ALGOS`` (one object shared
by ``train``, ``enjoy`` and the experiment manager), so this wrapper adds ``hieros`` to it (and a hyperparameter
sampler for ``-optimize``), registers gymnasium ids for the benchmark suites and then hands the command line to
rl_zoo3's own ``train()`` / ``enjoy()``. Needs the ``zoo`` extra (``pip install 'sb3-hieros[zoo]'``).

Hyperparameters come from ``benchmarks/hyperparams/hieros.yml`` unless ``-conf`` is given: keys ``atari`` (any
``ALE/<Game>-v5`` id, Atari100k protocol, paper preset), ``CartPole-v1`` and ``Pendulum-v1`` (small preset), and the
DMC ids registered here:

* ``HierosDMC-<domain>-<task>-v0``: DMC from 64x64 pixels, action repeat 2 (``suites.make_env("dmc_vision", ...)``),
  one id per task of thesis Table 5.2;
* ``HierosDMCProprio-<domain>-<task>-v0``: the same tasks from proprioceptive state (``"dmc_proprio"``).

Examples::

    python -m benchmarks.zoo train --algo hieros --env CartPole-v1 -n 2000
    python -m benchmarks.zoo train --algo hieros --env ALE/Pong-v5 --eval-episodes 10 --seed 0
    MUJOCO_GL=egl python -m benchmarks.zoo train --algo hieros --env HierosDMC-cartpole-balance-v0
    python -m benchmarks.zoo enjoy --algo hieros --env CartPole-v1 -f logs/ --no-render -n 500
    python -m benchmarks.zoo optimize --algo hieros --env CartPole-v1 -n 5000 --n-trials 10

Outputs go where rl_zoo3 puts them (``logs/hieros/<env>_<run id>/`` by default). Caveats: ``enjoy`` here loads
through :class:`EnjoyHIEROS`, which allocates a one-chunk replay (as the zoo does for its own off-policy algorithms)
instead of the full one saved with the model. The suite ids exist only in
processes that imported this module: with ``--vec-env subproc`` they are unknown in the workers, so keep the default
``dummy`` vec env for them.
"""

from __future__ import annotations

import json
import pathlib
import sys
import zipfile
from typing import Any

import gymnasium as gym
from stable_baselines3.common.save_util import open_path

from benchmarks.suites import DMC_VISION_TASKS, make_env
from sb3_hieros import HIEROS, get_preset

__all__ = [
    "HYPERPARAMS_FILE",
    "EnjoyHIEROS",
    "dmc_env_id",
    "main",
    "register_dmc_envs",
    "register_hieros",
    "sample_hieros_params",
]

#: The default hyperparameter file (rl-zoo format).
HYPERPARAMS_FILE = pathlib.Path(__file__).resolve().parent / "hyperparams" / "hieros.yml"


def dmc_env_id(task: str, pixels: bool = True) -> str:
    """Gymnasium id of a DMC suite task registered by :func:`register_dmc_envs`.

    :param task: ``"<domain>-<task>"``, e.g. ``"cartpole-balance"``
    :param pixels: the 64x64 pixel version (``dmc_vision``) instead of the proprioceptive one (``dmc_proprio``)
    :return: e.g. ``"HierosDMC-cartpole-balance-v0"``
    """
    return f"HierosDMC{'' if pixels else 'Proprio'}-{task}-v0"


def _make_suite_env(suite: str, task: str, **kwargs: Any) -> gym.Env:
    return make_env(suite, task, **kwargs)


def register_dmc_envs(tasks: tuple[str, ...] = DMC_VISION_TASKS) -> None:
    """Register ``HierosDMC-<task>-v0`` (pixels) and ``HierosDMCProprio-<task>-v0`` for every task (idempotent).

    :param tasks: ``"<domain>-<task>"`` names
    """
    for task in tasks:
        for pixels, suite in ((True, "dmc_vision"), (False, "dmc_proprio")):
            env_id = dmc_env_id(task, pixels)
            if env_id not in gym.registry:
                gym.register(env_id, entry_point=_make_suite_env, kwargs={"suite": suite, "task": task})


def sample_hieros_params(trial: Any, n_actions: int, n_envs: int, additional_args: dict[str, Any]) -> dict[str, Any]:
    """Optuna search space of HIEROS for rl_zoo3's ``-optimize`` (the zoo's sampler signature).

    Searches what matters most on a CPU budget: the world-model learning rate, the train ratio, the imagination
    horizon and the subgoal interval; everything else comes from the preset of the hyperparameter file.

    :param trial: the optuna trial
    :param n_actions: size of the action space (unused)
    :param n_envs: number of envs (unused)
    :param additional_args: the zoo's extra arguments (unused)
    :return: HIEROS keywords (``learning_rate`` and ``config_overrides``)
    """
    return {
        "learning_rate": trial.suggest_float("learning_rate", 1e-4, 3e-3, log=True),
        "config_overrides": {
            "train_ratio": trial.suggest_categorical("train_ratio", [16, 32, 64, 128, 256]),
            "imag_horizon": trial.suggest_categorical("imag_horizon", [8, 16]),
            "subgoal_interval": trial.suggest_categorical("subgoal_interval", [4, 8]),
        },
    }


class EnjoyHIEROS(HIEROS):
    """:class:`HIEROS` as rl_zoo3's ``enjoy`` needs it: ``load`` allocates a minimal replay (one chunk per env) unless
    ``buffer_size`` is given (the zoo does the same for its own off-policy algorithms)."""

    @classmethod
    def load(cls, path: Any, env: Any = None, device: Any = "auto", custom_objects: Any = None, **kwargs: Any) -> Any:  # type: ignore[override]
        """:meth:`HIEROS.load` with a one-chunk replay.

        :return: the loaded :class:`HIEROS` model
        """
        if "buffer_size" not in kwargs:
            with zipfile.ZipFile(open_path(path, "r", verbose=0, suffix="zip")) as archive:
                data = json.loads(archive.read("data").decode())  # plain values only: nothing is unpickled
            length = data.get("batch_length")  # saves of models built when it was a constructor keyword
            if length is None:
                length = get_preset(data["preset"]).replace(**data.get("config_overrides", {})).batch_length
            kwargs["buffer_size"] = int(length) * max(1, int(data.get("n_envs", 1)))  # one chunk
        return HIEROS.load(path, env=env, device=device, custom_objects=custom_objects, **kwargs)


def register_hieros(enjoy: bool = False) -> None:
    """Add ``hieros`` to rl_zoo3's algorithm registry and optuna samplers, and register the DMC suite ids.

    :param enjoy: register :class:`EnjoyHIEROS` (for ``enjoy``) instead of :class:`HIEROS`
    """
    try:
        import rl_zoo3
        import rl_zoo3.hyperparams_opt as hyperparams_opt
    except ImportError as error:
        raise ImportError(f"benchmarks.zoo needs the 'zoo' extra: pip install 'sb3-hieros[zoo]' ({error})") from error
    rl_zoo3.ALGOS["hieros"] = EnjoyHIEROS if enjoy else HIEROS
    hyperparams_opt.HYPERPARAMS_SAMPLER["hieros"] = sample_hieros_params
    hyperparams_opt.HYPERPARAMS_CONVERTER["hieros"] = dict
    register_dmc_envs()


def main(argv: list[str] | None = None) -> None:
    """``python -m benchmarks.zoo train|enjoy|optimize [rl_zoo3 arguments]`` (see the module docstring).

    :param argv: the arguments after the program name (default: ``sys.argv[1:]``)
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    commands = ("train", "enjoy", "optimize")
    if not argv or argv[0] not in commands:
        raise SystemExit(f"usage: python -m benchmarks.zoo {{{','.join(commands)}}} [rl_zoo3 arguments]")
    command, rest = argv[0], argv[1:]
    register_hieros(enjoy=command == "enjoy")
    if command != "enjoy" and not {"-conf", "--conf-file"} & set(rest):
        rest += ["-conf", str(HYPERPARAMS_FILE)]
    if command == "optimize":
        rest.append("-optimize")
    saved = sys.argv
    sys.argv = [f"benchmarks.zoo {command}", *rest]
    try:
        if command == "enjoy":
            from rl_zoo3.enjoy import enjoy

            enjoy()
        else:
            from rl_zoo3.train import train

            train()
    finally:
        sys.argv = saved


if __name__ == "__main__":
    main()
