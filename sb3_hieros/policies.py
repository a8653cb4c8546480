"""HIEROS policy: the stack of subactors and acting with the hierarchical recurrent state (thesis 4.6.1, Algorithm 1).

:class:`HierosPolicy` is one SB3 ``BasePolicy`` holding every level of the hierarchy as an ``nn.ModuleList`` of
:class:`~sb3_hieros.agent.subactor.Subactor` (so ``policy.save`` / ``HierosPolicy.load`` and the algorithm's
``save`` / ``load`` cover all of them) and the function that advances the hierarchy by one environment step,
:meth:`HierosPolicy.hierarchy_step`, which both :meth:`HierosPolicy.predict` and the training loop of
:class:`~sb3_hieros.HIEROS` use.

One environment step (Algorithm 1), with ``k = subgoal_interval`` and a step counter t per env:

* level i **updates** env j at step t when ``t % k**i == 0`` or env j starts an episode at t (level 0 updates at
  every step). The counter is a global clock: it is not reset at episode starts, so in training all envs update
  in lock-step, and an episode start only adds an update for the env that starts;
* bottom-up: level 0 encodes o_t (``Subactor.observe_step`` with the previous action and ``is_first``); each time
  level i-1 updates an env, its world state ``[h, z]`` (``Subactor.encoded_observation``) is pushed into the k-slot
  history of level i; level i observes the concatenated history when it updates. At an episode start the history
  is zeroed before the new state is pushed, and every level's latent state is reset (``is_first``);
* top-down: an updating level acts (``Subactor.act``) with the subgoal of the level above in force (the top level
  has none); its action is held until its next update and is the subgoal of the level below. Level 0's action is
  the environment action.

Recurrent state of :meth:`HierosPolicy.predict` (the RecurrentPPO convention: a tuple of numpy arrays, batch on
axis 0, one row per env), in this order (see :meth:`HierosPolicy.state_names`):

``step`` (n,) int64, then for each level i: ``level{i}/stoch``, ``level{i}/deter``, ``level{i}/seq`` (complex64 S5
states, or the GRU state of the RSSM), ``level{i}/logits``, ``level{i}/prior_logits`` (the
:class:`~sb3_hieros.agent.world_model.LatentState` fields), ``level{i}/action`` (the action in force as a float
vector: one-hot, grouped one-hot subgoal, or Box action in [-1, 1]) and, for i >= 1, ``level{i}/history``
(n, k, D_{i-1}), the last k world states of level i-1.

Ablations (thesis 5.3, ``docs/ablations.md``): with ``higher_level_input="last"`` (5.3.6) a level observes only the
newest state of its history; with ``hierarchical_world_models=False`` (5.3.1) the levels i >= 1 are
:class:`~sb3_hieros.agent.shared.SharedLevel` without world models, their history holds the last ``k**i`` world
states of level 0 and the state tuple has no ``level{i}/stoch`` ... ``level{i}/prior_logits`` entries for them; with
``update_subgoals_in_imagination=True`` (5.3.9) every level below the top gets an :class:`ImaginationSubgoals`.

``MlpPolicy``, ``CnnPolicy`` and ``MultiInputPolicy`` are the same class under the names SB3 and rl-zoo expect: the
world model picks a CNN for every image key and a symlog MLP for the vector keys of any observation space.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np
import torch as th
import torch.nn.functional as F
from gymnasium import spaces
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from torch import nn

from sb3_hieros.agent.shared import SharedLevel
from sb3_hieros.agent.subactor import Subactor
from sb3_hieros.agent.world_model import LatentState
from sb3_hieros.config import (
    ActorCriticConfig,
    HierosConfig,
    ReferenceCompatConfig,
    SubgoalConfig,
    WorldModelConfig,
    get_preset,
)

__all__ = [
    "CnnPolicy",
    "HierarchyState",
    "HierarchyStep",
    "HierosPolicy",
    "ImaginationSubgoals",
    "MlpPolicy",
    "MultiInputPolicy",
    "check_action_space",
    "check_finite_observations",
    "check_observation_space",
    "config_from_dict",
]

_LATENT_FIELDS = LatentState._fields  # ("stoch", "deter", "seq", "logits", "prior_logits")


def check_observation_space(observation_space: spaces.Space) -> None:
    """Raise ``ValueError`` unless HIEROS supports the observation space: a ``Box`` (vector, or a channel-first
    uint8 image) or a ``Dict`` of such Boxes.

    :param observation_space: the (possibly image-transposed) observation space
    """
    if isinstance(observation_space, spaces.Dict):
        if len(observation_space.spaces) == 0:
            raise ValueError("observation_space is an empty Dict space; HIEROS needs at least one Box entry")
        for key, sub in observation_space.spaces.items():
            if not isinstance(sub, spaces.Box):
                raise ValueError(
                    f"observation_space[{key!r}] is {sub}; HIEROS supports Dict observation spaces whose entries are "
                    "all Box spaces (vectors or images)"
                )
        return
    if not isinstance(observation_space, spaces.Box):
        raise ValueError(
            f"observation space {observation_space} ({type(observation_space).__name__}) is not supported by HIEROS; "
            "supported: Box (vectors or images) and Dict of Boxes"
        )


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


def config_from_dict(config: Mapping[str, Any] | HierosConfig | None) -> HierosConfig:
    """A :class:`HierosConfig` from its ``dataclasses.asdict`` form (what the policy saves), or the paper preset.

    :param config: a HierosConfig, a dict of its fields (nested sections as dicts), or None for the ``"paper"`` preset
    :return: the configuration
    """
    if config is None:
        return get_preset("paper")
    if isinstance(config, HierosConfig):
        return config
    if not isinstance(config, Mapping):
        raise ValueError(f"config must be a HierosConfig, a dict of its fields or None, got {type(config).__name__}")
    sections = {
        "world_model": WorldModelConfig,
        "actor_critic": ActorCriticConfig,
        "subgoal": SubgoalConfig,
        "reference": ReferenceCompatConfig,
    }
    names = {f.name for f in dataclasses.fields(HierosConfig)}
    unknown = set(config) - names
    if unknown:
        raise ValueError(f"config has unknown fields {sorted(unknown)}; expected some of {sorted(names)}")
    values = dict(config)
    for name, cls in sections.items():
        if name in values and isinstance(values[name], Mapping):
            values[name] = cls(**values[name])
    return HierosConfig(**values)


class HierarchyState(NamedTuple):
    """Recurrent state of the whole hierarchy for n envs (torch tensors on the policy's device).

    :param step: (n,) int64 step counter (global clock, see the module docstring)
    :param latents: per level with a world model of its own, the world state (batch (n,)); only level 0's with
        ``hierarchical_world_models=False`` (ablation 5.3.1)
    :param actions: per level, (n, A_i) float action in force (level 0: environment action vector)
    :param histories: per level i >= 1 (at index i - 1), (n, k, D_{i-1}) last k world states of level i - 1, or
        (n, k**i, D_0) last k**i world states of level 0 with ``hierarchical_world_models=False``
    """

    step: th.Tensor
    latents: tuple[LatentState, ...]
    actions: tuple[th.Tensor, ...]
    histories: tuple[th.Tensor, ...]

    @property
    def n_envs(self) -> int:
        """Number of envs (batch size)."""
        return int(self.step.shape[0])


class HierarchyStep(NamedTuple):
    """What one :meth:`HierosPolicy.hierarchy_step` did, for the replay bookkeeping of the training loop.

    :param updated: per level, (n,) bool: the level observed and acted for that env at this step
    :param prev_actions: per level, (n, A_i) the action in force before this step (the one that led to the
        observation of an updating level)
    """

    updated: tuple[th.Tensor, ...]
    prev_actions: tuple[th.Tensor, ...]


def _scatter(old: th.Tensor, index: th.Tensor | None, new: th.Tensor) -> th.Tensor:
    """``old`` with rows ``index`` replaced by ``new`` (all rows if ``index`` is None)."""
    return new if index is None else old.index_copy(0, index, new)


def _scatter_state(old: LatentState, index: th.Tensor | None, new: LatentState) -> LatentState:
    return new if index is None else LatentState(*(_scatter(o, index, x) for o, x in zip(old, new, strict=True)))


def _take(x: th.Tensor, index: th.Tensor | None) -> th.Tensor:
    """Rows ``index`` of ``x`` (all rows if ``index`` is None)."""
    return x if index is None else x[index]


def _rows(state: LatentState, index: th.Tensor | None) -> LatentState:
    return state if index is None else state.select(index)


class ImaginationSubgoals:
    """Subgoals re-planned during level i's imagination by the levels above (ablation 5.3.9).

    Installed as ``Subactor.imagination_subgoal_fn`` of every level below the top when
    ``update_subgoals_in_imagination=True``. Level i calls it every k imagined steps with the last k imagined world
    states; level i+1 encodes them (``higher_level_observation``) with its own world model, carrying its latent
    state from call to call within one rollout (the first call starts it like an episode start), and acts. A level
    i+1 below the top needs a subgoal of its own: at the first call of a rollout, level i+2 proposes one from a window
    that holds only level i+1's first state (episode-start semantics), recursively up to the top, and it is held for
    the rest of the rollout (with the thesis' k=4 and horizon 16, level i+2 would act at most once in that time).

    :param levels: all levels of the policy
    :param level: the level i whose imagination asks for subgoals (``i < n_levels - 1``)
    :param higher_level_input: ``"all"`` or ``"last"`` (ablation 5.3.6), as the policy observes
    """

    def __init__(self, levels: Sequence[Subactor], level: int, higher_level_input: str) -> None:
        if not 0 <= level < len(levels) - 1:
            raise ValueError(f"level must lie in [0, {len(levels) - 1}) (a level with a level above), got {level}")
        self.levels = levels
        self.level = level
        self.last_only = higher_level_input == "last"

    def _observation(self, window: th.Tensor) -> th.Tensor:
        return window[:, -1] if self.last_only else window.reshape(window.shape[0], -1)

    def _propose_fresh(self, level: int, encoded_below: th.Tensor) -> th.Tensor:
        """Subgoal of ``level`` from a window holding only ``encoded_below`` (n, D) (its slots before are empty)."""
        upper = self.levels[level]
        n = encoded_below.shape[0]
        k = upper.config.subgoal_interval
        window = encoded_below.new_zeros(n, k, encoded_below.shape[-1])
        window[:, -1] = encoded_below
        first = th.ones(n, dtype=th.bool, device=encoded_below.device)
        prev = encoded_below.new_zeros(n, upper.action_dim)
        state = upper.observe_step(None, self._observation(window), prev, first)
        goal = None
        if level < len(self.levels) - 1:
            goal = self._propose_fresh(level + 1, upper.encoded_observation(state))
        return upper.act(state, goal)

    @th.no_grad()
    def __call__(self, window: th.Tensor, subgoal: th.Tensor, carry: Any) -> tuple[th.Tensor, Any]:
        """Next subgoal for level i.

        :param window: (N, k, D_i + Z_i) the last k imagined world states of level i, oldest first
        :param subgoal: (N, S) the subgoal code in force (level i+1's previous action)
        :param carry: None at the first call of a rollout, else what the previous call returned
        :return: the new (N, S) subgoal code and the carry (level i+1's latent state, its own subgoal)
        """
        upper = self.levels[self.level + 1]
        n = window.shape[0]
        first = carry is None
        state_before = None if first else carry[0]
        is_first = th.full((n,), first, dtype=th.bool, device=window.device)
        state = upper.observe_step(state_before, self._observation(window), subgoal, is_first)
        if first:
            own_goal = None
            if self.level + 2 < len(self.levels):
                own_goal = self._propose_fresh(self.level + 2, upper.encoded_observation(state))
        else:
            own_goal = carry[1]
        return upper.act(state, own_goal), (state, own_goal)


class HierosPolicy(BasePolicy):
    """All levels of HIEROS (thesis 4.3, Figure 4.2) and acting with the hierarchical recurrent state.

    :param observation_space: observation space (Box vector, channel-first uint8 image Box, or Dict of Boxes)
    :param action_space: ``Discrete`` or 1-d ``Box`` action space
    :param lr_schedule: learning-rate schedule (unused by the policy: :class:`~sb3_hieros.HIEROS` sets the world
        models' learning rate; kept for the SB3 policy signature)
    :param config: the resolved :class:`~sb3_hieros.config.HierosConfig` or its ``dataclasses.asdict`` dict; None
        for the ``"paper"`` preset
    :param decoded_subgoal_input: feed the actors the decoded subgoal instead of its code (ablation 5.3.8)
    :param bf16: bfloat16 autocast opt-in of the world models
    :param compile: ``torch.compile`` opt-in of the world models' sequence models
    :param normalize_images: kept for the SB3 signature; images are always scaled by the world model (uint8 ->
        x/255 - 0.5), so only True is accepted
    """

    levels: nn.ModuleList

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        lr_schedule: Schedule,
        config: Mapping[str, Any] | HierosConfig | None = None,
        decoded_subgoal_input: bool = False,
        bf16: bool = False,
        compile: bool = False,
        normalize_images: bool = True,
    ) -> None:
        check_observation_space(observation_space)
        check_action_space(action_space)
        if not normalize_images:
            raise ValueError(
                "normalize_images=False is not supported: the HIEROS world model scales uint8 images itself and "
                "treats float observations as vectors"
            )
        super().__init__(
            observation_space,
            action_space,
            normalize_images=normalize_images,
            squash_output=isinstance(action_space, spaces.Box),
        )
        self.config = config_from_dict(config)
        if decoded_subgoal_input and self.config.n_levels == 1:
            raise ValueError(
                "decoded_subgoal_input=True needs a hierarchy (n_levels >= 2): with one level there is no subgoal"
            )
        #: ablation 5.3.8; the policy keyword is an alias of ``HierosConfig.decoded_subgoal_input``
        self.decoded_subgoal_input = bool(decoded_subgoal_input) or self.config.decoded_subgoal_input
        self.bf16 = bool(bf16)
        self.compile = bool(compile)
        self.n_levels = self.config.n_levels
        self.subgoal_interval = self.config.subgoal_interval
        #: ablation 5.3.1 when False: one world model (level 0's) for all levels
        self.hierarchical_world_models = self.config.hierarchical_world_models
        #: ablation 5.3.6 when ``"last"``: a higher level observes only the newest of its window of lower states
        self.higher_level_input = self.config.higher_level_input
        levels: list[Subactor | SharedLevel] = []
        for i in range(self.n_levels):
            below = levels[-1] if levels else None
            if below is not None and not self.hierarchical_world_models:
                level0 = levels[0]
                assert isinstance(level0, Subactor)
                levels.append(
                    SharedLevel(
                        level0.latent_dim,
                        level0.h_dim,
                        level0.z_dim,
                        self.history_length(i) if self.higher_level_input == "all" else 1,
                        self.config,
                        level=i,
                        subgoal_input=i < self.n_levels - 1,
                        decoded_subgoal_input=self.decoded_subgoal_input,
                    )
                )
                continue
            if below is not None:
                assert isinstance(below, Subactor)
                window = self.subgoal_interval if self.higher_level_input == "all" else 1
            levels.append(
                Subactor(
                    observation_space if below is None else below.higher_level_observation_space(window),
                    action_space if below is None else below.subgoal_space(),
                    self.config,
                    level=i,
                    subgoal_input=i < self.n_levels - 1,
                    decoded_subgoal_input=self.decoded_subgoal_input,
                    bf16=self.bf16,
                    compile=self.compile,
                )
            )
        self.levels = nn.ModuleList(levels)
        if self.config.update_subgoals_in_imagination:  # ablation 5.3.9
            for i in range(self.n_levels - 1):
                self.subactor(i).imagination_subgoal_fn = ImaginationSubgoals(self.levels, i, self.higher_level_input)
        #: the level-0 world-model optimiser under SB3's conventional name (``load`` falls back on ``policy.optimizer``)
        self.optimizer = self.levels[0].wm_optimizer

    # ------------------------------------------------------------------------------------------------ SB3 plumbing

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            lr_schedule=self._dummy_schedule,
            config=dataclasses.asdict(self.config),
            decoded_subgoal_input=self.decoded_subgoal_input,
            bf16=self.bf16,
            compile=self.compile,
        )
        return data

    def optimizer_names(self) -> list[str]:
        """Attribute paths (relative to the policy) of every optimiser, ``"optimizer"`` (level-0 world model) first.

        :return: e.g. ``["optimizer", "levels.0.actor_optimizer", ...]``
        """
        names = ["optimizer"]
        for i in range(self.n_levels):
            attrs = ("actor_optimizer", "critic_optimizer", "ae_optimizer")
            own_world_model = i > 0 and self.has_world_model(i)
            names += [f"levels.{i}.{a}" for a in (("wm_optimizer", *attrs) if own_world_model else attrs)]
        return names

    def subactor(self, level: int) -> Subactor:
        """The :class:`Subactor` of ``level`` (0 = acts in the environment); with ``hierarchical_world_models=False``
        the levels i >= 1 are :class:`~sb3_hieros.agent.shared.SharedLevel` (no world model).

        :param level: index in ``[0, n_levels)``
        :return: the subactor
        """
        return self.levels[level]  # type: ignore[return-value]

    def has_world_model(self, level: int) -> bool:
        """Whether ``level`` has a world model of its own (all levels, or only level 0 for ablation 5.3.1).

        :param level: index in ``[0, n_levels)``
        :return: True for a :class:`Subactor`
        """
        return level == 0 or self.hierarchical_world_models

    def history_length(self, level: int) -> int:
        """Number of lower world states level ``level`` >= 1 keeps: k of level i-1 (hierarchical world models) or
        ``k**level`` of level 0 (one shared world model, ablation 5.3.1).

        :param level: index in ``[1, n_levels)``
        :return: slots of ``HierarchyState.histories[level - 1]``
        """
        return self.subgoal_interval if self.hierarchical_world_models else self.subgoal_interval**level

    def higher_level_observation(self, history: th.Tensor) -> th.Tensor:
        """What a higher level observes of its history of lower world states (thesis 4.3; ablation 5.3.6).

        :param history: (n, w, D) lower world states, oldest first
        :return: (n, w * D) all of them concatenated (``higher_level_input="all"``) or (n, D), the newest (``"last"``)
        """
        if history.dim() != 3:
            raise ValueError(f"history must have shape (n, w, D), got {tuple(history.shape)}")
        if self.higher_level_input == "last":
            return history[:, -1]
        return history.reshape(history.shape[0], -1)

    # ------------------------------------------------------------------------------------------------ actions

    def env_actions(self, action: th.Tensor) -> np.ndarray:
        """Level-0 action vectors as environment actions.

        :param action: (n, A): one-hot (Discrete) or values in [-1, 1] (Box)
        :return: (n,) int64 indices for Discrete; (n, *shape) in the env bounds and the space's dtype for Box
        """
        if isinstance(self.action_space, spaces.Discrete):
            return action.argmax(-1).cpu().numpy().astype(np.int64)
        scaled = action.float().cpu().numpy()
        unscaled = np.clip(self.unscale_action(scaled), self.action_space.low, self.action_space.high)
        return unscaled.astype(self.action_space.dtype)

    def action_vectors(self, env_actions: np.ndarray) -> th.Tensor:
        """Environment actions as level-0 action vectors (inverse of :meth:`env_actions`).

        :param env_actions: (n,) indices (Discrete) or (n, *shape) actions in the env bounds (Box)
        :return: (n, A) float on the policy's device
        """
        if isinstance(self.action_space, spaces.Discrete):
            index = th.as_tensor(np.asarray(env_actions).reshape(-1), dtype=th.long, device=self.device)
            return F.one_hot(index, int(self.action_space.n)).float()
        scaled = self.scale_action(np.asarray(env_actions, dtype=np.float64)).reshape(-1, self.action_space.shape[0])
        return th.as_tensor(np.clip(scaled, -1.0, 1.0), dtype=th.float32, device=self.device)

    def subgoal_indices(self, level: int, action: th.Tensor) -> np.ndarray:
        """Actions (subgoals) of a level i >= 1 as ``MultiDiscrete`` indices, the form its replay stores.

        :param level: i >= 1
        :param action: (n, n_cat * n_classes) grouped one-hot
        :return: (n, n_cat) int64
        """
        sub = self.subactor(level)
        return action.reshape(-1, sub.action_groups, sub.action_classes).argmax(-1).cpu().numpy().astype(np.int64)

    def random_action_vectors(self, n_envs: int) -> list[th.Tensor | None]:
        """Uniformly random actions for every level (warm-up before ``learning_starts``).

        Level 0 draws from ``action_space.sample()`` (seeded by SB3's ``set_random_seed``), higher levels draw
        their subgoal indices from numpy's global generator.

        :param n_envs: number of envs
        :return: per level (n, A_i) action vectors
        """
        vectors: list[th.Tensor | None] = [
            self.action_vectors(np.array([self.action_space.sample() for _ in range(n_envs)]))
        ]
        for level in self.levels[1:]:
            index = np.random.randint(0, level.action_classes, size=(n_envs, level.action_groups))  # noqa: NPY002
            one_hot = F.one_hot(th.as_tensor(index, device=self.device), level.action_classes).float()
            vectors.append(one_hot.reshape(n_envs, level.action_dim))
        return vectors

    # ------------------------------------------------------------------------------------------------ state

    def initial_hierarchy_state(self, n_envs: int) -> HierarchyState:
        """Fresh state for ``n_envs`` envs (every env starts an episode at its next step).

        :param n_envs: batch size
        :return: zero state, step counters 0
        """
        if isinstance(n_envs, bool) or not isinstance(n_envs, int | np.integer) or n_envs < 1:
            raise ValueError(f"n_envs must be a positive int, got {n_envs!r}")
        n = int(n_envs)
        device = self.device
        own = [i for i in range(self.n_levels) if self.has_world_model(i)]
        latents = tuple(self.subactor(i).initial_state(n) for i in own)
        actions = tuple(th.zeros(n, level.action_dim, device=device) for level in self.levels)
        histories = tuple(
            th.zeros(n, self.history_length(i), self._history_dim(i), device=device) for i in range(1, self.n_levels)
        )
        return HierarchyState(th.zeros(n, dtype=th.long, device=device), latents, actions, histories)

    def _history_dim(self, level: int) -> int:
        """Size of one world state in the history of ``level`` >= 1 (level i-1's, or level 0's when shared)."""
        return self.subactor(level - 1 if self.hierarchical_world_models else 0).latent_dim

    def state_names(self) -> list[str]:
        """Names of the arrays of the :meth:`predict` state tuple, in order.

        :return: ``["step", "level0/stoch", ..., "level1/history", ...]``
        """
        names = ["step"]
        for i in range(self.n_levels):
            if self.has_world_model(i):
                names += [f"level{i}/{f}" for f in _LATENT_FIELDS]
            names.append(f"level{i}/action")
            if i >= 1:
                names.append(f"level{i}/history")
        return names

    def _flatten(self, state: HierarchyState) -> list[th.Tensor]:
        out = [state.step]
        for i, action in enumerate(state.actions):
            if self.has_world_model(i):
                out += [*state.latents[i]]
            out.append(action)
            if i >= 1:
                out.append(state.histories[i - 1])
        return out

    def _unflatten(self, tensors: Sequence[th.Tensor]) -> HierarchyState:
        pos = 1
        latents, actions, histories = [], [], []
        for i in range(self.n_levels):
            if self.has_world_model(i):
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
        template = self._flatten(self.initial_hierarchy_state(1))
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
            tensors.append(th.as_tensor(array, device=self.device).to(ref.dtype))
        return self._unflatten(tensors)

    # ------------------------------------------------------------------------------------------------ acting

    def _update_mask(self, step: th.Tensor, is_first: th.Tensor, level: int) -> th.Tensor:
        """(n,) bool: level ``level`` updates an env when ``step % k**level == 0`` or the env starts an episode."""
        if level == 0:
            return th.ones_like(is_first)
        return ((step % self.subgoal_interval**level) == 0) | is_first

    @staticmethod
    def _index(mask: th.Tensor) -> th.Tensor | None:
        """Row indices of ``mask``; None when all rows are set (no gather/scatter needed)."""
        return None if bool(mask.all()) else mask.nonzero().squeeze(1)

    @th.no_grad()
    def hierarchy_step(
        self,
        state: HierarchyState,
        observation: PyTorchObs,
        is_first: th.Tensor,
        deterministic: bool = False,
        random_actions: Sequence[th.Tensor | None] | None = None,
    ) -> tuple[HierarchyState, HierarchyStep]:
        """Advance the hierarchy by one environment step (Algorithm 1): encode bottom-up, act top-down.

        :param state: state before the step (batch (n,))
        :param observation: o_t as a tensor (n, *obs_shape) or a dict of them (channel-first images)
        :param is_first: (n,) bool, envs whose episode starts with o_t (their whole hierarchy is reset)
        :param deterministic: posterior modes and policy modes instead of samples (nothing is sampled)
        :param random_actions: per level (n, A_i) action vectors to take instead of the actors' (warm-up), or None
        :return: the new state (``state.actions[0]`` is the environment action vector) and what was updated
        """
        n = state.n_envs
        is_first = is_first.to(device=self.device, dtype=th.bool).reshape(n)
        if not self.hierarchical_world_models:
            return self._shared_hierarchy_step(state, observation, is_first, deterministic, random_actions)
        masks = tuple(self._update_mask(state.step, is_first, i) for i in range(self.n_levels))
        latents = list(state.latents)
        actions = list(state.actions)
        histories = list(state.histories)

        # bottom-up: encode (Algorithm 1 lines 11-19)
        latents[0] = self.subactor(0).observe_step(latents[0], observation, actions[0], is_first, deterministic)
        for i in range(1, self.n_levels):
            below = self.subactor(i - 1)
            history = histories[i - 1] * (~is_first).to(histories[i - 1].dtype).reshape(n, 1, 1)  # (n, k, D)
            lower = masks[i - 1]
            if bool(lower.any()):
                pushed = th.cat([history[:, 1:], below.encoded_observation(latents[i - 1]).unsqueeze(1)], 1)
                history = th.where(lower.reshape(n, 1, 1), pushed, history)
            histories[i - 1] = history
            if not bool(masks[i].any()):
                continue
            index = self._index(masks[i])
            obs_i = self.higher_level_observation(history)
            new = self.subactor(i).observe_step(
                _rows(latents[i], index),
                obs_i if index is None else obs_i[index],
                actions[i] if index is None else actions[i][index],
                is_first if index is None else is_first[index],
                deterministic,
            )
            latents[i] = _scatter_state(latents[i], index, new)

        # top-down: act (Algorithm 1 lines 21-29)
        prev_actions = tuple(actions)
        for i in reversed(range(self.n_levels)):
            if not bool(masks[i].any()):
                continue
            index = self._index(masks[i])
            chosen = random_actions[i] if random_actions is not None else None
            if chosen is None:
                goal = None if i == self.n_levels - 1 else actions[i + 1]  # subgoal in force from above
                if goal is not None and index is not None:
                    goal = goal[index]
                chosen = self.subactor(i).act(_rows(latents[i], index), goal, deterministic)
            elif index is not None:
                chosen = chosen[index]
            actions[i] = _scatter(actions[i], index, chosen.to(actions[i].dtype))

        new_state = HierarchyState(state.step + 1, tuple(latents), tuple(actions), tuple(histories))
        return new_state, HierarchyStep(masks, prev_actions)

    def _shared_hierarchy_step(
        self,
        state: HierarchyState,
        observation: PyTorchObs,
        is_first: th.Tensor,
        deterministic: bool,
        random_actions: Sequence[th.Tensor | None] | None,
    ) -> tuple[HierarchyState, HierarchyStep]:
        """:meth:`hierarchy_step` with one world model (ablation 5.3.1): level 0 encodes o_t, every level i >= 1
        pushes level 0's world state into its window of the last ``k**i`` of them and acts every ``k**i`` steps."""
        n = state.n_envs
        masks = tuple(self._update_mask(state.step, is_first, i) for i in range(self.n_levels))
        level0 = self.subactor(0)
        latent = level0.observe_step(state.latents[0], observation, state.actions[0], is_first, deterministic)
        newest = level0.encoded_observation(latent).unsqueeze(1)  # (n, 1, D + G*K)
        keep = (~is_first).to(newest.dtype).reshape(n, 1, 1)
        histories = tuple(th.cat([h[:, 1:] * keep, newest], 1) for h in state.histories)
        wm = level0.world_model
        reward, cont, entropy = wm.reward(latent), wm.cont(latent), wm.prior_entropy(latent)
        prev_actions = tuple(state.actions)
        actions = list(state.actions)
        for i in reversed(range(self.n_levels)):
            if not bool(masks[i].any()):
                continue
            index = self._index(masks[i])
            chosen = random_actions[i] if random_actions is not None else None
            if chosen is None:
                goal = None if i == self.n_levels - 1 else _take(actions[i + 1], index)
                if i == 0:
                    chosen = level0.act(_rows(latent, index), goal, deterministic)
                else:
                    level = self.levels[i]
                    assert isinstance(level, SharedLevel)
                    window = _take(self.higher_level_observation(histories[i - 1]), index)
                    extras = (_take(x, index) for x in (reward, cont, entropy))
                    chosen = level.act(window, *extras, goal, deterministic)
            elif index is not None:
                chosen = chosen[index]
            actions[i] = _scatter(actions[i], index, chosen.to(actions[i].dtype))
        new_state = HierarchyState(state.step + 1, (latent,), tuple(actions), histories)
        return new_state, HierarchyStep(masks, prev_actions)

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
        return super()._apply(fn, recurse)

    def set_training_mode(self, mode: bool) -> None:
        """SB3's train/eval switch, skipped when every module is already in ``mode``.

        SB3 calls it on every ``predict``; reading the flags of the hierarchy's modules is several times cheaper than
        setting them all again.

        :param mode: True for training mode, False for evaluation mode
        """
        if any(module.training != bool(mode) for module in self.modules()):
            self.train(mode)

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        """Actions from a fresh hierarchy state (each observation taken as an episode start).

        :param observation: (n, *obs_shape) tensor or dict of tensors
        :param deterministic: no sampling
        :return: (n,) indices (Discrete) or (n, A) actions in [-1, 1] (Box)
        """
        n = _batch_size(observation)
        state = self.initial_hierarchy_state(n)
        state, _ = self.hierarchy_step(state, observation, th.ones(n, dtype=th.bool, device=self.device), deterministic)
        action = state.actions[0]
        return action.argmax(-1) if isinstance(self.action_space, spaces.Discrete) else action

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
        if state is None:
            hier = self.initial_hierarchy_state(n)
            starts = np.ones(n, dtype=bool)
        else:
            hier = self.state_from_numpy(state, n)
            starts = np.zeros(n, dtype=bool)
        if episode_start is not None:
            flags = np.asarray(episode_start).reshape(-1)
            if flags.shape != (n,):
                raise ValueError(
                    f"episode_start has shape {np.shape(episode_start)}, expected ({n},) for an observation batch "
                    f"of {n}"
                )
            starts = starts | flags.astype(bool)
        with th.no_grad():
            hier, _ = self.hierarchy_step(hier, obs_tensor, th.as_tensor(starts, device=self.device), deterministic)
        actions = self.env_actions(hier.actions[0]).reshape((-1, *self.action_space.shape))
        if not vectorized_env:
            actions = actions.squeeze(axis=0)
        return actions, self.state_to_numpy(hier)


def _batch_size(observation: PyTorchObs) -> int:
    if isinstance(observation, Mapping):
        return int(next(iter(observation.values())).shape[0])
    return int(observation.shape[0])


#: Policy for vector observations (the world model picks its encoders from the observation space).
MlpPolicy = HierosPolicy


class CnnPolicy(HierosPolicy):
    """:class:`HierosPolicy` under the name SB3 uses for image observations (same networks: the world model uses a
    CNN encoder/decoder for every image key)."""


class MultiInputPolicy(HierosPolicy):
    """:class:`HierosPolicy` under the name SB3 uses for Dict observations (CNNs for the image keys, one symlog MLP
    over all vector keys)."""
