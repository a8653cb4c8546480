"""What every level learns from its imagination, with or without a world model of its own (thesis 4.3, 4.6.2).

:func:`level_actor_critic` and :func:`level_optimizers` build a level's actor-critic (with the reward weights of
eq. 4.3) and its optimisers; :func:`imagination_start_indices` picks the posterior states that start imagination;
:func:`learn_from_imagination` takes the actor, critic and subgoal-autoencoder steps on an imagined trajectory
(Algorithm 2 lines 8-10). Both :class:`~sb3_hieros.agent.subactor.Subactor` and the levels of the shared-world-model
ablation (:mod:`sb3_hieros.agent.shared`) use them.
"""

from __future__ import annotations

from typing import Any

import torch as th
from gymnasium import spaces
from torch import nn

from sb3_hieros.agent.actor_critic import ActorCritic, ReplaySequences
from sb3_hieros.agent.subgoal import SubgoalAutoencoder
from sb3_hieros.config import HierosConfig
from sb3_hieros.nn.guard import step_if_finite
from sb3_hieros.nn.networks import bf16_autocast
from sb3_hieros.nn.optim import user_optimizer
from sb3_hieros.spaces import subgoal_space

__all__ = [
    "SUBGOAL_SUCCESS_THRESHOLD",
    "LevelLearner",
    "imagination_start_indices",
    "learn_from_imagination",
    "level_actor_critic",
    "level_optimizers",
]

#: A subgoal counts as reached when the max-cosine reward (eq. 4.4) of the last imagined state is at least this.
SUBGOAL_SUCCESS_THRESHOLD = 0.5


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
        action_groups=groups,
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
        return_normalization=ac.return_normalization,
        value_gradient=ac.value_gradient,
        return_critic=ac.return_critic,
        replay_value_scale=ac.replay_value_loss,
    )


def level_optimizers(
    actor_critic: ActorCritic,
    autoencoder: SubgoalAutoencoder,
    config: HierosConfig,
    optimizer_class: type[th.optim.Optimizer] | None = None,
    optimizer_kwargs: dict[str, Any] | None = None,
) -> tuple[th.optim.Optimizer, th.optim.Optimizer, th.optim.Optimizer]:
    """AdamW optimisers (no weight decay) of the actor, the critics and the subgoal autoencoder of one level; with
    SB3's ``optimizer_class`` / ``optimizer_kwargs`` the user's (:func:`~sb3_hieros.nn.optim.user_optimizer`).

    :param actor_critic: the level's actor-critic
    :param autoencoder: the level's subgoal autoencoder
    :param config: hyperparameters (``actor_critic`` and ``subgoal`` sections)
    :param optimizer_class: a ``torch.optim.Optimizer`` subclass, or None
    :param optimizer_kwargs: its keywords (not ``lr``), or None
    :return: (actor, critic, autoencoder) optimisers
    """
    ac, sg = config.actor_critic, config.subgoal
    if optimizer_class is not None or optimizer_kwargs:
        learners = (
            (actor_critic.actor_parameters(), ac.actor_lr, ac.eps),
            (actor_critic.critic_parameters(), ac.critic_lr, ac.eps),
            (autoencoder.parameters(), sg.lr, sg.eps),
        )
        actor, critic, ae = (
            user_optimizer([(params, True)], lr, eps, 0.0, optimizer_class, optimizer_kwargs)
            for params, lr, eps in learners
        )
        return actor, critic, ae
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
    count = max(1, round(fraction * n_states))
    if count >= n_states:
        return None
    return th.randperm(n_states, device=device)[:count]


class LevelLearner(nn.Module):
    """What every level learns besides a world model (thesis 4.3): the subgoal autoencoder G^i on the level's h and the
    actor-critic Pi^i, their optimisers, and what the actor sees of a received subgoal.

    Subclasses (:class:`~sb3_hieros.agent.subactor.Subactor`, :class:`~sb3_hieros.agent.shared.SharedLevel`) set
    ``config``, ``subgoal_input`` and ``decoded_subgoal_input`` and call :meth:`_build_learners`.
    """

    config: HierosConfig
    subgoal_input: bool
    decoded_subgoal_input: bool
    autoencoder: SubgoalAutoencoder
    actor_critic: ActorCritic
    #: compute the actor-critic and autoencoder losses under a bfloat16 autocast (:func:`learn_from_imagination`):
    #: True, False or "auto" (where the device computes bf16 natively)
    bf16: bool | str = False

    def _build_learners(self, h_dim: int, feat_dim: int, kind: str, classes: int, groups: int, gradient: str) -> None:
        """The autoencoder on h, then the actor-critic (:func:`level_actor_critic`) and their optimisers.

        :param h_dim: size of the h the autoencoder encodes
        :param feat_dim: actor / critic input size
        :param kind: ``"discrete"`` or ``"box"``
        :param classes: classes per categorical (discrete) or action dims (box)
        :param groups: number of categoricals
        :param gradient: ``"reinforce"`` or ``"dynamics"``
        """
        sg = self.config.subgoal
        self.autoencoder = SubgoalAutoencoder(h_dim, sg.n_cat, sg.n_classes, sg.units, sg.layers, sg.beta)
        self.actor_critic = level_actor_critic(
            feat_dim, kind, classes, groups, gradient, self.config, self.subgoal_input
        )
        self.actor_optimizer, self.critic_optimizer, self.ae_optimizer = level_optimizers(
            self.actor_critic, self.autoencoder, self.config
        )

    def use_optimizer(
        self, optimizer_class: type[th.optim.Optimizer] | None, optimizer_kwargs: dict[str, Any] | None
    ) -> None:
        """Rebuild this level's optimisers under SB3's ``optimizer_class`` / ``optimizer_kwargs``
        (:func:`level_optimizers`); call it before any training step.

        :param optimizer_class: a ``torch.optim.Optimizer`` subclass, or None for AdamW
        :param optimizer_kwargs: its keywords (not ``lr``), or None
        """
        self.actor_optimizer, self.critic_optimizer, self.ae_optimizer = level_optimizers(
            self.actor_critic, self.autoencoder, self.config, optimizer_class, optimizer_kwargs
        )

    @property
    def reward_terms(self) -> tuple[str, ...]:
        """Reward terms with a critic (weight > 0), in the order of eq. 4.3."""
        return self.actor_critic.active_terms

    def subgoal_space(self) -> spaces.MultiDiscrete:
        """Space of the subgoals this level receives, i.e. the action space of the level above.

        :return: ``MultiDiscrete([n_classes] * n_cat)``
        """
        return subgoal_space(self.config.subgoal)

    def goal_features(self, subgoal: th.Tensor | None) -> th.Tensor | None:
        """What the actor sees of the received subgoal: the one-hot code (thesis) or its decoding (ablation 5.3.8).

        :param subgoal: (N, n_cat * n_classes) one-hot code, or None at the top level
        :return: (N, S') or None
        """
        if subgoal is None or not self.decoded_subgoal_input:
            return subgoal
        with th.no_grad():
            return self.autoencoder.decode(subgoal)


def learn_from_imagination(
    level: LevelLearner,
    feats: th.Tensor,
    actions: th.Tensor,
    rewards: dict[str, th.Tensor],
    continues: th.Tensor,
    h_all: th.Tensor,
    replay: ReplaySequences | None = None,
) -> dict[str, th.Tensor]:
    """Actor, critic and subgoal-autoencoder steps of one level on its imagined trajectory (Algorithm 2 lines 8-10).

    Actor (eq. 4.6-4.9) and critics (eq. 4.3 terms) each take one guarded step (:func:`step_if_finite`): a skipped
    actor or critic step also undoes the return normalisers' update, and the slow critics follow only a taken critic
    step. The autoencoder (eq. 4.2) trains on ``h_all`` detached. Every gradient stays in its own module. With
    ``level.bf16`` both losses are computed under a bfloat16 autocast (:func:`~sb3_hieros.nn.networks.bf16_autocast`);
    the backward passes and the optimiser steps run after it.

    :param level: the level whose modules and optimisers train
    :param feats: (M+1, N, F) actor inputs of s_0..s_M
    :param actions: (M, N, *action_shape) imagined actions
    :param rewards: term -> (M+1, N) rewards of s_0..s_M (index 0 unused by the returns)
    :param continues: (M+1, N) continue flags
    :param h_all: (..., D) deterministic states the autoencoder trains on
    :param replay: the replayed sequences the imagination started from, for the critics' replay value loss
        (``actor_critic.replay_value_loss`` > 0), or None
    :return: 0-d metric tensors: ``actor/*``, ``critic/*`` (per term ``<term>_loss``, ``<term>_value``,
        ``<term>_grad_norm``, with a replay value loss ``<term>_replay_loss``), ``return/<term>``,
        ``return/<term>_scale`` (with a replay value loss ``return/<term>_replay``), ``reward/<term>``, ``ae/*`` and
        ``nonfinite/{actor,critic,autoencoder}`` (1.0 where that step was skipped)
    """
    clip = level.config.actor_critic.grad_clip
    ac = level.actor_critic
    out: dict[str, th.Tensor] = {}
    retnorm_state = {k: v.clone() for k, v in ac.normalizers.state_dict().items()}
    with bf16_autocast(level.bf16, feats.device):
        actor_loss, critic_loss, ac_metrics = ac.loss(feats, actions, rewards, continues, replay=replay)
    actor_params = list(ac.actor_parameters())
    level.actor_optimizer.zero_grad(set_to_none=True)
    level.critic_optimizer.zero_grad(set_to_none=True)
    # One backward pass for both: the actor loss reaches no critic parameter (its values come from detached critic
    # parameters) and the critic loss no actor parameter (it sees detached features and returns), so each parameter
    # gets exactly its own loss's gradient; nothing accumulates into world model or autoencoder.
    (actor_loss + critic_loss).backward(inputs=actor_params + list(ac.critic_parameters()))
    out["actor/grad_norm"] = nn.utils.clip_grad_norm_(actor_params, clip)
    actor_ok = step_if_finite(level.actor_optimizer, actor_loss, out["actor/grad_norm"])
    for name, critic in ac.critics.items():
        out[f"critic/{name}_grad_norm"] = nn.utils.clip_grad_norm_(critic.net.parameters(), clip)
    critic_ok = step_if_finite(level.critic_optimizer, critic_loss, *(out[f"critic/{n}_grad_norm"] for n in ac.critics))
    if not (actor_ok and critic_ok):  # keep the return statistics finite too
        ac.normalizers.load_state_dict(retnorm_state)
    if critic_ok:
        ac.update_slow_critics()

    ae_params = list(level.autoencoder.parameters())
    with bf16_autocast(level.bf16, feats.device):
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
        if f"{name}/replay_critic_loss" in ac_metrics:
            out[f"critic/{name}_replay_loss"] = ac_metrics[f"{name}/replay_critic_loss"]
            out[f"return/{name}_replay"] = ac_metrics[f"{name}/replay_return_mean"]
    for name, r in rewards.items():
        out[f"reward/{name}"] = r[1:].detach().mean()
    for key, value in ae_metrics.items():
        out["ae/" + key.split("/", 1)[1]] = value
    return out
