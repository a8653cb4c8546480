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
    "action_layout",
    "check_action_space",
    "check_finite_observations",
    "check_finite_step",
    "check_observation_space",
    "check_spaces",
    "stacked_state_space",
    "subgoal_space",
]


def _check_box(space: spaces.Space, name: str) -> None:
    if not isinstance(space, spaces.Box):
        raise ValueError(
            f"{name} {space} ({type(space).__name__}) is not supported by HIEROS; supported: Box (vectors or "
            "channel-first uint8 images) and Dict of Boxes"
        )
    if is_image_space(space, check_channels=False) and not is_image_space_channels_first(space):
        raise ValueError(
            f"{name} is a channel-last image of shape {space.shape}; HIEROS expects channel-first (C, H, W) images: "
            "wrap the env in VecTransposeImage (HIEROS does this itself for the env it is given)"
        )


def check_observation_space(observation_space: spaces.Space) -> None:
    """Raise ``ValueError`` unless HIEROS supports the observation space: a ``Box`` (vector, or a channel-first
    uint8 image) or a ``Dict`` of such Boxes with string keys.

    :param observation_space: the (image-transposed) observation space
    """
    if not isinstance(observation_space, spaces.Dict):
        _check_box(observation_space, "observation space")
        return
    if len(observation_space.spaces) == 0:
        raise ValueError("observation_space is an empty Dict space; HIEROS needs at least one Box entry")
    for key, sub in observation_space.spaces.items():
        if not isinstance(key, str) or not key or "." in key:
            raise ValueError(f"observation keys must be non-empty strings without '.', got {key!r}")
        _check_box(sub, f"observation_space[{key!r}]")


def check_action_space(action_space: spaces.Space) -> None:
    """Raise ``ValueError`` unless HIEROS supports the action space: ``Discrete`` starting at 0 with at least two
    actions, or a 1-d ``Box`` with finite bounds.

    :param action_space: the environment's action space
    """
    if isinstance(action_space, spaces.Discrete):
        if int(action_space.start) != 0 or int(action_space.n) < 2:
            raise ValueError(f"action space {action_space} is not supported: need Discrete(n) with n >= 2 and start 0")
        return
    if isinstance(action_space, spaces.Box):
        if len(action_space.shape) != 1:
            raise ValueError(
                f"action space {action_space} is not supported: Box actions must be 1-d, got shape {action_space.shape}"
            )
        if not (np.all(np.isfinite(action_space.low)) and np.all(np.isfinite(action_space.high))):
            raise ValueError(f"action space {action_space} is not supported: Box actions need finite bounds")
        return
    raise ValueError(
        f"action space {action_space} ({type(action_space).__name__}) is not supported by HIEROS; "
        "supported: Discrete and 1-d Box"
    )


def check_spaces(observation_space: spaces.Space, action_space: spaces.Space) -> None:
    """:func:`check_observation_space` and :func:`check_action_space`.

    :param observation_space: the (image-transposed) observation space
    :param action_space: the environment's action space
    """
    check_observation_space(observation_space)
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
            batch = {k: v[None] for k, v in final.items()} if isinstance(final, dict) else np.asarray(final)[None]
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
        space) -> G categoricals of K classes; 1-d ``Box`` -> a bounded normal per dim
    :return: (kind ``"discrete"`` or ``"box"``, classes per group (discrete) or dims (box), number of groups)
    """
    if isinstance(action_space, spaces.Discrete):
        return "discrete", int(action_space.n), 1
    if isinstance(action_space, spaces.MultiDiscrete):
        return "discrete", int(action_space.nvec[0]), len(action_space.nvec)
    return "box", int(action_space.shape[0]), 1
