"""One level of the HIEROS hierarchy: world model, actor-critic and subgoal autoencoder (thesis 4.3, 4.6, Algorithm 2).

A :class:`Subactor` owns the three learners of one level i (thesis Figure 4.2) and their optimisers:

* the world model W^i (:func:`~sb3_hieros.agent.world_model.make_world_model`, thesis 4.4),
* the actor-critic Pi^i (:class:`~sb3_hieros.agent.actor_critic.ActorCritic`, thesis 4.3.2) with one critic per
  active reward term of eq. 4.3,
* the subgoal autoencoder G^i on the deterministic state h (:class:`~sb3_hieros.agent.subgoal.SubgoalAutoencoder`,
  thesis 4.3.1).

Spaces. Level 0 acts in the environment (``Discrete`` or a 1-d ``Box``); a level i > 0 acts in the subgoal space of
level i-1, ``MultiDiscrete([n_classes] * n_cat)``, treated as ``n_cat`` one-hot categoricals. Actions are float
vectors everywhere inside the level: one-hot (flattened to ``n_cat * n_classes`` for subgoals) for discrete spaces,
values in [-1, 1] for Box (the policy rescales them to the env bounds). The observation of level i > 0 is the
concatenation of the last k world states ``[h, z]`` of level i-1 (:meth:`Subactor.higher_level_observation_space`).

Subgoals. The subgoal g a level *receives* lives in the code space of its *own* autoencoder: the level above acts in
``subgoal_space()`` of this level, and this level's decoder maps g into its own h space for the subgoal reward (thesis
4.3: "G^i decodes these subgoals g^i"). The actor and critics see the encoded one-hot g (thesis default) or, with
``decoded_subgoal_input=True``, the decoded h-space vector (ablation 5.3.8). The top level (``subgoal_input=False``)
has neither a subgoal input nor a subgoal critic.

Training (:meth:`Subactor.train_step`, Algorithm 2 / thesis 4.6.2): world-model step on the sampled chunk; imagination
of ``imag_horizon`` steps from every posterior state, holding each row's subgoal fixed (thesis 4.6.2, ablation 5.3.9);
per-state rewards (eq. 4.3-4.5); actor and critic steps; autoencoder step on the sampled and imagined h (eq. 4.2).

Documented choices:

* Imagination runs under ``torch.no_grad`` for REINFORCE (discrete actions and subgoals): the actor loss needs only
  log-probabilities of stored actions at detached features. For dynamics backpropagation (Box actions) the graph
  through the world model is kept, only the actor's parameters receive gradients (``backward(inputs=...)``), so the
  world model and the autoencoder are never changed by the actor loss. As in DreamerV3 the actor sees detached
  features while imagining; the gradient reaches it through the reparameterised actions.
* The actor input extras (predicted reward, continue probability, prior entropy, eq. 4.6) are the world-model heads'
  predictions at every state, the start states included, exactly as at acting time (:meth:`Subactor.act`). The
  *loss* continue of a start state is ``1 - is_terminal`` of its replay row (DreamerV3), the imagined ones are the
  continue head's probabilities (detached).
* The novelty reward is computed without gradient; the subgoal reward (a function of h) keeps the dynamics gradient.
* Replay stores the received subgoal *code*; it is decoded with the current autoencoder at every training step, so
  the reward target never goes stale (the reference stores the decoded vector, research note 8.8). The prior entropy
  fed to the actor is that of the prior at the state both in imagination and when acting (the reference feeds the
  posterior entropy when acting, note 5.1).
* Actor, critic and autoencoder use AdamW without weight decay (as the reference and DreamerV3); each critic's
  gradient norm is clipped on its own (the reference gives each critic its own optimiser).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Mapping
from typing import Any, Protocol

import numpy as np
import torch as th
import torch.nn.functional as F
from gymnasium import spaces
from torch import nn

from sb3_hieros.agent.actor_critic import ActorCritic, actor_input, actor_input_dim
from sb3_hieros.agent.subgoal import SubgoalAutoencoder, max_cosine_subgoal_reward, novelty_reward
from sb3_hieros.agent.world_model import (
    LatentState,
    WorldModel,
    make_world_model,
    world_model_lr_scheduler,
    world_model_optimizer,
)
from sb3_hieros.buffers import SequenceSamples
from sb3_hieros.config import HierosConfig, SubgoalConfig
from sb3_hieros.nn.guard import step_if_finite

__all__ = [
    "SUBGOAL_SUCCESS_THRESHOLD",
    "ImaginationLearner",
    "Subactor",
    "action_layout",
    "imagination_start_indices",
    "learn_from_imagination",
    "level_actor_critic",
    "level_optimizers",
    "metric_floats",
    "subgoal_space",
]

#: A subgoal counts as reached when the max-cosine reward (eq. 4.4) of the last imagined state is at least this.
SUBGOAL_SUCCESS_THRESHOLD = 0.5


def subgoal_space(config: SubgoalConfig) -> spaces.MultiDiscrete:
    """Space of the subgoals a level receives: ``n_cat`` categoricals of ``n_classes`` classes (thesis 4.3.1).

    It is the action space of the level above.

    :param config: subgoal autoencoder hyperparameters
    :return: ``MultiDiscrete([n_classes] * n_cat)``
    """
    return spaces.MultiDiscrete([config.n_classes] * config.n_cat)


def action_layout(action_space: spaces.Space) -> tuple[str, int, int]:
    """How a level's action space maps onto the actor's output.

    :param action_space: ``Discrete(n)`` -> one categorical of n classes; ``MultiDiscrete([K] * G)`` (all entries
        equal, e.g. a subgoal space) -> G categoricals of K classes; 1-d ``Box`` -> a bounded normal per dim
    :return: (kind ``"discrete"`` or ``"box"``, classes per group (discrete) or dims (box), number of groups)
    """
    if isinstance(action_space, spaces.Discrete):
        if int(action_space.start) != 0:
            raise ValueError(f"action_space must be a Discrete space starting at 0, got {action_space}")
        if int(action_space.n) < 2:
            raise ValueError(f"action_space must have at least 2 actions, got {action_space}")
        return "discrete", int(action_space.n), 1
    if isinstance(action_space, spaces.MultiDiscrete):
        nvec = np.asarray(action_space.nvec)
        if nvec.ndim != 1 or nvec.size < 1 or not np.all(nvec == nvec[0]) or int(nvec[0]) < 2:
            raise ValueError(
                f"action_space must be a 1-d MultiDiscrete with equal entries >= 2 (e.g. the subgoal space "
                f"MultiDiscrete([8] * 8)), got nvec={nvec.tolist()}"
            )
        if np.any(np.asarray(action_space.start) != 0):
            raise ValueError(f"action_space must be a MultiDiscrete space starting at 0, got {action_space}")
        return "discrete", int(nvec[0]), int(nvec.size)
    if isinstance(action_space, spaces.Box):
        if len(action_space.shape) != 1:
            raise ValueError(f"a Box action_space must be 1-d, got shape {action_space.shape}")
        if not (np.all(np.isfinite(action_space.low)) and np.all(np.isfinite(action_space.high))):
            raise ValueError(f"a Box action_space must have finite bounds, got {action_space}")
        return "box", int(action_space.shape[0]), 1
    raise ValueError(
        f"action_space must be Discrete, MultiDiscrete (subgoals) or a 1-d Box, got {type(action_space).__name__}"
    )


def level_actor_critic(
    feat_dim: int, kind: str, classes: int, groups: int, gradient: str, config: HierosConfig, subgoal_input: bool
) -> ActorCritic:
    """The actor-critic of one level with the reward weights of eq. 4.3 (and the switch of ablation 5.3.10).

    :param feat_dim: actor / critic input size
    :param kind: ``"discrete"`` or ``"box"``
    :param classes: classes per categorical (discrete) or action dims (box)
    :param groups: number of categoricals
    :param gradient: ``"reinforce"`` or ``"dynamics"``
    :param config: hyperparameters (``actor_critic``, ``extrinsic_reward_levels``, ``reference``)
    :param subgoal_input: False for the top level (no subgoal critic)
    :return: the actor-critic
    """
    ac = config.actor_critic
    extrinsic_here = config.extrinsic_reward_levels == "all" or not subgoal_input  # ablation 5.3.10
    weights = {
        "extrinsic": ac.extrinsic_weight if extrinsic_here else 0.0,
        "subgoal": ac.subgoal_weight if subgoal_input else 0.0,
        "novelty": ac.novelty_weight,
    }
    return ActorCritic(
        feat_dim,
        kind,
        classes,
        groups,
        hidden=ac.units,
        layers=ac.layers,
        reward_weights=weights,
        discount=ac.discount,
        lambda_=ac.lambda_,
        entropy_coef=ac.entropy,
        gradient=gradient,
        unimix=ac.unimix,
        slow_fraction=ac.slow_critic_fraction,
        reinforce_advantage=config.reference.reinforce_advantage,
    )


def level_optimizers(
    actor_critic: ActorCritic, autoencoder: SubgoalAutoencoder, config: HierosConfig
) -> tuple[th.optim.Optimizer, th.optim.Optimizer, th.optim.Optimizer]:
    """AdamW optimisers (no weight decay) of the actor, the critics and the subgoal autoencoder of one level.

    :param actor_critic: the level's actor-critic
    :param autoencoder: the level's subgoal autoencoder
    :param config: hyperparameters (``actor_critic`` and ``subgoal`` sections)
    :return: (actor, critic, autoencoder) optimisers
    """
    ac, sg = config.actor_critic, config.subgoal
    return (
        th.optim.AdamW(actor_critic.actor_parameters(), lr=ac.actor_lr, eps=ac.eps, weight_decay=0.0),
        th.optim.AdamW(actor_critic.critic_parameters(), lr=ac.critic_lr, eps=ac.eps, weight_decay=0.0),
        th.optim.AdamW(autoencoder.parameters(), lr=sg.lr, eps=sg.eps, weight_decay=0.0),
    )


def imagination_start_indices(n_states: int, fraction: float, device: th.device) -> th.Tensor | None:
    """Which of the B*T posterior states of a batch start an imagination rollout (Algorithm 2 line 6).

    The thesis and DreamerV3 start from all of them (``fraction=1``); otherwise ``max(1, round(fraction * N))`` are
    drawn uniformly without replacement (torch's global generator, so seeded runs stay reproducible).

    :param n_states: posterior states of the batch, N = B*T
    :param fraction: share of the states to start from, in (0, 1]
    :param device: device of the indices
    :return: (n,) indices into the N states, or None for all of them
    """
    if not 0.0 < fraction <= 1.0:
        raise ValueError(f"fraction must be in (0, 1], got {fraction!r}")
    count = max(1, round(fraction * n_states))
    if count >= n_states:
        return None
    return th.randperm(n_states, device=device)[:count]


class ImaginationLearner(Protocol):
    """What :func:`learn_from_imagination` needs of a level (a :class:`Subactor` or a shared-world-model level)."""

    config: HierosConfig
    actor_critic: ActorCritic
    autoencoder: SubgoalAutoencoder
    actor_optimizer: th.optim.Optimizer
    critic_optimizer: th.optim.Optimizer
    ae_optimizer: th.optim.Optimizer


def learn_from_imagination(
    level: ImaginationLearner,
    feats: th.Tensor,
    actions: th.Tensor,
    rewards: dict[str, th.Tensor],
    continues: th.Tensor,
    h_all: th.Tensor,
) -> dict[str, th.Tensor]:
    """Actor, critic and subgoal-autoencoder steps of one level on its imagined trajectory (Algorithm 2 lines 8-10).

    Actor (eq. 4.6-4.9) and critics (eq. 4.3 terms) each take one guarded step (:func:`step_if_finite`): a skipped
    actor or critic step also undoes the return normalisers' update, and the slow critics follow only a taken critic
    step. The autoencoder (eq. 4.2) trains on ``h_all`` detached. Every gradient stays in its own module.

    :param level: the level whose modules and optimisers train
    :param feats: (M+1, N, F) actor inputs of s_0..s_M
    :param actions: (M, N, *action_shape) imagined actions
    :param rewards: term -> (M+1, N) rewards of s_0..s_M (index 0 unused by the returns)
    :param continues: (M+1, N) continue flags
    :param h_all: (..., D) deterministic states the autoencoder trains on
    :return: 0-d metric tensors: ``actor/*``, ``critic/*`` (per term ``<term>_loss``, ``<term>_value``,
        ``<term>_grad_norm``), ``return/<term>``, ``return/<term>_scale``, ``reward/<term>``, ``ae/*`` and
        ``nonfinite/{actor,critic,autoencoder}`` (1.0 where that step was skipped)
    """
    clip = level.config.actor_critic.grad_clip
    ac = level.actor_critic
    out: dict[str, th.Tensor] = {}
    retnorm_state = {k: v.clone() for k, v in ac.normalizers.state_dict().items()}
    actor_loss, critic_loss, ac_metrics = ac.loss(feats, actions, rewards, continues)
    actor_params = list(ac.actor_parameters())
    level.actor_optimizer.zero_grad(set_to_none=True)
    actor_loss.backward(inputs=actor_params)  # never accumulates into world model / autoencoder / critics
    out["actor/grad_norm"] = nn.utils.clip_grad_norm_(actor_params, clip)
    actor_ok = step_if_finite(level.actor_optimizer, actor_loss, out["actor/grad_norm"])
    level.critic_optimizer.zero_grad(set_to_none=True)
    critic_loss.backward(inputs=list(ac.critic_parameters()))
    for name, critic in ac.critics.items():
        out[f"critic/{name}_grad_norm"] = nn.utils.clip_grad_norm_(critic.net.parameters(), clip)
    critic_ok = step_if_finite(level.critic_optimizer, critic_loss, *(out[f"critic/{n}_grad_norm"] for n in ac.critics))
    if not (actor_ok and critic_ok):  # keep the return statistics finite too
        ac.normalizers.load_state_dict(retnorm_state)
    if critic_ok:
        ac.update_slow_critics()

    ae_params = list(level.autoencoder.parameters())
    ae_loss, ae_metrics = level.autoencoder.loss(h_all.detach().reshape(-1, h_all.shape[-1]))
    level.ae_optimizer.zero_grad(set_to_none=True)
    ae_loss.backward(inputs=ae_params)
    out["ae/grad_norm"] = nn.utils.clip_grad_norm_(ae_params, level.config.subgoal.grad_clip)
    ae_ok = step_if_finite(level.ae_optimizer, ae_loss, out["ae/grad_norm"])

    one = feats.new_ones(())
    out["nonfinite/actor"] = one * (not actor_ok)
    out["nonfinite/critic"] = one * (not critic_ok)
    out["nonfinite/autoencoder"] = one * (not ae_ok)
    out["actor/loss"] = ac_metrics["actor_loss"]
    out["actor/entropy"] = ac_metrics["actor_entropy"]
    out["actor/advantage_mean"] = ac_metrics["advantage_mean"]
    out["actor/advantage_std"] = ac_metrics["advantage_std"]
    out["critic/loss"] = ac_metrics["critic_loss"]
    for name in ac.critics:
        out[f"critic/{name}_loss"] = ac_metrics[f"{name}/critic_loss"]
        out[f"critic/{name}_value"] = ac_metrics[f"{name}/value_mean"]
        out[f"return/{name}"] = ac_metrics[f"{name}/return_mean"]
        out[f"return/{name}_scale"] = ac_metrics[f"{name}/return_scale"]
    for name, r in rewards.items():
        out[f"reward/{name}"] = r[1:].detach().mean()
    for key, value in ae_metrics.items():
        out["ae/" + key.split("/", 1)[1]] = value
    return out


def metric_floats(tensors: Mapping[str, th.Tensor]) -> dict[str, float]:
    """0-d metric tensors as Python floats, with one device-to-host copy for all of them.

    :param tensors: name -> 0-d tensor
    :return: name -> float
    """
    names = list(tensors)
    if not names:
        return {}
    values = th.stack([tensors[k].detach().float().reshape(()) for k in names]).cpu().tolist()
    return dict(zip(names, values, strict=True))


def _count(params: Any) -> int:
    return sum(p.numel() for p in params)


class Subactor(nn.Module):
    """One HIEROS level i (thesis 4.3): world model W^i, actor-critic Pi^i and subgoal autoencoder G^i.

    :param observation_space: observations of this level: the env's for level 0, otherwise
        ``lower.higher_level_observation_space(k)``
    :param action_space: ``Discrete`` or 1-d ``Box`` at level 0; ``lower.subgoal_space()`` above
    :param config: hyperparameters (world model, actor-critic and subgoal sections, ``imag_horizon``)
    :param level: index i of the level (0 = acts in the environment); informational
    :param subgoal_input: False for the top level: no subgoal input, no subgoal reward or critic
    :param decoded_subgoal_input: feed the actor and critics the decoded subgoal (h space) instead of the one-hot code
        (ablation 5.3.8; default False = thesis); has no effect at the top level
    :param bf16: bfloat16 autocast opt-in of the world model
    :param compile: ``torch.compile`` opt-in of the world model's sequence model
    """

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        config: HierosConfig,
        level: int = 0,
        subgoal_input: bool = True,
        decoded_subgoal_input: bool = False,
        bf16: bool = False,
        compile: bool = False,
    ) -> None:
        super().__init__()
        if not isinstance(config, HierosConfig):
            raise ValueError(f"config must be a HierosConfig, got {type(config).__name__}")
        if isinstance(level, bool) or not isinstance(level, int) or level < 0:
            raise ValueError(f"level must be an int >= 0, got {level!r}")
        if not isinstance(observation_space, spaces.Space):
            raise ValueError(f"observation_space must be a gymnasium Space, got {type(observation_space).__name__}")
        if not isinstance(action_space, spaces.Space):
            raise ValueError(f"action_space must be a gymnasium Space, got {type(action_space).__name__}")
        kind, classes, groups = action_layout(action_space)
        self.config = config
        self.level = level
        self.observation_space = observation_space
        self.action_space = action_space
        self.subgoal_input = bool(subgoal_input)
        self.decoded_subgoal_input = bool(decoded_subgoal_input) and self.subgoal_input
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
            observation_space, self.action_dim, config.world_model, bf16=bf16, compile=compile
        )
        self.h_dim = self.world_model.deter_dim
        self.z_dim = self.world_model.stoch_dim
        self.autoencoder = SubgoalAutoencoder(self.h_dim, sg.n_cat, sg.n_classes, sg.units, sg.layers, sg.beta)
        #: flat size of a received subgoal (n_cat * n_classes)
        self.subgoal_dim = sg.n_cat * sg.n_classes
        goal_feat = 0
        if self.subgoal_input:
            goal_feat = self.h_dim if self.decoded_subgoal_input else self.subgoal_dim
        self.feat_dim = actor_input_dim(self.h_dim, self.z_dim, goal_feat, ac.actor_extras)
        self.actor_critic = level_actor_critic(
            self.feat_dim, kind, classes, groups, self.imag_gradient, config, self.subgoal_input
        )
        #: ablation 5.3.9: ``fn(window, subgoal, carry) -> (new_subgoal, carry)`` called every ``subgoal_interval``
        #: imagined steps (see :meth:`_imagine_updating_subgoals`); None holds the replay subgoal fixed (thesis default)
        self.imagination_subgoal_fn: Callable[[th.Tensor, th.Tensor, Any], tuple[th.Tensor, Any]] | None = None
        #: packed posterior states (B, T, C) of the last :meth:`train_step` on a batch with replay context, else None
        self.last_context: th.Tensor | None = None

        self.wm_optimizer = world_model_optimizer(self.world_model)
        self.wm_scheduler: th.optim.lr_scheduler.LRScheduler | None = world_model_lr_scheduler(
            self.wm_optimizer, config.world_model.warmup
        )
        self.actor_optimizer, self.critic_optimizer, self.ae_optimizer = level_optimizers(
            self.actor_critic, self.autoencoder, config
        )

    # ------------------------------------------------------------------------------------------------ spaces

    @property
    def latent_dim(self) -> int:
        """Size D + G*K of one world state ``[h, z]`` (:meth:`encoded_observation`)."""
        return self.h_dim + self.z_dim

    @property
    def reward_terms(self) -> tuple[str, ...]:
        """Reward terms with a critic (weight > 0), in the order of eq. 4.3."""
        return self.actor_critic.active_terms

    def subgoal_space(self) -> spaces.MultiDiscrete:
        """Space of the subgoals this level receives, i.e. the action space of the level above.

        :return: ``MultiDiscrete([n_classes] * n_cat)``
        """
        return subgoal_space(self.config.subgoal)

    def higher_level_observation_space(self, k: int) -> spaces.Box:
        """Observation space of the level above: k consecutive world states of this level, concatenated (thesis 4.3).

        :param k: number of stacked states (``config.subgoal_interval``; 1 for ablation 5.3.6)
        :return: ``Box(-inf, inf, (k * (D + G*K),), float32)``
        """
        if isinstance(k, bool) or not isinstance(k, int | np.integer) or k < 1:
            raise ValueError(f"k must be a positive int, got {k!r}")
        return spaces.Box(-np.inf, np.inf, (int(k) * self.latent_dim,), np.float32)

    # ------------------------------------------------------------------------------------------------ checks

    def _check_state(self, state: Any, name: str = "state") -> int:
        if not isinstance(state, LatentState):
            raise ValueError(f"{name} must be a LatentState, got {type(state).__name__}")
        if len(state.batch_shape) != 1:
            raise ValueError(f"{name} must have batch shape (B,), got {tuple(state.batch_shape)}")
        if state.deter.shape[-1] != self.h_dim or state.stoch.shape[-1] != self.z_dim:
            raise ValueError(
                f"{name} has deter/stoch sizes {state.deter.shape[-1]}/{state.stoch.shape[-1]}, expected "
                f"{self.h_dim}/{self.z_dim}"
            )
        return int(state.batch_shape[0])

    def _flat_subgoal(self, subgoal: Any, lead: tuple[int, ...], name: str) -> th.Tensor:
        """A subgoal tensor of shape (*lead, S) or (*lead, n_cat, n_classes) as float (*lead, S)."""
        sg = self.config.subgoal
        accepted = ((*lead, self.subgoal_dim), (*lead, sg.n_cat, sg.n_classes))
        if not isinstance(subgoal, th.Tensor):
            raise ValueError(f"{name} must be a torch.Tensor of shape {accepted[0]}, got {type(subgoal).__name__}")
        if tuple(subgoal.shape) not in accepted:
            raise ValueError(f"{name} has shape {tuple(subgoal.shape)}, expected {accepted[0]} or {accepted[1]}")
        if not subgoal.is_floating_point():
            raise ValueError(f"{name} must be a float (one-hot) tensor, got dtype {subgoal.dtype}")
        return subgoal.reshape(*lead, self.subgoal_dim).float()

    def _check_subgoal_arg(self, subgoal: Any, lead: tuple[int, ...], name: str) -> th.Tensor | None:
        if not self.subgoal_input:
            if subgoal is not None:
                raise ValueError(f"{name} must be None: this is the top level (subgoal_input=False)")
            return None
        if subgoal is None:
            raise ValueError(f"{name} is required: this level takes a subgoal of shape {(*lead, self.subgoal_dim)}")
        return self._flat_subgoal(subgoal, lead, name)

    def action_vectors(self, actions: th.Tensor, is_first: th.Tensor) -> th.Tensor:
        """Replay actions as the float vectors the world model consumes (previous actions, zero where ``is_first``).

        Float vectors ``(B, T, A)`` pass unchanged. For discrete spaces, integer indices ``(B, T)`` / ``(B, T, 1)``
        (Discrete) or ``(B, T, G)`` (MultiDiscrete, as SB3 buffers store them) are one-hot encoded and zeroed where
        ``is_first`` (where replay holds a placeholder 0). Box actions must already be in [-1, 1].

        :param actions: (B, T, A) float, or integer indices as above
        :param is_first: (B, T) episode starts
        :return: (B, T, A) float
        """
        if not isinstance(actions, th.Tensor):
            raise ValueError(f"samples.actions must be a torch.Tensor, got {type(actions).__name__}")
        lead = tuple(is_first.shape)
        if tuple(actions.shape) == (*lead, self.action_dim) and actions.is_floating_point():
            return actions
        if self.action_kind == "discrete":
            index_shapes = [(*lead, self.action_groups)] + ([lead] if self.action_groups == 1 else [])
            if tuple(actions.shape) in index_shapes:
                index = actions.reshape(*lead, self.action_groups)
                if index.is_floating_point():
                    if not th.equal(index, index.round()):
                        raise ValueError("samples.actions holds non-integer values where action indices are expected")
                index = index.long()
                if index.min() < 0 or index.max() >= self.action_classes:
                    raise ValueError(
                        f"samples.actions indices must lie in [0, {self.action_classes}), got range "
                        f"[{int(index.min())}, {int(index.max())}]"
                    )
                one_hot = F.one_hot(index, self.action_classes).float().reshape(*lead, self.action_dim)
                return one_hot * (~is_first.bool()).unsqueeze(-1).float()
        raise ValueError(
            f"samples.actions has shape {tuple(actions.shape)} and dtype {actions.dtype}; expected float "
            f"{(*lead, self.action_dim)}" + (" or integer indices" if self.action_kind == "discrete" else "")
        )

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
        observation: th.Tensor | Mapping[str, th.Tensor],
        prev_action: th.Tensor,
        is_first: th.Tensor,
        deterministic: bool = False,
    ) -> LatentState:
        """Encode one observation into the world state (Algorithm 1 ``Encode``; no gradients).

        :param state: previous state (batch (B,)), or None at the very start
        :param observation: (B, *obs_shape) (dict for Dict spaces)
        :param prev_action: (B, A) float action vector taken after the previous observation (from :meth:`act`)
        :param is_first: (B,) bool, new episodes (state and ``prev_action`` ignored there)
        :param deterministic: take the posterior mode instead of a sample
        :return: posterior state (batch (B,))
        """
        return self.world_model.obs_step(state, observation, prev_action, is_first, deterministic)

    def _goal_features(self, subgoal: th.Tensor | None) -> th.Tensor | None:
        """What the actor sees of the subgoal: the one-hot code (thesis) or its decoding (ablation 5.3.8)."""
        if subgoal is None or not self.decoded_subgoal_input:
            return subgoal
        with th.no_grad():
            return self.autoencoder.decode(subgoal)

    def _features(self, state: LatentState, goal_feat: th.Tensor | None) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        """Actor / critic input s_t of eq. 4.6 and the world model's reward and continue predictions at ``state``.

        :param state: states of any batch shape *B
        :param goal_feat: (*B, S') subgoal features or None
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

    def _checked_features(
        self, state: LatentState, subgoal: th.Tensor | None
    ) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        """:meth:`_features` of a user-given ``state`` (batch (B,)) and ``subgoal``, both checked first."""
        batch = self._check_state(state)
        goal = self._check_subgoal_arg(subgoal, (batch,), "subgoal")
        return self._features(state, self._goal_features(goal))

    @th.no_grad()
    def act(self, state: LatentState, subgoal: th.Tensor | None, deterministic: bool = False) -> th.Tensor:
        """Action of this level in ``state`` (eq. 4.6; no gradients).

        :param state: current world state (batch (B,))
        :param subgoal: (B, n_cat * n_classes) or (B, n_cat, n_classes) one-hot subgoal from the level above; None at
            the top level
        :param deterministic: the distribution's mode (thesis 4.3.2 for environment interaction) instead of a sample
        :return: (B, A): one-hot for Discrete, ``n_cat * n_classes`` grouped one-hot for subgoals, [-1, 1] for Box
        """
        feat, _, _ = self._checked_features(state, subgoal)
        action = self.actor_critic.act(feat, deterministic)
        return action.reshape(feat.shape[0], self.action_dim)

    @th.no_grad()
    def state_estimates(self, state: LatentState, subgoal: th.Tensor | None) -> dict[str, th.Tensor]:
        """What this level predicts about ``state``: the world model's reward and continue heads and the value of
        each active reward term's fast critic (eq. 4.3), for diagnostics (e.g. ``benchmarks/cartpole_failures.py``).

        :param state: world state (batch (B,))
        :param subgoal: (B, n_cat * n_classes) or (B, n_cat, n_classes) one-hot subgoal in force; None at the top
        :return: ``"reward"``, ``"continue"`` and ``"value/<term>"`` for every term of :attr:`reward_terms`, each (B,)
        """
        feat, reward, cont = self._checked_features(state, subgoal)
        out = {"reward": reward, "continue": cont}
        for name in self.reward_terms:
            out[f"value/{name}"] = self.actor_critic.critics[name].value(feat)
        return out

    @th.no_grad()
    def encoded_observation(self, state: LatentState) -> th.Tensor:
        """One world state as the level above sees it (thesis 4.3), to be concatenated over k steps.

        :param state: world state (batch (B,))
        :return: (B, D + G*K) = ``[h, z]`` (h is already symlog-scaled inside the world model)
        """
        self._check_state(state)
        return self.world_model.features(state)

    @th.no_grad()
    def decode_subgoal(self, subgoal: th.Tensor) -> th.Tensor:
        """Subgoal code -> target state h of this level (decoder of G^i, eq. 4.1).

        :param subgoal: (B, n_cat * n_classes) or (B, n_cat, n_classes)
        :return: (B, D)
        """
        if not isinstance(subgoal, th.Tensor) or subgoal.dim() < 2:
            shape = tuple(subgoal.shape) if isinstance(subgoal, th.Tensor) else type(subgoal).__name__
            raise ValueError(f"subgoal must be a tensor of shape (B, {self.subgoal_dim}), got {shape}")
        return self.autoencoder.decode(self._flat_subgoal(subgoal, (int(subgoal.shape[0]),), "subgoal"))

    @th.no_grad()
    def decode_state_observation(self, h: th.Tensor, stoch: th.Tensor) -> th.Tensor | dict[str, th.Tensor]:
        """Observation the world-model decoder predicts from ``(h, z)`` (subgoal visualisation: a decoded subgoal h
        with the current z, reference 6.4).

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

    def _check_samples(self, samples: Any) -> tuple[SequenceSamples, th.Tensor | None]:
        for field in ("observations", "actions", "rewards", "is_first", "is_terminal"):
            if not hasattr(samples, field):
                raise ValueError(f"samples must have the attribute {field!r} (SequenceSamples-like)")
        is_first = samples.is_first
        if not isinstance(is_first, th.Tensor) or is_first.dim() != 2:
            shape = tuple(is_first.shape) if isinstance(is_first, th.Tensor) else type(is_first).__name__
            raise ValueError(f"samples.is_first must be a (B, T) tensor, got {shape}")
        lead = tuple(is_first.shape)
        is_terminal = samples.is_terminal
        if not isinstance(is_terminal, th.Tensor) or tuple(is_terminal.shape) != lead:
            shape = tuple(is_terminal.shape) if isinstance(is_terminal, th.Tensor) else type(is_terminal).__name__
            raise ValueError(f"samples.is_terminal must have shape {lead}, got {shape}")
        subgoals = self._check_subgoal_arg(getattr(samples, "subgoals", None), lead, "samples.subgoals")
        checked = SequenceSamples(
            samples.observations,
            self.action_vectors(samples.actions, is_first),
            samples.rewards,
            is_first,
            is_terminal,
            subgoals,
        )
        return checked, subgoals

    def _imagine(
        self,
        start: LatentState,
        goal_feat: th.Tensor | None,
        replan: Callable[[list[LatentState]], th.Tensor] | None = None,
    ) -> tuple[LatentState, th.Tensor, th.Tensor, th.Tensor, th.Tensor]:
        """Roll out ``imag_horizon`` steps with the current actor (thesis 4.4.3, Algorithm 2 line 7).

        The world-model heads are evaluated once per state and reused for the actor input and the rewards. The
        actor acts on detached features (DreamerV3); with dynamics backpropagation the reparameterised actions carry
        the gradient into the rollout.

        :param start: (N,) detached posterior states
        :param goal_feat: (N, S') subgoal features in force at s_0, or None
        :param replan: None holds ``goal_feat`` over the horizon (thesis default); otherwise it is called at every
            imagined step t > 0 with ``t % subgoal_interval == 0`` with the states s_0..s_t so far and returns the
            subgoal features in force from s_t on (ablation 5.3.9)
        :return: states (H+1, N), features (H+1, N, F), actions (H, N, *action_shape), predicted rewards (H+1, N),
            continue probabilities (H+1, N)
        """
        wm, actor = self.world_model, self.actor_critic.actor
        horizon, k = self.config.imag_horizon, self.config.subgoal_interval
        state = start
        states, feats, actions, rewards, conts = [start], [], [], [], []
        with wm.reuse_step_weights():  # one discretisation for the whole rollout (S5WM)
            for t in range(horizon + 1):
                if replan is not None and t > 0 and t % k == 0:
                    goal_feat = replan(states)
                feat, reward, cont = self._features(state, goal_feat)
                feats.append(feat)
                rewards.append(reward)
                conts.append(cont)
                if t == horizon:
                    break
                action = actor(feat.detach()).sample()  # (N, *action_shape)
                actions.append(action)
                state, _ = wm.img_step(state, action.reshape(action.shape[0], self.action_dim))
                states.append(state)
        trajectory = LatentState(*(th.stack(fields, 0) for fields in zip(*states, strict=True)))
        return trajectory, th.stack(feats, 0), th.stack(actions, 0), th.stack(rewards, 0), th.stack(conts, 0)

    def _imagine_updating_subgoals(
        self, start: LatentState, codes: th.Tensor
    ) -> tuple[LatentState, th.Tensor, th.Tensor, th.Tensor, th.Tensor, th.Tensor]:
        """:meth:`_imagine` with the subgoal re-planned every k imagined steps (ablation 5.3.9).

        At every imagined step t > 0 with ``t % subgoal_interval == 0`` the level above is invoked through
        :attr:`imagination_subgoal_fn` with the world states ``[h, z]`` of the last k imagined states s_{t-k+1..t}
        (N, k, D + G*K), the subgoal code in force and its carry (None at the first call of a rollout); it returns the
        new subgoal code and the carry for its next call. The actor sees the new subgoal from s_t on. The subgoal
        reward of s_t is measured against the subgoal that was in force when a_{t-1} was chosen.

        :param start: (N,) detached posterior states
        :param codes: (N, n_cat * n_classes) subgoal codes of the replay rows (in force at s_0)
        :return: as :meth:`_imagine`, plus (H+1, N, D) decoded subgoal targets of the subgoal reward per state
        """
        fn = self.imagination_subgoal_fn
        if fn is None:
            raise ValueError(
                "imagination_subgoal_fn is not set: the policy installs it (update_subgoals_in_imagination)"
            )
        wm = self.world_model
        horizon, k = self.config.imag_horizon, self.config.subgoal_interval
        with th.no_grad():
            target = self.autoencoder.decode(codes)  # (N, D)
        planned = [target]  # planned[j]: decoded subgoal in force at the imagined steps j*k .. (j+1)*k - 1
        plan: dict[str, Any] = {"code": codes, "carry": None}

        def goal_features(code: th.Tensor, decoded: th.Tensor) -> th.Tensor:
            return decoded if self.decoded_subgoal_input else code

        @th.no_grad()
        def replan(states: list[LatentState]) -> th.Tensor:
            window = th.stack([wm.features(s.detach()) for s in states[-k:]], 1)  # (N, k, D + G*K)
            code, plan["carry"] = fn(window, plan["code"], plan["carry"])
            plan["code"] = code.reshape(code.shape[0], self.subgoal_dim).float()
            planned.append(self.autoencoder.decode(plan["code"]))
            return goal_features(plan["code"], planned[-1])

        rollout = self._imagine(start, goal_features(codes, target), replan)
        # the target of s_{t+1} is the one pursued by a_t, i.e. in force at step t
        targets = th.stack([target] + [planned[t // k] for t in range(horizon)], 0)
        return (*rollout, targets)

    def context_start(self, samples: Any) -> LatentState | None:
        """The world state before each chunk of a batch, from its replay context (``samples.context``, see
        :mod:`sb3_hieros.buffers`), or None (start from zeros) for a batch without one.

        :param samples: a batch of B chunks
        :return: state of batch shape (B,) or None
        """
        context = getattr(samples, "context", None)
        return None if context is None else self.world_model.unpack_context(context)

    def world_model_step(self, batch: SequenceSamples, samples: Any) -> tuple[dict[str, float], LatentState]:
        """Step 1 of :meth:`train_step` (also used by the shared-world-model hierarchy): one world-model update on
        ``batch``, started from the replay context of ``samples`` (:meth:`context_start`), whose packed posterior
        states it keeps in :attr:`last_context` (None without a context).

        :param batch: the checked batch the world model trains on (previous actions as float vectors)
        :param samples: the batch as sampled (its ``context``, if any)
        :return: metrics ``wm/*`` (with ``wm/lr``) and ``nonfinite/world_model``, and the detached posterior states
        """
        wm = self.world_model
        wm_metrics, post = wm.train_step(batch, self.wm_optimizer, self.wm_scheduler, self.context_start(samples))
        self.last_context = None if getattr(samples, "context", None) is None else wm.pack_context(post)
        metrics = {f"wm/{k}": float(v) for k, v in wm_metrics.items()}
        metrics["nonfinite/world_model"] = metrics.pop("wm/nonfinite")
        metrics["wm/lr"] = float(self.wm_optimizer.param_groups[0]["lr"])
        return metrics, post

    def train_step(self, samples: Any) -> dict[str, float]:
        """One training iteration of this level on a batch of chunks (Algorithm 2, thesis 4.6.2).

        1. World-model step on the chunk (eq. 4.10-4.13, warm-up scheduler, clip ``world_model.grad_clip``).
        2. Imagination of ``imag_horizon`` steps from all B*T detached posterior states (or the share
           ``imag_start_fraction`` of them, :func:`imagination_start_indices`), each row's subgoal held fixed.
        3. Rewards per imagined state (eq. 4.3-4.5): extrinsic = reward head; subgoal = max-cosine of h and the
           decoded subgoal (not at the top level); novelty = autoencoder reconstruction error of h (no gradient).
           Continues: ``1 - is_terminal`` for the start state, the continue head afterwards.
        4. Actor and critic losses (:meth:`ActorCritic.loss`), one step each, slow-critic EMA.
        5. Autoencoder step (eq. 4.2) on the sampled and imagined h (detached).

        Metrics (floats): ``wm/*`` (world-model loss terms, ``grad_norm``, ``lr``); ``actor/loss``,
        ``actor/entropy``, ``actor/advantage_mean``, ``actor/advantage_std``, ``actor/grad_norm``; ``critic/loss``
        and per active term ``critic/<term>_loss``, ``critic/<term>_value``, ``critic/<term>_grad_norm``,
        ``return/<term>``, ``return/<term>_scale``; ``reward/<term>`` = mean predicted reward of the imagined states
        s_1..s_H for every computed term (``subgoal`` below the top, ``novelty`` if its weight is > 0);
        ``subgoal/final_reward`` = mean subgoal reward of the last imagined state s_H and ``subgoal/success`` = the
        fraction of rollouts whose s_H reaches a subgoal reward >= :data:`SUBGOAL_SUCCESS_THRESHOLD` (below the top
        only); ``imag/continue`` = mean continue probability of s_1..s_H; ``ae/*`` (autoencoder loss terms,
        ``grad_norm``); ``nonfinite/<name>`` for ``world_model``, ``actor``, ``critic`` and ``autoencoder``: 1.0 when
        that step was skipped because its loss or gradient norm was not finite (no parameter or optimiser state
        changes; a skipped actor or critic step also undoes the return normalisers' update, a skipped critic step
        leaves the slow critics alone), else 0.0.

        :param samples: :class:`~sb3_hieros.buffers.SequenceSamples` (B, T, ...): ``actions[:, t]`` = a_{t-1} (float
            vectors or, for discrete spaces, indices, see :meth:`action_vectors`); ``subgoals`` (B, T, n_cat *
            n_classes) or (B, T, n_cat, n_classes) required unless this is the top level; with a ``context``
            the world model starts each chunk there (:meth:`context_start`) and :attr:`last_context` holds the
            packed posterior states for the buffer's ``store_context``
        :return: metrics
        """
        batch, subgoals = self._check_samples(samples)
        tensors: dict[str, th.Tensor] = {}

        # (1) world model, from the replay context where the batch has one
        metrics, post = self.world_model_step(batch, samples)

        # (2) imagination from every posterior state (or imag_start_fraction of them), subgoal of the row held fixed
        start = post.flatten_batch()  # (N,) with N = B*T, detached
        first_cont = 1.0 - batch.is_terminal.reshape(-1).float()  # (N,)
        flat_goals = None if subgoals is None else subgoals.reshape(-1, self.subgoal_dim)  # (N, G)
        chosen = imagination_start_indices(
            int(start.batch_shape[0]), self.config.imag_start_fraction, start.deter.device
        )
        if chosen is not None:
            start, first_cont = start.select(chosen), first_cont[chosen]
            flat_goals = None if flat_goals is None else flat_goals[chosen]
        goal = goal_feat = None
        if flat_goals is not None:
            with th.no_grad():
                goal = self.autoencoder.decode(flat_goals)  # (N, D): target in this level's h space
            goal_feat = goal if self.decoded_subgoal_input else flat_goals
        dynamics = self.imag_gradient == "dynamics"
        with contextlib.nullcontext() if dynamics else th.no_grad():
            if self.imagination_subgoal_fn is not None and subgoals is not None:  # ablation 5.3.9
                traj, feats, actions, ext_reward, cont_pred, goal = self._imagine_updating_subgoals(start, flat_goals)
            else:
                traj, feats, actions, ext_reward, cont_pred = self._imagine(start, goal_feat)

            # (3) rewards per state s_0..s_H (index 0 unused by the returns)
            rewards = {"extrinsic": ext_reward}
            if goal is not None:
                rewards["subgoal"] = max_cosine_subgoal_reward(traj.deter, goal)  # (H+1, N), in [-1, 1]
            if "novelty" in self.reward_terms:
                with th.no_grad():
                    rewards["novelty"] = novelty_reward(traj.deter, self.autoencoder)
        continues = th.cat([first_cont.unsqueeze(0), cont_pred[1:].detach()], 0)  # (H+1, N)

        # (4) actor and critics, (5) subgoal autoencoder on the sampled (s_0) and imagined (s_1..s_H) states
        tensors.update(learn_from_imagination(self, feats, actions, rewards, continues, traj.deter))
        if "subgoal" in rewards:
            final = rewards["subgoal"][-1].detach()  # (N,)
            tensors["subgoal/final_reward"] = final.mean()
            tensors["subgoal/success"] = (final >= SUBGOAL_SUCCESS_THRESHOLD).float().mean()
        tensors["imag/continue"] = cont_pred[1:].detach().mean()
        metrics.update(metric_floats(tensors))
        return metrics

    # ------------------------------------------------------------------------------------------------ bookkeeping

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
