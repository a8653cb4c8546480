"""The part both world models share (thesis 4.4): encoder and decoder, heads, loss, replay context and the rollout.

Both models describe the world by a latent state ``(h_t, z_t)``: ``h_t`` deterministic, ``z_t`` a vector of
``stoch_groups`` one-hot categoricals of ``stoch_classes`` classes::

    Sequence model:     (m_t, h_t) = f(h_{t-1}, z_{t-1}, a_{t-1})
    Encoder:            z_t ~ q(z_t | o_t)            (S5WM)   or  q(z_t | h_t, o_t)  (RSSM; WorldModelConfig.posterior)
    Dynamics predictor: z^_t ~ p(z^_t | m_t)          (S5WM)   or  p(z^_t | h_t)      (RSSM)
    Reward, continue and decoder heads on (h_t, z_t).

Time alignment: a training row t holds ``o_t``, ``a_{t-1}`` (the action taken after ``o_{t-1}``, which led to
``o_t``; zeros where ``is_first_t``), ``r_t`` (received on arriving at ``o_t``), ``is_first_t`` and ``is_terminal_t``.
The sequence model at row t consumes ``(z_{t-1}, a_{t-1})``, identically in training (:meth:`WorldModel.observe`),
acting (:meth:`WorldModel.obs_step`) and imagination (:meth:`WorldModel.img_step`). Where ``is_first_t``, ``z_{t-1}``
and ``a_{t-1}`` are zeroed and the recurrent state is reset, so the first ``h`` of an episode is the successor of
:meth:`WorldModel.initial_state`, computed like every later ``h``.

The public methods check their arguments; the underscore methods they call (``_observe``, ``_obs_step``,
``_img_step``) trust them and are what the hierarchy's acting and training loops use.

Options (off by default): ``bf16=True`` computes the training loss (:meth:`WorldModel.loss`: encoder, decoder,
heads and the dense layers around the sequence model) under a bfloat16 autocast; the S5 scan, its complex state and
RSSM's recurrent loop stay in fp32, and so do acting and imagination (step form on small batches, where bf16 would
add casts and save nothing). It pays only on CPUs with native bf16 (AVX512-BF16, AMX) and on GPUs; ``bf16="auto"``
turns it on exactly there (:func:`~sb3_hieros.nn.networks.native_bf16`).
``compile=True`` compiles the convolution stacks and the sequence model with ``torch.compile``.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Mapping
from typing import Any

import torch as th
import torch.nn.functional as F
from gymnasium import spaces
from torch import nn

from sb3_hieros.agent.world_model.checks import check_actions, check_is_first, check_state
from sb3_hieros.agent.world_model.latent import LatentState, stack_states
from sb3_hieros.agent.world_model.observations import (
    SINGLE_KEY,
    ObservationDecoder,
    ObservationOptions,
    ObservationSpec,
    make_observation_encoder,
)
from sb3_hieros.config import WorldModelConfig
from sb3_hieros.nn.augment import random_shift
from sb3_hieros.nn.distributions import (
    ContinueBernoulli,
    OneHotCategoricalST,
    TwoHotSymlog,
    bins_are_antisymmetric,
    symlog_bins,
)
from sb3_hieros.nn.guard import step_if_finite
from sb3_hieros.nn.metrics import metric_floats
from sb3_hieros.nn.networks import MLP, bf16_autocast, check_bf16, evaluation_mode, trunc_normal_init_
from sb3_hieros.type_aliases import SequenceSamples

__all__ = ["REWARD_BINS", "ObsDict", "WorldModel"]

#: Bins of the symlog two-hot reward head.
REWARD_BINS = 255

#: Observations of a world model by key (a non-dict space under the single key ``"obs"``).
ObsDict = dict[str, th.Tensor]
#: ``step(t, state)`` of :meth:`WorldModel.rollout`: the action a_t taken in s_t, (N, A).
StepFn = Callable[[int, LatentState], th.Tensor | None]


def _grouped_kl(log_p: th.Tensor, log_q: th.Tensor, p: th.Tensor | None = None) -> th.Tensor:
    """``KL(p || q)`` summed over groups and classes, for already normalised log-probabilities (..., G, K).

    Same value as :func:`~sb3_hieros.nn.distributions.categorical_kl`, without re-normalising inputs that the world
    model keeps normalised (``LatentState.logits`` / ``prior_logits``).

    :param p: ``log_p.exp()`` when the caller already has it (the loss needs it for both KL terms)
    """
    return ((log_p.exp() if p is None else p) * (log_p - log_q)).sum((-2, -1))


class WorldModel(nn.Module):
    """Common part of both world models: encoder, heads, loss (eq. 4.10-4.13), imagination and input checks.

    Subclasses implement the sequence model: :meth:`_build_sequence_model`, :meth:`_observe`, :meth:`_obs_step`,
    :meth:`_img_step`, :meth:`_initial_state` and :meth:`no_weight_decay_parameters`.

    :param observation_space: observation space of this level (Box image (C, H, W) uint8, Box vector, Discrete,
        MultiDiscrete, MultiBinary, or a Dict of them)
    :param action_dim: size of the action vector (one-hot size for Discrete actions and subgoals, Box entries)
    :param config: world-model hyperparameters
    :param bf16: compute the training loss under a bfloat16 autocast: ``True``, ``False`` or ``"auto"`` (see the module
        docstring)
    :param compile: ``torch.compile`` the convolution stacks and the sequence model (opt-in)
    :param observation_options: SB3's observation keywords (image scaling, a user's features extractor), or None
    """

    kind: str = ""

    def __init__(
        self,
        observation_space: spaces.Space,
        action_dim: int,
        config: WorldModelConfig,
        bf16: bool | str = False,
        compile: bool = False,
        observation_options: ObservationOptions | None = None,
    ) -> None:
        super().__init__()
        self.config = config
        self.observation_space = observation_space
        self.action_dim = int(action_dim)
        normalize_images = observation_options is None or observation_options.normalize_images
        self.spec = ObservationSpec(observation_space, normalize_images)
        self.groups = config.stoch_groups
        self.classes = config.stoch_classes
        self.stoch_dim = self.groups * self.classes
        self.deter_dim = config.deter_dim
        self.feat_dim = self.deter_dim + self.stoch_dim
        self.bf16 = check_bf16(bf16)
        self.compile = compile
        self.encoder = make_observation_encoder(self.spec, config, observation_options)
        self.embed_dim = self.encoder.out_dim
        self.decoder = ObservationDecoder(self.spec, self.feat_dim, config)
        self.reward_head = MLP(self.feat_dim, REWARD_BINS, config.head_units, config.head_layers, out_scale=0.0)
        self.cont_head = MLP(self.feat_dim, 1, config.head_units, config.head_layers)
        self.register_buffer("reward_bins", symlog_bins(REWARD_BINS), persistent=False)
        self.reward_bins_antisymmetric = bins_are_antisymmetric(self.reward_bins)
        if compile:
            # convolution stacks: Inductor fuses the per-pixel LayerNorm and SiLU around the oneDNN convolutions
            for conv in [*self.encoder.convs.values(), *self.decoder.convs.values()]:
                conv.forward = th.compile(conv.forward, dynamic=False)
        self._build_sequence_model(config, compile)

    def _build_sequence_model(self, config: WorldModelConfig, compile: bool) -> None:
        """Build the sequence model and the prior and posterior layers (after the encoder, decoder and heads).

        :param config: world-model hyperparameters
        :param compile: ``torch.compile`` opt-in
        """
        raise NotImplementedError

    def _build_split_posterior(self, hidden: int) -> None:
        """The posterior layer ``Linear -> LayerNorm -> SiLU -> Linear`` on ``[h_t, e_t]`` (on e_t alone where
        ``config.posterior`` says so), its first Linear split by input so that the embedding's part is computed for a
        whole chunk outside the time loop of :meth:`_observe` (:meth:`_split_posterior`).

        :param hidden: width of the hidden layer
        """
        self.post_deter = nn.Linear(self.deter_dim, hidden, bias=False) if self.config.posterior_reads_state else None
        self.post_embed = nn.Linear(self.embed_dim, hidden, bias=False)
        self.post_norm = nn.LayerNorm(hidden, eps=1e-3)
        self.post_out = nn.Linear(hidden, self.stoch_dim)
        for layer in (self.post_deter, self.post_embed, self.post_out):
            if layer is not None:
                trunc_normal_init_(layer)

    def _split_posterior(self, deter: th.Tensor, embed_pre: th.Tensor) -> th.Tensor:
        """Raw posterior logits ``q(z_t | h_t, e_t)`` (or ``q(z_t | e_t)``) from h_t and ``post_embed(e_t)``.

        :param deter: (..., D) h_t
        :param embed_pre: (..., hidden) the embedding's part, ``post_embed(e_t)``
        :return: (..., G*K)
        """
        pre = embed_pre if self.post_deter is None else self.post_deter(deter) + embed_pre
        return self.post_out(F.silu(self.post_norm(pre)))

    # ---------------------------------------------------------------- small helpers

    @property
    def device(self) -> th.device:
        """Device of the parameters."""
        return self.reward_bins.device

    def _autocast(self) -> contextlib.AbstractContextManager:
        return bf16_autocast(self.bf16, self.device)

    def _dist(self, raw: th.Tensor) -> OneHotCategoricalST:
        """Grouped categorical over z from flat raw logits (..., G*K), with unimix."""
        return OneHotCategoricalST(
            raw.reshape(*raw.shape[:-1], self.groups, self.classes), self.config.unimix, event_ndims=1
        )

    def _draw(self, raw: th.Tensor, deterministic: bool) -> tuple[th.Tensor, th.Tensor]:
        """One-hot z (sample or mode, straight-through) and the normalised mixed log-probs.

        :param raw: (..., G*K) raw logits
        :param deterministic: take the mode instead of sampling
        :return: z (..., G*K) and logits (..., G, K)
        """
        dist = self._dist(raw)
        stoch = dist.mode() if deterministic else dist.sample()
        return stoch.flatten(-2), dist.logits

    def _normalise(self, raw: th.Tensor) -> th.Tensor:
        """Normalised mixed log-probabilities (..., G, K) from raw logits (..., G*K)."""
        return self._dist(raw).logits

    def _uniform_logits(self, batch_size: int) -> th.Tensor:
        return th.full((batch_size, self.groups, self.classes), -math.log(self.classes), device=self.device)

    # ---------------------------------------------------------------- input checks of the public methods

    def _check_state(self, state: Any, lead: tuple[int, ...], name: str = "state") -> LatentState:
        return check_state(state, lead, self.stoch_dim, self.deter_dim, name)

    def _check_actions(self, actions: Any, ndim: int, name: str) -> th.Tensor:
        return check_actions(actions, self.action_dim, ndim, name)

    def _check_sequence(
        self, observations: Any, prev_actions: Any, is_first: Any
    ) -> tuple[ObsDict, th.Tensor, th.Tensor, tuple[int, int]]:
        actions = self._check_actions(prev_actions, 3, "prev_actions")
        lead = (int(actions.shape[0]), int(actions.shape[1]))
        return self.spec.check(observations, lead), actions, check_is_first(is_first, lead), lead

    def _check_step(
        self, observation: Any, prev_action: Any, is_first: Any
    ) -> tuple[ObsDict, th.Tensor, th.Tensor, int]:
        action = self._check_actions(prev_action, 2, "prev_action")
        batch = int(action.shape[0])
        return self.spec.check(observation, (batch,), "observation"), action, check_is_first(is_first, (batch,)), batch

    def _embed(self, obs: dict[str, th.Tensor], lead: tuple[int, ...]) -> th.Tensor:
        return self.encoder(obs, lead)

    # ---------------------------------------------------------------- interface of the sequence model

    def initial_state(self, batch_size: int) -> LatentState:
        """State before the first step of an episode (all zeros; its successor is the first real state).

        :param batch_size: number of parallel states
        :return: state of batch shape (batch_size,)
        """
        if isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size < 1:
            raise ValueError(f"batch_size must be a positive int, got {batch_size!r}")
        return self._initial_state(batch_size)

    def _initial_state(self, batch_size: int) -> LatentState:
        """:meth:`initial_state` of a checked ``batch_size``."""
        raise NotImplementedError

    #: whether ``deter`` is the recurrent memory itself (RSSM), so :meth:`unpack_context` restores it from ``seq``
    _deter_is_seq = False
    #: whether ``deter`` is recurrent memory besides ``seq`` (S5WM with ``deter_from="gru"``), packed after it
    _deter_in_context = False

    @property
    def context_dim(self) -> int:
        """Floats per step in :meth:`pack_context`: z_t plus the sequence model's memory (complex parts as pairs)."""
        seq = self.initial_state(1).seq
        deter = self.deter_dim if self._deter_in_context else 0
        return self.stoch_dim + seq[0].numel() * (2 if seq.is_complex() else 1) + deter

    def pack_context(self, state: LatentState) -> th.Tensor:
        """What :meth:`observe` needs to continue after ``state`` (z_t and the recurrent memory) as one float vector
        per step, to be stored in replay and handed back through :meth:`unpack_context` (replay context: a chunk then
        starts from the state its previous step had when last trained on, as in acting, not from zeros).

        :param state: states of batch shape ``lead``
        :return: (*lead, :attr:`context_dim`) float32, detached
        """
        lead = tuple(state.batch_shape)
        seq = th.view_as_real(state.seq) if state.seq.is_complex() else state.seq
        parts = [state.stoch.detach().float(), seq.detach().reshape(*lead, -1).float()]
        if self._deter_in_context:
            parts.append(state.deter.detach().float())
        return th.cat(parts, -1)

    def unpack_context(self, context: th.Tensor) -> LatentState:
        """The state a :meth:`pack_context` vector stands for, as the ``state`` argument of :meth:`observe`.

        Only z_t and the recurrent memory are restored (all that :meth:`observe` reads); for S5WM ``deter`` is left
        at zero (except with ``deter_from="gru"``, where it is memory) and the logits uniform. All-zero vectors give
        :meth:`initial_state`.

        :param context: (B, :attr:`context_dim`)
        :return: state of batch shape (B,)
        """
        if not isinstance(context, th.Tensor) or context.dim() != 2 or context.shape[-1] != self.context_dim:
            shape = tuple(context.shape) if isinstance(context, th.Tensor) else type(context).__name__
            raise ValueError(f"context must have shape (B, {self.context_dim}), got {shape}")
        template = self.initial_state(int(context.shape[0]))
        context = context.to(template.stoch.device, th.float32)
        stoch, rest = context[:, : self.stoch_dim], context[:, self.stoch_dim :]
        deter = template.deter
        if self._deter_in_context:
            rest, deter = rest[:, : -self.deter_dim], rest[:, -self.deter_dim :]
        if template.seq.is_complex():
            seq = th.view_as_complex(rest.reshape(*template.seq.shape, 2).contiguous())
        else:
            seq = rest.reshape(template.seq.shape)
        if self._deter_is_seq:
            deter = seq
        return template._replace(stoch=stoch, deter=deter, seq=seq)

    def observe(
        self,
        observations: th.Tensor | Mapping[str, th.Tensor],
        prev_actions: th.Tensor,
        is_first: th.Tensor,
        state: LatentState | None = None,
        deterministic: bool = False,
    ) -> tuple[LatentState, th.Tensor]:
        """Posterior states of a whole chunk (training, thesis 4.4.1).

        :param observations: (B, T, *obs_shape) (a dict of such tensors for Dict spaces)
        :param prev_actions: (B, T, A) with row t = a_{t-1}, the action that led to o_t
        :param is_first: (B, T) bool, True where o_t starts an episode
        :param state: state before row 0 (batch (B,)), or None for :meth:`initial_state`
        :param deterministic: take posterior modes instead of samples
        :return: posterior states (batch (B, T)) and the prior logits (B, T, G, K)
        """
        obs, actions, is_first, (batch, _) = self._check_sequence(observations, prev_actions, is_first)
        if state is not None:
            self._check_state(state, (batch,))
        return self._observe(obs, actions, is_first, state, deterministic)

    def _observe(
        self, obs: ObsDict, actions: th.Tensor, is_first: th.Tensor, state: LatentState | None, deterministic: bool
    ) -> tuple[LatentState, th.Tensor]:
        """:meth:`observe` of checked inputs (``obs`` as a dict, ``actions`` the previous actions, ``is_first``
        bool)."""
        raise NotImplementedError

    def obs_step(
        self,
        state: LatentState | None,
        observation: th.Tensor | Mapping[str, th.Tensor],
        prev_action: th.Tensor,
        is_first: th.Tensor,
        deterministic: bool = False,
    ) -> LatentState:
        """One step of :meth:`observe` (acting, Algorithm 1 ``Encode``).

        :param state: previous state (batch (B,)) or None for :meth:`initial_state`
        :param observation: (B, *obs_shape)
        :param prev_action: (B, A), the action taken after the previous observation
        :param is_first: (B,) bool; where True, state and ``prev_action`` are ignored (reset)
        :param deterministic: take the posterior mode instead of a sample
        :return: the posterior state (batch (B,))
        """
        obs, action, is_first, batch = self._check_step(observation, prev_action, is_first)
        state = self.initial_state(batch) if state is None else self._check_state(state, (batch,))
        return self._obs_step(state, obs, action, is_first, deterministic)

    def _obs_step(
        self, state: LatentState, obs: ObsDict, action: th.Tensor, is_first: th.Tensor, deterministic: bool
    ) -> LatentState:
        """:meth:`obs_step` of checked inputs (``state`` given, ``obs`` as a dict, ``action`` the previous action,
        ``is_first`` bool)."""
        raise NotImplementedError

    def img_step(
        self, state: LatentState, action: th.Tensor, deterministic: bool = False
    ) -> tuple[LatentState, th.Tensor]:
        """One imagined step: ``s_{t+1}`` from ``s_t`` and the action ``a_t`` taken in it (thesis 4.4.3).

        :param state: current state (batch (N,))
        :param action: (N, A)
        :param deterministic: take the prior mode instead of a sample
        :return: next state (z drawn from the prior) and its prior logits (N, G, K)
        """
        action = self._check_actions(action, 2, "action")
        self._check_state(state, (int(action.shape[0]),))
        return self._img_step(state, action, deterministic)

    def _img_step(self, state: LatentState, action: th.Tensor, deterministic: bool) -> tuple[LatentState, th.Tensor]:
        """:meth:`img_step` of checked inputs."""
        raise NotImplementedError

    def reuse_step_weights(self) -> contextlib.AbstractContextManager:
        """A block in which the sequence model may reuse per-rollout step weights (S5WM: the discretisation,
        :meth:`sb3_hieros.nn.s5.S5Stack.reuse_step_weights`); the parameters must not change inside it.

        :return: context manager (a no-op for models without such weights)
        """
        return contextlib.nullcontext()

    def no_weight_decay_parameters(self) -> list[nn.Parameter]:
        """Parameters to train without weight decay: SSM parameters (S5WM), norms, biases and other 1-d tensors.

        :return: list of parameters
        """
        return [p for p in self.parameters() if p.dim() <= 1]

    # ---------------------------------------------------------------- heads

    def features(self, state: LatentState) -> th.Tensor:
        """World-state features ``[h_t, z_t]`` fed to heads, actor and critics.

        :param state: any state
        :return: (..., D + G*K)
        """
        return th.cat([state.deter, state.stoch], -1)

    def reward_dist(self, state: LatentState) -> TwoHotSymlog:
        """p(r_t | h_t, z_t): symlog two-hot over 255 bins.

        :param state: any state
        :return: distribution with batch shape of ``state``
        """
        return TwoHotSymlog(self.reward_head(self.features(state)), self.reward_bins, self.reward_bins_antisymmetric)

    def cont_dist(self, state: LatentState) -> ContinueBernoulli:
        """p(c_t | h_t, z_t), c_t = 1 - is_terminal_t.

        :param state: any state
        :return: Bernoulli with batch shape of ``state``
        """
        return ContinueBernoulli(self.cont_head(self.features(state)).squeeze(-1))

    def reward(self, state: LatentState) -> th.Tensor:
        """Predicted reward (expectation of the two-hot head, raw units).

        :param state: any state
        :return: (...) rewards
        """
        return self.reward_dist(state).mean

    def cont(self, state: LatentState) -> th.Tensor:
        """Predicted continue probability.

        :param state: any state
        :return: (...) probabilities in [0, 1]
        """
        return self.cont_dist(state).mean

    def decode(self, state: LatentState) -> th.Tensor | dict[str, th.Tensor]:
        """Mean observation predicted from a state (images as float pixels in [0, 255], vectors in raw units, discrete
        keys as their most likely value in the space: int64 indices, MultiBinary bits in its dtype).

        :param state: any state
        :return: tensor (..., *obs_shape), or a dict of them for Dict spaces
        """
        out = self.decoder.mean(self.decoder(self.features(state)))
        return out if self.spec.is_dict else out[SINGLE_KEY]

    def prior_entropy(self, state: LatentState) -> th.Tensor:
        """Entropy of the prior p(z^_t | m_t) at each state (actor input, eq. 4.6), summed over the groups.

        :param state: any state
        :return: (...) nats
        """
        probs = state.prior_logits.exp()
        return -(probs * state.prior_logits).sum((-2, -1))

    # ---------------------------------------------------------------- loss

    def loss(self, samples: Any, state: LatentState | None = None) -> tuple[th.Tensor, dict[str, float], LatentState]:
        """World-model loss of a batch of chunks, eq. 4.10-4.13, averaged over B x T.

        ``L = L_pred + dyn_scale * max(free, KL[sg(q) || p]) + rep_scale * max(free, KL[q || sg(p)])`` with the KL
        summed over the categorical groups; ``L_pred`` is the negative log-likelihood of o_t, r_t and
        ``c_t = 1 - is_terminal_t`` under the heads on (h_t, z_t), that of r_t weighted by ``reward_scale``. With
        ``config.reward_overshoot`` > 0, :meth:`open_loop_reward_nll` is added, also weighted by ``reward_scale``; with
        ``config.prior_decoder_scale`` > 0, :meth:`prior_observation_nll` is added with that weight.

        :param samples: object with ``observations`` (B, T, ...), ``actions`` (B, T, A) = previous actions,
            ``rewards`` (B, T), ``is_first`` (B, T), ``is_terminal`` (B, T) (e.g. ``SequenceSamples``)
        :param state: state before row 0, or None
        :return: scalar loss, metrics and the posterior states (batch (B, T), attached to the graph)
        """
        loss, metrics, post = self._loss(self._checked(samples, state), state)
        return loss, metric_floats(metrics), post

    def _checked(self, samples: Any, state: LatentState | None) -> SequenceSamples:
        """``samples`` checked, with float previous actions and bool ``is_first`` (what :meth:`_loss` trusts)."""
        for field in ("observations", "actions", "rewards", "is_first", "is_terminal"):
            if not hasattr(samples, field):
                raise ValueError(f"samples must have the attribute {field!r} (SequenceSamples-like)")
        _, actions, is_first, lead = self._check_sequence(samples.observations, samples.actions, samples.is_first)
        if state is not None:
            self._check_state(state, lead[:1])
        for field in ("rewards", "is_terminal"):
            value = getattr(samples, field)
            if not isinstance(value, th.Tensor) or tuple(value.shape) != lead:
                shape = tuple(value.shape) if isinstance(value, th.Tensor) else type(value).__name__
                raise ValueError(f"samples.{field} must be a tensor of shape {lead}, got {shape}")
        return SequenceSamples(samples.observations, actions, samples.rewards, is_first, samples.is_terminal, None)

    def _loss(self, samples: Any, state: LatentState | None) -> tuple[th.Tensor, dict[str, th.Tensor], LatentState]:
        """:meth:`loss` of a trusted batch (float previous actions, bool ``is_first``), under the ``bf16`` autocast."""
        with self._autocast():
            return self._loss_terms(samples, state)

    def _loss_terms(
        self, samples: Any, state: LatentState | None
    ) -> tuple[th.Tensor, dict[str, th.Tensor], LatentState]:
        # images are converted to x/255 - 0.5 once, for the encoder and as the decoder's target
        obs = self.spec.preprocess(self.spec.as_dict(samples.observations))
        if self.training and self.config.image_shift:
            # the encoder and the decoder's target see the same shifted frames
            shift = self.config.image_shift
            obs = {k: random_shift(v, shift) if k in self.spec.image_keys else v for k, v in obs.items()}
        post, prior_logits = self._observe(obs, samples.actions, samples.is_first, state, False)
        lead = tuple(post.batch_shape)
        feat = self.features(post)
        pred = self.decoder(feat)
        reward_logits = self.reward_head(feat)
        cont_logits = self.cont_head(feat)
        obs_nll = self.decoder.nll(pred, obs, lead)
        reward_nll = -TwoHotSymlog(reward_logits, self.reward_bins, self.reward_bins_antisymmetric).log_prob(
            samples.rewards.float()
        )
        cont_target = 1.0 - samples.is_terminal.float()
        cont_nll = -ContinueBernoulli(cont_logits.squeeze(-1)).log_prob(cont_target)
        post_probs = post.logits.exp()  # (B, T, G, K), one exp for both KL terms and the entropy metric
        kl_dyn = _grouped_kl(post.logits.detach(), prior_logits, post_probs.detach())  # (B, T), summed over groups
        kl_rep = _grouped_kl(post.logits, prior_logits.detach(), post_probs)
        free = self.config.free_bits
        dyn = kl_dyn.clamp(min=free)
        rep = kl_rep.clamp(min=free)
        per_step = (
            obs_nll
            + self.config.reward_scale * reward_nll
            + cont_nll
            + self.config.dyn_scale * dyn
            + self.config.rep_scale * rep
        )
        loss = per_step.mean()
        extra: dict[str, th.Tensor] = {}
        if self.config.reward_overshoot:
            overshoot_nll = self.open_loop_reward_nll(post, samples.actions, samples.rewards, samples.is_first)
            loss = loss + self.config.reward_scale * overshoot_nll
            extra["reward_overshoot_loss"] = overshoot_nll.detach()
        if self.config.prior_decoder_scale:
            prior_obs_nll = self.prior_observation_nll(post, prior_logits, obs)
            loss = loss + self.config.prior_decoder_scale * prior_obs_nll
            extra["prior_obs_loss"] = prior_obs_nll.detach()
        with th.no_grad():
            metrics = {
                "loss": loss.detach(),
                "obs_loss": obs_nll.mean(),
                "reward_loss": reward_nll.mean(),
                **extra,
                "cont_loss": cont_nll.mean(),
                "kl": kl_dyn.mean(),
                "dyn_loss": dyn.mean(),
                "rep_loss": rep.mean(),
                "prior_entropy": self.prior_entropy(post).mean(),
                "post_entropy": -(post_probs * post.logits).sum((-2, -1)).mean(),
            }
        return loss, metrics, post

    def prior_observation_nll(self, post: LatentState, prior_logits: th.Tensor, obs: dict[str, th.Tensor]) -> th.Tensor:
        """Negative log-likelihood of the observations under the decoder on one-step prior states
        (``config.prior_decoder_scale``; not in the thesis, whose eq. 4.11 decodes posterior states only).

        At each row the decoder reads ``[h_t, z^_t]`` with z^_t drawn (straight-through) from the prior
        p(z^_t | m_t) instead of the posterior: o_t is predicted from s_{t-1} and a_{t-1} alone. The gradient reaches
        the decoder, the prior, the sequence model and, through the earlier posterior states, the encoder.

        :param post: posterior states (B, T), attached to the graph
        :param prior_logits: (B, T, G, K) normalised log-probabilities of the prior (unimix included)
        :param obs: the preprocessed observations the posterior was built from
        :return: scalar mean over B x T
        """
        prior_stoch = OneHotCategoricalST(prior_logits, 0.0, event_ndims=1).sample().flatten(-2)  # (B, T, G*K)
        pred = self.decoder(self.features(post._replace(stoch=prior_stoch)))
        return self.decoder.nll(pred, obs, tuple(post.batch_shape)).mean()

    def open_loop_reward_nll(
        self, post: LatentState, actions: th.Tensor, rewards: th.Tensor, is_first: th.Tensor
    ) -> th.Tensor:
        """Negative log-likelihood of the replayed rewards under the reward head on open-loop prior states
        (``config.reward_overshoot``; not in the thesis, whose eq. 4.11 reads the reward from posterior states only).

        From each posterior state s_t the prior is rolled k = 1..K steps under the replayed actions a_t..a_{t+k-1}
        (``actions[:, t + k]``, the previous action of row t + k), and its reward head is scored on r_{t+k}. A step
        counts while t + k stays inside the chunk and no episode starts in rows t+1..t+k. The gradient reaches the
        dynamics, the posterior states and, through them, the encoder: the state must hold what the reward will be
        after the actions, not only what it is now.

        :param post: posterior states (B, T), attached to the graph
        :param actions: (B, T, A) previous actions (row t holds a_{t-1})
        :param rewards: (B, T)
        :param is_first: (B, T) bool
        :return: scalar mean over the counted (start, k) pairs (0 when there are none)
        """
        batch, length = rewards.shape
        starts = th.arange(length - 1, device=rewards.device)  # t = 0 .. T-2
        state = post.select((slice(None), slice(0, length - 1))).flatten_batch()  # (B*(T-1),)
        inside = th.ones(batch, length - 1, dtype=th.bool, device=rewards.device)
        total = rewards.new_zeros((), dtype=th.float32)
        count = rewards.new_zeros((), dtype=th.float32)
        with self.reuse_step_weights():
            for k in range(1, self.config.reward_overshoot + 1):
                rows = (starts + k).clamp(max=length - 1)  # (T-1,)
                inside = inside & (starts + k < length) & ~is_first[:, rows]  # (B, T-1)
                if not inside.any():
                    break
                state, _ = self._img_step(state, actions[:, rows].reshape(batch * (length - 1), -1), False)
                nll = -self.reward_dist(state).log_prob(rewards[:, rows].reshape(-1).float())
                weight = inside.reshape(-1).float()
                total = total + (nll.float() * weight).sum()
                count = count + weight.sum()
        return total / count.clamp(min=1.0)

    def train_step(
        self,
        samples: Any,
        optimizer: th.optim.Optimizer,
        scheduler: th.optim.lr_scheduler.LRScheduler | None = None,
        state: LatentState | None = None,
    ) -> tuple[dict[str, float], LatentState]:
        """One gradient step on :meth:`loss` with gradient-norm clipping at ``config.grad_clip``.

        The step (and the scheduler step) is skipped when the loss or the gradient norm is not finite
        (:func:`~sb3_hieros.nn.guard.step_if_finite`); the metric ``nonfinite`` is then 1.

        :param samples: batch of chunks (see :meth:`loss`)
        :param optimizer: e.g. from :func:`world_model_optimizer`
        :param scheduler: optional learning-rate schedule stepped after the update
        :param state: state before row 0 (e.g. :meth:`unpack_context` of the replay context), or None for zeros
        :return: metrics (with ``grad_norm`` and ``nonfinite``) and the detached posterior states
        """
        metrics, post = self._train_step(self._checked(samples, state), optimizer, scheduler, state)
        return metric_floats(metrics), post

    def _train_step(
        self,
        samples: Any,
        optimizer: th.optim.Optimizer,
        scheduler: th.optim.lr_scheduler.LRScheduler | None,
        state: LatentState | None,
    ) -> tuple[dict[str, th.Tensor], LatentState]:
        """:meth:`train_step` of a trusted batch (see :meth:`_loss`)."""
        loss, metrics, post = self._loss(samples, state)
        return self._step(loss, metrics, post, optimizer, scheduler)

    def _step(
        self,
        loss: th.Tensor,
        metrics: dict[str, th.Tensor],
        post: LatentState,
        optimizer: th.optim.Optimizer,
        scheduler: th.optim.lr_scheduler.LRScheduler | None,
    ) -> tuple[dict[str, th.Tensor], LatentState]:
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        grad_norm = nn.utils.clip_grad_norm_(self.parameters(), self.config.grad_clip)
        stepped = step_if_finite(optimizer, loss, grad_norm)
        if stepped and scheduler is not None:
            scheduler.step()
        metrics["grad_norm"] = grad_norm.detach()
        metrics["nonfinite"] = grad_norm.new_tensor(float(not stepped))
        return metrics, post.detach()

    # ---------------------------------------------------------------- imagination

    def rollout(
        self,
        start: LatentState,
        horizon: int,
        step: StepFn,
        deterministic: bool = False,
        keep_seq: bool = False,
    ) -> tuple[LatentState, th.Tensor]:
        """The imagination rollout (thesis 4.4.3, Figure 4.7): ``a_t = step(t, s_t)`` and s_{t+1} from the prior for
        t = 0 .. H-1, then ``step(H, s_H)`` once more (its return value is ignored) so that the caller sees s_H.

        Every imagination in the library is this loop; its callers differ in ``step``: a level's actor with the
        subgoals of the levels above (:class:`~sb3_hieros.agent.hierarchy.Hierarchy`), all levels of one shared world
        model, a given policy (:meth:`imagine`), recorded actions (``ImaginationCallback``). It runs in step form with
        one discretisation for the whole rollout (:meth:`reuse_step_weights`) and without dropout, also when the model
        is in training mode (dropout regularises the world-model loss; an imagined trajectory is a function of the
        sampled latents and actions alone, and the mode is restored afterwards). The recurrent state is not detached
        between steps and ``start`` is not modified, so gradients flow back through the whole rollout (dynamics
        backpropagation). The inputs are trusted.

        :param start: (N,) start states
        :param horizon: imagined steps H
        :param step: ``step(t, s_t) -> a_t``, (N, A) float; called H + 1 times, in order of t
        :param deterministic: prior modes instead of samples
        :param keep_seq: keep the recurrent memory of every state; otherwise ``states.seq`` is an empty (H+1, N, 0)
            tensor (nothing downstream reads it, and for S5WM it is the largest field)
        :return: states s_0..s_H (H+1, N) and actions a_0..a_{H-1} (H, N, A)
        """
        empty_seq = start.seq.new_zeros(start.seq.shape[0], 0)

        def stored(state: LatentState) -> LatentState:
            return state if keep_seq else state._replace(seq=empty_seq)

        states, actions = [stored(start)], []
        state = start
        with self.reuse_step_weights(), evaluation_mode(self):
            for t in range(horizon):
                action = step(t, state)
                actions.append(action)
                state, _ = self._img_step(state, action, deterministic)
                states.append(stored(state))
            step(horizon, state)
        return stack_states(states, 0), th.stack(actions, 0)

    def imagine(
        self,
        start: LatentState,
        policy: Callable[[LatentState], th.Tensor],
        horizon: int,
        deterministic: bool = False,
        keep_seq: bool = False,
    ) -> tuple[LatentState, th.Tensor, th.Tensor]:
        """:meth:`rollout` with actions from ``policy``, without dropout (the world model's training mode is restored
        afterwards), e.g. to inspect or time the world model on its own.

        :param start: start states of batch shape (N,) (e.g. ``post.flatten_batch()``)
        :param policy: state (N,) -> action (N, A); ``actions[i]`` is the action taken in ``states[i]``
        :param horizon: number of imagined steps H
        :param deterministic: take prior modes instead of samples
        :param keep_seq: see :meth:`rollout`
        :return: states (H+1, N) including ``start``, actions (H+1, N, A) and prior entropies (H+1, N)
        """
        if isinstance(horizon, bool) or not isinstance(horizon, int) or horizon < 1:
            raise ValueError(f"horizon must be a positive int, got {horizon!r}")
        if not isinstance(start, LatentState) or len(start.batch_shape) != 1:
            shape = tuple(start.batch_shape) if isinstance(start, LatentState) else type(start).__name__
            raise ValueError(f"start must be a LatentState of batch shape (N,), got {shape}; use flatten_batch()")
        n = int(start.batch_shape[0])
        self._check_state(start, (n,), "start")
        actions, entropies = [], []

        def step(t: int, state: LatentState) -> th.Tensor:
            action = policy(state)
            if not isinstance(action, th.Tensor) or tuple(action.shape) != (n, self.action_dim):
                shape = tuple(action.shape) if isinstance(action, th.Tensor) else type(action).__name__
                raise ValueError(f"policy must return actions of shape {(n, self.action_dim)}, got {shape}")
            actions.append(action)
            entropies.append(self.prior_entropy(state))
            return action.float()

        states, _ = self.rollout(start, horizon, step, deterministic, keep_seq)
        return states, th.stack(actions, 0), th.stack(entropies, 0)
