"""HIEROS policy: the SB3 face of the hierarchy (predict with the hierarchical recurrent state, action conversion).

:class:`HierosPolicy` is one SB3 ``BasePolicy`` holding the :class:`~sb3_hieros.agent.hierarchy.Hierarchy` (so
``policy.save`` / ``HierosPolicy.load`` and the algorithm's ``save`` / ``load`` cover every level). It checks the
spaces once (:func:`sb3_hieros.spaces.check_spaces`), converts between environment actions and the hierarchy's action
vectors, and threads the recurrent state of :meth:`HierosPolicy.predict` through :meth:`Hierarchy.step`.

The recurrent state of :meth:`HierosPolicy.predict` follows the RecurrentPPO convention: a tuple of numpy arrays,
batch on axis 0, one row per env, in the order of :meth:`HierosPolicy.state_names`: ``step`` (n,) int64, then for each
level i: ``level{i}/stoch``, ``level{i}/deter``, ``level{i}/seq`` (complex64 S5 states, or the GRU state of the
RSSM), ``level{i}/logits``, ``level{i}/prior_logits`` (the :class:`~sb3_hieros.agent.world_model.LatentState` fields;
only for levels with a world model of their own), ``level{i}/action`` (the action in force as a float vector: one-hot,
grouped one-hot subgoal, or Box action in [-1, 1]) and, for i >= 1, ``level{i}/history`` (n, w_i, D), the last world
states the level observes.

``MlpPolicy``, ``CnnPolicy`` and ``MultiInputPolicy`` are the same class under the names SB3 and rl-zoo expect: the
world model picks a CNN for every image key and one MLP for the vector and discrete keys of any observation space.

SB3's policy keywords: ``normalize_images`` (False: every rank-3 Box is an image taken as it is),
``features_extractor_class`` / ``features_extractor_kwargs`` (a user's encoder for level 0's world model,
:class:`~sb3_hieros.agent.world_model.observations.FeaturesExtractorEncoder`), ``optimizer_class`` /
``optimizer_kwargs`` (every optimiser of every level, :func:`~sb3_hieros.nn.optim.user_optimizer`). Keywords of SB3's
own networks (``activation_fn``, ``n_critics``, ...) have no HIEROS meaning and are refused with a ``ValueError``
naming them.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch as th
import torch.nn.functional as F
from gymnasium import spaces
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor, CombinedExtractor, FlattenExtractor, NatureCNN
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from torch import nn

from sb3_hieros.agent.hierarchy import Hierarchy, HierarchyState, make_hierarchy
from sb3_hieros.agent.world_model import LatentState, ObservationOptions
from sb3_hieros.config import HierosConfig, config_from_dict
from sb3_hieros.nn.networks import check_bf16
from sb3_hieros.nn.optim import check_optimizer_options
from sb3_hieros.spaces import check_finite_observations, check_spaces

__all__ = ["CnnPolicy", "HierosPolicy", "MlpPolicy", "MultiInputPolicy"]

_LATENT_FIELDS = LatentState._fields  # ("stoch", "deter", "seq", "logits", "prior_logits")

#: keywords of SB3's own policy networks, which HIEROS's networks do not have
_SB3_NETWORK_KEYWORDS = (
    "net_arch",
    "activation_fn",
    "share_features_extractor",
    "n_critics",
    "log_std_init",
    "use_sde",
    "use_expln",
    "clip_mean",
    "squash_output",
    "ortho_init",
    "full_std",
    "dueling",
    "lstm_hidden_size",
    "n_lstm_layers",
    "shared_lstm",
    "enable_critic_lstm",
    "lstm_kwargs",
)


def _refuse_policy_keywords(kwargs: dict[str, Any]) -> None:
    """A clear error for SB3 policy keywords without a HIEROS meaning, TypeError for unknown ones."""
    if "decoded_subgoal_input" in kwargs:
        raise ValueError(
            "decoded_subgoal_input is not a policy keyword: set it with "
            f"config_overrides={{'decoded_subgoal_input': {kwargs['decoded_subgoal_input']!r}}} (ablation 5.3.8)"
        )
    sb3 = sorted(name for name in kwargs if name in _SB3_NETWORK_KEYWORDS)
    if sb3:
        raise ValueError(
            f"{', '.join(sb3)}: SB3 policy keywords without a HIEROS meaning. HIEROS's networks (world model, whose "
            "sequence model is the recurrence, actor, critics with one critic per reward term, subgoal autoencoder; "
            "SiLU activations) are sized by HierosConfig "
            "fields: set them with config_overrides, e.g. {'actor_critic': {'units': 64, 'layers': 2}} (HIEROS "
            "itself maps policy_kwargs net_arch onto those two fields)"
        )
    if kwargs:
        raise TypeError(f"HierosPolicy got unexpected keywords {sorted(kwargs)}")


class HierosPolicy(BasePolicy):
    """The HIEROS hierarchy (thesis 4.3, Figure 4.2) behind SB3's policy interface.

    :param observation_space: observation space (Box vector or image, Discrete, MultiDiscrete, MultiBinary, or a Dict
        of them)
    :param action_space: ``Discrete`` or ``Box`` action space (any shape: flattened for the networks)
    :param lr_schedule: learning-rate schedule (unused by the policy: :class:`~sb3_hieros.HIEROS` sets the world
        models' learning rate; kept for the SB3 policy signature)
    :param config: the resolved :class:`~sb3_hieros.config.HierosConfig` or its ``dataclasses.asdict`` dict; None
        for the ``"paper"`` preset
    :param bf16: bfloat16 autocast of the training losses (world models, actor-critics, subgoal autoencoders; acting,
        imagination and the S5 scan stay float32): ``"auto"`` (default) where the device computes bf16 natively (CPUs
        with AVX512-BF16 or AMX, CUDA GPUs with bf16; :func:`~sb3_hieros.nn.networks.native_bf16`), ``True`` always,
        ``False`` never (float32 throughout)
    :param compile: ``torch.compile`` opt-in of the world models' sequence models
    :param normalize_images: SB3's keyword: True scales uint8 images (``x / 255 - 0.5`` in the world model); False
        takes every rank-3 Box as an image as it is (float image-like inputs; the decoder predicts them in their
        units)
    :param optimizer_class: the class of every optimiser of every level (world model, actor, critics, subgoal
        autoencoder); None keeps HIEROS's AdamW (:func:`~sb3_hieros.nn.optim.user_optimizer`)
    :param optimizer_kwargs: keywords of every optimiser over the configuration's (e.g. ``eps``, ``betas``,
        ``weight_decay``); not ``lr``: the learning rates stay per learner, from the configuration and
        ``learning_rate``
    :param features_extractor_class: an SB3 ``BaseFeaturesExtractor`` subclass that replaces the encoder of level 0's
        world model (it receives SB3-preprocessed observations: images in [0, 1], discrete entries one-hot; see
        :class:`~sb3_hieros.agent.world_model.observations.FeaturesExtractorEncoder`); the decoder still reconstructs
        the observations. None: HIEROS's CNN / MLP encoder
    :param features_extractor_kwargs: its keywords; given alone, as in SB3, they configure the default extractor of the
        policy name (``FlattenExtractor`` for ``MlpPolicy``, ``NatureCNN`` for ``CnnPolicy``, ``CombinedExtractor``
        for ``MultiInputPolicy``), with a ``UserWarning``
    :param images_channel_first: take every image as channel-first (HIEROS passes True: it wraps the env by SB3's
        rule); False checks with SB3's heuristic (:func:`~sb3_hieros.spaces.check_observation_space`)
    """

    hierarchy: Hierarchy
    #: SB3's default features extractor of the policy name, used only for ``features_extractor_kwargs`` given without
    #: ``features_extractor_class``
    default_extractor_class: type[BaseFeaturesExtractor] = FlattenExtractor

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        lr_schedule: Schedule,
        config: Mapping[str, Any] | HierosConfig | None = None,
        bf16: bool | str = "auto",
        compile: bool = False,
        normalize_images: bool = True,
        optimizer_class: type[th.optim.Optimizer] | None = None,
        optimizer_kwargs: dict[str, Any] | None = None,
        features_extractor_class: type[BaseFeaturesExtractor] | None = None,
        features_extractor_kwargs: dict[str, Any] | None = None,
        images_channel_first: bool = False,
        **kwargs: Any,
    ) -> None:
        _refuse_policy_keywords(kwargs)
        check_spaces(observation_space, action_space, bool(normalize_images), bool(images_channel_first))
        check_optimizer_options(optimizer_class, optimizer_kwargs)
        features_extractor_class, extractor_kwargs = _features_extractor(
            features_extractor_class, features_extractor_kwargs, bool(normalize_images), self.default_extractor_class
        )
        super().__init__(
            observation_space,
            action_space,
            normalize_images=normalize_images,
            squash_output=isinstance(action_space, spaces.Box),
        )
        self.config = config_from_dict(config)
        self.bf16 = check_bf16(bf16)
        self.compile = bool(compile)
        self.images_channel_first = bool(images_channel_first)
        #: SB3's policy attributes (None: HIEROS's AdamW per learner / its own encoder)
        self.optimizer_class, self.optimizer_kwargs = optimizer_class, optimizer_kwargs
        self.features_extractor_class, self.features_extractor_kwargs = features_extractor_class, extractor_kwargs
        options = ObservationOptions(self.normalize_images, features_extractor_class, extractor_kwargs)
        self.hierarchy = make_hierarchy(
            observation_space,
            action_space,
            self.config,
            bf16=self.bf16,
            compile=self.compile,
            observation_options=options,
        )
        if optimizer_class is not None or optimizer_kwargs:
            self.hierarchy.use_optimizer(optimizer_class, optimizer_kwargs)
        if features_extractor_class is not None:
            # SB3's name for the policy's extractor: a reference to the one in level 0's world model, not a second
            # registration (the policy's state dict keeps one copy of its parameters)
            object.__setattr__(self, "features_extractor", self.hierarchy.levels[0].world_model.encoder.extractor)
        #: the level-0 world-model optimiser under SB3's conventional name (``load`` falls back on ``policy.optimizer``)
        self.optimizer = self.hierarchy.levels[0].wm_optimizer
        self._register_load_state_dict_pre_hook(_rename_flat_levels)

    # ------------------------------------------------------------------------------------------------ SB3 plumbing

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            lr_schedule=self._dummy_schedule,
            config=dataclasses.asdict(self.config),
            bf16=self.bf16,
            compile=self.compile,
            optimizer_class=self.optimizer_class,
            optimizer_kwargs=self.optimizer_kwargs,
            features_extractor_class=self.features_extractor_class,
            features_extractor_kwargs=self.features_extractor_kwargs,
            images_channel_first=self.images_channel_first,
        )
        return data

    def optimizer_names(self) -> list[str]:
        """Attribute paths (relative to the policy) of every optimiser, ``"optimizer"`` (level-0 world model) first.

        :return: e.g. ``["optimizer", "hierarchy.levels.0.actor_optimizer", ...]``
        """
        return ["optimizer", *(f"hierarchy.{name}" for name in self.hierarchy.optimizer_names()[1:])]

    @property
    def device(self) -> th.device:
        """The device of the parameters, cached (SB3 walks the modules on every access; :meth:`_apply`, which ``to``,
        ``cpu`` and ``cuda`` go through, clears the cache)."""
        cached = self.__dict__.get("_cached_device")
        if cached is None:
            cached = super().device
            self.__dict__["_cached_device"] = cached
        return cached

    def _apply(self, fn: Any, recurse: bool = True) -> HierosPolicy:
        self.__dict__.pop("_cached_device", None)
        self.__dict__.pop("_state_template", None)
        return super()._apply(fn, recurse)

    def _all_modules(self) -> tuple[nn.Module, ...]:
        """Every module of the policy, listed once (the tree is fixed after construction; walking it costs more
        than a whole acting step of the small preset)."""
        cached = self.__dict__.get("_module_list")
        if cached is None:
            cached = tuple(self.modules())
            self.__dict__["_module_list"] = cached
        return cached

    def set_training_mode(self, mode: bool) -> None:
        """SB3's train/eval switch, skipped when every module is already in ``mode``.

        SB3 calls it on every ``predict``; reading the flags of the hierarchy's modules is several times cheaper than
        setting them all again.

        :param mode: True for training mode, False for evaluation mode
        """
        mode = bool(mode)
        for module in self._all_modules():
            if module.training != mode:
                self.train(mode)
                return

    # ------------------------------------------------------------------------------------------------ actions

    def env_actions(self, action: th.Tensor) -> np.ndarray:
        """Level-0 action vectors as environment actions.

        :param action: (n, A): one-hot (Discrete) or values in [-1, 1] (Box, A its entries flattened)
        :return: (n,) int64 indices for Discrete; (n, *shape) in the env bounds and the space's dtype for Box
        """
        if isinstance(self.action_space, spaces.Discrete):
            return action.argmax(-1).cpu().numpy().astype(np.int64)
        scaled = action.float().cpu().numpy().reshape(-1, *self.action_space.shape)
        unscaled = np.clip(self.unscale_action(scaled), self.action_space.low, self.action_space.high)
        return unscaled.astype(self.action_space.dtype)

    def action_vectors(self, env_actions: np.ndarray) -> th.Tensor:
        """Environment actions as level-0 action vectors (inverse of :meth:`env_actions`).

        :param env_actions: (n,) indices (Discrete) or (n, *shape) actions in the env bounds (Box; flattened (n, A)
            taken too)
        :return: (n, A) float on the policy's device
        """
        if isinstance(self.action_space, spaces.Discrete):
            index = th.as_tensor(np.asarray(env_actions).reshape(-1), dtype=th.long, device=self.device)
            return F.one_hot(index, int(self.action_space.n)).float()
        shape = self.action_space.shape
        actions = np.asarray(env_actions, dtype=np.float64).reshape(-1, *shape)
        scaled = self.scale_action(actions).reshape(-1, int(np.prod(shape)))
        return th.as_tensor(np.clip(scaled, -1.0, 1.0), dtype=th.float32, device=self.device)

    def random_action_vectors(self, n_envs: int) -> list[th.Tensor]:
        """Uniformly random actions for every level (warm-up before ``learning_starts``).

        Level 0 draws from ``action_space.sample()`` (seeded by SB3's ``set_random_seed``), higher levels draw
        their subgoal indices from numpy's global generator.

        :param n_envs: number of envs
        :return: per level (n, A_i) action vectors
        """
        level0 = self.action_vectors(np.array([self.action_space.sample() for _ in range(n_envs)]))
        return [level0, *self.hierarchy.random_subgoals(n_envs)]

    # ------------------------------------------------------------------------------------------------ state codec

    def state_names(self) -> list[str]:
        """Names of the arrays of the :meth:`predict` state tuple, in order.

        :return: ``["step", "level0/stoch", ..., "level1/history", ...]``
        """
        names = ["step"]
        for i in range(self.hierarchy.n_levels):
            if self.hierarchy.has_world_model(i):
                names += [f"level{i}/{f}" for f in _LATENT_FIELDS]
            names.append(f"level{i}/action")
            if i >= 1:
                names.append(f"level{i}/history")
        return names

    def _flatten(self, state: HierarchyState) -> list[th.Tensor]:
        out = [state.step]
        for i, action in enumerate(state.actions):
            if self.hierarchy.has_world_model(i):
                out += [*state.latents[i]]
            out.append(action)
            if i >= 1:
                out.append(state.histories[i - 1])
        return out

    def _unflatten(self, tensors: Sequence[th.Tensor]) -> HierarchyState:
        pos = 1
        latents, actions, histories = [], [], []
        for i in range(self.hierarchy.n_levels):
            if self.hierarchy.has_world_model(i):
                latents.append(LatentState(*tensors[pos : pos + len(_LATENT_FIELDS)]))
                pos += len(_LATENT_FIELDS)
            actions.append(tensors[pos])
            pos += 1
            if i >= 1:
                histories.append(tensors[pos])
                pos += 1
        return HierarchyState(tensors[0], tuple(latents), tuple(actions), tuple(histories))

    def state_to_numpy(self, state: HierarchyState) -> tuple[np.ndarray, ...]:
        """The state as the tuple of numpy arrays :meth:`predict` returns (order: :meth:`state_names`).

        :param state: torch state
        :return: tuple of arrays, batch on axis 0
        """
        return tuple(t.detach().cpu().numpy() for t in self._flatten(state))

    def state_from_numpy(self, state: Sequence[np.ndarray], n_envs: int) -> HierarchyState:
        """Check and convert a :meth:`predict` state tuple for a batch of ``n_envs`` observations.

        :param state: tuple of arrays in the order of :meth:`state_names`
        :param n_envs: batch size of the observation
        :return: torch state
        """
        names = self.state_names()
        if not isinstance(state, tuple | list) or len(state) != len(names):
            got = f"a {type(state).__name__} of length {len(state)}" if isinstance(state, tuple | list) else type(state)
            raise ValueError(
                f"state must be the tuple of {len(names)} arrays that predict() returned ({', '.join(names)}), "
                f"got {got}"
            )
        template = self.__dict__.get("_state_template")
        if template is None:  # cleared by _apply with the device
            template = self._flatten(self.hierarchy.initial_state(1))
            self.__dict__["_state_template"] = template
        tensors = []
        for name, value, ref in zip(names, state, template, strict=True):
            array = np.asarray(value)
            expected = (n_envs, *ref.shape[1:])
            if array.shape != expected:
                raise ValueError(
                    f"state entry {name!r} has shape {array.shape}, expected {expected} for an observation batch of "
                    f"{n_envs}"
                )
            if np.iscomplexobj(array) != ref.is_complex() or (
                not (ref.is_floating_point() or ref.is_complex()) and not np.issubdtype(array.dtype, np.integer)
            ):
                raise ValueError(f"state entry {name!r} has dtype {array.dtype}, expected {ref.dtype}")
            if np.issubdtype(array.dtype, np.inexact) and not np.isfinite(array).all():
                raise ValueError(f"state entry {name!r} contains NaN or inf; pass the state predict() returned")
            tensors.append(th.as_tensor(array, device=ref.device).to(ref.dtype))
        return self._unflatten(tensors)

    # ------------------------------------------------------------------------------------------------ acting

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        """Actions from a fresh hierarchy state (each observation taken as an episode start).

        :param observation: (n, *obs_shape) tensor or dict of tensors
        :param deterministic: no sampling
        :return: (n,) indices (Discrete) or (n, A) actions in [-1, 1] (Box, entries flattened)
        """
        n = _batch_size(observation)
        state = self.hierarchy.initial_state(n)
        state, _ = self.hierarchy.step(state, observation, th.ones(n, dtype=th.bool), deterministic)
        action = state.actions[0]
        return action.argmax(-1) if isinstance(self.action_space, spaces.Discrete) else action

    def obs_to_tensor(self, observation: np.ndarray | dict[str, np.ndarray]) -> tuple[PyTorchObs, bool]:
        """SB3's conversion (:meth:`~stable_baselines3.common.policies.BaseModel.obs_to_tensor`) of arrays of any
        memory layout: a view with negative strides, as dm_control's renders reach an env's observation, is copied
        first, since torch cannot wrap it.

        :param observation: one observation or a batch, an array or a dict of arrays
        :return: the tensor (or dict of tensors) and whether the observation was a batch
        """
        if isinstance(observation, dict):
            observation = {
                k: np.ascontiguousarray(v) if isinstance(v, np.ndarray) else v for k, v in observation.items()
            }
        elif isinstance(observation, np.ndarray):
            observation = np.ascontiguousarray(observation)
        return super().obs_to_tensor(observation)

    def predict(
        self,
        observation: np.ndarray | dict[str, np.ndarray],
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = False,
    ) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
        """Actions for a batch of observations, threading the hierarchical recurrent state (RecurrentPPO style).

        :param observation: one observation or a batch (n, *obs_shape); channel-last images are transposed
        :param state: the state tuple a previous call returned (see the module docstring), or None for a fresh state
            sized from the observation batch (every env then starts an episode)
        :param episode_start: (n,) bool, envs whose episode starts with this observation (their whole hierarchy is
            reset first); None means no starts (with a given state)
        :param deterministic: posterior and policy modes (nothing is sampled)
        :return: the actions (env bounds and dtype; batch dim dropped for a single observation) and the new state
        """
        self.set_training_mode(False)
        if isinstance(observation, tuple) and len(observation) == 2 and isinstance(observation[1], dict):
            raise ValueError(
                "You have passed a tuple to the predict() function instead of a Numpy array or a Dict. "
                "You are probably mixing Gym API with SB3 VecEnv API: `obs, info = env.reset()` (Gym) "
                "vs `obs = vec_env.reset()` (SB3 VecEnv)."
            )
        obs_tensor, vectorized_env = self.obs_to_tensor(observation)
        check_finite_observations(obs_tensor)
        n = _batch_size(obs_tensor)
        hier = self.hierarchy.initial_state(n) if state is None else self.state_from_numpy(state, n)
        starts = np.full(n, state is None)
        if episode_start is not None:
            flags = np.asarray(episode_start).reshape(-1)
            if flags.shape != (n,):
                raise ValueError(
                    f"episode_start has shape {np.shape(episode_start)}, expected ({n},) for an observation batch "
                    f"of {n}"
                )
            starts = starts | flags.astype(bool)
        hier, _ = self.hierarchy.step(hier, obs_tensor, th.as_tensor(starts), deterministic)
        actions = self.env_actions(hier.actions[0]).reshape((-1, *self.action_space.shape))
        if not vectorized_env:
            actions = actions.squeeze(axis=0)
        return actions, self.state_to_numpy(hier)

    def state_estimates(self, state: tuple[np.ndarray, ...], level: int = 0) -> dict[str, np.ndarray]:
        """What ``level`` predicts at its world state in a :meth:`predict` state: reward and continue heads and each
        critic's value (:meth:`~sb3_hieros.agent.hierarchy.Hierarchy.state_estimates`).

        :param state: a state tuple :meth:`predict` returned
        :param level: a level with a world model of its own
        :return: ``"reward"``, ``"continue"`` and ``"value/<term>"``, each (n,)
        """
        n = int(np.asarray(state[0]).shape[0]) if isinstance(state, tuple | list) and state else 0
        estimates = self.hierarchy.state_estimates(self.state_from_numpy(state, n), level)
        return {name: value.cpu().numpy() for name, value in estimates.items()}


def _features_extractor(
    extractor_class: type[BaseFeaturesExtractor] | None,
    kwargs: dict[str, Any] | None,
    normalize_images: bool,
    default_class: type[BaseFeaturesExtractor],
) -> tuple[type[BaseFeaturesExtractor] | None, dict[str, Any] | None]:
    """Check SB3's ``features_extractor_class`` / ``features_extractor_kwargs`` and return the class and keywords the
    extractor of level 0's world model is built with (None, None: HIEROS's own encoder).

    As in SB3, keywords without a class configure the policy name's default extractor (``default_class``), with a
    warning that it replaces HIEROS's encoder; SB3's ``normalized_image=True`` is added for its image extractors when
    images are not scaled.
    """
    if extractor_class is None:
        if not kwargs:
            return None, None
        extractor_class = default_class
        warnings.warn(
            f"features_extractor_kwargs={kwargs!r} without features_extractor_class: as in SB3 they configure the "
            f"policy's default extractor, so level 0's world model encodes observations with SB3's "
            f"{default_class.__name__} instead of HIEROS's own encoder (whose sizes are the config fields "
            "world_model.cnn_depth, mlp_units and mlp_layers)",
            UserWarning,
            stacklevel=4,
        )
    if not (isinstance(extractor_class, type) and issubclass(extractor_class, BaseFeaturesExtractor)):
        raise ValueError(
            f"features_extractor_class must be a stable_baselines3 BaseFeaturesExtractor subclass, got "
            f"{extractor_class!r}"
        )
    out = dict(kwargs or {})
    if not normalize_images and issubclass(extractor_class, NatureCNN | CombinedExtractor):
        out.setdefault("normalized_image", True)
    return extractor_class, out


def _batch_size(observation: PyTorchObs) -> int:
    if isinstance(observation, Mapping):
        return int(next(iter(observation.values())).shape[0])
    return int(observation.shape[0])


def _rename_flat_levels(state_dict: dict[str, Any], prefix: str, *args: Any) -> None:
    """Load-state-dict hook: entries ``levels.*`` of saves whose policy held the levels directly are read as
    ``hierarchy.levels.*``."""
    for key in [k for k in state_dict if k.startswith(prefix + "levels.")]:
        state_dict[prefix + "hierarchy." + key[len(prefix) :]] = state_dict.pop(key)


#: Policy for vector observations (the world model picks its encoders from the observation space).
MlpPolicy = HierosPolicy


class CnnPolicy(HierosPolicy):
    """:class:`HierosPolicy` under the name SB3 uses for image observations (same networks: the world model uses a
    CNN encoder/decoder for every image key)."""

    default_extractor_class = NatureCNN


class MultiInputPolicy(HierosPolicy):
    """:class:`HierosPolicy` under the name SB3 uses for Dict observations (CNNs for the image keys, one MLP over all
    vector and discrete keys)."""

    default_extractor_class = CombinedExtractor
