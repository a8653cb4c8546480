"""One level of the HIEROS hierarchy: world model, actor-critic and subgoal autoencoder (thesis 4.3, 4.6, Algorithm 2).

A :class:`Subactor` owns the three learners of one level i (thesis Figure 4.2) and their optimisers: the world model
W^i (:mod:`sb3_hieros.agent.world_model`, thesis 4.4), the actor-critic Pi^i with one critic per active reward term of
eq. 4.3 (:class:`~sb3_hieros.agent.actor_critic.ActorCritic`) and the subgoal autoencoder G^i on the deterministic
state h (:class:`~sb3_hieros.agent.subgoal.SubgoalAutoencoder`).

Actions are float vectors inside a level: one-hot for discrete spaces (``n_cat * n_classes`` grouped one-hot for
subgoals), values in [-1, 1] for Box. The subgoal a level *receives* lives in the code space of its *own*
autoencoder, whose decoder maps it into the level's h space for the subgoal reward; the actor and critics see the code
(thesis) or, with ``decoded_subgoal_input=True``, the decoded vector (ablation 5.3.8). The top level has neither a
subgoal input nor a subgoal critic.

:meth:`Subactor.train_step` is Algorithm 2 for this level; :class:`~sb3_hieros.agent.hierarchy.Hierarchy` calls it
for every level that is due and passes the subgoal updates of ablation 5.3.9. The per-step methods used by the
hierarchy's acting loop (:meth:`~Subactor.observe_step`, :meth:`~Subactor.act`, ...) trust their inputs; the
diagnostics (:meth:`~Subactor.state_estimates`, :meth:`~Subactor.decode_subgoal`,
:meth:`~Subactor.decode_state_observation`) check theirs.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Mapping
from typing import Any, NamedTuple

import torch as th
import torch.nn.functional as F
from gymnasium import spaces

from sb3_hieros.agent.actor_critic import ReplaySequences, actor_input, actor_input_dim
from sb3_hieros.agent.learning import (
    SUBGOAL_SUCCESS_THRESHOLD,
    LevelLearner,
    imagination_start_indices,
    learn_from_imagination,
)
from sb3_hieros.agent.subgoal import max_cosine_subgoal_reward, novelty_reward
from sb3_hieros.agent.world_model import (
    LatentState,
    ObservationOptions,
    WorldModel,
    make_world_model,
    world_model_lr_scheduler,
    world_model_optimizer,
)
from sb3_hieros.config import HierosConfig
from sb3_hieros.nn.metrics import metric_floats
from sb3_hieros.nn.networks import check_bf16
from sb3_hieros.spaces import action_layout, stacked_state_space
from sb3_hieros.type_aliases import LevelUpdate, Observation, SequenceSamples

__all__ = ["Imagination", "Replan", "Subactor", "current_action_alignment"]

#: ``replan(window, code, carry) -> (code, carry)``: the subgoal from the level above every k imagined steps
#: (ablation 5.3.9; :meth:`~sb3_hieros.agent.hierarchy.Hierarchy.replan`)
Replan = Callable[[th.Tensor, th.Tensor, Any], tuple[th.Tensor, Any]]


class Imagination(NamedTuple):
    """One imagined trajectory s_0..s_H of a level (time-major).

    :param states: (H+1, N) states (without the recurrent memory)
    :param features: (H+1, N, F) actor / critic inputs
    :param actions: (H, N, *action_shape) actions of the actor
    :param rewards: (H+1, N) rewards predicted by the world model
    :param continues: (H+1, N) continue probabilities predicted by the world model
    :param targets: decoded subgoals the subgoal reward compares with: (N, D) held, (H+1, N, D) with subgoal updates,
        None at the top level
    """

    states: LatentState
    features: th.Tensor
    actions: th.Tensor
    rewards: th.Tensor
    continues: th.Tensor
    targets: th.Tensor | None


def current_action_alignment(action_vectors: th.Tensor, is_first: th.Tensor) -> th.Tensor:
    """Row t carries a_t (the action chosen at o_t) instead of a_{t-1}: the reference code's world-model training
    alignment (reference-compat switch ``reference.action_alignment="current"``).

    Row t gets row t+1's action; it is zero where row t is an episode start (as in the reference), where row t+1 is
    one (the action after a final observation) and in the chunk's last row (its a_t is not in the chunk).

    :param action_vectors: (B, T, A) the batch's actions a_{t-1} as float vectors (:meth:`Subactor.action_vectors`)
    :param is_first: (B, T) episode starts
    :return: (B, T, A) float actions a_t
    """
    is_first = is_first.bool()
    shifted = th.cat([action_vectors[:, 1:], th.zeros_like(action_vectors[:, :1])], 1)
    next_first = th.cat([is_first[:, 1:], th.zeros_like(is_first[:, :1])], 1)
    keep = ~(is_first | next_first)
    return shifted * keep.unsqueeze(-1).to(shifted.dtype)


def _count(params: Any) -> int:
    return sum(p.numel() for p in params)


class Subactor(LevelLearner):
    """One HIEROS level i (thesis 4.3): world model W^i, actor-critic Pi^i and subgoal autoencoder G^i.

    :param observation_space: observations of this level: the env's for level 0, otherwise
        ``lower.higher_level_observation_space(k)``
    :param action_space: ``Discrete`` or ``Box`` at level 0; ``lower.subgoal_space()`` above
    :param config: hyperparameters (world model, actor-critic and subgoal sections, ``imag_horizon``)
    :param level: index i of the level (0 = acts in the environment); informational
    :param subgoal_input: False for the top level: no subgoal input, no subgoal reward or critic
    :param decoded_subgoal_input: feed the actor and critics the decoded subgoal (h space) instead of the one-hot code
        (ablation 5.3.8; default False = thesis); has no effect at the top level
    :param bf16: bfloat16 autocast of the world model's and of the actor-critic and autoencoder losses: ``True``,
        ``False`` or ``"auto"`` (where the device computes bf16 natively, :func:`~sb3_hieros.nn.networks.native_bf16`)
    :param compile: ``torch.compile`` opt-in of the world model's sequence model
    :param observation_options: SB3's observation keywords of the world model (level 0), or None
    """

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        config: HierosConfig,
        level: int = 0,
        subgoal_input: bool = True,
        decoded_subgoal_input: bool = False,
        bf16: bool | str = False,
        compile: bool = False,
        observation_options: ObservationOptions | None = None,
    ) -> None:
        super().__init__()
        kind, classes, groups = action_layout(action_space)
        self.config = config
        self.level = level
        self.observation_space = observation_space
        self.action_space = action_space
        self.subgoal_input = bool(subgoal_input)
        self.decoded_subgoal_input = bool(decoded_subgoal_input) and self.subgoal_input
        self.bf16 = check_bf16(bf16)
        self.action_kind = kind
        self.action_groups = groups
        self.action_classes = classes
        #: size A of the flat action vector (one-hot size for discrete, dims for Box)
        self.action_dim = classes * groups
        ac, sg = config.actor_critic, config.subgoal
        if ac.imag_gradient == "auto":
            self.imag_gradient = "reinforce" if kind == "discrete" else "dynamics"
        else:
            self.imag_gradient = ac.imag_gradient

        self.world_model: WorldModel = make_world_model(
            observation_space,
            self.action_dim,
            config.world_model,
            bf16=bf16,
            compile=compile,
            observation_options=observation_options,
        )
        self.h_dim = self.world_model.deter_dim
        self.z_dim = self.world_model.stoch_dim
        #: flat size of a received subgoal (n_cat * n_classes)
        self.subgoal_dim = sg.n_cat * sg.n_classes
        goal_feat = 0
        if self.subgoal_input:
            goal_feat = self.h_dim if self.decoded_subgoal_input else self.subgoal_dim
        self.feat_dim = actor_input_dim(self.h_dim, self.z_dim, goal_feat, ac.actor_extras)
        self._build_learners(self.h_dim, self.feat_dim, kind, classes, groups, self.imag_gradient)
        self.wm_optimizer = world_model_optimizer(self.world_model)
        self.wm_scheduler: th.optim.lr_scheduler.LRScheduler | None = world_model_lr_scheduler(
            self.wm_optimizer, config.world_model.warmup
        )

    # ------------------------------------------------------------------------------------------------ spaces

    @property
    def latent_dim(self) -> int:
        """Size D + G*K of one world state ``[h, z]`` (:meth:`encoded_observation`)."""
        return self.h_dim + self.z_dim

    def higher_level_observation_space(self, k: int) -> spaces.Box:
        """Observation space of the level above: k consecutive world states of this level, concatenated (thesis 4.3).

        :param k: number of stacked states (``config.subgoal_interval``; 1 for ablation 5.3.6)
        :return: ``Box(-inf, inf, (k * (D + G*K),), float32)``
        """
        return stacked_state_space(self.latent_dim, k)

    def action_vectors(self, actions: th.Tensor, is_first: th.Tensor) -> th.Tensor:
        """Replay actions as the float vectors the world model consumes (previous actions, zero where ``is_first``).

        Float vectors ``(B, T, A)`` pass unchanged. For discrete spaces, integer indices ``(B, T)`` / ``(B, T, 1)``
        (Discrete) or ``(B, T, G)`` (MultiDiscrete, as SB3 buffers store them) are one-hot encoded and zeroed where
        ``is_first`` (where replay holds a placeholder 0). Box actions must already be in [-1, 1].

        :param actions: (B, T, A) float, or integer indices as above
        :param is_first: (B, T) episode starts
        :return: (B, T, A) float
        """
        lead = tuple(is_first.shape)
        if actions.is_floating_point() and tuple(actions.shape) == (*lead, self.action_dim):
            return actions
        index = actions.reshape(*lead, self.action_groups).long()
        one_hot = F.one_hot(index, self.action_classes).float().reshape(*lead, self.action_dim)
        return one_hot * (~is_first.bool()).unsqueeze(-1).float()

    # ------------------------------------------------------------------------------------------------ acting

    def initial_state(self, batch_size: int) -> LatentState:
        """World state before the first observation (see :meth:`WorldModel.initial_state`).

        :param batch_size: number of parallel envs
        :return: state of batch shape (batch_size,)
        """
        return self.world_model.initial_state(batch_size)

    @th.no_grad()
    def observe_step(
        self,
        state: LatentState | None,
        observation: Observation,
        prev_action: th.Tensor,
        is_first: th.Tensor,
        deterministic: bool = False,
    ) -> LatentState:
        """Encode one observation into the world state (Algorithm 1 ``Encode``; no gradients).

        :param state: previous state (batch (B,)), or None for :meth:`initial_state`
        :param observation: (B, *obs_shape) (dict for Dict spaces)
        :param prev_action: (B, A) float action vector taken after the previous observation (from :meth:`act`)
        :param is_first: (B,) bool, new episodes (state and ``prev_action`` ignored there)
        :param deterministic: take the posterior mode instead of a sample
        :return: posterior state (batch (B,))
        """
        wm = self.world_model
        if state is None:
            state = wm.initial_state(int(prev_action.shape[0]))
        return wm._obs_step(state, wm.spec.as_dict(observation), prev_action, is_first, deterministic)

    def features(self, state: LatentState, goal_feat: th.Tensor | None) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        """Actor / critic input s_t of eq. 4.6 and the world model's reward and continue predictions at ``state``.

        :param state: states of any batch shape *B
        :param goal_feat: (*B, S') :meth:`goal_features` or None
        :return: features (*B, feat_dim), predicted reward (*B), continue probability (*B)
        """
        wm = self.world_model
        reward, cont = wm.reward(state), wm.cont(state)
        feat = actor_input(
            state.deter,
            state.stoch,
            goal_feat,
            reward,
            cont,
            wm.prior_entropy(state),
            use_extras=self.config.actor_critic.actor_extras,
        )
        return feat, reward, cont

    @th.no_grad()
    def act(self, state: LatentState, subgoal: th.Tensor | None, deterministic: bool = False) -> th.Tensor:
        """Action of this level in ``state`` (eq. 4.6; no gradients).

        :param state: current world state (batch (B,))
        :param subgoal: (B, n_cat * n_classes) one-hot subgoal from the level above; None at the top level
        :param deterministic: the distribution's mode (thesis 4.3.2 for environment interaction) instead of a sample
        :return: (B, A): one-hot for Discrete, ``n_cat * n_classes`` grouped one-hot for subgoals, [-1, 1] for Box
        """
        feat, _, _ = self.features(state, self.goal_features(subgoal))
        return self.actor_critic.act(feat, deterministic).reshape(feat.shape[0], self.action_dim)

    @th.no_grad()
    def encoded_observation(self, state: LatentState) -> th.Tensor:
        """One world state as the level above sees it (thesis 4.3), to be concatenated over k steps.

        :param state: world state (batch (B,))
        :return: (B, D + G*K) = ``[h, z]`` (h is already symlog-scaled inside the world model)
        """
        return self.world_model.features(state)

    # ------------------------------------------------------------------------------------------------ diagnostics

    def _check_state(self, state: Any) -> int:
        if not isinstance(state, LatentState) or len(state.batch_shape) != 1:
            got = tuple(state.batch_shape) if isinstance(state, LatentState) else type(state).__name__
            raise ValueError(f"state must be a LatentState of batch shape (B,), got {got}")
        if state.deter.shape[-1] != self.h_dim or state.stoch.shape[-1] != self.z_dim:
            raise ValueError(
                f"state has deter/stoch sizes {state.deter.shape[-1]}/{state.stoch.shape[-1]}, expected "
                f"{self.h_dim}/{self.z_dim}"
            )
        return int(state.batch_shape[0])

    def _flat_subgoal(self, subgoal: Any, batch: int, name: str = "subgoal") -> th.Tensor:
        """A subgoal tensor of shape (B, S) or (B, n_cat, n_classes) as float (B, S)."""
        sg = self.config.subgoal
        accepted = ((batch, self.subgoal_dim), (batch, sg.n_cat, sg.n_classes))
        if not isinstance(subgoal, th.Tensor) or tuple(subgoal.shape) not in accepted:
            got = tuple(subgoal.shape) if isinstance(subgoal, th.Tensor) else type(subgoal).__name__
            raise ValueError(f"{name} must be a tensor of shape {accepted[0]} or {accepted[1]}, got {got}")
        return subgoal.reshape(batch, self.subgoal_dim).float()

    @th.no_grad()
    def state_estimates(self, state: LatentState, subgoal: th.Tensor | None) -> dict[str, th.Tensor]:
        """What this level predicts about ``state``: the world model's reward and continue heads and the value of
        each active reward term's fast critic (eq. 4.3), for diagnostics (e.g. ``benchmarks/cartpole_failures.py``).

        :param state: world state (batch (B,))
        :param subgoal: (B, n_cat * n_classes) or (B, n_cat, n_classes) one-hot subgoal in force; None at the top
        :return: ``"reward"``, ``"continue"`` and ``"value/<term>"`` for every term of :attr:`reward_terms`, each (B,)
        """
        batch = self._check_state(state)
        if (subgoal is None) == self.subgoal_input:
            raise ValueError(
                f"subgoal must be {'given' if self.subgoal_input else 'None'} at level {self.level} "
                f"(subgoal_input={self.subgoal_input})"
            )
        goal = None if subgoal is None else self._flat_subgoal(subgoal, batch)
        feat, reward, cont = self.features(state, self.goal_features(goal))
        out = {"reward": reward, "continue": cont}
        for name in self.reward_terms:
            out[f"value/{name}"] = self.actor_critic.critics[name].value(feat)
        return out

    @th.no_grad()
    def decode_subgoal(self, subgoal: th.Tensor) -> th.Tensor:
        """Subgoal code -> target state h of this level (decoder of G^i, eq. 4.1).

        :param subgoal: (B, n_cat * n_classes) or (B, n_cat, n_classes)
        :return: (B, D)
        """
        batch = int(subgoal.shape[0]) if isinstance(subgoal, th.Tensor) and subgoal.dim() >= 2 else -1
        return self.autoencoder.decode(self._flat_subgoal(subgoal, batch))

    @th.no_grad()
    def decode_state_observation(self, h: th.Tensor, stoch: th.Tensor) -> Observation:
        """Observation the world-model decoder predicts from ``(h, z)`` (to show a subgoal: a decoded subgoal h with
        the current z).

        :param h: (B, D) deterministic state, e.g. :meth:`decode_subgoal`
        :param stoch: (B, G*K) stochastic state
        :return: (B, *obs_shape) (images as float pixels in [0, 255]), or a dict for Dict spaces
        """
        for name, x, size in (("h", h, self.h_dim), ("stoch", stoch, self.z_dim)):
            if not isinstance(x, th.Tensor) or x.dim() != 2 or x.shape[-1] != size:
                shape = tuple(x.shape) if isinstance(x, th.Tensor) else type(x).__name__
                raise ValueError(f"{name} must have shape (B, {size}), got {shape}")
        if h.shape[0] != stoch.shape[0]:
            raise ValueError(f"h {tuple(h.shape)} and stoch {tuple(stoch.shape)} must share the batch size")
        wm = self.world_model
        unused = th.zeros(h.shape[0], wm.groups, wm.classes, device=h.device)
        return wm.decode(LatentState(stoch.float(), h.float(), h.float(), unused, unused))

    # ------------------------------------------------------------------------------------------------ training

    def training_batch(self, samples: SequenceSamples) -> tuple[SequenceSamples, th.Tensor | None]:
        """A replay batch as this level trains on it: previous actions as float vectors (the current ones with
        ``reference.action_alignment="current"``, :func:`current_action_alignment`), subgoals flattened.

        :param samples: a batch of chunks (B, T, ...) of this level's replay
        :return: the batch and its (B, T, n_cat * n_classes) subgoals (None at the top level or without subgoals)
        """
        is_first = samples.is_first
        actions = self.action_vectors(samples.actions, is_first)
        if self.config.reference.action_alignment == "current":
            actions = current_action_alignment(actions, is_first)
        subgoals = None
        if self.subgoal_input and samples.subgoals is not None:
            subgoals = samples.subgoals.reshape(*is_first.shape, self.subgoal_dim).float()
        batch = SequenceSamples(samples.observations, actions, samples.rewards, is_first, samples.is_terminal, subgoals)
        return batch, subgoals

    def world_model_step(
        self, batch: SequenceSamples, context: th.Tensor | None
    ) -> tuple[dict[str, th.Tensor], LatentState, th.Tensor | None]:
        """Step 1 of :meth:`train_step` (also used by the shared-world-model hierarchy): one world-model update on
        ``batch``, started from the replay context (the world state stored for the row before each chunk).

        :param batch: the batch from :meth:`training_batch`
        :param context: (B, C) packed states of the replay context, or None to start every chunk from zeros
        :return: metrics ``wm/*`` and ``nonfinite/world_model`` (0-d tensors), the detached posterior states and,
            with a context, the packed posterior states (B, T, C) to store back into the replay
        """
        wm = self.world_model
        start = None if context is None else wm.unpack_context(context)
        wm_metrics, post = wm._train_step(batch, self.wm_optimizer, self.wm_scheduler, start)
        metrics = {f"wm/{k}": v for k, v in wm_metrics.items()}
        metrics["nonfinite/world_model"] = metrics.pop("wm/nonfinite")
        return metrics, post, None if context is None else wm.pack_context(post)

    def world_model_update(self, samples: SequenceSamples) -> LevelUpdate:
        """A world-model update without imagination (``HierosConfig.world_model_updates`` > 1): step 1 of
        :meth:`train_step` on a batch of its own.

        :param samples: a batch of this level's replay (B, T, ...), as for :meth:`train_step`
        :return: the metrics ``wm/*`` and ``nonfinite/world_model`` and the packed posterior states for the replay
            context
        """
        batch, _ = self.training_batch(samples)
        tensors, _, context = self.world_model_step(batch, samples.context)
        return LevelUpdate(metric_floats(tensors), context)

    def imagine(self, start: LatentState, codes: th.Tensor | None, replan: Replan | None = None) -> Imagination:
        """Imagination of ``imag_horizon`` steps with the current actor from ``start`` (thesis 4.4.3, Algorithm 2
        line 7), through :meth:`WorldModel.rollout`.

        The world-model heads are evaluated once per state and serve the actor input and the rewards. The actor acts
        on detached features (DreamerV3); with dynamics backpropagation the reparameterised actions carry the
        gradient into the rollout. The subgoal ``codes`` are held over the horizon (thesis), or, with ``replan``
        (ablation 5.3.9), at every imagined step t > 0 with ``t % subgoal_interval == 0`` the level above gets the
        world states of the last k imagined states (N, k, D + G*K), the code in force and its carry (None at the
        first call of a rollout) and returns the new code; the actor sees it from s_t on, and the subgoal reward of
        s_{t+1} is measured against the subgoal in force when a_t was chosen.

        :param start: (N,) detached posterior states
        :param codes: (N, n_cat * n_classes) subgoal codes in force at s_0, or None at the top level
        :param replan: the subgoal updates of the level above, or None to hold ``codes``
        :return: the imagined trajectory
        """
        wm, actor = self.world_model, self.actor_critic.actor
        horizon, k = self.config.imag_horizon, self.config.subgoal_interval
        target = goal_feat = None
        if codes is not None:
            with th.no_grad():
                target = self.autoencoder.decode(codes)  # (N, D): the subgoal in this level's h space
            goal_feat = target if self.decoded_subgoal_input else codes
        replanning = replan is not None and codes is not None
        planned = [target]  # planned[j]: decoded subgoal in force at the imagined steps j*k .. (j+1)*k - 1
        plan: list[Any] = [codes, None]  # code in force, carry of replan
        recent: list[LatentState] = []
        feats, actions, rewards, conts = [], [], [], []

        @th.no_grad()
        def replanned() -> th.Tensor:
            window = th.stack([wm.features(s.detach()) for s in recent[-k:]], 1)  # (N, k, D + G*K)
            code, plan[1] = replan(window, plan[0], plan[1])  # type: ignore[misc]
            plan[0] = code.reshape(code.shape[0], self.subgoal_dim).float()
            planned.append(self.autoencoder.decode(plan[0]))
            return planned[-1] if self.decoded_subgoal_input else plan[0]

        def step(t: int, state: LatentState) -> th.Tensor | None:
            nonlocal goal_feat
            if replanning:
                recent.append(state)
                del recent[:-k]
                if t > 0 and t % k == 0:
                    goal_feat = replanned()
            feat, reward, cont = self.features(state, goal_feat)
            feats.append(feat)
            rewards.append(reward)
            conts.append(cont)
            if t == horizon:
                return None
            action = actor(feat.detach()).sample()  # (N, *action_shape)
            actions.append(action)
            return action.reshape(action.shape[0], self.action_dim)

        states, _ = wm.rollout(start, horizon, step)
        if replanning:  # the target of s_{t+1} is the one pursued by a_t, i.e. in force at step t
            target = th.stack([planned[0]] + [planned[t // k] for t in range(horizon)], 0)
        return Imagination(
            states, th.stack(feats, 0), th.stack(actions, 0), th.stack(rewards, 0), th.stack(conts, 0), target
        )

    def imagined_rewards(self, imagined: Imagination) -> dict[str, th.Tensor]:
        """Rewards per imagined state s_0..s_H (eq. 4.3-4.5; index 0 is not used by the returns): extrinsic = the
        reward head; subgoal = max-cosine of h and the decoded subgoal (not at the top level); novelty = the
        autoencoder's reconstruction error of h (without gradient, if its weight is > 0).

        :param imagined: the trajectory of :meth:`imagine`
        :return: term -> (H+1, N)
        """
        deter = imagined.states.deter
        rewards = {"extrinsic": imagined.rewards}
        if imagined.targets is not None:
            rewards["subgoal"] = max_cosine_subgoal_reward(deter, imagined.targets)  # in [-1, 1]
        if "novelty" in self.reward_terms:
            with th.no_grad():
                rewards["novelty"] = novelty_reward(deter, self.autoencoder)
        return rewards

    @th.no_grad()
    def replay_sequences(
        self, batch: SequenceSamples, post: LatentState, subgoals: th.Tensor | None, starts: th.Tensor | None
    ) -> ReplaySequences:
        """The replayed posterior states as this level's critics see them, with the rewards of every term recorded
        along them, for the replay value loss (:meth:`~sb3_hieros.agent.actor_critic.ActorCritic.replay_value_loss`).

        Extrinsic: the replayed rewards; subgoal: the max-cosine reward of s_t against the subgoal in force at
        s_{t-1}, when a_{t-1} was chosen (as in :meth:`imagined_rewards`); novelty: the autoencoder's error of h_t.

        :param batch: the batch from :meth:`training_batch` (B, T, ...)
        :param post: its posterior states (B, T)
        :param subgoals: (B, T, n_cat * n_classes) subgoals in force, or None at the top level
        :param starts: (N,) flat indices of the imagination's start states, or None for all
        :return: the sequences, batch-major
        """
        target = goal_feat = None
        if subgoals is not None:
            target = self.autoencoder.decode(subgoals)  # (B, T, D)
            goal_feat = target if self.decoded_subgoal_input else subgoals
        feats, _, _ = self.features(post, goal_feat)  # (B, T, F)
        rewards = {"extrinsic": batch.rewards}
        if target is not None:
            rewards["subgoal"] = F.pad(max_cosine_subgoal_reward(post.deter[:, 1:], target[:, :-1]), (1, 0))
        if "novelty" in self.reward_terms:
            rewards["novelty"] = novelty_reward(post.deter, self.autoencoder)
        return ReplaySequences(feats, rewards, 1.0 - batch.is_terminal.float(), batch.is_first, starts)

    def train_step(self, samples: SequenceSamples, replan: Replan | None = None) -> LevelUpdate:
        """One training iteration of this level on a batch of chunks (Algorithm 2, thesis 4.6.2).

        1. World-model step on the chunk (eq. 4.10-4.13, warm-up scheduler, clip ``world_model.grad_clip``), from
           the replay context where the batch has one.
        2. Imagination of ``imag_horizon`` steps from all B*T detached posterior states (or the share
           ``imag_start_fraction`` of them, :func:`~sb3_hieros.agent.learning.imagination_start_indices`), each
           row's subgoal held fixed or updated by ``replan`` (:meth:`imagine`).
        3. Rewards per imagined state (:meth:`imagined_rewards`); continues: ``1 - is_terminal`` for the start state,
           the continue head afterwards.
        4. Actor and critic steps, slow-critic EMA; 5. autoencoder step on the sampled and imagined h
           (:func:`~sb3_hieros.agent.learning.learn_from_imagination`).

        Metrics: ``wm/*`` (world-model loss terms, ``grad_norm``, ``lr``); ``actor/*``, ``critic/*``, ``return/*``,
        ``reward/<term>`` (mean over s_1..s_H) and ``ae/*`` (see ``learn_from_imagination``); below the top
        ``subgoal/final_reward`` (mean subgoal reward of s_H) and ``subgoal/success`` (share of rollouts whose s_H
        reaches :data:`~sb3_hieros.agent.learning.SUBGOAL_SUCCESS_THRESHOLD`); ``imag/continue`` (mean continue
        probability of s_1..s_H); ``nonfinite/<name>`` for ``world_model``, ``actor``, ``critic`` and
        ``autoencoder``: 1.0 when that step was skipped because its loss or gradient norm was not finite.

        :param samples: a batch of this level's replay (B, T, ...): ``actions[:, t]`` = a_{t-1} (float vectors or
            indices, see :meth:`action_vectors`), ``subgoals`` below the top level, ``context`` with a replay context
        :param replan: subgoal updates during imagination (ablation 5.3.9), or None
        :return: the metrics and the packed posterior states for the replay context
        """
        batch, subgoals = self.training_batch(samples)
        tensors, post, context = self.world_model_step(batch, samples.context)
        lr = float(self.wm_optimizer.param_groups[0]["lr"])

        start = post.flatten_batch()  # (N,) with N = B*T, detached
        first_cont = 1.0 - batch.is_terminal.reshape(-1).float()  # (N,)
        codes = None if subgoals is None else subgoals.reshape(-1, self.subgoal_dim)  # (N, G)
        chosen = imagination_start_indices(
            int(start.batch_shape[0]), self.config.imag_start_fraction, start.deter.device
        )
        if chosen is not None:
            start, first_cont = start.select(chosen), first_cont[chosen]
            codes = None if codes is None else codes[chosen]
        dynamics = self.imag_gradient == "dynamics"
        with contextlib.nullcontext() if dynamics else th.no_grad():
            imagined = self.imagine(start, codes, replan)
            rewards = self.imagined_rewards(imagined)
        continues = th.cat([first_cont.unsqueeze(0), imagined.continues[1:].detach()], 0)  # (H+1, N)
        deter = imagined.states.deter
        replay = None
        if self.actor_critic.replay_value_scale > 0.0:
            replay = self.replay_sequences(batch, post, subgoals, chosen)
        tensors.update(
            learn_from_imagination(self, imagined.features, imagined.actions, rewards, continues, deter, replay)
        )
        if "subgoal" in rewards:
            final = rewards["subgoal"][-1].detach()  # (N,)
            tensors["subgoal/final_reward"] = final.mean()
            tensors["subgoal/success"] = (final >= SUBGOAL_SUCCESS_THRESHOLD).float().mean()
        tensors["imag/continue"] = imagined.continues[1:].detach().mean()
        return LevelUpdate({**metric_floats(tensors), "wm/lr": lr}, context)

    # ------------------------------------------------------------------------------------------------ bookkeeping

    def use_optimizer(
        self, optimizer_class: type[th.optim.Optimizer] | None, optimizer_kwargs: dict[str, Any] | None
    ) -> None:
        """Rebuild all four optimisers (and the world model's warm-up scheduler) under SB3's ``optimizer_class`` /
        ``optimizer_kwargs``; call it before any training step.

        :param optimizer_class: a ``torch.optim.Optimizer`` subclass, or None for AdamW
        :param optimizer_kwargs: its keywords (not ``lr``), or None
        """
        super().use_optimizer(optimizer_class, optimizer_kwargs)
        self.wm_optimizer = world_model_optimizer(self.world_model, None, optimizer_class, optimizer_kwargs)
        self.wm_scheduler = world_model_lr_scheduler(self.wm_optimizer, self.config.world_model.warmup)

    @property
    def optimizers(self) -> dict[str, th.optim.Optimizer]:
        """The four optimisers by name: ``world_model``, ``actor``, ``critic``, ``autoencoder``."""
        return {
            "world_model": self.wm_optimizer,
            "actor": self.actor_optimizer,
            "critic": self.critic_optimizer,
            "autoencoder": self.ae_optimizer,
        }

    def optimizer_state_dict(self) -> dict[str, Any]:
        """State of all optimisers and of the world model's warm-up scheduler (for saving).

        :return: name -> state dict
        """
        state = {name: opt.state_dict() for name, opt in self.optimizers.items()}
        if self.wm_scheduler is not None:
            state["world_model_scheduler"] = self.wm_scheduler.state_dict()
        return state

    def load_optimizer_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restore what :meth:`optimizer_state_dict` returned.

        :param state: name -> state dict
        """
        missing = [name for name in self.optimizers if name not in state]
        if missing:
            raise ValueError(f"state lacks the optimiser states {missing}; got keys {sorted(state)}")
        for name, opt in self.optimizers.items():
            opt.load_state_dict(state[name])
        if self.wm_scheduler is not None and "world_model_scheduler" in state:
            self.wm_scheduler.load_state_dict(state["world_model_scheduler"])

    def parameter_counts(self) -> dict[str, int]:
        """Number of (real-valued) parameters per component, slow critics listed separately.

        World model: ``encoder``, ``decoder``, ``heads`` (reward and continue) and ``sequence_model`` (everything
        else: input layer, S5 stack or GRU, h read-out, prior and posterior layers).

        :return: component -> count, with ``"total"``
        """
        wm = self.world_model
        encoder, decoder = _count(wm.encoder.parameters()), _count(wm.decoder.parameters())
        heads = _count(wm.reward_head.parameters()) + _count(wm.cont_head.parameters())
        critics = self.actor_critic.critics.values()
        counts = {
            "world_model/encoder": encoder,
            "world_model/sequence_model": _count(wm.parameters()) - encoder - decoder - heads,
            "world_model/heads": heads,
            "world_model/decoder": decoder,
            "actor": _count(self.actor_critic.actor.parameters()),
            "critics": sum(_count(c.net.parameters()) for c in critics),
            "slow_critics": sum(_count(c.slow_net.parameters()) for c in critics),
            "subgoal_autoencoder": _count(self.autoencoder.parameters()),
        }
        counts["total"] = _count(self.parameters())
        if sum(counts.values()) != 2 * counts["total"]:
            raise RuntimeError("parameter_counts: the components do not add up to the total")
        return counts
