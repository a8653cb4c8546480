"""The spaces HIEROS supports, checked once where a model is built, and how a level's spaces map onto its networks.

:func:`check_spaces` is the one check of the environment's spaces (called by
:class:`~sb3_hieros.policies.HierosPolicy`, which every ``HIEROS`` construction and ``load`` goes through); the code
below it trusts the spaces. :func:`check_finite_observations` is the per-step check of observation values at the
public boundary (``predict`` and the environment steps of ``learn``, :func:`check_finite_step`).

Inside the hierarchy, level 0 acts in the environment's action space and observes its observations; a level i > 0
acts in :func:`subgoal_space` (the subgoals of level i-1) and observes :func:`stacked_state_space` (the last world
states of level i-1, concatenated).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.preprocessing import is_image_space, is_image_space_channels_first

from sb3_hieros.config import SubgoalConfig

__all__ = [
    "SUPPORTED_OBSERVATIONS",
    "action_layout",
    "check_action_space",
    "check_finite_observations",
    "check_finite_step",
    "check_observation_space",
    "check_spaces",
    "is_image_observation",
    "stacked_state_space",
    "subgoal_space",
]


#: the observation spaces HIEROS encodes (inside a Dict too), by class name for messages
SUPPORTED_OBSERVATIONS = "Box (vectors or images), Discrete, MultiDiscrete, MultiBinary, and a Dict of them"


def is_image_observation(space: spaces.Space, normalize_images: bool = True) -> bool:
    """Whether the world model encodes ``space`` as an image (a CNN), by SB3's rule (``is_image_space``): a rank-3 uint8
    Box with bounds [0, 255]; with ``normalize_images=False`` any rank-3 Box (float image-like inputs, taken as they
    are, as SB3's ``NatureCNN`` takes them with ``normalized_image=True``).

    :param space: an observation space (not a Dict)
    :param normalize_images: SB3's policy keyword
    :return: True for an image
    """
    return is_image_space(space, check_channels=False, normalized_image=not normalize_images)


def _check_leaf(space: spaces.Space, name: str, normalize_images: bool, images_channel_first: bool) -> None:
    if isinstance(space, spaces.Discrete | spaces.MultiDiscrete | spaces.MultiBinary):
        if isinstance(space, spaces.MultiDiscrete) and (space.nvec.size == 0 or np.any(space.nvec < 1)):
            raise ValueError(f"{name} {space} is not supported: a MultiDiscrete needs at least one entry, each >= 1")
        if isinstance(space, spaces.MultiBinary) and int(np.prod(space.shape)) == 0:
            raise ValueError(f"{name} {space} is not supported: a MultiBinary needs at least one entry")
        return
    if not isinstance(space, spaces.Box):
        raise ValueError(
            f"{name} {space} ({type(space).__name__}) is not supported by HIEROS; supported: {SUPPORTED_OBSERVATIONS}"
        )
    if images_channel_first or not is_image_observation(space, normalize_images):
        return
    if not is_image_space_channels_first(space):
        raise ValueError(
            f"{name} is an image of shape {space.shape} that SB3's rule (is_image_space_channels_first) takes as "
            "channel-last; a HierosPolicy built on its own takes channel-first (C, H, W) images: build it from "
            "VecTransposeImage(env).observation_space, or build HIEROS with the env, which follows SB3's rule "
            "(it adds VecTransposeImage unless the env already has one, e.g. VecTransposeImage(env, skip=True) for "
            "a channel-first frame stack)"
        )


def check_observation_space(
    observation_space: spaces.Space, normalize_images: bool = True, images_channel_first: bool = False
) -> None:
    """Raise ``ValueError`` unless HIEROS supports the observation space: a ``Box`` (vector, or an image, see
    :func:`is_image_observation`), ``Discrete``, ``MultiDiscrete``, ``MultiBinary``, or a ``Dict`` of them with string
    keys.

    Image channel order follows SB3: the algorithm wraps the env in ``VecTransposeImage`` when SB3's heuristic takes
    an image as channel-last and the env has no such wrapper yet, and the networks take the first dimension as the
    channels. ``images_channel_first=True`` (what :class:`~sb3_hieros.HIEROS` passes after that wrapping) trusts the
    order; otherwise a channel-last image (by ``is_image_space_channels_first``) is refused.

    :param observation_space: the (image-transposed) observation space
    :param normalize_images: SB3's policy keyword (False: every rank-3 Box is an image, taken as it is)
    :param images_channel_first: take every image as channel-first
    """
    if not isinstance(observation_space, spaces.Dict):
        _check_leaf(observation_space, "observation space", normalize_images, images_channel_first)
        return
    if len(observation_space.spaces) == 0:
        raise ValueError("observation_space is an empty Dict space; HIEROS needs at least one entry")
    for key, sub in observation_space.spaces.items():
        if not isinstance(key, str) or not key or "." in key:
            raise ValueError(f"observation keys must be non-empty strings without '.', got {key!r}")
        _check_leaf(sub, f"observation_space[{key!r}]", normalize_images, images_channel_first)


def check_action_space(action_space: spaces.Space) -> None:
    """Raise ``ValueError`` unless HIEROS supports the action space: ``Discrete`` starting at 0 with at least two
    actions, or a ``Box`` of any shape with finite bounds (flattened for the networks, reshaped for the env, as SAC
    and TD3 do).

    :param action_space: the environment's action space
    """
    if isinstance(action_space, spaces.Discrete):
        if int(action_space.start) != 0 or int(action_space.n) < 2:
            raise ValueError(f"action space {action_space} is not supported: need Discrete(n) with n >= 2 and start 0")
        return
    if isinstance(action_space, spaces.Box):
        if int(np.prod(action_space.shape)) == 0:
            raise ValueError(f"action space {action_space} is not supported: a Box action needs at least one entry")
        if not (np.all(np.isfinite(action_space.low)) and np.all(np.isfinite(action_space.high))):
            raise ValueError(f"action space {action_space} is not supported: Box actions need finite bounds")
        return
    raise ValueError(
        f"action space {action_space} ({type(action_space).__name__}) is not supported by HIEROS; "
        "supported: Discrete and Box"
    )


def check_spaces(
    observation_space: spaces.Space,
    action_space: spaces.Space,
    normalize_images: bool = True,
    images_channel_first: bool = False,
) -> None:
    """:func:`check_observation_space` and :func:`check_action_space`.

    :param observation_space: the (image-transposed) observation space
    :param action_space: the environment's action space
    :param normalize_images: SB3's policy keyword
    :param images_channel_first: take every image as channel-first (see :func:`check_observation_space`)
    """
    check_observation_space(observation_space, normalize_images, images_channel_first)
    check_action_space(action_space)


def check_finite_observations(
    observation: np.ndarray | th.Tensor | Mapping[str, np.ndarray | th.Tensor],
    what: str = "observation",
    envs: Sequence[int] | None = None,
) -> None:
    """Raise ``ValueError`` if a batch of observations holds NaN or inf, naming the rows (env indices) and the key.

    Integer arrays (uint8 images) cannot hold NaN and are not scanned.

    :param observation: (n, *obs_shape) array or tensor, or a dict of them (Dict spaces); row j is env j
    :param what: what the observation is, for the message (e.g. ``"terminal observation"``)
    :param envs: the env index of each row, if row j is not env j
    """
    items = observation.items() if isinstance(observation, Mapping) else [(None, observation)]
    for key, value in items:
        if isinstance(value, th.Tensor):
            if not (value.is_floating_point() or value.is_complex()) or value.dim() == 0:
                continue
            bad = (~th.isfinite(value).reshape(value.shape[0], -1).all(1)).cpu().numpy()
        else:
            array = np.asarray(value)
            if not np.issubdtype(array.dtype, np.inexact) or array.ndim == 0:
                continue
            bad = ~np.isfinite(array.reshape(array.shape[0], -1)).all(1)
        if bad.any():
            rows = list(range(len(bad))) if envs is None else list(envs)
            where = f" (key {key!r})" if key is not None else ""
            bad_envs = ", ".join(str(rows[j]) for j in np.flatnonzero(bad))
            raise ValueError(
                f"{what}{where} of env {bad_envs} contains NaN or inf; HIEROS "
                "cannot learn from or act on non-finite observations. Fix the environment, or wrap the VecEnv in "
                "stable_baselines3.common.vec_env.VecCheckNan(env, raise_exception=True) to stop at the step that "
                "produced it"
            )


def check_finite_step(
    new_obs: np.ndarray | Mapping[str, np.ndarray], reward: np.ndarray, dones: np.ndarray, infos: Sequence[dict]
) -> None:
    """Raise ``ValueError`` if one vec-env step brought a NaN or inf: in the new observations, the rewards or the
    terminal observations of the envs whose episode ended, naming the env (and the Dict key).

    :param new_obs: (n, ...) observations after the step
    :param reward: (n,) rewards
    :param dones: (n,) episode ends
    :param infos: the step's info dicts (``"terminal_observation"`` where an episode ended)
    """
    check_finite_observations(new_obs, "new observation")
    bad = np.flatnonzero(~np.isfinite(np.asarray(reward, dtype=np.float64).reshape(-1)))
    if bad.size:
        raise ValueError(
            f"reward of env {', '.join(str(j) for j in bad)} is not finite "
            f"({np.asarray(reward).reshape(-1)[bad].tolist()}); fix the environment or wrap the VecEnv in "
            "VecCheckNan(env, raise_exception=True)"
        )
    for j in np.flatnonzero(np.asarray(dones, dtype=bool).reshape(-1)):
        final = infos[j].get("terminal_observation")
        if final is not None:
            batch = (
                {k: np.asarray(v)[None] for k, v in final.items()}
                if isinstance(final, dict)
                else np.asarray(final)[None]
            )
            check_finite_observations(batch, "terminal observation", envs=[int(j)])


def subgoal_space(config: SubgoalConfig) -> spaces.MultiDiscrete:
    """Space of the subgoals a level receives: ``n_cat`` categoricals of ``n_classes`` classes (thesis 4.3.1).

    It is the action space of the level above.

    :param config: subgoal autoencoder hyperparameters
    :return: ``MultiDiscrete([n_classes] * n_cat)``
    """
    return spaces.MultiDiscrete([config.n_classes] * config.n_cat)


def stacked_state_space(state_dim: int, window: int) -> spaces.Box:
    """Observation space of a level above another: ``window`` world states ``[h, z]`` of the level below,
    concatenated (thesis 4.3).

    :param state_dim: size D + G*K of one world state of the level below
    :param window: number of stacked states (k, or 1 for ablation 5.3.6)
    :return: ``Box(-inf, inf, (window * state_dim,), float32)``
    """
    return spaces.Box(-np.inf, np.inf, (window * state_dim,), np.float32)


def action_layout(action_space: spaces.Space) -> tuple[str, int, int]:
    """How a level's action space maps onto its actor's output.

    :param action_space: ``Discrete(n)`` -> one categorical of n classes; ``MultiDiscrete([K] * G)`` (a subgoal
        space) -> G categoricals of K classes; ``Box`` -> a bounded normal per entry (flattened)
    :return: (kind ``"discrete"`` or ``"box"``, classes per group (discrete) or entries (box), number of groups)
    """
    if isinstance(action_space, spaces.Discrete):
        return "discrete", int(action_space.n), 1
    if isinstance(action_space, spaces.MultiDiscrete):
        return "discrete", int(action_space.nvec[0]), len(action_space.nvec)
    return "box", int(np.prod(action_space.shape)), 1
