"""The HIEROS hierarchy: its levels and the walks over them (thesis 4.3, Figure 4.2; Algorithms 1 and 2).

:class:`Hierarchy` owns the levels (one :class:`~sb3_hieros.agent.subactor.Subactor` each) and everything that
involves more than one of them:

* :meth:`~Hierarchy.step`, one environment step (Algorithm 1): encode bottom-up, act top-down;
* :meth:`~Hierarchy.update_rows` and :meth:`~Hierarchy.encode_terminal`, the replay rows of the levels above 0;
* :meth:`~Hierarchy.train_step`, one update (Algorithm 2 for every level that is due), with the subgoal updates of the
  levels above during imagination (:meth:`~Hierarchy.replan`, ablation 5.3.9);
* :meth:`~Hierarchy.decode_subgoals`, the subgoals of every level shown in the environment's observation space.

One environment step, with ``k = subgoal_interval`` and a step counter t per env: level i **updates** env j when
``t % k**i == 0`` or env j starts an episode at t (level 0 at every step). The counter is a global clock, not reset at
episode starts, so in training all envs update in lock-step and an episode start only adds an update for the env that
starts. Bottom-up, level 0 encodes o_t; each time level i-1 updates an env, its world state ``[h, z]`` is pushed into
the k-slot history of level i, which observes the concatenated history (or its newest entry, ablation 5.3.6) when it
updates. At an episode start the history is zeroed before the new state is pushed and every level's latent state is
reset. Top-down, an updating level acts with the subgoal of the level above in force (the top level has none); its
action is held until its next update and is the subgoal of the level below. Level 0's action is the environment
action.

The ablation with one shared world model (5.3.1) is the subclass
:class:`~sb3_hieros.agent.shared.SharedWorldModelHierarchy`; :func:`make_hierarchy` picks the class.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np
import torch as th
import torch.nn.functional as F
from gymnasium import spaces
from torch import nn

from sb3_hieros.agent.subactor import Replan, Subactor
from sb3_hieros.agent.world_model import LatentState
from sb3_hieros.config import HierosConfig
from sb3_hieros.nn.networks import evaluation_mode
from sb3_hieros.type_aliases import LevelRows, LevelUpdate, Observation, SequenceSamples

__all__ = ["Hierarchy", "HierarchyState", "HierarchyStep"]


class HierarchyState(NamedTuple):
    """Recurrent state of the whole hierarchy for n envs.

    :param step: (n,) int64 step counter (the global clock of the module docstring), always on the CPU
    :param latents: per level with a world model of its own, the world state (batch (n,)) on the model's device
    :param actions: per level, (n, A_i) float action in force (level 0: environment action vector)
    :param histories: per level i >= 1 (at index i - 1), (n, w_i, D) the last world states the level observes
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
    """What one :meth:`Hierarchy.step` did, for the replay rows of the levels above 0.

    :param updated: per level, (n,) bool on the CPU: the level observed and acted for that env at this step
    :param prev_actions: per level, (n, A_i) the action in force before this step (the one that led to the
        observation of an updating level)
    """

    updated: tuple[th.Tensor, ...]
    prev_actions: tuple[th.Tensor, ...]


#: per level, (n,) bool on the CPU: which envs the level updates at this step
Masks = tuple[th.Tensor, ...]
#: what the bottom-up half of a step produced: latent states, histories, and what acting needs besides
Encoded = tuple[tuple[LatentState, ...], tuple[th.Tensor, ...], Any]


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


class Hierarchy(nn.Module):
    """All levels of HIEROS (thesis 4.3) and the walks over them; see the module docstring.

    :param observation_space: the environment's (checked, image-transposed) observation space
    :param action_space: the environment's (checked) action space
    :param config: the resolved configuration
    :param world_model_options: ``bf16`` and ``compile`` opt-ins of the world models, and level 0's
        ``observation_options`` (:class:`~sb3_hieros.agent.world_model.ObservationOptions`)
    """

    levels: nn.ModuleList

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        config: HierosConfig,
        **world_model_options: Any,
    ) -> None:
        super().__init__()
        self.config = config
        self.n_levels = config.n_levels
        self.subgoal_interval = config.subgoal_interval
        #: ablation 5.3.6: a higher level observes only the newest of its window of lower states
        self.last_state_only = config.higher_level_input == "last"
        self.levels = nn.ModuleList(self._build_levels(observation_space, action_space, world_model_options))

    def _build_levels(
        self, observation_space: spaces.Space, action_space: spaces.Space, options: dict[str, Any]
    ) -> list[nn.Module]:
        """Level 0 on the environment's spaces, level i on the subgoal space and the stacked states of level i-1."""
        levels: list[Subactor] = []
        window = 1 if self.last_state_only else self.subgoal_interval
        higher = {name: value for name, value in options.items() if name != "observation_options"}
        for i in range(self.n_levels):
            below = levels[-1] if levels else None
            levels.append(
                Subactor(
                    observation_space if below is None else below.higher_level_observation_space(window),
                    action_space if below is None else below.subgoal_space(),
                    self.config,
                    level=i,
                    subgoal_input=i < self.n_levels - 1,
                    decoded_subgoal_input=self.config.decoded_subgoal_input,
                    **(options if below is None else higher),
                )
            )
        return list(levels)

    # ------------------------------------------------------------------------------------------------ layout

    @property
    def device(self) -> th.device:
        """The device of the parameters."""
        return self.levels[0].world_model.device

    @property
    def replay_levels(self) -> int:
        """Number of levels with a replay of their own (levels 0 .. replay_levels - 1)."""
        return self.n_levels

    def has_world_model(self, level: int) -> bool:
        """Whether ``level`` has a world model (and a latent state) of its own.

        :param level: index in ``[0, n_levels)``
        :return: True for every level here
        """
        return True

    def history_length(self, level: int) -> int:
        """Number of lower world states level ``level`` >= 1 keeps (k).

        :param level: index in ``[1, n_levels)``
        :return: slots of ``HierarchyState.histories[level - 1]``
        """
        return self.subgoal_interval

    def _history_dim(self, level: int) -> int:
        """Size of one world state in the history of ``level`` >= 1."""
        return self.levels[level - 1].latent_dim

    def observation_window(self, history: th.Tensor) -> th.Tensor:
        """What a higher level observes of its window of lower world states (thesis 4.3; ablation 5.3.6).

        :param history: (n, w, D) lower world states, oldest first
        :return: (n, w * D) all of them concatenated, or (n, D) the newest with ``higher_level_input="last"``
        """
        return history[:, -1] if self.last_state_only else history.reshape(history.shape[0], -1)

    def optimizer_names(self) -> list[str]:
        """Attribute paths (relative to the hierarchy) of every optimiser, level 0's world model first.

        :return: e.g. ``["levels.0.wm_optimizer", "levels.0.actor_optimizer", ...]``
        """
        names = []
        for i in range(self.n_levels):
            attrs = ("actor_optimizer", "critic_optimizer", "ae_optimizer")
            names += [f"levels.{i}.{a}" for a in (("wm_optimizer", *attrs) if self.has_world_model(i) else attrs)]
        return names

    def use_optimizer(
        self, optimizer_class: type[th.optim.Optimizer] | None, optimizer_kwargs: dict[str, Any] | None
    ) -> None:
        """Every optimiser of every level under SB3's ``optimizer_class`` / ``optimizer_kwargs`` (the policy
        keywords): learning rates, epsilons and which parameters decay stay those of the configuration unless the
        keywords say otherwise (:func:`~sb3_hieros.nn.optim.user_optimizer`).

        :param optimizer_class: a ``torch.optim.Optimizer`` subclass, or None for AdamW
        :param optimizer_kwargs: its keywords (not ``lr``), or None
        """
        for level in self.levels:
            level.use_optimizer(optimizer_class, optimizer_kwargs)

    # ------------------------------------------------------------------------------------------------ acting

    def initial_state(self, n_envs: int) -> HierarchyState:
        """Fresh state for ``n_envs`` envs (every env starts an episode at its next step).

        :param n_envs: batch size
        :return: zero state, step counters 0
        """
        device = self.device
        own = [i for i in range(self.n_levels) if self.has_world_model(i)]
        latents = tuple(self.levels[i].initial_state(n_envs) for i in own)
        actions = tuple(th.zeros(n_envs, level.action_dim, device=device) for level in self.levels)
        histories = tuple(
            th.zeros(n_envs, self.history_length(i), self._history_dim(i), device=device)
            for i in range(1, self.n_levels)
        )
        return HierarchyState(th.zeros(n_envs, dtype=th.long), latents, actions, histories)

    def _update_masks(self, step: th.Tensor, is_first: th.Tensor) -> Masks:
        """Per level, (n,) bool on the CPU: level i updates an env when ``step % k**i == 0`` or the env starts an
        episode (level 0 always)."""
        masks = [th.ones_like(is_first)]
        for i in range(1, self.n_levels):
            masks.append(((step % self.subgoal_interval**i) == 0) | is_first)
        return tuple(masks)

    @staticmethod
    def _index(mask: th.Tensor, device: th.device) -> th.Tensor | None:
        """Row indices of a CPU ``mask`` on ``device``; None when all rows are set (no gather/scatter needed)."""
        return None if bool(mask.all()) else mask.nonzero().squeeze(1).to(device)

    @th.no_grad()
    def step(
        self,
        state: HierarchyState,
        observation: Observation,
        is_first: th.Tensor | np.ndarray,
        deterministic: bool = False,
        random_actions: Sequence[th.Tensor] | None = None,
    ) -> tuple[HierarchyState, HierarchyStep]:
        """Advance the hierarchy by one environment step (Algorithm 1): encode bottom-up, act top-down.

        The inputs are trusted (``HierosPolicy.predict`` and ``HIEROS`` check them).

        :param state: state before the step (batch (n,))
        :param observation: o_t as a tensor (n, *obs_shape) or a dict of them (channel-first images), on the device
        :param is_first: (n,) bool on the host, envs whose episode starts with o_t (their whole hierarchy is reset)
        :param deterministic: posterior modes and policy modes instead of samples (nothing is sampled)
        :param random_actions: per level (n, A_i) action vectors to take instead of the actors' (warm-up), or None
        :return: the new state (``state.actions[0]`` is the environment action vector) and what was updated
        """
        n = state.n_envs
        first_host = th.as_tensor(is_first, dtype=th.bool).reshape(n)
        masks = self._update_masks(state.step, first_host)
        device = state.actions[0].device
        first = first_host.to(device)
        encoded = self._encode(state, observation, first, masks, deterministic)  # Algorithm 1 lines 11-19
        actions = list(state.actions)
        for i in reversed(range(self.n_levels)):  # top-down: act (Algorithm 1 lines 21-29)
            if not bool(masks[i].any()):
                continue
            index = self._index(masks[i], device)
            if random_actions is not None:
                chosen = _take(random_actions[i], index)
            else:
                goal = None if i == self.n_levels - 1 else _take(actions[i + 1], index)  # subgoal from above
                chosen = self._act(i, encoded, index, goal, deterministic)
            actions[i] = _scatter(actions[i], index, chosen.to(actions[i].dtype))
        latents, histories, _ = encoded
        new_state = HierarchyState(state.step + 1, latents, tuple(actions), histories)
        return new_state, HierarchyStep(masks, tuple(state.actions))

    def _encode(
        self, state: HierarchyState, observation: Observation, is_first: th.Tensor, masks: Masks, deterministic: bool
    ) -> Encoded:
        """Bottom-up half of :meth:`step`: level 0 encodes o_t; each update of level i-1 pushes its world state into
        level i's history, and an updating level i encodes its history.

        :return: the new latent states, the new histories, and what :meth:`_act` needs besides (nothing here)
        """
        n = state.n_envs
        latents, histories = list(state.latents), list(state.histories)
        levels: Any = self.levels
        latents[0] = levels[0].observe_step(latents[0], observation, state.actions[0], is_first, deterministic)
        for i in range(1, self.n_levels):
            history = histories[i - 1] * (~is_first).to(histories[i - 1].dtype).reshape(n, 1, 1)  # (n, k, D)
            lower = masks[i - 1]
            if bool(lower.any()):
                pushed = th.cat([history[:, 1:], levels[i - 1].encoded_observation(latents[i - 1]).unsqueeze(1)], 1)
                history = th.where(lower.to(is_first.device).reshape(n, 1, 1), pushed, history)
            histories[i - 1] = history
            if not bool(masks[i].any()):
                continue
            index = self._index(masks[i], is_first.device)
            new = levels[i].observe_step(
                _rows(latents[i], index),
                _take(self.observation_window(history), index),
                _take(state.actions[i], index),
                _take(is_first, index),
                deterministic,
            )
            latents[i] = _scatter_state(latents[i], index, new)
        return tuple(latents), tuple(histories), None

    def _act(
        self, level: int, encoded: Encoded, index: th.Tensor | None, goal: th.Tensor | None, deterministic: bool
    ) -> th.Tensor:
        """The action of ``level`` for the envs ``index`` (all if None) with the subgoal ``goal`` in force.

        :param level: the level
        :param encoded: what :meth:`_encode` returned
        :param index: env rows, or None for all
        :param goal: (m, S) subgoal from the level above, or None at the top
        :param deterministic: the mode instead of a sample
        :return: (m, A) action vectors
        """
        latents = encoded[0]
        return self.levels[level].act(_rows(latents[level], index), goal, deterministic)

    def random_subgoals(self, n_envs: int) -> list[th.Tensor]:
        """Uniformly random subgoals of the levels i >= 1 (warm-up), from numpy's global generator.

        :param n_envs: number of envs
        :return: per level i >= 1, (n, A_i) one-hot vectors
        """
        out = []
        for level in self.levels[1:]:
            index = np.random.randint(0, level.action_classes, size=(n_envs, level.action_groups))  # noqa: NPY002
            one_hot = F.one_hot(th.as_tensor(index, device=self.device), level.action_classes).float()
            out.append(one_hot.reshape(n_envs, level.action_dim))
        return out

    # ------------------------------------------------------------------------------------------------ replay rows

    def subgoal_indices(self, level: int, action: th.Tensor) -> np.ndarray:
        """Actions (subgoals) of a level i >= 1 as ``MultiDiscrete`` indices, the form its replay stores.

        :param level: i >= 1
        :param action: (n, n_cat * n_classes) grouped one-hot
        :return: (n, n_cat) int64
        """
        sub = self.levels[level]
        return action.reshape(-1, sub.action_groups, sub.action_classes).argmax(-1).cpu().numpy().astype(np.int64)

    def _level_rows(
        self, level: int, envs: np.ndarray, history: th.Tensor, prev_action: th.Tensor, subgoal: th.Tensor | None
    ) -> LevelRows:
        observation = self.observation_window(history).cpu().numpy()
        goal = None if subgoal is None else subgoal.cpu().numpy()
        return LevelRows(level, envs, observation, self.subgoal_indices(level, prev_action), goal)

    def update_rows(self, state: HierarchyState, step: HierarchyStep) -> list[LevelRows]:
        """Replay rows of the levels i >= 1 that updated at ``step`` (lock-step updates and episode starts): what
        the level observed, the subgoal it held before, and the subgoal in force from the level above.

        :param state: the state after the step
        :param step: what the step did
        :return: rows per level with at least one updating env
        """
        rows = []
        for i in range(1, self.replay_levels):
            envs = np.flatnonzero(step.updated[i].numpy())
            if envs.size == 0:
                continue
            index = th.as_tensor(envs, device=self.device)
            subgoal = state.actions[i + 1][index] if i + 1 < self.n_levels else None
            rows.append(self._level_rows(i, envs, state.histories[i - 1][index], step.prev_actions[i][index], subgoal))
        return rows

    @th.no_grad()
    def encode_terminal(
        self, state: HierarchyState, observation: Observation | None, envs: np.ndarray
    ) -> list[LevelRows]:
        """The terminal rows of the levels i >= 1 for envs whose episode ended: the terminal observation is encoded
        bottom-up (with the actions in force, no reset) and each level's window ends with the terminal world state of
        the level below. ``state`` is not changed.

        :param state: the state after the step that ended the episodes
        :param observation: the terminal observations of ``envs`` (m, *obs_shape), or None when the env gave none
            (the windows then end with the last encoded states)
        :param envs: (m,) the envs whose episode ended
        :return: one row set per level i >= 1 (empty without higher replays)
        """
        if self.replay_levels == 1:
            return []
        levels: Any = self.levels
        index = th.as_tensor(envs, device=self.device)
        not_first = th.zeros(envs.size, dtype=th.bool, device=self.device)
        encoded: th.Tensor | None = None
        if observation is not None:
            latent = levels[0].observe_step(
                state.latents[0].select(index), observation, state.actions[0][index], not_first
            )
            encoded = levels[0].encoded_observation(latent)
        rows = []
        for i in range(1, self.replay_levels):
            history = state.histories[i - 1][index]  # (m, k, D)
            if encoded is not None:
                history = th.cat([history[:, 1:], encoded.unsqueeze(1)], 1)
            subgoal = state.actions[i + 1][index] if i + 1 < self.n_levels else None
            rows.append(self._level_rows(i, envs, history, state.actions[i][index], subgoal))
            if encoded is not None and i + 1 < self.replay_levels:
                latent = levels[i].observe_step(
                    state.latents[i].select(index), self.observation_window(history), state.actions[i][index], not_first
                )
                encoded = levels[i].encoded_observation(latent)
        return rows

    # ------------------------------------------------------------------------------------------------ training

    def levels_due(self, update: int) -> list[int]:
        """The levels with a replay that train at level 0's ``update``-th update: level i at every k**i-th.

        :param update: number of level-0 updates so far
        :return: level indices
        """
        return [i for i in range(self.replay_levels) if update % self.subgoal_interval**i == 0]

    def train_step(self, batches: Sequence[SequenceSamples | None]) -> list[LevelUpdate | None]:
        """One update of the hierarchy: Algorithm 2 (:meth:`Subactor.train_step`) for every level with a batch,
        bottom-up, with the subgoal updates of the levels above during imagination if
        ``update_subgoals_in_imagination`` (:meth:`replan`).

        :param batches: per level with a replay, a batch of its replay or None (the level does not train now)
        :return: per level, what its update returned, or None
        """
        updates: list[LevelUpdate | None] = [None] * self.n_levels
        for i, batch in enumerate(batches):
            if batch is not None:
                updates[i] = self.levels[i].train_step(batch, self.replan_of(i))
        return updates

    def world_model_updates(self, batches: Sequence[SequenceSamples | None]) -> list[LevelUpdate | None]:
        """World-model updates without imagination (:meth:`Subactor.world_model_update`) for every level with a batch.

        :param batches: per level with a replay, a batch of its replay or None
        :return: per level, what its update returned, or None
        """
        updates: list[LevelUpdate | None] = [None] * self.n_levels
        for i, batch in enumerate(batches):
            if batch is not None:
                updates[i] = self.levels[i].world_model_update(batch)
        return updates

    def replan_of(self, level: int) -> Replan | None:
        """The subgoal updates of the levels above ``level`` during its imagination, or None (thesis default, or the
        top level).

        :param level: the imagining level
        :return: ``replan(window, code, carry) -> (code, carry)``, see :meth:`replan`
        """
        if not self.config.update_subgoals_in_imagination or level >= self.n_levels - 1:
            return None
        return lambda window, code, carry: self.replan(level, window, code, carry)

    @th.no_grad()
    def replan(self, level: int, window: th.Tensor, subgoal: th.Tensor, carry: Any) -> tuple[th.Tensor, Any]:
        """The next subgoal for ``level`` in its imagination (ablation 5.3.9): level i+1 encodes the last k imagined
        world states of level i with its own world model, carrying its latent state from call to call within one
        rollout (the first call starts it like an episode start), and acts.

        A level i+1 below the top needs a subgoal of its own: at the first call of a rollout, level i+2 proposes one
        from a window that holds only level i+1's first state (episode-start semantics), recursively up to the top,
        and it is held for the rest of the rollout (with the thesis' k=4 and horizon 16, level i+2 would act at most
        once in that time).

        :param level: the imagining level i (< n_levels - 1)
        :param window: (N, k, D_i + Z_i) the last k imagined world states of level i, oldest first
        :param subgoal: (N, S) the subgoal code in force (level i+1's previous action)
        :param carry: None at the first call of a rollout, else what the previous call returned
        :return: the new (N, S) subgoal code and the carry (level i+1's latent state, its own subgoal)
        """
        upper = self.levels[level + 1]
        n = window.shape[0]
        first = carry is None
        is_first = th.full((n,), first, dtype=th.bool, device=window.device)
        with evaluation_mode(upper.world_model):  # imagined states are observed without dropout, as in rollout
            state = upper.observe_step(None if first else carry[0], self.observation_window(window), subgoal, is_first)
        if first:
            own_goal = None
            if level + 2 < self.n_levels:
                own_goal = self._propose_fresh(level + 2, upper.encoded_observation(state))
        else:
            own_goal = carry[1]
        return upper.act(state, own_goal), (state, own_goal)

    def _propose_fresh(self, level: int, encoded_below: th.Tensor) -> th.Tensor:
        """Subgoal of ``level`` from a window holding only ``encoded_below`` (n, D) (its slots before are empty)."""
        upper = self.levels[level]
        n = encoded_below.shape[0]
        window = encoded_below.new_zeros(n, self.subgoal_interval, encoded_below.shape[-1])
        window[:, -1] = encoded_below
        first = th.ones(n, dtype=th.bool, device=encoded_below.device)
        prev = encoded_below.new_zeros(n, upper.action_dim)
        with evaluation_mode(upper.world_model):
            state = upper.observe_step(None, self.observation_window(window), prev, first)
        goal = None
        if level < self.n_levels - 1:
            goal = self._propose_fresh(level + 1, upper.encoded_observation(state))
        return upper.act(state, goal)

    # ------------------------------------------------------------------------------------------------ diagnostics

    @th.no_grad()
    def decode_subgoals(self, state: HierarchyState) -> list[Observation]:
        """The subgoal in force from every level i >= 1, decoded into the environment's observation space (thesis
        4.3.2, last paragraph).

        Level i's subgoal (its action ``state.actions[i]``) goes through level i-1's autoencoder decoder into level
        i-1's h space (eq. 4.1); together with the current stochastic state z of level i-1 the world-model decoder of
        level i-1 turns it into level i-1's observation. Above level 1 that observation is k stacked world states
        ``[h, z]`` of level i-2 (or only the newest, ablation 5.3.6); the last of them is decoded by level i-2's world
        model, and so on down to level 0, whose decoder gives an environment observation. The decoded z of a lower
        level is used as it comes out of the decoder (a soft vector, not snapped to one-hot).

        :param state: the hierarchy state
        :return: per level i = 1 .. n_levels - 1 (list index i - 1), the decoded observation of every env:
            (n, *obs_shape) (images as float pixels in [0, 255]) or a dict of such tensors for Dict spaces
        """
        n = state.n_envs
        decoded: list[Observation] = []
        for level in range(1, self.n_levels):
            below = self.levels[level - 1]
            h = below.decode_subgoal(state.actions[level])  # (n, D_{i-1})
            obs = below.decode_state_observation(h, state.latents[level - 1].stoch)
            for j in range(level - 2, -1, -1):
                lower = self.levels[j]
                last = obs.reshape(n, -1, lower.latent_dim)[:, -1]  # (n, D_j + Z_j): the newest of the k states
                obs = lower.decode_state_observation(last[:, : lower.h_dim], last[:, lower.h_dim :])
            decoded.append(obs)
        return decoded

    def state_estimates(self, state: HierarchyState, level: int = 0) -> dict[str, th.Tensor]:
        """:meth:`Subactor.state_estimates` of ``level`` at its world state in ``state``, with the subgoal in force.

        :param state: the hierarchy state
        :param level: a level with a world model of its own
        :return: ``"reward"``, ``"continue"`` and ``"value/<term>"``, each (n,)
        """
        if not (0 <= level < self.n_levels and self.has_world_model(level)):
            raise ValueError(f"level must be a level with a world model in [0, {self.n_levels}), got {level}")
        subgoal = state.actions[level + 1] if level + 1 < self.n_levels else None
        return self.levels[level].state_estimates(state.latents[level], subgoal)


def make_hierarchy(
    observation_space: spaces.Space, action_space: spaces.Space, config: HierosConfig, **world_model_options: Any
) -> Hierarchy:
    """The hierarchy of ``config``: :class:`Hierarchy`, or with ``hierarchical_world_models=False`` (ablation 5.3.1)
    :class:`~sb3_hieros.agent.shared.SharedWorldModelHierarchy`.

    :param observation_space: the environment's observation space
    :param action_space: the environment's action space
    :param config: the resolved configuration
    :param world_model_options: ``bf16`` and ``compile`` opt-ins of the world models, level 0's
        ``observation_options``
    :return: the hierarchy
    """
    from sb3_hieros.agent.shared import SharedWorldModelHierarchy  # it subclasses Hierarchy

    cls = Hierarchy if config.hierarchical_world_models else SharedWorldModelHierarchy
    return cls(observation_space, action_space, config, **world_model_options)
