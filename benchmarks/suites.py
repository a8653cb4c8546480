"""Environment makers for the benchmark suites of the thesis (Mattes 2023, chapter 5).

* ``"atari100k"`` (thesis Table 5.1): ALE v5 games with the protocol of the thesis and DreamerV3: RGB observations
  resized to 64x64, action repeat 4 through ALE's own ``frameskip=4`` (rewards of the skipped frames summed), no
  sticky actions unless ``sticky=True`` (then ALE's ``repeat_action_probability=0.25``), episodes capped at
  108,000 frames, up to 30 random no-ops after each reset (the reference configuration's ``noops``), the minimal
  action set, lives unused. Budget: 100k agent steps (400k frames).
* ``"dmc_vision"`` (thesis Table 5.2): DeepMind Control suite tasks through shimmy's dm_control compatibility env,
  observations replaced by the 64x64 RGB render (gymnasium's ``AddRenderObservation``), action repeat 2 (rewards
  summed). Budget: 1M environment steps (500k agent steps).
* ``"dmc_proprio"``: the same tasks with the state vectors flattened into one float32 vector.
* ``"classic"``: gymnasium's classic-control tasks (:data:`CLASSIC_TASKS`, any registered id is accepted) as
  ``gym.make`` gives them: cheap CPU checks of the benchmark scripts, ``MlpPolicy``.

The thesis' reference tables are copied into ``benchmarks/data`` (:data:`DATA_DIR`, see its README).

Every maker returns a plain ``gymnasium.Env`` (no ``Monitor``: SB3 adds one), already reset once with ``seed`` so
that later unseeded resets continue a seeded stream, with its action space seeded too.

The DMC makers need the ``dmc`` extra (dm-control, mujoco, shimmy, and imageio, which gymnasium's MuJoCo renderer
imports when shimmy loads). Rendering without a display needs an offscreen OpenGL backend: the DMC maker sets
``MUJOCO_GL=egl`` unless the variable is already set, which only takes effect if dm_control was not imported before.
"""

from __future__ import annotations

import os
import pathlib
from dataclasses import dataclass
from typing import Any, SupportsFloat

import gymnasium as gym
import numpy as np
from gymnasium import spaces

#: Folder of the thesis' reference tables (``thesis_table_5_1_atari100k.csv``, ``thesis_table_5_2_dmc_vision.csv``).
DATA_DIR = pathlib.Path(__file__).resolve().parent / "data"

#: The 26 games of the Atari100k benchmark (ALE v5 names, ``ALE/<game>-v5``).
ATARI100K_GAMES: tuple[str, ...] = (
    "Alien",
    "Amidar",
    "Assault",
    "Asterix",
    "BankHeist",
    "BattleZone",
    "Boxing",
    "Breakout",
    "ChopperCommand",
    "CrazyClimber",
    "DemonAttack",
    "Freeway",
    "Frostbite",
    "Gopher",
    "Hero",
    "Jamesbond",
    "Kangaroo",
    "Krull",
    "KungFuMaster",
    "MsPacman",
    "Pong",
    "PrivateEye",
    "Qbert",
    "RoadRunner",
    "Seaquest",
    "UpNDown",
)

#: Game name -> its row label in thesis Table 5.1 (``benchmarks/data/thesis_table_5_1_atari100k.csv``). The thesis
#: reports 25 games: every Atari100k game except UpNDown.
ATARI100K_THESIS_LABELS: dict[str, str] = {
    game: {
        "BattleZone": "Battle Zone",
        "ChopperCommand": "Chop.Command",
        "Jamesbond": "JamesBond",
        "MsPacman": "Ms.Packman",
    }.get(game, game)
    for game in ATARI100K_GAMES
    if game != "UpNDown"
}

#: The 20 tasks of thesis Table 5.2 as ``"<domain>-<task>"`` with dm_control's domain and task names.
DMC_VISION_TASKS: tuple[str, ...] = (
    "acrobot-swingup",
    "cartpole-balance",
    "cartpole-balance_sparse",
    "cartpole-swingup",
    "cartpole-swingup_sparse",
    "cheetah-run",
    "ball_in_cup-catch",
    "finger-spin",
    "finger-turn_easy",
    "finger-turn_hard",
    "hopper-hop",
    "hopper-stand",
    "pendulum-swingup",
    "quadruped-run",
    "quadruped-walk",
    "reacher-easy",
    "reacher-hard",
    "walker-run",
    "walker-stand",
    "walker-walk",
)

#: Task -> its row label in thesis Table 5.2 (``benchmarks/data/thesis_table_5_2_dmc_vision.csv``).
DMC_VISION_THESIS_LABELS: dict[str, str] = {
    task: "Cup Catch"
    if task == "ball_in_cup-catch"
    else " ".join(word.capitalize() for word in task.replace("-", "_").split("_"))
    for task in DMC_VISION_TASKS
}

#: Classic-control tasks of the ``"classic"`` suite (gymnasium ids; the suite accepts any registered id).
CLASSIC_TASKS: tuple[str, ...] = (
    "CartPole-v1",
    "Pendulum-v1",
    "Acrobot-v1",
    "MountainCar-v0",
    "MountainCarContinuous-v0",
)

#: Camera of the pixel observations: the quadruped tasks use camera 2 (as DreamerV3 does), all others camera 0.
DMC_CAMERAS: dict[str, int] = {"quadruped": 2}


@dataclass(frozen=True)
class SuiteSpec:
    """What defines one benchmark suite.

    :param name: suite name as given to :func:`make_env`
    :param tasks: the suite's tasks (games for Atari)
    :param action_repeat: environment steps per agent step
    :param agent_steps: training budget in agent steps (``learn(total_timesteps=...)``)
    :param env_steps: the same budget in environment steps (frames), as the papers count it
    """

    name: str
    tasks: tuple[str, ...]
    action_repeat: int
    agent_steps: int
    env_steps: int


SUITES: dict[str, SuiteSpec] = {
    "atari100k": SuiteSpec("atari100k", ATARI100K_GAMES, 4, 100_000, 400_000),
    "dmc_vision": SuiteSpec("dmc_vision", DMC_VISION_TASKS, 2, 500_000, 1_000_000),
    "dmc_proprio": SuiteSpec("dmc_proprio", DMC_VISION_TASKS, 2, 250_000, 500_000),
    "classic": SuiteSpec("classic", CLASSIC_TASKS, 1, 50_000, 50_000),
}

#: SB3 policy name of each suite's observations.
SUITE_POLICIES: dict[str, str] = {
    "atari100k": "CnnPolicy",
    "dmc_vision": "CnnPolicy",
    "dmc_proprio": "MlpPolicy",
    "classic": "MlpPolicy",
}


class ActionRepeat(gym.Wrapper):
    """Repeat every action ``repeat`` times, summing the rewards; stops early when the episode ends.

    :param env: environment to wrap
    :param repeat: environment steps per agent step (>= 1)
    """

    def __init__(self, env: gym.Env, repeat: int) -> None:
        if not isinstance(repeat, int) or repeat < 1:
            raise ValueError(f"repeat must be an int >= 1, got {repeat!r}")
        super().__init__(env)
        self.repeat = repeat

    def step(self, action: Any) -> tuple[Any, SupportsFloat, bool, bool, dict[str, Any]]:
        total = 0.0
        for _ in range(self.repeat):
            obs, reward, terminated, truncated, info = self.env.step(action)
            total += float(reward)
            if terminated or truncated:
                break
        return obs, total, terminated, truncated, info


class RandomNoopReset(gym.Wrapper):
    """After each reset, take a uniform number in ``[0, noop_max]`` of NOOP actions (action 0).

    Unlike SB3's ``NoopResetEnv`` (at least one no-op), zero no-ops is possible and ``noop_max=0`` is allowed.

    :param env: an ALE environment whose action 0 is NOOP
    :param noop_max: largest number of no-ops (>= 0)
    """

    def __init__(self, env: gym.Env, noop_max: int) -> None:
        if not isinstance(noop_max, int) or noop_max < 0:
            raise ValueError(f"noop_max must be an int >= 0, got {noop_max!r}")
        meanings = env.unwrapped.get_action_meanings()  # type: ignore[attr-defined]
        if meanings[0] != "NOOP":
            raise ValueError(f"action 0 of {env} must be NOOP for no-op resets, got {meanings[0]!r}")
        super().__init__(env)
        self.noop_max = noop_max

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        obs, info = self.env.reset(seed=seed, options=options)
        for _ in range(int(self.unwrapped.np_random.integers(0, self.noop_max + 1))):
            obs, _, terminated, truncated, info = self.env.step(0)
            if terminated or truncated:
                obs, info = self.env.reset(options=options)
        return obs, info


def _seeded(env: gym.Env, seed: int) -> gym.Env:
    env.reset(seed=seed)
    env.action_space.seed(seed)
    return env


def _float32_box(box: spaces.Box) -> spaces.Box:
    """The same box with float32 bounds and dtype (cast before constructing: no precision warning)."""
    return spaces.Box(box.low.astype(np.float32), box.high.astype(np.float32), dtype=np.float32)


def _float32_actions(env: gym.Env) -> gym.Env:
    """Expose a float64 Box action space as float32 (what SB3 policies emit); actions go back as float64."""
    box = env.action_space
    if not isinstance(box, spaces.Box) or box.dtype != np.float64:
        return env
    return gym.wrappers.TransformAction(env, lambda action: np.asarray(action, dtype=np.float64), _float32_box(box))


def _check_size(size: int) -> None:
    if not isinstance(size, int) or isinstance(size, bool) or size < 1:
        raise ValueError(f"size must be a positive int (pixels per side), got {size!r}")


def atari100k_wrapper(env: gym.Env, noop_max: int = 30, size: int = 64) -> gym.Env:
    """The wrappers :func:`make_atari_env` puts around an ALE env: random no-op resets and RGB resize.

    For ``env_wrapper`` in rl-zoo hyperparameter files, where the zoo makes the ALE env itself (then give it
    ``frameskip=4``, ``repeat_action_probability=0.0`` and ``max_num_frames_per_episode=108000`` as ``env_kwargs``).

    :param env: an ALE v5 env with RGB observations
    :param noop_max: at most this many random no-ops after each reset (0: none)
    :param size: side of the square RGB observation
    :return: the wrapped env
    """
    _check_size(size)
    if noop_max:
        env = RandomNoopReset(env, noop_max)
    return gym.wrappers.ResizeObservation(env, (size, size))  # cv2 INTER_AREA


def make_atari_env(
    game: str,
    seed: int = 0,
    sticky: bool = False,
    size: int = 64,
    full_action_space: bool = False,
    noop_max: int = 30,
) -> gym.Env:
    """One Atari game with the Atari100k protocol (see the module docstring).

    :param game: ALE v5 game name, e.g. ``"Pong"`` (any game ALE registers as ``ALE/<game>-v5``)
    :param seed: seed of the first reset and of the action space
    :param sticky: sticky actions (``repeat_action_probability=0.25``) instead of none
    :param size: side of the square RGB observation
    :param full_action_space: all 18 actions instead of the game's minimal set
    :param noop_max: at most this many random no-ops after each reset (0: none)
    :return: env with ``Box(0, 255, (size, size, 3), uint8)`` observations, each step 4 ALE frames
    """
    try:
        import ale_py
    except ImportError as error:
        raise ImportError("Atari suites need the 'atari' extra: pip install 'sb3-hieros[atari]'") from error
    _check_size(size)
    gym.register_envs(ale_py)
    env_id = f"ALE/{game}-v5"
    if not isinstance(game, str) or env_id not in gym.registry:
        raise ValueError(
            f"unknown Atari game {game!r}: ALE registers no {env_id!r}; Atari100k games: {ATARI100K_GAMES}"
        )
    env = gym.make(
        env_id,
        obs_type="rgb",
        frameskip=4,
        repeat_action_probability=0.25 if sticky else 0.0,
        full_action_space=full_action_space,
        max_num_frames_per_episode=108_000,
    )
    return _seeded(atari100k_wrapper(env, noop_max=noop_max, size=size), seed)


def _dmc_domain_task(task: str) -> tuple[str, str]:
    """``"cartpole-balance"`` -> ``("cartpole", "balance")``, checked against dm_control's suite."""
    from dm_control import suite

    parts = task.split("-") if isinstance(task, str) else []
    if len(parts) != 2 or tuple(parts) not in suite.ALL_TASKS:
        raise ValueError(
            f"unknown DMC task {task!r}: expected '<domain>-<task>' of a dm_control suite task, "
            f"e.g. one of {DMC_VISION_TASKS}"
        )
    return parts[0], parts[1]


def make_dmc_env(
    task: str,
    seed: int = 0,
    pixels: bool = True,
    size: int = 64,
    action_repeat: int = 2,
    camera_id: int | None = None,
) -> gym.Env:
    """One DeepMind Control suite task, from pixels or from its flattened state.

    :param task: ``"<domain>-<task>"`` with dm_control's names, e.g. ``"cartpole-balance"``, ``"ball_in_cup-catch"``
    :param seed: seed of the first reset (dm_control's task random state) and of the action space
    :param pixels: observations are the ``(size, size, 3)`` uint8 render; otherwise the state vectors
        flattened into one float32 vector
    :param size: side of the square render
    :param action_repeat: physics control steps per agent step (rewards summed)
    :param camera_id: render camera; None = :data:`DMC_CAMERAS` of the domain, else 0
    :return: env with a Box action space in [-1, 1]; episodes end after 1000 control steps
    """
    if pixels:
        _check_size(size)
        os.environ.setdefault("MUJOCO_GL", "egl")
    try:
        import shimmy
    except ImportError as error:
        raise ImportError(
            f"DMC suites need the 'dmc' extra (dm-control, mujoco, shimmy, imageio): importing shimmy failed: {error}"
        ) from error
    gym.register_envs(shimmy)
    domain, name = _dmc_domain_task(task)
    kwargs: dict[str, Any] = {}
    if pixels:
        camera = DMC_CAMERAS.get(domain, 0) if camera_id is None else camera_id
        kwargs = {"render_mode": "rgb_array", "render_kwargs": {"height": size, "width": size, "camera_id": camera}}
    env: gym.Env = gym.make(f"dm_control/{domain}-{name}-v0", **kwargs)
    env = ActionRepeat(env, action_repeat)  # renders once per agent step, not once per control step
    env = _float32_actions(env)
    if pixels:
        env = gym.wrappers.AddRenderObservation(env, render_only=True)
    else:
        env = gym.wrappers.FlattenObservation(env)
        flat = env.observation_space
        assert isinstance(flat, spaces.Box)
        env = gym.wrappers.TransformObservation(env, lambda obs: obs.astype(np.float32), _float32_box(flat))
    return _seeded(env, seed)


def make_env(suite: str, task: str, seed: int = 0, **kwargs: Any) -> gym.Env:
    """The environment of one task of a named suite.

    ``"atari100k"`` and ``"dmc_vision"`` accept only their own tasks (:data:`ATARI100K_GAMES`,
    :data:`DMC_VISION_TASKS`); ``"dmc_proprio"`` accepts any dm_control suite task, ``"classic"`` any gymnasium id.

    :param suite: ``"atari100k"``, ``"dmc_vision"``, ``"dmc_proprio"`` or ``"classic"``
    :param task: game, ``"<domain>-<task>"`` or gymnasium id
    :param seed: seed of the first reset and of the action space
    :param kwargs: further keywords of :func:`make_atari_env` or :func:`make_dmc_env`
    :return: the environment
    """
    if suite not in SUITES:
        raise ValueError(f"unknown suite {suite!r}; expected one of {sorted(SUITES)}")
    if suite == "classic":
        if not isinstance(task, str) or task not in gym.registry:
            raise ValueError(f"unknown classic task {task!r}: not a registered gymnasium id, e.g. {CLASSIC_TASKS}")
        return _seeded(gym.make(task, **kwargs), seed)
    if suite != "dmc_proprio" and task not in SUITES[suite].tasks:
        raise ValueError(f"unknown {suite} task {task!r}; expected one of {SUITES[suite].tasks}")
    if suite == "atari100k":
        return make_atari_env(task, seed=seed, **kwargs)
    if "pixels" in kwargs:
        raise ValueError(f"suite {suite!r} fixes pixels; got pixels={kwargs['pixels']!r}")
    return make_dmc_env(task, seed=seed, pixels=suite == "dmc_vision", **kwargs)
