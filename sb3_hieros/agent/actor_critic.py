"""DreamerV3-style actor-critic trained on imagined trajectories (thesis 4.3.2, eq. 4.3, 4.6 - 4.9).

One actor and up to three critics, one per reward term (``"extrinsic"``, ``"subgoal"``, ``"novelty"``). Each critic
predicts the lambda-return of its own term as a 255-bin symlog two-hot distribution, has a slow EMA copy used as a
regulariser, and owns a :class:`ReturnNormalizer`. The actor maximises the weighted sum of the per-term normalised
advantages (eq. 4.3 applied at the advantage level, as in the reference and DreamerV3), with REINFORCE for discrete
actions and backpropagation through the imagined dynamics for Box actions, plus an entropy bonus.

The thesis states its value loss as a squared TD(0) error (eq. 4.7, 4.8) and its baseline as the slow critics
(eq. 4.9), but says that HIEROS adopts DreamerV3's actor-critic unchanged apart from the per-term critics; we follow
DreamerV3 (and the reference): critics regress lambda-returns with the two-hot NLL, and returns and baseline come from
the fast critics, the slow critics acting as a regulariser of the critic loss (``return_critic="slow"`` takes returns
and baseline from the slow critics instead, as eq. 4.9 and DreamerV2's target critic do).

The module knows nothing about the world model: the caller imagines a trajectory and hands in features, actions,
per-term rewards and continue probabilities (time-major, see :meth:`ActorCritic.loss`).
"""

from __future__ import annotations

import copy
from collections.abc import Collection, Iterator, Mapping
from typing import Literal, NamedTuple

import torch as th
from torch import nn
from torch.func import functional_call

from sb3_hieros.agent.returns import ReturnNormalizer, cumulative_discount, lambda_returns, replay_lambda_returns
from sb3_hieros.config import RETURN_CRITICS, VALUE_GRADIENTS
from sb3_hieros.nn.distributions import (
    BoundedNormal,
    OneHotCategoricalST,
    TwoHotSymlog,
    bins_are_antisymmetric,
    symlog,
    symlog_bins,
)
from sb3_hieros.nn.networks import MLP

#: Names of the reward terms, in the order of eq. 4.3.
REWARD_TERMS = ("extrinsic", "subgoal", "novelty")
#: Reward weights of thesis table 4.6.3 (extrinsic 1, subgoal 0.3, novelty 0.1).
DEFAULT_REWARD_WEIGHTS: dict[str, float] = {"extrinsic": 1.0, "subgoal": 0.3, "novelty": 0.1}
#: Bounds of the standard deviation of Box actions (:class:`~sb3_hieros.nn.distributions.BoundedNormal`, DreamerV3).
ACTION_MIN_STD, ACTION_MAX_STD = 0.1, 1.0
#: Bins of the critics' symlog two-hot value distribution (DreamerV3).
VALUE_BINS = 255
#: How advantages are scaled (:class:`ActorCritic`, ``return_normalization``).
RETURN_NORMALIZATIONS = ("combined", "per_term")
#: Names of the optional scalar actor inputs of eq. 4.6.
EXTRA_INPUTS = ("reward", "cont", "entropy")


# --------------------------------------------------------------------------------------------------------------------
# Actor input (eq. 4.6)
# --------------------------------------------------------------------------------------------------------------------


def _resolve_extras(use_extras: bool | Collection[str]) -> tuple[str, ...]:
    if use_extras is True:
        return EXTRA_INPUTS
    if use_extras is False:
        return ()
    unknown = set(use_extras) - set(EXTRA_INPUTS)
    if unknown:
        raise ValueError(f"use_extras may only name {EXTRA_INPUTS}, got unknown {sorted(unknown)}")
    return tuple(name for name in EXTRA_INPUTS if name in use_extras)


def actor_input_dim(h_dim: int, z_dim: int, subgoal_dim: int = 0, use_extras: bool | Collection[str] = True) -> int:
    """Feature size produced by :func:`actor_input`.

    :param h_dim: size of the deterministic state h
    :param z_dim: flattened size of the stochastic state z (e.g. 32 * 32)
    :param subgoal_dim: flattened subgoal size (e.g. 8 * 8), 0 for the top level
    :param use_extras: see :func:`actor_input`
    :return: total feature size
    """
    return h_dim + z_dim + subgoal_dim + len(_resolve_extras(use_extras))


def actor_input(
    h: th.Tensor,
    z: th.Tensor,
    subgoal: th.Tensor | None = None,
    reward: th.Tensor | None = None,
    cont: th.Tensor | None = None,
    prior_entropy: th.Tensor | None = None,
    use_extras: bool | Collection[str] = True,
) -> th.Tensor:
    """Actor / critic input s_t = (h_t, z_t, g_t, r_t, c_t, H(p(z^_t | m_t))) of eq. 4.6, concatenated.

    The scalar extras are passed through ``symlog``. Each extra can be switched off (ablation 5.3.11): ``use_extras``
    is ``True`` (all of ``"reward"``, ``"cont"``, ``"entropy"``), ``False`` (none) or a collection of those names.
    A disabled extra is not read (may be None); an enabled one must be given.

    :param h: (*B, H) deterministic state
    :param z: (*B, Z) or (*B, G, K) stochastic state (flattened here)
    :param subgoal: (*B, 64) or (*B, 8, 8) subgoal from the level above, or None at the top level
    :param reward: (*B) or (*B, 1) predicted reward
    :param cont: (*B) or (*B, 1) predicted continue probability
    :param prior_entropy: (*B) or (*B, 1) entropy of the prior over z
    :param use_extras: which scalar extras to append
    :return: (*B, F) with F = :func:`actor_input_dim`
    """
    if h.dim() < 1:
        raise ValueError(f"h must have shape (*B, H), got {tuple(h.shape)}")
    lead = h.shape[:-1]

    def flat(name: str, x: th.Tensor) -> th.Tensor:
        if x.dim() < len(lead) + 1 or x.shape[: len(lead)] != lead:
            raise ValueError(f"{name} must have leading dims {tuple(lead)} like h, got {tuple(x.shape)}")
        return x.reshape(*lead, -1)

    parts = [h, flat("z", z)]
    if subgoal is not None:
        parts.append(flat("subgoal", subgoal))
    values = {"reward": reward, "cont": cont, "entropy": prior_entropy}
    for name in _resolve_extras(use_extras):
        x = values[name]
        if x is None:
            raise ValueError(f"actor input extra '{name}' is enabled but was not given (pass it or disable it)")
        if not (x.shape == lead or x.shape == (*lead, 1)):
            raise ValueError(f"{name} must have shape {tuple(lead)} or {(*lead, 1)}, got {tuple(x.shape)}")
        parts.append(symlog(x.reshape(*lead, 1).to(h.dtype)))
    return th.cat(parts, -1)


# --------------------------------------------------------------------------------------------------------------------
# Actor and critic
# --------------------------------------------------------------------------------------------------------------------

ActionDistribution = OneHotCategoricalST | BoundedNormal


class Actor(nn.Module):
    """Policy network pi(a | s) (eq. 4.6): an MLP with a one-hot categorical or bounded normal output.

    * ``"discrete"``: ``action_dim`` classes; with ``action_groups = G > 1`` the action is G independent categoricals
      of shape (G, action_dim) (the 8 x 8 subgoal of a higher level), log-prob and entropy summed over the groups.
      Unimix and straight-through gradients, see :class:`~sb3_hieros.nn.distributions.OneHotCategoricalST`.
    * ``"box"``: ``action_dim`` continuous actions in [-1, 1], see
      :class:`~sb3_hieros.nn.distributions.BoundedNormal`; the policy rescales them to the env bounds.

    :param feat_dim: input features (:func:`actor_input_dim`)
    :param action_kind: ``"discrete"`` or ``"box"``
    :param action_dim: number of classes (discrete) or of action dims (box)
    :param action_groups: number of categoricals (discrete only)
    :param hidden: MLP width
    :param layers: MLP hidden layers
    :param unimix: uniform mixture of the categorical
    """

    def __init__(
        self,
        feat_dim: int,
        action_kind: str,
        action_dim: int,
        action_groups: int = 1,
        hidden: int = 256,
        layers: int = 2,
        unimix: float = 0.01,
    ) -> None:
        super().__init__()
        if action_kind not in ("discrete", "box"):
            raise ValueError(f"action_kind must be 'discrete' or 'box', got {action_kind!r}")
        if action_dim < 1 or action_groups < 1:
            raise ValueError(f"action_dim and action_groups must be >= 1, got {action_dim}, {action_groups}")
        if action_kind == "box" and action_groups != 1:
            raise ValueError(f"action_groups must be 1 for box actions, got {action_groups}")
        if action_kind == "discrete" and action_dim < 2:
            raise ValueError(f"a discrete action needs at least 2 classes, got action_dim={action_dim}")
        self.feat_dim, self.action_kind, self.action_dim, self.action_groups = (
            feat_dim,
            action_kind,
            action_dim,
            action_groups,
        )
        self.unimix = unimix
        out = action_dim * action_groups if action_kind == "discrete" else 2 * action_dim
        self.net = MLP(feat_dim, out, hidden, layers)

    @property
    def action_shape(self) -> tuple[int, ...]:
        """Shape of one action: (K,), (G, K) or (A,)."""
        if self.action_kind == "discrete" and self.action_groups > 1:
            return (self.action_groups, self.action_dim)
        return (self.action_dim,)

    def forward(self, feat: th.Tensor) -> ActionDistribution:
        """:param feat: (*B, feat_dim)
        :return: the action distribution with batch shape *B
        """
        out = self.net(feat)
        if self.action_kind == "box":
            mean_raw, std_raw = out.chunk(2, -1)
            return BoundedNormal(mean_raw, std_raw, ACTION_MIN_STD, ACTION_MAX_STD)
        logits = out.reshape(*out.shape[:-1], *self.action_shape)
        return OneHotCategoricalST(logits, self.unimix, event_ndims=1 if self.action_groups > 1 else 0)

    def act(self, feat: th.Tensor, deterministic: bool = False) -> th.Tensor:
        """Action for acting: the mode when ``deterministic`` (thesis 4.3.2: mode in the environment), else a sample.

        :param feat: (*B, feat_dim)
        :param deterministic: take the mode
        :return: (*B, *action_shape)
        """
        dist = self(feat)
        return dist.mode() if deterministic else dist.sample()


class Critic(nn.Module):
    """Value network v(s) with a 255-bin symlog two-hot output, zero-initialised, plus a slow EMA copy.

    The slow copy is updated by :meth:`update_slow` (``slow <- (1 - f) slow + f fast`` with f = 0.02, once per
    training step as in DreamerV3 / the reference) and regularises the critic: the loss adds
    ``slow_reg * -log p(slow mean)`` (DreamerV3 slow-critic regulariser).

    :param feat_dim: input features
    :param hidden: MLP width
    :param layers: MLP hidden layers
    :param slow_fraction: EMA fraction f of :meth:`update_slow`, in (0, 1]
    :param slow_reg: weight of the slow-critic regulariser
    """

    bins: th.Tensor

    def __init__(
        self, feat_dim: int, hidden: int = 256, layers: int = 2, slow_fraction: float = 0.02, slow_reg: float = 1.0
    ) -> None:
        super().__init__()
        if not 0.0 < slow_fraction <= 1.0:
            raise ValueError(f"slow_fraction must be in (0, 1], got {slow_fraction}")
        if slow_reg < 0.0:
            raise ValueError(f"slow_reg must be >= 0, got {slow_reg}")
        self.slow_fraction = slow_fraction
        self.slow_reg = slow_reg
        self.net = MLP(feat_dim, VALUE_BINS, hidden, layers, out_scale=0.0)
        self.slow_net = copy.deepcopy(self.net).requires_grad_(False)
        # constant: non-persistent so that it stays out of the state_dict (SB3 save/load contract)
        self.register_buffer("bins", symlog_bins(VALUE_BINS), persistent=False)
        self.bins_antisymmetric = bins_are_antisymmetric(self.bins)

    def forward(self, feat: th.Tensor) -> TwoHotSymlog:
        """:param feat: (*B, feat_dim)
        :return: value distribution with batch shape *B
        """
        return TwoHotSymlog(self.net(feat), self.bins, self.bins_antisymmetric)

    def value(self, feat: th.Tensor, detach_params: bool = False, slow: bool = False) -> th.Tensor:
        """Expected value (raw units) of the fast critic, or of its slow copy.

        :param feat: (*B, feat_dim)
        :param detach_params: let gradients flow into ``feat`` but not into the critic's parameters (for the
            dynamics-backprop actor loss)
        :param slow: the slow copy's value; its parameters never take gradients, ``feat`` does where it requires them
        :return: (*B)
        """
        if slow:
            return TwoHotSymlog(self.slow_net(feat), self.bins, self.bins_antisymmetric).mean
        if not detach_params:
            return self(feat).mean
        params = {name: p.detach() for name, p in self.net.named_parameters()}
        return TwoHotSymlog(functional_call(self.net, params, (feat,)), self.bins, self.bins_antisymmetric).mean

    @th.no_grad()
    def slow_value(self, feat: th.Tensor) -> th.Tensor:
        """Expected value of the slow copy (no gradient).

        :param feat: (*B, feat_dim)
        :return: (*B)
        """
        return self.value(feat, slow=True)

    @th.no_grad()
    def update_slow(self, fraction: float | None = None) -> None:
        """EMA step of the slow copy towards the fast critic.

        :param fraction: EMA fraction, default ``slow_fraction``; 1.0 copies
        """
        f = self.slow_fraction if fraction is None else fraction
        if not 0.0 <= f <= 1.0:
            raise ValueError(f"fraction must be in [0, 1], got {f}")
        for slow, fast in zip(self.slow_net.parameters(), self.net.parameters(), strict=True):
            slow.lerp_(fast.detach(), f)

    def loss(
        self,
        feat: th.Tensor,
        target: th.Tensor,
        weights: th.Tensor | None = None,
        dist: TwoHotSymlog | None = None,
    ) -> tuple[th.Tensor, dict[str, th.Tensor]]:
        """Two-hot NLL of ``target`` plus the slow-critic regulariser, weighted and averaged.

        ``feat`` and ``target`` are detached here, so only the critic's parameters get gradients.

        :param feat: (*B, feat_dim)
        :param target: (*B) regression targets (lambda-returns), raw units
        :param weights: (*B) per-sample weights (cumulative discount), default 1
        :param dist: the fast critic's output at ``feat`` if the caller has it already (saves a forward pass);
            it must come from ``self(feat.detach())``
        :return: (scalar loss, metrics)
        """
        feat = feat.detach()
        if dist is None:
            dist = self(feat)
        elif dist.logits.shape[:-1] != feat.shape[:-1]:
            raise ValueError(
                f"dist has batch shape {tuple(dist.logits.shape[:-1])}, expected {tuple(feat.shape[:-1])} like feat"
            )
        nll = -dist.log_prob(target.detach())
        loss = nll
        if self.slow_reg > 0.0:
            loss = loss - self.slow_reg * dist.log_prob(self.slow_value(feat))
        if weights is not None:
            if weights.shape != nll.shape:
                raise ValueError(f"weights must have shape {tuple(nll.shape)}, got {tuple(weights.shape)}")
            loss = loss * weights.detach()
        metrics = {"critic_nll": nll.mean().detach(), "value_mean": dist.mean.mean().detach()}
        return loss.mean(), metrics


# --------------------------------------------------------------------------------------------------------------------
# The actor-critic of one level
# --------------------------------------------------------------------------------------------------------------------


class ReplaySequences(NamedTuple):
    """One level's replayed sequences as its critics see them, for the replay value loss (batch-major, as replayed).

    :param feats: (B, T, F) actor / critic inputs of the posterior states s_t
    :param rewards: term -> (B, T), ``rewards[k][:, t]`` = r^k received with s_t (index 0 unused); every active term
    :param continues: (B, T) c_t = 1 - is_terminal
    :param is_first: (B, T) bool, episode starts
    :param starts: (N,) flat indices ``b * T + t`` of the states the imagination started from, in the order of its
        rollouts, or None when it started from every state in that order
    """

    feats: th.Tensor
    rewards: Mapping[str, th.Tensor]
    continues: th.Tensor
    is_first: th.Tensor
    starts: th.Tensor | None = None


class ActorCritic(nn.Module):
    """One actor and one critic per active reward term (thesis 4.3.2), trained on imagined trajectories.

    Terms with weight 0 (or left out of ``reward_weights``) get no critic; the top level simply passes no
    ``"subgoal"`` weight. The actor objective per imagined step t follows eq. 4.3, which mixes the terms into one reward
    ``r = r_extr + alpha_g r_g + alpha_nov r_nov``. Its lambda-return is the weighted sum of the terms' returns, so with
    one critic per term (``return_normalization="combined"``, default)

    .. math::
        A_t = \\frac{\\sum_k \\alpha_k (R^k_t - v^k(s_t))}{\\max(1, S)}

    with alpha = ``reward_weights``, R^k the lambda-returns of term k under its fast critic and S the return scale
    (:class:`ReturnNormalizer`) of the mixed return ``sum_k alpha_k R^k``: DreamerV3's normalisation of the one return
    the thesis defines. Each term then pulls on the actor in proportion to its weight *and* its size in reward units,
    as eq. 4.3 says: where the extrinsic rewards are large and dense, the bounded subgoal reward (|r_g| <= 1) nudges
    the policy; where they are sparse, it drives it. ``return_normalization="per_term"`` divides each term by its own
    scale S_k instead (Director's choice): each term's pull is then set by its weight alone, so the subgoal term keeps
    0.3 of the extrinsic term's pull whatever the task's rewards and can outweigh small but decisive extrinsic
    differences (``benchmarks/control_failures.py`` measures each term's share of the actor's gradient). Unlike the
    reference code, REINFORCE also uses the normalised advantage.

    * ``gradient="reinforce"`` (default for discrete): ``-w_t (log pi(a_t|s_t) sg(A_t) + eta H_t)``.
    * ``gradient="dynamics"`` (default for box): ``-w_t (A_t + eta H_t)``, where A_t carries gradients back through
      the rewards, values and features to the (reparameterised) actions; ``value_gradient`` says which values do:
      ``"all"`` (DreamerV3's code) the values inside the lambda-returns and the baseline v^k(s_t). The baseline's
      gradient changes the objective, not only its variance: the actor is also paid for reaching states whose
      imagined return exceeds the critic's estimate. Summed over t with the weights w_t (continues 1), the value of an
      intermediate imagined state s_k then enters with the net weight ``-(gamma lambda)^k`` and that of s_H with
      ``gamma^H (1 - lambda^H) / (1 - lambda)``: weights that nearly cancel, so the value path pulls along the
      differences of the critic's gradients between the states of a rollout. ``"returns"`` holds the baseline fixed
      (the actor climbs the lambda-returns, DreamerV2's dynamics objective); ``"none"`` holds every value fixed (the
      gradient comes through the imagined rewards of the horizon alone). The caller must build
      ``feats`` and ``rewards`` differentiably from the imagined actions; critic parameters get no gradient from
      this loss, but whatever produced ``feats`` / ``rewards`` (the world model) does: step only the actor's
      optimiser with it and zero the other gradients before their own backward.

    with eta = ``entropy_coef`` and w_t the cumulative discount. Critic k minimises the two-hot NLL of R^k_t plus the
    slow-critic regulariser, weighted by w_t.

    ``return_critic="slow"`` computes R^k and v^k(s_t) with the slow copy of critic k (its EMA over recent updates)
    instead of the fast one, in the returns the critics regress as well as in the actor's advantage; under dynamics
    backpropagation the value path then follows the slow copy's input gradient.

    :param feat_dim: actor / critic input size (:func:`actor_input_dim`)
    :param action_kind: ``"discrete"`` or ``"box"``
    :param action_dim: classes (discrete) or dims (box)
    :param action_groups: number of categoricals (8 for a subgoal action)
    :param hidden: MLP width (actor and critics)
    :param layers: MLP hidden layers (actor and critics)
    :param reward_weights: term -> weight alpha_k; default :data:`DEFAULT_REWARD_WEIGHTS`. Missing terms have weight 0.
    :param discount: gamma
    :param lambda_: lambda of the returns
    :param entropy_coef: eta
    :param gradient: ``"reinforce"``, ``"dynamics"`` or None (reinforce for discrete, dynamics for box)
    :param unimix: actor unimix (discrete)
    :param slow_fraction: slow-critic EMA fraction
    :param slow_reg: slow-critic regulariser weight
    :param retnorm_decay: return normaliser EMA decay
    :param retnorm_percentiles: return normaliser percentiles
    :param retnorm_min_scale: return normaliser floor
    :param return_normalization: ``"combined"`` (default: one scale for the mixed return of eq. 4.3) or
        ``"per_term"`` (one scale per reward term), see above
    :param reinforce_advantage: ``"normalized"`` (default, the A_t above) or ``"raw"``: REINFORCE uses the reference
        code's unnormalised weighted average ``sum_k alpha_k (R^k_t - v^k(s_t)) / sum_k alpha_k`` (reference-compat
        switch). Dynamics backpropagation always uses A_t.
    :param value_gradient: with ``gradient="dynamics"``, the values that pass gradient: ``"all"``, ``"returns"``
        or ``"none"`` (see above)
    :param return_critic: ``"fast"`` (default) or ``"slow"``: the critic copy whose values enter the lambda-returns
        and the baseline (see above)
    :param replay_value_scale: weight of the replay value loss (:meth:`replay_value_loss`; DreamerV3's later
        releases: 0.3), 0 to train the critics on imagination alone (the thesis)
    """

    def __init__(
        self,
        feat_dim: int,
        action_kind: Literal["discrete", "box"],
        action_dim: int,
        *,
        action_groups: int = 1,
        hidden: int = 256,
        layers: int = 2,
        reward_weights: Mapping[str, float] | None = None,
        discount: float = 0.997,
        lambda_: float = 0.95,
        entropy_coef: float = 3e-4,
        gradient: str | None = None,
        unimix: float = 0.01,
        slow_fraction: float = 0.02,
        slow_reg: float = 1.0,
        retnorm_decay: float = 0.99,
        retnorm_percentiles: tuple[float, float] = (5.0, 95.0),
        retnorm_min_scale: float = 1.0,
        reinforce_advantage: str = "normalized",
        return_normalization: str = "combined",
        value_gradient: str = "all",
        return_critic: str = "fast",
        replay_value_scale: float = 0.0,
    ) -> None:
        super().__init__()
        if replay_value_scale < 0.0:
            raise ValueError(f"replay_value_scale must be >= 0, got {replay_value_scale}")
        self.replay_value_scale = replay_value_scale
        if value_gradient not in VALUE_GRADIENTS:
            raise ValueError(f"value_gradient must be one of {VALUE_GRADIENTS}, got {value_gradient!r}")
        self.value_gradient = value_gradient
        if return_critic not in RETURN_CRITICS:
            raise ValueError(f"return_critic must be one of {RETURN_CRITICS}, got {return_critic!r}")
        self.return_critic = return_critic
        if reinforce_advantage not in ("normalized", "raw"):
            raise ValueError(f"reinforce_advantage must be 'normalized' or 'raw', got {reinforce_advantage!r}")
        self.reinforce_advantage = reinforce_advantage
        weights = dict(DEFAULT_REWARD_WEIGHTS if reward_weights is None else reward_weights)
        unknown = set(weights) - set(REWARD_TERMS)
        if unknown:
            raise ValueError(f"reward_weights keys must be among {REWARD_TERMS}, got unknown {sorted(unknown)}")
        if any(w < 0 for w in weights.values()):
            raise ValueError(f"reward_weights must be >= 0, got {weights}")
        self.reward_weights = {k: float(weights[k]) for k in REWARD_TERMS if weights.get(k, 0.0) > 0.0}
        if not self.reward_weights:
            raise ValueError(f"at least one reward weight must be > 0, got {weights}")
        if gradient is None:
            gradient = "reinforce" if action_kind == "discrete" else "dynamics"
        if gradient not in ("reinforce", "dynamics"):
            raise ValueError(f"gradient must be 'reinforce', 'dynamics' or None, got {gradient!r}")
        if not 0.0 < discount <= 1.0:
            raise ValueError(f"discount must be in (0, 1], got {discount}")
        if entropy_coef < 0.0:
            raise ValueError(f"entropy_coef must be >= 0, got {entropy_coef}")
        self.feat_dim, self.gradient = feat_dim, gradient
        self.discount, self.lambda_, self.entropy_coef = discount, lambda_, entropy_coef
        self.actor = Actor(
            feat_dim,
            action_kind,
            action_dim,
            action_groups,
            hidden,
            layers,
            unimix=unimix,
        )
        self.critics = nn.ModuleDict(
            {k: Critic(feat_dim, hidden, layers, slow_fraction, slow_reg) for k in self.reward_weights}
        )
        if return_normalization not in RETURN_NORMALIZATIONS:
            raise ValueError(
                f"return_normalization must be one of {RETURN_NORMALIZATIONS}, got {return_normalization!r}"
            )
        self.return_normalization = return_normalization
        names = self.reward_weights if return_normalization == "per_term" else ("combined",)
        self.normalizers = nn.ModuleDict(
            {k: ReturnNormalizer(retnorm_decay, retnorm_percentiles, retnorm_min_scale) for k in names}
        )

    def return_scale(self, term: str) -> th.Tensor:
        """The scale S that divides term ``term``'s advantage: its own (``"per_term"``) or the shared one.

        :param term: an active reward term
        :return: 0-d detached scale
        """
        if term not in self.reward_weights:
            raise ValueError(f"term must be one of the active terms {self.active_terms}, got {term!r}")
        return self.normalizers[term if self.return_normalization == "per_term" else "combined"].scale()

    @property
    def active_terms(self) -> tuple[str, ...]:
        """Reward terms with a critic, in :data:`REWARD_TERMS` order."""
        return tuple(self.reward_weights)

    def actor_parameters(self) -> Iterator[nn.Parameter]:
        """Parameters of the actor (for the actor optimiser)."""
        return self.actor.parameters()

    def critic_parameters(self) -> Iterator[nn.Parameter]:
        """Trainable parameters of all critics (the slow copies excluded)."""
        for critic in self.critics.values():
            yield from critic.net.parameters()

    def act(self, feat: th.Tensor, deterministic: bool = False) -> th.Tensor:
        """See :meth:`Actor.act`."""
        return self.actor.act(feat, deterministic)

    @th.no_grad()
    def update_slow_critics(self, fraction: float | None = None) -> None:
        """One EMA step of every slow critic (call once per training step)."""
        for critic in self.critics.values():
            critic.update_slow(fraction)

    def _check_inputs(
        self,
        feats: th.Tensor,
        actions: th.Tensor,
        rewards: Mapping[str, th.Tensor],
        continues: th.Tensor,
        weights: th.Tensor | None,
    ) -> None:
        if feats.dim() < 3 or feats.shape[0] < 2 or feats.shape[-1] != self.feat_dim:
            raise ValueError(f"feats must have shape (H+1, *B, {self.feat_dim}) with H >= 1, got {tuple(feats.shape)}")
        states = feats.shape[:-1]  # (H+1, *B)
        expected_actions = (states[0] - 1, *states[1:], *self.actor.action_shape)
        if tuple(actions.shape) != expected_actions:
            raise ValueError(
                f"actions must have shape (H, *B, *action_shape) = {expected_actions}, got {tuple(actions.shape)}"
            )
        unknown = set(rewards) - set(REWARD_TERMS)
        if unknown:
            raise ValueError(f"rewards keys must be among {REWARD_TERMS}, got unknown {sorted(unknown)}")
        missing = set(self.reward_weights) - set(rewards)
        if missing:
            raise ValueError(f"rewards lack the active terms {sorted(missing)} (active: {self.active_terms})")
        for name, r in rewards.items():
            if name in self.reward_weights and r.shape != states:
                raise ValueError(f"rewards['{name}'] must have shape (H+1, *B) = {tuple(states)}, got {tuple(r.shape)}")
        if continues.shape != states:
            raise ValueError(f"continues must have shape (H+1, *B) = {tuple(states)}, got {tuple(continues.shape)}")
        if weights is not None and weights.shape != states:
            raise ValueError(f"weights must have shape (H+1, *B) = {tuple(states)}, got {tuple(weights.shape)}")

    def replay_value_loss(
        self, term: str, replay: ReplaySequences, start_returns: th.Tensor
    ) -> tuple[th.Tensor, th.Tensor]:
        """Critic ``term``'s two-hot NLL (with the slow-critic regulariser) of the replay lambda-returns of
        :func:`~sb3_hieros.agent.returns.replay_lambda_returns` on the replayed states (DreamerV3's replay value loss).

        The thesis and DreamerV3's first release train the critics on imagined states only, whose rewards and
        continues come from the world model. This loss grounds them in what the environment returned: along each
        replayed sequence the returns follow the recorded rewards, bootstrapped at every step with the imagined
        return R_0 of the rollout that started from that state, or, for states the imagination did not start from
        (``imag_start_fraction`` < 1), with the critic's own value. Rows whose next state starts a new episode, and
        the last row, get weight 0.

        :param term: an active reward term
        :param replay: the replayed sequences
        :param start_returns: (N,) the imagined returns R_0 of the rollouts, in the order of ``replay.starts``
        :return: (scalar loss, mean replay return over the weighted rows, detached)
        """
        critic = self.critics[term]
        feats = replay.feats.detach()  # (B, T, F)
        batch = feats.shape[:2]
        dist = critic(feats)  # (B, T)
        boot = dist.mean.detach().float().reshape(-1)  # (B*T,), the returns in float32 under a bf16 autocast too
        start_returns = start_returns.detach().float().reshape(-1)
        if replay.starts is None:
            if start_returns.shape != boot.shape:
                raise ValueError(f"start_returns must have {boot.numel()} entries, got {start_returns.numel()}")
            boot = start_returns
        else:
            if replay.starts.shape != start_returns.shape:
                raise ValueError(
                    f"replay.starts has {replay.starts.numel()} entries, start_returns {start_returns.numel()}"
                )
            boot = boot.index_copy(0, replay.starts, start_returns)
        returns, valid = replay_lambda_returns(
            replay.rewards[term].transpose(0, 1).float(),
            replay.continues.transpose(0, 1).float(),
            replay.is_first.transpose(0, 1),
            boot.reshape(batch).transpose(0, 1),
            self.discount,
            self.lambda_,
        )  # (T, B)
        returns, valid = returns.transpose(0, 1), valid.transpose(0, 1).to(returns.dtype)  # (B, T)
        loss, _ = critic.loss(feats, returns, valid, dist=dist)
        return loss, (returns * valid).sum() / valid.sum().clamp_min(1.0)

    def loss(
        self,
        feats: th.Tensor,
        actions: th.Tensor,
        rewards: Mapping[str, th.Tensor],
        continues: th.Tensor,
        weights: th.Tensor | None = None,
        update_normalizers: bool = True,
        replay: ReplaySequences | None = None,
    ) -> tuple[th.Tensor, th.Tensor, dict[str, th.Tensor]]:
        """Actor and critic losses on one imagined trajectory s_0 .. s_H (time-major).

        Side effect: updates each term's :class:`ReturnNormalizer` with its returns (unless ``update_normalizers`` is
        False). Call :meth:`update_slow_critics` once per training step separately.

        :param feats: (H+1, *B, feat_dim) actor / critic inputs of s_0 .. s_H (:func:`actor_input`)
        :param actions: (H, *B, *action_shape) action a_t taken in s_t (one-hot for discrete)
        :param rewards: term -> (H+1, *B) per-state rewards, ``rewards[k][t]`` = r^k(s_t) (for the extrinsic term the
            reward head's prediction at s_t, i.e. the reward of arriving in s_t); index 0 is not used. Must hold every
            active term; known terms with weight 0 are ignored.
        :param continues: (H+1, *B) continue probabilities c(s_t); ``continues[0]`` is that of the start state
        :param weights: (H+1, *B) loss weights; default :func:`cumulative_discount` of ``continues``
        :param update_normalizers: update the return normalisers with this batch
        :param replay: the replayed sequences the imagination started from; with ``replay_value_scale`` > 0 each
            critic's loss adds that weight times its :meth:`replay_value_loss` on them
        :return: (actor_loss, critic_loss summed over the critics, metrics of detached 0-d tensors)
        """
        self._check_inputs(feats, actions, rewards, continues, weights)
        if weights is None:
            weights = cumulative_discount(continues, self.discount)
        weights = weights.detach()
        w = weights[:-1]  # (H, *B): one weight per action / return
        feats_sg = feats.detach()
        dynamics = self.gradient == "dynamics"
        slow = self.return_critic == "slow"
        metrics: dict[str, th.Tensor] = {}
        advantage = th.zeros_like(w)
        raw_advantage = th.zeros_like(w)  # sum_k alpha_k (R^k - v^k), unnormalised
        mixed_returns = th.zeros_like(w)  # sum_k alpha_k R^k, the return of eq. 4.3's mixed reward
        critic_loss = feats.new_zeros(())
        for name, alpha in self.reward_weights.items():
            critic = self.critics[name]
            fast: TwoHotSymlog | None = None
            if dynamics and self.value_gradient != "none":
                values = critic.value(feats, detach_params=True, slow=slow)  # (H+1, *B), differentiable w.r.t. feats
            elif slow:
                values = critic.slow_value(feats_sg)  # (H+1, *B)
            else:
                # one forward pass of the fast critic serves the returns (detached) and its own loss (s_0..s_{H-1})
                dist_all = critic(feats_sg)  # (H+1, *B)
                values = dist_all.mean.detach()
                fast = TwoHotSymlog(dist_all.logits[:-1], critic.bins, critic.bins_antisymmetric)
            returns = lambda_returns(
                rewards[name][1:], values[:-1], continues[1:], values[-1], self.discount, self.lambda_
            )  # (H, *B)
            baseline = values[:-1] if self.value_gradient == "all" else values[:-1].detach()
            raw_advantage = raw_advantage + alpha * (returns - baseline)
            if self.return_normalization == "per_term":
                _, scale = self.normalizers[name](returns, update=update_normalizers)
                advantage = advantage + alpha * (returns - baseline) / scale
            else:
                mixed_returns = mixed_returns + alpha * returns.detach()
                scale = self.normalizers["combined"].scale()  # this batch's update follows below
            c_loss, c_metrics = critic.loss(feats_sg[:-1], returns.detach(), w, dist=fast)
            if replay is not None and self.replay_value_scale > 0.0:
                r_loss, r_return = self.replay_value_loss(name, replay, returns[0])
                c_loss = c_loss + self.replay_value_scale * r_loss
                metrics[f"{name}/replay_critic_loss"] = r_loss.detach()
                metrics[f"{name}/replay_return_mean"] = r_return
            critic_loss = critic_loss + c_loss
            metrics[f"{name}/return_mean"] = returns.mean().detach()
            metrics[f"{name}/reward_mean"] = rewards[name][1:].mean().detach()
            metrics[f"{name}/return_scale"] = scale
            metrics[f"{name}/critic_loss"] = c_loss.detach()
            metrics[f"{name}/value_mean"] = c_metrics["value_mean"]
        if self.return_normalization == "combined":
            _, scale = self.normalizers["combined"](mixed_returns, update=update_normalizers)
            advantage = raw_advantage / scale
            for name in self.reward_weights:
                metrics[f"{name}/return_scale"] = scale
        dist = self.actor(feats_sg[:-1])
        entropy = dist.entropy()  # (H, *B)
        if dynamics:
            objective = advantage
        elif self.reinforce_advantage == "raw":  # reference code: unnormalised weighted average
            advantage = raw_advantage / sum(self.reward_weights.values())
            objective = dist.log_prob(actions.detach()) * advantage.detach()
        else:
            objective = dist.log_prob(actions.detach()) * advantage.detach()
        actor_loss = -(w * (objective + self.entropy_coef * entropy)).mean()
        metrics["actor_loss"] = actor_loss.detach()
        metrics["actor_entropy"] = entropy.mean().detach()
        metrics["advantage_mean"] = advantage.mean().detach()
        metrics["advantage_std"] = advantage.std().detach() if advantage.numel() > 1 else advantage.new_zeros(())
        metrics["critic_loss"] = critic_loss.detach()
        return actor_loss, critic_loss, metrics


__all__ = [
    "DEFAULT_REWARD_WEIGHTS",
    "EXTRA_INPUTS",
    "REWARD_TERMS",
    "Actor",
    "ActorCritic",
    "Critic",
    "ReplaySequences",
    "ReturnNormalizer",
    "actor_input",
    "actor_input_dim",
    "cumulative_discount",
    "lambda_returns",
]
