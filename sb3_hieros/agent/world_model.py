"""World model of one HIEROS level (thesis 4.4): S5WM and DreamerV3's RSSM behind one interface.

Both models describe the world by a latent state ``(h_t, z_t)``: ``h_t`` deterministic, ``z_t`` a vector of
``stoch_groups`` one-hot categoricals of ``stoch_classes`` classes (thesis 4.4)::

    Sequence model:     (m_t, h_t) = f(h_{t-1}, z_{t-1}, a_{t-1})
    Encoder:            z_t ~ q(z_t | o_t)            (S5WM)   or  q(z_t | h_t, o_t)  (RSSM)
    Dynamics predictor: z^_t ~ p(z^_t | m_t)          (S5WM)   or  p(z^_t | h_t)      (RSSM)
    Reward, continue and decoder heads on (h_t, z_t).

Time alignment (research note hieros_reference.md 8.1). A training row t holds ``o_t``, ``a_{t-1}`` (the action
taken after ``o_{t-1}``, which led to ``o_t``; zeros where ``is_first_t``), ``r_t`` (received on arriving at
``o_t``), ``is_first_t`` and ``is_terminal_t``. The sequence model at row t consumes ``(z_{t-1}, a_{t-1})``,
identically in training (:meth:`WorldModel.observe`), acting (:meth:`WorldModel.obs_step`) and imagination
(:meth:`WorldModel.img_step`). Where ``is_first_t``, ``z_{t-1}`` and ``a_{t-1}`` are zeroed and the recurrent state
is reset, so the first ``h`` of an episode is computed exactly like every later ``h`` (fixes note 8.12): it is the
successor of :meth:`WorldModel.initial_state`.

Design decisions (documented deviations from the public reference code, hieros_reference.md 3.5-3.7, 8):

* S5WM ``h_t`` (``deter_from="state"``, thesis 5.3.5) is ``symlog(Linear([Re x_t, Im x_t]))`` over the complex
  states x_t of all S5 layers. The reference reads out ``Re`` only; the imaginary part carries the phase of the
  rotating modes, so both parts are used (the read-out Linear doubles its input width: negligible in training,
  about 10 % of an imagination step at paper width).
  With ``deter_from="output"`` it is ``symlog(Linear(m_t))``.
* The posterior of S5WM is computed from the observation embedding only (thesis 4.4.2), so a whole chunk is
  encoded in one batched pass; the S5 stack then runs once in its parallel form.
* Imagination never detaches the S5 state between steps (note 3.7) and never writes into the start state
  (note 8.7), so dynamics-backpropagation gradients flow through the whole rollout.
* The RSSM uses DreamerV3's LayerNorm GRU (one Linear over ``[x, h]``, LayerNorm, update-gate bias -1) and the
  "optimized" loop of perf_anchors.md 2.4: the embedding half of the posterior layer, the action half of the
  input layer and the whole prior head are computed outside the time loop, which iterates with ``unbind(1)``.
* Imagination runs without dropout and by default does not keep the recurrent memory of imagined states
  (``imagine(keep_seq=True)`` does); image convolutions run in the channels-last memory format.
* Actions enter as float vectors (one-hot for discrete actions and subgoals, [-1, 1] for Box). DreamerV3's
  ``a / max(1, |a|)`` rescaling is the identity on such inputs and is therefore not applied.

Optional speed opt-ins (off by default): ``bf16=True`` runs encoder, decoder, heads and the dense layers around the
sequence model, and the S5 layers' input/output projections, under CPU/GPU bfloat16 autocast (the S5 scan and its
complex state stay in fp32; the RSSM observe loop stays in fp32 because casting tiny per-step matmuls costs more
than it saves, perf_anchors.md 2.6); only useful on CPUs with native bf16 (AVX512-BF16 / AMX), elsewhere it is
emulated and many times slower. And
``compile=True`` compiles the convolutional encoder/decoder and the S5 parallel scan (``compile_s5``; the step form
stays eager) or the RSSM loop cell with ``torch.compile`` (tens of seconds of compilation per new input shape; save
the ``state_dict``, not the pickled module).
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np
import torch as th
import torch.nn.functional as F
from gymnasium import spaces
from stable_baselines3.common.preprocessing import is_image_space, is_image_space_channels_first
from torch import nn

from sb3_hieros.config import WorldModelConfig
from sb3_hieros.nn.distributions import (
    ContinueBernoulli,
    OneHotCategoricalST,
    TwoHotSymlog,
    symexp,
    symlog,
    symlog_bins,
    symlog_mse,
)
from sb3_hieros.nn.guard import step_if_finite
from sb3_hieros.nn.networks import MLP, ConvDecoder, ConvEncoder, preprocess_image, trunc_normal_init_
from sb3_hieros.nn.s5 import S5Stack, compile_s5

__all__ = [
    "LatentState",
    "ObservationSpec",
    "RSSMWorldModel",
    "S5WorldModel",
    "WorldModel",
    "cat_states",
    "make_world_model",
    "stack_states",
    "world_model_lr_scheduler",
    "world_model_optimizer",
]

REWARD_BINS = 255
_SINGLE_KEY = "obs"


# ----------------------------------------------------------------------------------------------------------------------
# Latent state container
# ----------------------------------------------------------------------------------------------------------------------


class LatentState(NamedTuple):
    """World state ``(h_t, z_t)`` plus what is needed to continue from it; all fields share the batch shape.

    :param stoch: (..., G*K) flattened one-hot z_t (straight-through gradients where sampled)
    :param deter: (..., D) deterministic state h_t
    :param seq: recurrent memory of the sequence model: (..., L, P) complex64 S5 states of all layers (S5WM) or the
        (..., D) GRU state (RSSM, the same tensor as ``deter``)
    :param logits: (..., G, K) normalised log-probabilities (unimix included) of the distribution ``stoch`` was drawn
        from: the posterior for observed states, the prior for imagined ones
    :param prior_logits: (..., G, K) normalised log-probabilities of the prior p(z^_t | m_t) at this step (for the
        actor's prior-entropy input, eq. 4.6); equal to ``logits`` for imagined states
    """

    stoch: th.Tensor
    deter: th.Tensor
    seq: th.Tensor
    logits: th.Tensor
    prior_logits: th.Tensor

    @property
    def batch_shape(self) -> th.Size:
        """Leading (batch) shape shared by all fields, e.g. (B, T) or (N,)."""
        return self.stoch.shape[:-1]

    def map_fields(self, fn: Callable[[th.Tensor], th.Tensor]) -> LatentState:
        """Apply ``fn`` to every field.

        :param fn: tensor -> tensor
        :return: new state
        """
        return LatentState(*(fn(x) for x in self))

    def select(self, index: Any) -> LatentState:
        """Index the leading batch dims of every field, e.g. ``state.select((slice(None), 3))`` for step 3.

        :param index: anything valid as a tensor index that only touches batch dims (no Ellipsis)
        :return: new state
        """
        return self.map_fields(lambda x: x[index])

    def reshape_batch(self, *shape: int) -> LatentState:
        """Reshape the batch dims of every field, keeping each field's trailing event dims.

        :param shape: new batch shape (one entry may be -1)
        :return: new state
        """
        n_batch = len(self.batch_shape)
        return self.map_fields(lambda x: x.reshape(*shape, *x.shape[n_batch:]))

    def flatten_batch(self) -> LatentState:
        """All batch dims flattened into one, e.g. (B, T, ...) -> (B*T, ...) (imagination start states).

        :return: new state
        """
        return self.reshape_batch(-1)

    def detach(self) -> LatentState:
        """Copy of the state cut from the autograd graph.

        :return: new state
        """
        return self.map_fields(lambda x: x.detach())

    def masked(self, keep: th.Tensor) -> LatentState:
        """Every field multiplied by ``keep`` (zero where ``keep`` is False/0, e.g. ``~is_first``).

        :param keep: tensor of exactly the batch shape (bool or float)
        :return: new state
        """
        if tuple(keep.shape) != tuple(self.batch_shape):
            raise ValueError(f"keep must have the batch shape {tuple(self.batch_shape)}, got {tuple(keep.shape)}")
        n_batch = len(self.batch_shape)

        def apply(x: th.Tensor) -> th.Tensor:
            k = keep.to(x.real.dtype if x.is_complex() else x.dtype)
            return x * k.reshape(*k.shape, *([1] * (x.dim() - n_batch)))

        return self.map_fields(apply)


def stack_states(states: Sequence[LatentState], dim: int = 0) -> LatentState:
    """Stack states along a new batch dim (``dim`` counted from the front, >= 0).

    :param states: states of equal batch shape
    :param dim: position of the new dim among the batch dims
    :return: stacked state
    """
    if not states:
        raise ValueError("stack_states needs at least one state")
    if dim < 0:
        raise ValueError(f"dim must be >= 0 (counted among the batch dims), got {dim}")
    return LatentState(*(th.stack(fields, dim) for fields in zip(*states, strict=True)))


def cat_states(states: Sequence[LatentState], dim: int = 0) -> LatentState:
    """Concatenate states along an existing batch dim (``dim`` >= 0).

    :param states: states whose batch shapes agree except along ``dim``
    :param dim: batch dim to concatenate
    :return: concatenated state
    """
    if not states:
        raise ValueError("cat_states needs at least one state")
    if dim < 0:
        raise ValueError(f"dim must be >= 0 (counted among the batch dims), got {dim}")
    return LatentState(*(th.cat(fields, dim) for fields in zip(*states, strict=True)))


# ----------------------------------------------------------------------------------------------------------------------
# Observations: specification, encoder and decoder
# ----------------------------------------------------------------------------------------------------------------------


class ObservationSpec:
    """Which observation keys are images (CNN) and which are vectors (symlog MLP).

    A Box of rank 3 with uint8 pixels in [0, 255] is a channel-first (C, H, W) image; any other Box is a vector
    (flattened). A Dict space may mix both (its sub-spaces must be Boxes). Non-dict spaces use the single key
    ``"obs"`` internally.

    :param observation_space: the level's observation space
    """

    def __init__(self, observation_space: spaces.Space) -> None:
        self.is_dict = isinstance(observation_space, spaces.Dict)
        items = list(observation_space.spaces.items()) if self.is_dict else [(_SINGLE_KEY, observation_space)]
        if not items:
            raise ValueError("observation_space is an empty Dict space")
        self.shapes: dict[str, tuple[int, ...]] = {}
        self.image_keys: list[str] = []
        self.vector_keys: list[str] = []
        for key, space in items:
            name = f"observation_space[{key!r}]" if self.is_dict else "observation_space"
            if not isinstance(space, spaces.Box):
                raise ValueError(f"{name} must be a gymnasium Box (or a Dict of Boxes), got {space}")
            if not isinstance(key, str) or "." in key or not key:
                raise ValueError(f"observation keys must be non-empty strings without '.', got {key!r}")
            self.shapes[key] = tuple(int(s) for s in space.shape)
            if is_image_space(space, check_channels=False):
                if not is_image_space_channels_first(space):
                    raise ValueError(
                        f"{name} is a channel-last image of shape {space.shape}; the world model expects channel-first "
                        "(C, H, W) images: wrap the env in VecTransposeImage"
                    )
                self.image_keys.append(key)
            else:
                self.vector_keys.append(key)
        self.vector_sizes = [int(np.prod(self.shapes[k])) for k in self.vector_keys]
        self.vector_dim = sum(self.vector_sizes)

    def as_dict(self, observations: Any, name: str = "observations") -> dict[str, th.Tensor]:
        """Observations as a key -> tensor dict (wrapping a single tensor), type-checked.

        :param observations: a tensor, or a mapping for Dict spaces
        :param name: argument name used in error messages
        :return: dict of tensors
        """
        if self.is_dict:
            if not isinstance(observations, Mapping):
                raise ValueError(
                    f"{name} must be a dict of tensors for a Dict space, got {type(observations).__name__}"
                )
            missing = [k for k in self.shapes if k not in observations]
            if missing:
                raise ValueError(f"{name} lacks the keys {missing}; expected {sorted(self.shapes)}")
            obs = {k: observations[k] for k in self.shapes}
        else:
            obs = {_SINGLE_KEY: observations}
        for key, value in obs.items():
            if not isinstance(value, th.Tensor):
                label = f"{name}[{key!r}]" if self.is_dict else name
                raise ValueError(f"{label} must be a torch.Tensor, got {type(value).__name__}")
        return obs

    def check(self, obs: dict[str, th.Tensor], lead: tuple[int, ...], name: str = "observations") -> None:
        """Raise ``ValueError`` unless every entry has shape ``lead + space shape``.

        :param obs: dict from :meth:`as_dict`
        :param lead: expected batch shape, e.g. (B, T)
        :param name: argument name used in error messages
        """
        for key, value in obs.items():
            expected = (*lead, *self.shapes[key])
            if tuple(value.shape) != expected:
                label = f"{name}[{key!r}]" if self.is_dict else name
                raise ValueError(f"{label} has shape {tuple(value.shape)}, expected {expected}")

    def preprocess(self, obs: dict[str, th.Tensor]) -> dict[str, th.Tensor]:
        """uint8 images mapped to float ``x / 255 - 0.5`` (the encoder's input and decoder's output space); float
        images (taken as already mapped) and vectors pass unchanged.

        :param obs: dict from :meth:`as_dict`
        :return: new dict
        """
        out = dict(obs)
        for key in self.image_keys:
            images = obs[key]
            if images.dtype == th.uint8:
                # one conversion pass straight into the channels-last layout the convolutions use; the (N, C, H, W)
                # view of the result is channels-last, so encoder input and decoder target need no further copies
                flat = images.reshape(-1, *images.shape[-3:]).to(th.float32, memory_format=th.channels_last)
                out[key] = flat.mul_(1.0 / 255.0).sub_(0.5).view(images.shape)
        return out

    def vectors(self, obs: dict[str, th.Tensor], lead: tuple[int, ...]) -> th.Tensor:
        """Concatenation of all vector entries, flattened, as float: (..., vector_dim).

        :param obs: dict from :meth:`as_dict`
        :param lead: batch shape
        :return: float tensor
        """
        parts = [obs[k].reshape(*lead, -1).float() for k in self.vector_keys]
        return parts[0] if len(parts) == 1 else th.cat(parts, -1)


def _grouped_kl(log_p: th.Tensor, log_q: th.Tensor, p: th.Tensor | None = None) -> th.Tensor:
    """``KL(p || q)`` summed over groups and classes, for already normalised log-probabilities (..., G, K).

    Same value as :func:`~sb3_hieros.nn.distributions.categorical_kl`, without re-normalising inputs that the world
    model keeps normalised (``LatentState.logits`` / ``prior_logits``).

    :param p: ``log_p.exp()`` when the caller already has it (the loss needs it for both KL terms)
    """
    return ((log_p.exp() if p is None else p) * (log_p - log_q)).sum((-2, -1))


class _SquaredError(th.autograd.Function):
    """``((pred - target) ** 2).sum((-3, -2, -1))`` in one subtraction and one reduction pass, with a one-pass backward
    ``2 * (pred - target) * grad`` (no gradient to the target). Saves several full passes over the image batch
    compared to the composed ops."""

    @staticmethod
    def forward(ctx: Any, pred: th.Tensor, target: th.Tensor) -> th.Tensor:
        diff = pred - target.to(pred.dtype)
        ctx.save_for_backward(diff)
        return th.linalg.vector_norm(diff, dim=(-3, -2, -1)).square()

    @staticmethod
    def backward(ctx: Any, grad: th.Tensor) -> tuple[th.Tensor, None]:
        (diff,) = ctx.saved_tensors
        return diff * (2.0 * grad)[..., None, None, None], None


class ObservationEncoder(nn.Module):
    """Embedding of o_t (thesis 4.4): a :class:`ConvEncoder` per image key and one symlog MLP over all vector keys,
    concatenated. Accepts any leading batch dims.

    Convolutions run in the channels-last memory format (weights and activations): oneDNN's NHWC kernels are faster
    on CPU and the per-pixel channel LayerNorm then needs no transposing copies.

    :param spec: the observation specification
    :param config: world-model hyperparameters (``cnn_depth``, ``mlp_units``, ``mlp_layers``)
    :param channels_last: use the channels-last memory format for the convolutions
    """

    def __init__(self, spec: ObservationSpec, config: WorldModelConfig, channels_last: bool = True) -> None:
        super().__init__()
        self.spec = spec
        self.channels_last = channels_last
        self.convs = nn.ModuleDict({k: ConvEncoder(spec.shapes[k], config.cnn_depth) for k in spec.image_keys})
        if channels_last:
            self.convs.to(memory_format=th.channels_last)
        self.mlp = (
            MLP(spec.vector_dim, None, config.mlp_units, config.mlp_layers, symlog_inputs=True)
            if spec.vector_keys
            else None
        )
        self.out_dim = sum(c.out_dim for c in self.convs.values()) + (self.mlp.out_dim if self.mlp is not None else 0)

    def forward(self, obs: dict[str, th.Tensor], lead: tuple[int, ...]) -> th.Tensor:
        """:param obs: dict from :meth:`ObservationSpec.as_dict`, entries (*lead, *shape)
        :param lead: batch shape
        :return: (*lead, out_dim) embedding
        """
        parts = []
        for key in self.spec.image_keys:
            images = obs[key].reshape(-1, *self.spec.shapes[key])  # (N, C, H, W)
            if self.channels_last:
                images = images.contiguous(memory_format=th.channels_last)
            parts.append(self.convs[key](images).reshape(*lead, -1))
        if self.mlp is not None:
            parts.append(self.mlp(self.spec.vectors(obs, lead)))
        return parts[0] if len(parts) == 1 else th.cat(parts, -1)


class ObservationDecoder(nn.Module):
    """p(o_t | h_t, z_t): a :class:`ConvDecoder` per image key (mean in x/255 - 0.5 space, unit-variance Gaussian,
    i.e. MSE summed over pixels) and one MLP predicting ``symlog`` of all vector keys (symlog MSE).

    :param spec: the observation specification
    :param feat_dim: size of the world-state features
    :param config: world-model hyperparameters
    :param channels_last: use the channels-last memory format for the transposed convolutions
    """

    def __init__(
        self, spec: ObservationSpec, feat_dim: int, config: WorldModelConfig, channels_last: bool = True
    ) -> None:
        super().__init__()
        self.spec = spec
        self.convs = nn.ModuleDict(
            {k: ConvDecoder(feat_dim, spec.shapes[k], config.cnn_depth) for k in spec.image_keys}
        )
        if channels_last:
            self.convs.to(memory_format=th.channels_last)
        self.mlp = MLP(feat_dim, spec.vector_dim, config.mlp_units, config.mlp_layers) if spec.vector_keys else None

    def forward(self, feat: th.Tensor) -> dict[str, th.Tensor]:
        """:param feat: (..., feat_dim)
        :return: key -> prediction in model space (images (..., C, H, W) in x/255 - 0.5; the vector group under the
            key ``""`` as (..., vector_dim) in symlog space), always float32
        """
        out = {k: conv(feat).float() for k, conv in self.convs.items()}
        if self.mlp is not None:
            out[""] = self.mlp(feat).float()
        return out

    def nll(self, pred: dict[str, th.Tensor], obs: dict[str, th.Tensor], lead: tuple[int, ...]) -> th.Tensor:
        """Negative log-likelihood (up to constants) of the observations, eq. 4.11 third term.

        :param pred: output of :meth:`forward`
        :param obs: true observations (dict from :meth:`ObservationSpec.as_dict`)
        :param lead: batch shape
        :return: (*lead) loss, summed over pixels / vector entries and keys
        """
        total = th.zeros(lead, device=next(iter(pred.values())).device)
        for key in self.spec.image_keys:
            total = total + _SquaredError.apply(pred[key], preprocess_image(obs[key]))
        if self.mlp is not None:
            total = total + symlog_mse(pred[""], self.spec.vectors(obs, lead))
        return total

    def mean(self, pred: dict[str, th.Tensor]) -> dict[str, th.Tensor]:
        """Predicted observations in the units of the observation space.

        :param pred: output of :meth:`forward`
        :return: key -> images as float pixels in [0, 255] (..., C, H, W), vectors in raw units (..., *shape)
        """
        out = {k: ((pred[k] + 0.5) * 255.0).clamp(0.0, 255.0) for k in self.spec.image_keys}
        if self.mlp is not None:
            vec = symexp(pred[""])
            lead = vec.shape[:-1]
            for key, part in zip(self.spec.vector_keys, th.split(vec, self.spec.vector_sizes, -1), strict=True):
                out[key] = part.reshape(*lead, *self.spec.shapes[key])
        return out


# ----------------------------------------------------------------------------------------------------------------------
# Shared layers
# ----------------------------------------------------------------------------------------------------------------------


class InputLayer(nn.Module):
    """``Inp(z_{t-1}, a_{t-1}) = SiLU(LayerNorm(W_z z_{t-1} + W_a a_{t-1}))``: the sequence model's input.

    The Linear over the concatenation ``[z, a]`` is kept as two bias-free halves so that the action half can be
    computed for a whole chunk outside the RSSM's time loop.

    :param stoch_dim: size of the flattened z
    :param action_dim: size of the action vector
    :param out_dim: output width
    """

    def __init__(self, stoch_dim: int, action_dim: int, out_dim: int) -> None:
        super().__init__()
        self.stoch = nn.Linear(stoch_dim, out_dim, bias=False)
        self.action = nn.Linear(action_dim, out_dim, bias=False)
        self.norm = nn.LayerNorm(out_dim, eps=1e-3)
        trunc_normal_init_(self.stoch)
        trunc_normal_init_(self.action)

    def combine(self, pre: th.Tensor) -> th.Tensor:
        """Normalisation and activation of ``W_z z + W_a a``.

        :param pre: (..., out_dim)
        :return: (..., out_dim)
        """
        return F.silu(self.norm(pre))

    def forward(self, stoch: th.Tensor, action: th.Tensor) -> th.Tensor:
        """:param stoch: (..., stoch_dim)
        :param action: (..., action_dim)
        :return: (..., out_dim)
        """
        return self.combine(self.stoch(stoch) + self.action(action))


class LayerNormGRUCell(nn.Module):
    """DreamerV3's GRU cell: one Linear over ``[x, h]`` followed by LayerNorm, then the GRU gates with the update
    gate biased by -1 (``h' = u * tanh(r * c) + (1 - u) * h``, ``u = sigmoid(. - 1)``).

    :param input_size: size of x
    :param hidden_size: size of h
    """

    def __init__(self, input_size: int, hidden_size: int) -> None:
        super().__init__()
        self.hidden_size = hidden_size
        self.linear = nn.Linear(input_size + hidden_size, 3 * hidden_size, bias=False)
        self.norm = nn.LayerNorm(3 * hidden_size, eps=1e-3)
        trunc_normal_init_(self.linear)

    def forward(self, x: th.Tensor, h: th.Tensor) -> th.Tensor:
        """:param x: (B, input_size)
        :param h: (B, hidden_size)
        :return: (B, hidden_size) new state
        """
        parts = self.norm(self.linear(th.cat([x, h], -1)))
        reset, cand, update = parts.chunk(3, -1)
        cand = th.tanh(th.sigmoid(reset) * cand)
        update = th.sigmoid(update - 1.0)
        return update * cand + (1.0 - update) * h


# ----------------------------------------------------------------------------------------------------------------------
# Base class
# ----------------------------------------------------------------------------------------------------------------------


class WorldModel(nn.Module):
    """Common part of both world models: encoder, heads, loss (eq. 4.10-4.13), imagination and input checks.

    Subclasses implement the sequence model: :meth:`observe`, :meth:`obs_step`, :meth:`img_step`,
    :meth:`initial_state` and :meth:`no_weight_decay_parameters`.

    :param observation_space: observation space of this level (Box image (C, H, W) uint8, Box vector, or Dict)
    :param action_dim: size of the action vector (one-hot size for Discrete actions and subgoals, Box dims)
    :param config: world-model hyperparameters
    :param bf16: run matmul/conv-heavy parts under bfloat16 autocast (opt-in, see the module docstring)
    :param compile: ``torch.compile`` the convolution stacks and the sequence model (opt-in)
    """

    kind: str = ""

    def __init__(
        self,
        observation_space: spaces.Space,
        action_dim: int,
        config: WorldModelConfig,
        bf16: bool = False,
        compile: bool = False,
    ) -> None:
        super().__init__()
        if not isinstance(config, WorldModelConfig):
            raise ValueError(f"config must be a WorldModelConfig, got {type(config).__name__}")
        if isinstance(action_dim, bool) or not isinstance(action_dim, int | np.integer) or action_dim < 1:
            raise ValueError(f"action_dim must be a positive int, got {action_dim!r}")
        self.config = config
        self.observation_space = observation_space
        self.action_dim = int(action_dim)
        self.spec = ObservationSpec(observation_space)
        self.groups = config.stoch_groups
        self.classes = config.stoch_classes
        self.stoch_dim = self.groups * self.classes
        self.deter_dim = config.deter_dim
        self.feat_dim = self.deter_dim + self.stoch_dim
        self.bf16 = bf16
        self.compile = compile
        self.encoder = ObservationEncoder(self.spec, config)
        self.embed_dim = self.encoder.out_dim
        self.decoder = ObservationDecoder(self.spec, self.feat_dim, config)
        self.reward_head = MLP(self.feat_dim, REWARD_BINS, config.head_units, config.head_layers, out_scale=0.0)
        self.cont_head = MLP(self.feat_dim, 1, config.head_units, config.head_layers)
        self.register_buffer("reward_bins", symlog_bins(REWARD_BINS), persistent=False)
        if compile:
            # convolution stacks: Inductor fuses the per-pixel LayerNorm and SiLU around the oneDNN convolutions
            for conv in [*self.encoder.convs.values(), *self.decoder.convs.values()]:
                conv.forward = th.compile(conv.forward, dynamic=False)

    # ---------------------------------------------------------------- small helpers

    @property
    def device(self) -> th.device:
        """Device of the parameters."""
        return self.reward_bins.device

    def _autocast(self) -> contextlib.AbstractContextManager:
        if not self.bf16:
            return contextlib.nullcontext()
        return th.autocast(device_type=self.device.type, dtype=th.bfloat16)

    def _dist(self, raw: th.Tensor) -> OneHotCategoricalST:
        """Grouped categorical over z from flat raw logits (..., G*K), with unimix."""
        return OneHotCategoricalST(
            raw.float().reshape(*raw.shape[:-1], self.groups, self.classes), self.config.unimix, event_ndims=1
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

    # ---------------------------------------------------------------- input checks

    def _check_is_first(self, is_first: Any, shape: tuple[int, ...], name: str = "is_first") -> th.Tensor:
        if not isinstance(is_first, th.Tensor):
            raise ValueError(f"{name} must be a torch.Tensor of shape {shape}, got {type(is_first).__name__}")
        if tuple(is_first.shape) != shape:
            raise ValueError(f"{name} has shape {tuple(is_first.shape)}, expected {shape}")
        if is_first.dtype == th.bool:
            return is_first
        if is_first.is_complex():
            raise ValueError(f"{name} must be bool or real, got dtype {is_first.dtype}")
        return is_first != 0

    def _check_actions(self, actions: Any, ndim: int, name: str) -> th.Tensor:
        layout = "(B, T, A)" if ndim == 3 else "(N, A)"
        if not isinstance(actions, th.Tensor):
            raise ValueError(f"{name} must be a torch.Tensor of shape {layout}, got {type(actions).__name__}")
        if actions.dim() != ndim or actions.shape[-1] != self.action_dim:
            raise ValueError(
                f"{name} must have shape {layout} with A={self.action_dim}, got shape {tuple(actions.shape)}"
            )
        if not actions.is_floating_point():
            raise ValueError(f"{name} must be a float tensor (one-hot for discrete actions), got dtype {actions.dtype}")
        return actions.float()

    def _check_state(self, state: Any, lead: tuple[int, ...], name: str = "state") -> LatentState:
        if not isinstance(state, LatentState):
            raise ValueError(f"{name} must be a LatentState, got {type(state).__name__}")
        if tuple(state.batch_shape) != lead:
            raise ValueError(f"{name} has batch shape {tuple(state.batch_shape)}, expected {lead}")
        if state.stoch.shape[-1] != self.stoch_dim or state.deter.shape[-1] != self.deter_dim:
            raise ValueError(
                f"{name} has stoch/deter sizes {state.stoch.shape[-1]}/{state.deter.shape[-1]}, expected "
                f"{self.stoch_dim}/{self.deter_dim}"
            )
        return state

    def _check_sequence(
        self, observations: Any, prev_actions: Any, is_first: Any
    ) -> tuple[dict[str, th.Tensor], th.Tensor, th.Tensor, tuple[int, int]]:
        actions = self._check_actions(prev_actions, 3, "prev_actions")
        lead = (int(actions.shape[0]), int(actions.shape[1]))
        first = self._check_is_first(is_first, lead)
        obs = self.spec.as_dict(observations)
        self.spec.check(obs, lead)
        return obs, actions, first, lead

    def _check_step(
        self, observation: Any, prev_action: Any, is_first: Any
    ) -> tuple[dict[str, th.Tensor], th.Tensor, th.Tensor, int]:
        action = self._check_actions(prev_action, 2, "prev_action")
        batch = int(action.shape[0])
        first = self._check_is_first(is_first, (batch,))
        obs = self.spec.as_dict(observation, "observation")
        self.spec.check(obs, (batch,), "observation")
        return obs, action, first, batch

    def _embed(self, obs: dict[str, th.Tensor], lead: tuple[int, ...]) -> th.Tensor:
        with self._autocast():
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

    @property
    def context_dim(self) -> int:
        """Floats per step in :meth:`pack_context`: z_t plus the sequence model's memory (complex parts as pairs)."""
        seq = self.initial_state(1).seq
        return self.stoch_dim + seq[0].numel() * (2 if seq.is_complex() else 1)

    def pack_context(self, state: LatentState) -> th.Tensor:
        """What :meth:`observe` needs to continue after ``state`` (z_t and the recurrent memory) as one float vector
        per step, to be stored in replay and handed back through :meth:`unpack_context` (replay context: a chunk then
        starts from the state its previous step had when last trained on, as in acting, not from zeros).

        :param state: states of batch shape ``lead``
        :return: (*lead, :attr:`context_dim`) float32, detached
        """
        lead = tuple(state.batch_shape)
        seq = th.view_as_real(state.seq) if state.seq.is_complex() else state.seq
        return th.cat([state.stoch.detach().float(), seq.detach().reshape(*lead, -1).float()], -1)

    def unpack_context(self, context: th.Tensor) -> LatentState:
        """The state a :meth:`pack_context` vector stands for, as the ``state`` argument of :meth:`observe`.

        Only z_t and the recurrent memory are restored (all that :meth:`observe` reads); for S5WM ``deter`` is left
        at zero and the logits uniform. All-zero vectors give :meth:`initial_state`.

        :param context: (B, :attr:`context_dim`)
        :return: state of batch shape (B,)
        """
        if not isinstance(context, th.Tensor) or context.dim() != 2 or context.shape[-1] != self.context_dim:
            shape = tuple(context.shape) if isinstance(context, th.Tensor) else type(context).__name__
            raise ValueError(f"context must have shape (B, {self.context_dim}), got {shape}")
        template = self.initial_state(int(context.shape[0]))
        context = context.to(template.stoch.device, th.float32)
        stoch, rest = context[:, : self.stoch_dim], context[:, self.stoch_dim :]
        if template.seq.is_complex():
            seq = th.view_as_complex(rest.reshape(*template.seq.shape, 2).contiguous())
        else:
            seq = rest.reshape(template.seq.shape)
        deter = seq if self._deter_is_seq else template.deter
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
        self,
        obs: dict[str, th.Tensor],
        actions: th.Tensor,
        is_first: th.Tensor,
        state: LatentState | None,
        deterministic: bool,
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
        self,
        state: LatentState,
        obs: dict[str, th.Tensor],
        action: th.Tensor,
        is_first: th.Tensor,
        deterministic: bool,
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
        with self._autocast():
            logits = self.reward_head(self.features(state))
        return TwoHotSymlog(logits.float(), self.reward_bins)

    def cont_dist(self, state: LatentState) -> ContinueBernoulli:
        """p(c_t | h_t, z_t), c_t = 1 - is_terminal_t.

        :param state: any state
        :return: Bernoulli with batch shape of ``state``
        """
        with self._autocast():
            logits = self.cont_head(self.features(state))
        return ContinueBernoulli(logits.float().squeeze(-1))

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
        """Mean observation predicted from a state (images as float pixels in [0, 255], vectors in raw units).

        :param state: any state
        :return: tensor (..., *obs_shape), or a dict of them for Dict spaces
        """
        with self._autocast():
            pred = self.decoder(self.features(state))
        out = self.decoder.mean(pred)
        return out if self.spec.is_dict else out[_SINGLE_KEY]

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
        ``c_t = 1 - is_terminal_t`` under the heads on (h_t, z_t).

        :param samples: object with ``observations`` (B, T, ...), ``actions`` (B, T, A) = previous actions,
            ``rewards`` (B, T), ``is_first`` (B, T), ``is_terminal`` (B, T) (e.g. ``SequenceSamples``)
        :param state: state before row 0, or None
        :return: scalar loss, metrics (floats) and the posterior states (batch (B, T), attached to the graph)
        """
        for field in ("observations", "actions", "rewards", "is_first", "is_terminal"):
            if not hasattr(samples, field):
                raise ValueError(f"samples must have the attribute {field!r} (SequenceSamples-like)")
        # images are converted to x/255 - 0.5 once, for the encoder and as the decoder's target
        obs = self.spec.preprocess(self.spec.as_dict(samples.observations))
        observations = obs if self.spec.is_dict else obs[_SINGLE_KEY]
        post, prior_logits = self.observe(observations, samples.actions, samples.is_first, state)
        lead = tuple(post.batch_shape)
        for field in ("rewards", "is_terminal"):
            value = getattr(samples, field)
            if not isinstance(value, th.Tensor) or tuple(value.shape) != lead:
                shape = tuple(value.shape) if isinstance(value, th.Tensor) else type(value).__name__
                raise ValueError(f"samples.{field} must be a tensor of shape {lead}, got {shape}")
        feat = self.features(post)
        with self._autocast():
            pred = self.decoder(feat)
            reward_logits = self.reward_head(feat)
            cont_logits = self.cont_head(feat)
        obs_nll = self.decoder.nll(pred, obs, lead)
        reward_nll = -TwoHotSymlog(reward_logits.float(), self.reward_bins).log_prob(samples.rewards.float())
        cont_target = 1.0 - samples.is_terminal.float()
        cont_nll = -ContinueBernoulli(cont_logits.float().squeeze(-1)).log_prob(cont_target)
        post_probs = post.logits.exp()  # (B, T, G, K), one exp for both KL terms and the entropy metric
        kl_dyn = _grouped_kl(post.logits.detach(), prior_logits, post_probs.detach())  # (B, T), summed over groups
        kl_rep = _grouped_kl(post.logits, prior_logits.detach(), post_probs)
        free = self.config.free_bits
        dyn = kl_dyn.clamp(min=free)
        rep = kl_rep.clamp(min=free)
        per_step = obs_nll + reward_nll + cont_nll + self.config.dyn_scale * dyn + self.config.rep_scale * rep
        loss = per_step.mean()
        with th.no_grad():
            post_ent = -(post_probs * post.logits).sum((-2, -1)).mean()
            metrics = {
                "loss": loss.item(),
                "obs_loss": obs_nll.mean().item(),
                "reward_loss": reward_nll.mean().item(),
                "cont_loss": cont_nll.mean().item(),
                "kl": kl_dyn.mean().item(),
                "dyn_loss": dyn.mean().item(),
                "rep_loss": rep.mean().item(),
                "prior_entropy": self.prior_entropy(post).mean().item(),
                "post_entropy": post_ent.item(),
            }
        return loss, metrics, post

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
        :return: metrics (with ``grad_norm`` and ``nonfinite``) and the detached posterior states (imagination starts)
        """
        loss, metrics, post = self.loss(samples, state)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        grad_norm = nn.utils.clip_grad_norm_(self.parameters(), self.config.grad_clip)
        stepped = step_if_finite(optimizer, loss, grad_norm)
        if stepped and scheduler is not None:
            scheduler.step()
        metrics["grad_norm"] = float(grad_norm)
        metrics["nonfinite"] = float(not stepped)
        return metrics, post.detach()

    # ---------------------------------------------------------------- imagination

    def imagine(
        self,
        start: LatentState,
        policy: Callable[[LatentState], th.Tensor],
        horizon: int,
        deterministic: bool = False,
        keep_seq: bool = False,
    ) -> tuple[LatentState, th.Tensor, th.Tensor]:
        """Roll the world model forward from ``start`` with actions from ``policy`` (thesis 4.4.3, Figure 4.7).

        Step form; the recurrent state is not detached between steps and ``start`` is not modified, so gradients can
        flow back through the whole rollout (dynamics backpropagation for Box actions). The world model runs without
        dropout here (dropout regularises the world-model loss only; the rollout is then a function of the sampled
        latents alone), and its training mode is restored afterwards.

        :param start: start states of batch shape (N,) (e.g. ``post.flatten_batch()``)
        :param policy: state (N,) -> action (N, A); ``actions[i]`` is the action taken in ``states[i]``
        :param horizon: number of imagined steps H
        :param deterministic: take prior modes instead of samples
        :param keep_seq: also return the recurrent memory of every imagined state. Off by default: nothing downstream
            (heads, actor-critic, subgoal autoencoder) reads it, and for S5WM it is the largest field ((L, P) complex
            per state); the returned ``states.seq`` is then an empty (H+1, N, 0) tensor
        :return: states (H+1, N) including ``start``, actions (H+1, N, A) and prior entropies (H+1, N)
        """
        if isinstance(horizon, bool) or not isinstance(horizon, int) or horizon < 1:
            raise ValueError(f"horizon must be a positive int, got {horizon!r}")
        if not isinstance(start, LatentState) or len(start.batch_shape) != 1:
            shape = tuple(start.batch_shape) if isinstance(start, LatentState) else type(start).__name__
            raise ValueError(f"start must be a LatentState of batch shape (N,), got {shape}; use flatten_batch()")
        n = int(start.batch_shape[0])
        self._check_state(start, (n,), "start")

        def act(state: LatentState) -> th.Tensor:
            action = policy(state)
            if not isinstance(action, th.Tensor) or tuple(action.shape) != (n, self.action_dim):
                shape = tuple(action.shape) if isinstance(action, th.Tensor) else type(action).__name__
                raise ValueError(f"policy must return actions of shape {(n, self.action_dim)}, got {shape}")
            return action

        empty_seq = start.seq.new_zeros(n, 0)

        def stored(state: LatentState) -> LatentState:
            return state if keep_seq else state._replace(seq=empty_seq)

        was_training = self.training
        self.train(False)
        try:
            with self.reuse_step_weights():
                states, actions, entropies = [stored(start)], [], [self.prior_entropy(start)]
                state = start
                for _ in range(horizon):
                    action = act(state)
                    actions.append(action)
                    state, _ = self.img_step(state, action, deterministic)
                    states.append(stored(state))
                    entropies.append(self.prior_entropy(state))
                actions.append(act(state))
        finally:
            self.train(was_training)
        return stack_states(states, 0), th.stack(actions, 0), th.stack(entropies, 0)


# ----------------------------------------------------------------------------------------------------------------------
# S5WM
# ----------------------------------------------------------------------------------------------------------------------


class S5WorldModel(WorldModel):
    """S5WM (thesis 4.4): posterior from the observation alone, a stack of resettable S5 blocks as sequence model,
    ``h_t`` read out of the internal S5 states (thesis 5.3.5) and the prior from the stack output ``m_t``.

    :param observation_space: observation space of this level
    :param action_dim: size of the action vector
    :param config: world-model hyperparameters (``kind == "s5"``)
    :param bf16: bfloat16 autocast opt-in
    :param compile: ``torch.compile`` the S5 stack's parallel scan (``sb3_hieros.nn.s5.compile_s5``; the step form
        used for acting and imagination stays eager)
    """

    kind = "s5"

    def __init__(
        self,
        observation_space: spaces.Space,
        action_dim: int,
        config: WorldModelConfig,
        bf16: bool = False,
        compile: bool = False,
    ) -> None:
        super().__init__(observation_space, action_dim, config, bf16, compile)
        c = config
        self.inp = InputLayer(self.stoch_dim, self.action_dim, c.s5_model_dim)
        self.sequence_model = S5Stack(c.s5_layers, c.s5_model_dim, c.s5_state_dim, c.s5_hippo_blocks, c.dropout)
        readout_in = 2 * c.s5_layers * c.s5_state_dim if c.deter_from == "state" else c.s5_model_dim
        self.deter_out = nn.Linear(readout_in, self.deter_dim)
        trunc_normal_init_(self.deter_out)
        self.prior_net = MLP(c.s5_model_dim, self.stoch_dim, c.hidden, layers=1)
        self.post_net = MLP(self.embed_dim, self.stoch_dim, c.hidden, layers=1)
        if compile:
            # the S5 module's own opt-in: real-split parallel scan under torch.compile; the step form stays eager
            compile_s5(self.sequence_model)
        self._seq_forward: Callable[..., tuple[th.Tensor, th.Tensor]] = self.sequence_model.forward
        self._seq_step: Callable[..., tuple[th.Tensor, th.Tensor]] = self.sequence_model.step

    def reuse_step_weights(self) -> contextlib.AbstractContextManager:
        return self.sequence_model.reuse_step_weights()

    def no_weight_decay_parameters(self) -> list[nn.Parameter]:
        """SSM parameters of the S5 stack (Lambda, B, Delta) plus all 1-d parameters.

        :return: list of parameters
        """
        params = {id(p): p for p in self.sequence_model.ssm_parameters()}
        params.update({id(p): p for p in super().no_weight_decay_parameters()})
        return list(params.values())

    def _initial_state(self, batch_size: int) -> LatentState:
        uniform = self._uniform_logits(batch_size)
        return LatentState(
            stoch=th.zeros(batch_size, self.stoch_dim, device=self.device),
            deter=th.zeros(batch_size, self.deter_dim, device=self.device),
            seq=self.sequence_model.initial_state(batch_size, self.device),
            logits=uniform,
            prior_logits=uniform,
        )

    def _deterministic_state(self, seq: th.Tensor, out: th.Tensor) -> th.Tensor:
        """h_t = symlog(Linear([Re x_t, Im x_t] of all layers)) (thesis 5.3.5) or symlog(Linear(m_t)).

        :param seq: (..., L, P) complex S5 states
        :param out: (..., H) stack output m_t
        :return: (..., D) float32
        """
        source = th.view_as_real(seq).flatten(-3) if self.config.deter_from == "state" else out
        return symlog(self.deter_out(source).float())

    def _observe(
        self,
        obs: dict[str, th.Tensor],
        actions: th.Tensor,
        is_first: th.Tensor,
        state: LatentState | None,
        deterministic: bool,
    ) -> tuple[LatentState, th.Tensor]:
        batch, length = actions.shape[:2]
        embed = self._embed(obs, (batch, length))  # (B, T, E)
        with self._autocast():
            post_raw = self.post_net(embed)
        stoch, post_logits = self._draw(post_raw, deterministic)  # (B, T, G*K), (B, T, G, K)
        first_prev = th.zeros_like(stoch[:, :1]) if state is None else state.stoch.unsqueeze(1)
        prev_stoch = th.cat([first_prev, stoch[:, :-1]], 1)  # z_{t-1}
        keep = (~is_first).unsqueeze(-1).to(stoch.dtype)  # (B, T, 1)
        with self._autocast():
            u = self.inp(prev_stoch * keep, actions * keep)  # (B, T, H)
            out, seq = self._seq_forward(u.float(), is_first, None if state is None else state.seq)
            deter = self._deterministic_state(seq, out)  # (B, T, D)
            prior_raw = self.prior_net(out)
        prior_logits = self._normalise(prior_raw)
        return LatentState(stoch, deter, seq, post_logits, prior_logits), prior_logits

    def _prior_step(
        self, state: LatentState, action: th.Tensor, reset: th.Tensor | None
    ) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        """(m_t, h_t) = f(h_{t-1}, z_{t-1}, a_{t-1}) in step form; returns deter, S5 states and raw prior logits."""
        stoch = state.stoch
        if reset is not None:
            keep = (~reset).unsqueeze(-1).to(stoch.dtype)
            stoch, action = stoch * keep, action * keep
        with self._autocast():
            u = self.inp(stoch, action)
            out, seq = self._seq_step(u.float(), state.seq, reset)
            deter = self._deterministic_state(seq, out)
            prior_raw = self.prior_net(out)
        return deter, seq, prior_raw

    def _obs_step(
        self,
        state: LatentState,
        obs: dict[str, th.Tensor],
        action: th.Tensor,
        is_first: th.Tensor,
        deterministic: bool,
    ) -> LatentState:
        batch = int(action.shape[0])
        deter, seq, prior_raw = self._prior_step(state, action, is_first)
        embed = self._embed(obs, (batch,))
        with self._autocast():
            post_raw = self.post_net(embed)
        stoch, post_logits = self._draw(post_raw, deterministic)
        return LatentState(stoch, deter, seq, post_logits, self._normalise(prior_raw))

    def _img_step(self, state: LatentState, action: th.Tensor, deterministic: bool) -> tuple[LatentState, th.Tensor]:
        deter, seq, prior_raw = self._prior_step(state, action, None)
        stoch, prior_logits = self._draw(prior_raw, deterministic)
        return LatentState(stoch, deter, seq, prior_logits, prior_logits), prior_logits


# ----------------------------------------------------------------------------------------------------------------------
# RSSM
# ----------------------------------------------------------------------------------------------------------------------


class RSSMWorldModel(WorldModel):
    """DreamerV3's recurrent state-space model behind the same interface (ablation 5.3.2).

    ``h_t = GRU(h_{t-1}, Inp(z_{t-1}, a_{t-1}))``, posterior ``q(z_t | h_t, e_t)``, prior ``p(z^_t | h_t)``. The
    GRU state is the deterministic state (``seq`` and ``deter`` are the same tensor). The posterior depends on
    ``h_t``, so :meth:`observe` runs a time loop; everything that does not depend on the loop is hoisted out of it.

    :param observation_space: observation space of this level
    :param action_dim: size of the action vector
    :param config: world-model hyperparameters (``kind == "rssm"``; the S5 fields are unused)
    :param bf16: bfloat16 autocast opt-in (outside the time loop only)
    :param compile: ``torch.compile`` the loop cell
    """

    kind = "rssm"
    _deter_is_seq = True

    def __init__(
        self,
        observation_space: spaces.Space,
        action_dim: int,
        config: WorldModelConfig,
        bf16: bool = False,
        compile: bool = False,
    ) -> None:
        super().__init__(observation_space, action_dim, config, bf16, compile)
        c = config
        self.inp = InputLayer(self.stoch_dim, self.action_dim, c.hidden)
        self.gru = LayerNormGRUCell(c.hidden, self.deter_dim)
        self.prior_net = MLP(self.deter_dim, self.stoch_dim, c.hidden, layers=1)
        # posterior MLP on [h_t, e_t], split into halves so that the embedding half leaves the loop
        self.post_deter = nn.Linear(self.deter_dim, c.hidden, bias=False)
        self.post_embed = nn.Linear(self.embed_dim, c.hidden, bias=False)
        self.post_norm = nn.LayerNorm(c.hidden, eps=1e-3)
        self.post_out = nn.Linear(c.hidden, self.stoch_dim)
        for layer in (self.post_deter, self.post_embed, self.post_out):
            trunc_normal_init_(layer)
        self._cell: Callable[..., tuple[th.Tensor, th.Tensor]] = self._cell_eager
        if compile:
            self._cell = th.compile(self._cell_eager)

    def _initial_state(self, batch_size: int) -> LatentState:
        deter = th.zeros(batch_size, self.deter_dim, device=self.device)
        uniform = self._uniform_logits(batch_size)
        return LatentState(th.zeros(batch_size, self.stoch_dim, device=self.device), deter, deter, uniform, uniform)

    def _cell_eager(
        self, stoch: th.Tensor, action_pre: th.Tensor, deter: th.Tensor, embed_pre: th.Tensor
    ) -> tuple[th.Tensor, th.Tensor]:
        """One loop step: GRU update and raw posterior logits (the part that cannot leave the loop).

        :param stoch: (B, G*K) z_{t-1} (already zeroed where reset)
        :param action_pre: (B, hidden) ``W_a a_{t-1}``
        :param deter: (B, D) h_{t-1} (already zeroed where reset)
        :param embed_pre: (B, hidden) embedding half of the posterior layer
        :return: h_t (B, D) and raw posterior logits (B, G*K)
        """
        x = self.inp.combine(self.inp.stoch(stoch) + action_pre)
        deter = self.gru(x, deter)
        post_raw = self.post_out(F.silu(self.post_norm(self.post_deter(deter) + embed_pre)))
        return deter, post_raw

    def _observe(
        self,
        obs: dict[str, th.Tensor],
        actions: th.Tensor,
        is_first: th.Tensor,
        state: LatentState | None,
        deterministic: bool,
    ) -> tuple[LatentState, th.Tensor]:
        batch, length = actions.shape[:2]
        state = self.initial_state(batch) if state is None else state
        embed = self._embed(obs, (batch, length))
        keep = (~is_first).unsqueeze(-1).to(actions.dtype)  # (B, T, 1)
        with self._autocast():
            embed_pre = self.post_embed(embed).float()  # (B, T, hidden), hoisted
        action_pre = self.inp.action(actions * keep)  # (B, T, hidden), hoisted
        stoch, deter = state.stoch, state.deter
        stochs, deters, logits = [], [], []
        for e_t, a_t, k_t in zip(embed_pre.unbind(1), action_pre.unbind(1), keep.unbind(1), strict=True):
            deter, post_raw = self._cell(stoch * k_t, a_t, deter * k_t, e_t)
            stoch, post_logits = self._draw(post_raw, deterministic)
            stochs.append(stoch)
            deters.append(deter)
            logits.append(post_logits)
        deter_seq = th.stack(deters, 1)  # (B, T, D)
        with self._autocast():
            prior_raw = self.prior_net(deter_seq)  # hoisted
        prior_logits = self._normalise(prior_raw)
        post = LatentState(th.stack(stochs, 1), deter_seq, deter_seq, th.stack(logits, 1), prior_logits)
        return post, prior_logits

    def _obs_step(
        self,
        state: LatentState,
        obs: dict[str, th.Tensor],
        action: th.Tensor,
        is_first: th.Tensor,
        deterministic: bool,
    ) -> LatentState:
        batch = int(action.shape[0])
        keep = (~is_first).unsqueeze(-1).to(action.dtype)
        embed = self._embed(obs, (batch,))
        with self._autocast():
            embed_pre = self.post_embed(embed).float()
        deter, post_raw = self._cell(state.stoch * keep, self.inp.action(action * keep), state.deter * keep, embed_pre)
        stoch, post_logits = self._draw(post_raw, deterministic)
        with self._autocast():
            prior_raw = self.prior_net(deter)
        return LatentState(stoch, deter, deter, post_logits, self._normalise(prior_raw))

    def _img_step(self, state: LatentState, action: th.Tensor, deterministic: bool) -> tuple[LatentState, th.Tensor]:
        with self._autocast():
            deter = self.gru(self.inp(state.stoch, action), state.deter).float()
            prior_raw = self.prior_net(deter)
        stoch, prior_logits = self._draw(prior_raw, deterministic)
        return LatentState(stoch, deter, deter, prior_logits, prior_logits), prior_logits


# ----------------------------------------------------------------------------------------------------------------------
# Factory and optimiser
# ----------------------------------------------------------------------------------------------------------------------

_KINDS: dict[str, type[WorldModel]] = {"s5": S5WorldModel, "rssm": RSSMWorldModel}


def make_world_model(
    observation_space: spaces.Space,
    action_dim: int,
    config: WorldModelConfig,
    bf16: bool = False,
    compile: bool = False,
) -> WorldModel:
    """The world model selected by ``config.kind`` (``"s5"``: S5WM, ``"rssm"``: DreamerV3's RSSM).

    :param observation_space: observation space of the level
    :param action_dim: size of the action vector
    :param config: world-model hyperparameters
    :param bf16: bfloat16 autocast opt-in
    :param compile: ``torch.compile`` opt-in for the sequence model
    :return: the world model
    """
    if not isinstance(config, WorldModelConfig):
        raise ValueError(f"config must be a WorldModelConfig, got {type(config).__name__}")
    if config.kind not in _KINDS:
        raise ValueError(f"config.kind must be one of {sorted(_KINDS)}, got {config.kind!r}")
    return _KINDS[config.kind](observation_space, action_dim, config, bf16=bf16, compile=compile)


def world_model_optimizer(model: WorldModel, config: WorldModelConfig | None = None) -> th.optim.AdamW:
    """AdamW for a world model with two groups: weight decay ``config.weight_decay`` for weight matrices, none for
    :meth:`WorldModel.no_weight_decay_parameters` (S5 SSM parameters, norms, biases).

    :param model: the world model
    :param config: hyperparameters (``lr``, ``eps``, ``weight_decay``); default ``model.config``
    :return: the optimiser
    """
    cfg = model.config if config is None else config
    no_decay = model.no_weight_decay_parameters()
    no_decay_ids = {id(p) for p in no_decay}
    decay = [p for p in model.parameters() if id(p) not in no_decay_ids]
    groups = [{"params": decay, "weight_decay": cfg.weight_decay}, {"params": no_decay, "weight_decay": 0.0}]
    return th.optim.AdamW(groups, lr=cfg.lr, eps=cfg.eps)


def world_model_lr_scheduler(optimizer: th.optim.Optimizer, warmup: int) -> th.optim.lr_scheduler.LambdaLR:
    """Linear learning-rate warm-up over ``warmup`` updates (``config.warmup``), constant afterwards.

    :param optimizer: the optimiser
    :param warmup: number of warm-up updates (0: none)
    :return: scheduler to step once per update
    """
    if warmup < 0:
        raise ValueError(f"warmup must be >= 0, got {warmup}")
    return th.optim.lr_scheduler.LambdaLR(optimizer, lambda step: min(1.0, (step + 1) / warmup) if warmup else 1.0)
