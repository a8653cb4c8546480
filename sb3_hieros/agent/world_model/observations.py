"""Observations of a world model: which keys are images, vectors or discrete, the encoder and the decoder (thesis
4.4).

A Box of rank 3 with uint8 pixels in [0, 255] is a channel-first (C, H, W) image, encoded by a CNN (with SB3's
``normalize_images=False`` every rank-3 Box is, taken as it is); every other Box is a vector. ``Discrete`` and
``MultiDiscrete`` entries are one-hot encoded and ``MultiBinary`` entries taken as bits, as SB3's ``preprocess_obs``
does, and decoded by a categorical per discrete dimension and a Bernoulli per bit. All non-image keys together go
through one MLP. Non-dict spaces use the single key ``"obs"``.

A user's SB3 ``BaseFeaturesExtractor`` (``policy_kwargs`` ``features_extractor_class``) can replace the encoder
(:class:`FeaturesExtractorEncoder`); the decoder still reconstructs the observations.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

import numpy as np
import torch as th
import torch.nn.functional as F
from gymnasium import spaces
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from torch import nn

from sb3_hieros.config import WorldModelConfig
from sb3_hieros.nn.distributions import symexp, symlog, symlog_mse
from sb3_hieros.nn.networks import MLP, ConvDecoder, ConvEncoder, preprocess_image
from sb3_hieros.spaces import is_image_observation

__all__ = [
    "SINGLE_KEY",
    "FeaturesExtractorEncoder",
    "ObservationDecoder",
    "ObservationEncoder",
    "ObservationOptions",
    "ObservationSpec",
    "make_observation_encoder",
]

#: The key of a non-dict observation inside the world model.
SINGLE_KEY = "obs"
#: The decoder's prediction of all vector keys (observation keys are never empty).
_VECTORS = ""
#: The decoder's logits of all discrete keys (observation keys never contain '.').
_LOGITS = "."


@dataclasses.dataclass(frozen=True)
class ObservationOptions:
    """How level 0 encodes the environment's observations: SB3's policy keywords that concern them.

    :param normalize_images: False: every rank-3 Box is an image taken as it is (no ``x / 255`` scaling), as SB3's
        ``NatureCNN`` takes float image-like inputs
    :param features_extractor_class: an SB3 ``BaseFeaturesExtractor`` subclass that replaces the world model's
        encoder (:class:`FeaturesExtractorEncoder`), or None for the CNN / MLP encoder
    :param features_extractor_kwargs: its keywords besides the observation space
    """

    normalize_images: bool = True
    features_extractor_class: type[BaseFeaturesExtractor] | None = None
    features_extractor_kwargs: Mapping[str, Any] | None = None


class ObservationSpec:
    """Which observation keys are images (CNN), vectors (symlog MLP) and discrete (one-hot / bits).

    A Box of rank 3 with uint8 pixels in [0, 255] is a channel-first (C, H, W) image (with ``normalize_images=False``
    any rank-3 Box is, taken without scaling); any other Box is a vector (flattened). ``Discrete`` and
    ``MultiDiscrete`` keys are categorical (one categorical per entry), ``MultiBinary`` keys binary. A Dict space may
    mix them all. Non-dict spaces use the single key ``"obs"`` internally. The space is trusted (see
    :func:`sb3_hieros.spaces.check_observation_space`).

    :param observation_space: the level's observation space
    :param normalize_images: SB3's policy keyword (see :class:`ObservationOptions`)
    """

    def __init__(self, observation_space: spaces.Space, normalize_images: bool = True) -> None:
        self.is_dict = isinstance(observation_space, spaces.Dict)
        self.space = observation_space
        #: uint8 images are scaled to ``x / 255 - 0.5``; False: images are taken as they are
        self.scale_images = bool(normalize_images)
        items = list(observation_space.spaces.items()) if self.is_dict else [(SINGLE_KEY, observation_space)]
        self.spaces: dict[str, spaces.Space] = dict(items)
        self.shapes: dict[str, tuple[int, ...]] = {}
        self.image_keys: list[str] = []
        self.vector_keys: list[str] = []
        self.categorical_keys: list[str] = []
        self.binary_keys: list[str] = []
        for key, space in items:
            self.shapes[key] = tuple(int(s) for s in space.shape)
            if isinstance(space, spaces.Discrete | spaces.MultiDiscrete):
                self.categorical_keys.append(key)
            elif isinstance(space, spaces.MultiBinary):
                self.binary_keys.append(key)
            elif is_image_observation(space, normalize_images):
                self.image_keys.append(key)
            else:
                self.vector_keys.append(key)
        self.vector_sizes = [int(np.prod(self.shapes[k])) for k in self.vector_keys]
        self.vector_dim = sum(self.vector_sizes)
        #: per categorical key, the classes of each of its entries (flattened)
        self.classes = {k: _classes(self.spaces[k]) for k in self.categorical_keys}
        #: one-hot width of each discrete key (classes summed; bits for MultiBinary), categorical keys first
        self.discrete_widths = {k: sum(self.classes[k]) for k in self.categorical_keys}
        self.discrete_widths.update({k: int(np.prod(self.shapes[k])) for k in self.binary_keys})
        self.discrete_dim = sum(self.discrete_widths.values())

    @property
    def entry_keys(self) -> list[str]:
        """The keys that are not images (vectors and discrete), in the order of the space."""
        return [key for key in self.shapes if key not in self.image_keys]

    @property
    def discrete_keys(self) -> list[str]:
        """Categorical then binary keys (the order of their one-hot parts and logits)."""
        return [*self.categorical_keys, *self.binary_keys]

    def as_dict(self, observations: Any) -> dict[str, th.Tensor]:
        """Observations as a key -> tensor dict (a single tensor under the key ``"obs"``).

        :param observations: a tensor, or a mapping holding the keys of a Dict space
        :return: dict of tensors
        """
        if self.is_dict:
            return {k: observations[k] for k in self.shapes}
        return {SINGLE_KEY: observations}

    def check(self, observations: Any, lead: tuple[int, ...], name: str = "observations") -> dict[str, th.Tensor]:
        """Raise ``ValueError`` unless ``observations`` are tensors of shape ``lead + space shape``.

        :param observations: a tensor, or a mapping for Dict spaces
        :param lead: expected batch shape, e.g. (B, T)
        :param name: argument name used in error messages
        :return: :meth:`as_dict` of them
        """
        if self.is_dict:
            if not isinstance(observations, Mapping):
                raise ValueError(
                    f"{name} must be a dict of tensors for a Dict space, got {type(observations).__name__}"
                )
            missing = [k for k in self.shapes if k not in observations]
            if missing:
                raise ValueError(f"{name} lacks the keys {missing}; expected {sorted(self.shapes)}")
        obs = self.as_dict(observations)
        for key, value in obs.items():
            label = f"{name}[{key!r}]" if self.is_dict else name
            if not isinstance(value, th.Tensor):
                raise ValueError(f"{label} must be a torch.Tensor, got {type(value).__name__}")
            expected = (*lead, *self.shapes[key])
            if isinstance(self.spaces[key], spaces.Discrete) and tuple(value.shape) == (*lead, 1):
                obs[key] = value = value.reshape(lead)  # SB3's buffers keep a Discrete observation as (..., 1)
            if tuple(value.shape) != expected:
                raise ValueError(f"{label} has shape {tuple(value.shape)}, expected {expected}")
        return obs

    def preprocess(self, obs: dict[str, th.Tensor]) -> dict[str, th.Tensor]:
        """uint8 images mapped to float ``x / 255 - 0.5`` (the encoder's input and decoder's output space); float
        images (taken as already mapped), vectors and discrete entries pass unchanged. Without image scaling
        (``normalize_images=False``) images become float as they are.

        :param obs: dict from :meth:`as_dict`
        :return: new dict
        """
        out = dict(obs)
        for key in self.image_keys:
            images = obs[key]
            if not self.scale_images:
                out[key] = images.float()
            elif images.dtype == th.uint8:
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


def _classes(space: spaces.Space) -> list[int]:
    """Classes of each entry of a ``Discrete`` (one entry) or ``MultiDiscrete`` space, flattened."""
    if isinstance(space, spaces.Discrete):
        return [int(space.n)]
    return [int(n) for n in np.asarray(space.nvec).reshape(-1)]


def _starts(space: spaces.Space) -> list[int]:
    """The smallest value of each entry of a ``Discrete`` or ``MultiDiscrete`` space, flattened."""
    start = np.broadcast_to(np.asarray(getattr(space, "start", 0)), space.shape)
    return [int(s) for s in start.reshape(-1)]


class DiscreteLayout(nn.Module):
    """The discrete keys of an observation space as one vector: one-hot encodings (as SB3's ``preprocess_obs``) for
    the encoder, and a categorical per discrete entry and a Bernoulli per bit for the decoder (thesis 4.4: the
    decoder's likelihood of o_t).

    Categorical entries with fewer classes than the widest are padded to it, with padded logits masked out. The
    buffers are not saved (they follow from the space).

    :param spec: the observation specification (with at least one discrete key)
    """

    def __init__(self, spec: ObservationSpec) -> None:
        super().__init__()
        self.spec = spec
        classes = [n for key in spec.categorical_keys for n in spec.classes[key]]
        starts = [s for key in spec.categorical_keys for s in _starts(spec.spaces[key])]
        self.n_categorical = len(classes)
        self.categorical_dim = sum(classes)
        self.max_classes = max(classes, default=1)
        self.n_bits = spec.discrete_dim - self.categorical_dim
        offsets = np.concatenate([[0], np.cumsum(classes)[:-1]]).astype(np.int64) if classes else np.zeros(0, int)
        # one-hot position of value v of entry c: v - start_c + offset_c
        self.register_buffer("shift", th.as_tensor(offsets - np.asarray(starts, np.int64)), persistent=False)
        self.register_buffer("start", th.as_tensor(np.asarray(starts, np.int64)), persistent=False)
        # padded (C, K) logits: position (c, k) takes logit offset_c + k, or is masked out where k >= classes_c
        k = np.arange(self.max_classes)
        valid = k[None, :] < np.asarray(classes, np.int64)[:, None]  # (C, K)
        gather = np.where(valid, offsets[:, None] + k[None, :], 0)
        self.padded = not bool(valid.all())
        self.register_buffer("gather", th.as_tensor(gather.reshape(-1)), persistent=False)
        self.register_buffer("invalid", th.as_tensor(~valid), persistent=False)

    def _indices(self, obs: dict[str, th.Tensor], lead: tuple[int, ...]) -> th.Tensor:
        """(*lead, C) the values of every categorical entry, as stored (starts not removed)."""
        parts = [obs[k].reshape(*lead, -1).long() for k in self.spec.categorical_keys]
        return parts[0] if len(parts) == 1 else th.cat(parts, -1)

    def _bits(self, obs: dict[str, th.Tensor], lead: tuple[int, ...]) -> list[th.Tensor]:
        return [obs[k].reshape(*lead, -1).float() for k in self.spec.binary_keys]

    def one_hot(self, obs: dict[str, th.Tensor], lead: tuple[int, ...]) -> th.Tensor:
        """One-hot encodings of the categorical entries, then the bits of the binary keys (SB3's ``preprocess_obs``).

        :param obs: dict from :meth:`ObservationSpec.as_dict`
        :param lead: batch shape
        :return: (*lead, discrete_dim) float
        """
        parts = self._bits(obs, lead)
        if self.n_categorical:
            position = self._indices(obs, lead) + self.shift  # (*lead, C)
            one_hot = th.zeros(*lead, self.categorical_dim, device=position.device)
            parts.insert(0, one_hot.scatter_(-1, position, 1.0))
        return parts[0] if len(parts) == 1 else th.cat(parts, -1)

    def _categorical_logits(self, logits: th.Tensor) -> th.Tensor:
        """(..., C, K) normalised log-probabilities of every categorical entry (padding at -inf)."""
        flat = logits[..., : self.categorical_dim]
        if self.padded:
            grouped = flat[..., self.gather].unflatten(-1, (self.n_categorical, self.max_classes))
            grouped = grouped.masked_fill(self.invalid, -math.inf)
        else:
            grouped = flat.unflatten(-1, (self.n_categorical, self.max_classes))
        return grouped.log_softmax(-1)

    def nll(self, logits: th.Tensor, obs: dict[str, th.Tensor], lead: tuple[int, ...]) -> th.Tensor:
        """Negative log-likelihood of the discrete keys: categorical cross-entropy per entry, binary cross-entropy per
        bit, summed.

        :param logits: (*lead, discrete_dim) from the decoder
        :param obs: the true observations
        :param lead: batch shape
        :return: (*lead)
        """
        total = logits.new_zeros(lead)
        if self.n_categorical:
            target = (self._indices(obs, lead) - self.start).unsqueeze(-1)  # (*lead, C, 1)
            total = total - self._categorical_logits(logits).gather(-1, target).squeeze(-1).sum(-1)
        if self.n_bits:
            bits = th.cat(self._bits(obs, lead), -1) if len(self.spec.binary_keys) > 1 else self._bits(obs, lead)[0]
            bce = F.binary_cross_entropy_with_logits(logits[..., self.categorical_dim :], bits, reduction="none")
            total = total + bce.sum(-1)
        return total

    def mode(self, logits: th.Tensor) -> dict[str, th.Tensor]:
        """The most likely value of every discrete key, in the space: indices (int64) for ``Discrete`` /
        ``MultiDiscrete``, bits in the space's dtype for ``MultiBinary``.

        :param logits: (..., discrete_dim)
        :return: key -> (..., *shape)
        """
        lead = logits.shape[:-1]
        out = {}
        if self.n_categorical:
            values = self._categorical_logits(logits).argmax(-1) + self.start  # (..., C)
            sizes = [len(self.spec.classes[k]) for k in self.spec.categorical_keys]
            for key, part in zip(self.spec.categorical_keys, th.split(values, sizes, -1), strict=True):
                out[key] = part.reshape(*lead, *self.spec.shapes[key])
        if self.n_bits:
            sizes = [self.spec.discrete_widths[k] for k in self.spec.binary_keys]
            bits = logits[..., self.categorical_dim :] > 0
            for key, part in zip(self.spec.binary_keys, th.split(bits, sizes, -1), strict=True):
                dtype = th.from_numpy(np.zeros(0, self.spec.spaces[key].dtype)).dtype
                out[key] = part.reshape(*lead, *self.spec.shapes[key]).to(dtype)
        return out


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
    """Embedding of o_t (thesis 4.4): a :class:`ConvEncoder` per image key and one MLP over all other keys (symlog of
    the vector keys, one-hot encodings and bits of the discrete keys), concatenated. Accepts any leading batch dims.

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
        flat_dim = spec.vector_dim + spec.discrete_dim
        self.mlp = (
            MLP(flat_dim, None, config.mlp_units, config.mlp_layers, symlog_inputs=not spec.discrete_dim)
            if flat_dim
            else None
        )
        self.discrete = DiscreteLayout(spec) if spec.discrete_dim else None
        self.out_dim = sum(c.out_dim for c in self.convs.values()) + (self.mlp.out_dim if self.mlp is not None else 0)

    def forward(self, obs: dict[str, th.Tensor], lead: tuple[int, ...]) -> th.Tensor:
        """:param obs: dict from :meth:`ObservationSpec.as_dict`, entries (*lead, *shape)
        :param lead: batch shape
        :return: (*lead, out_dim) embedding
        """
        parts = []
        for key in self.spec.image_keys:
            images = obs[key].reshape(-1, *self.spec.shapes[key])  # (N, C, H, W)
            if not self.spec.scale_images:
                images = images.float()  # taken as they are (ConvEncoder would scale uint8 pixels)
            if self.channels_last:
                images = images.contiguous(memory_format=th.channels_last)
            parts.append(self.convs[key](images).reshape(*lead, -1))
        if self.mlp is not None:
            parts.append(self.mlp(self._flat_inputs(obs, lead)))
        return parts[0] if len(parts) == 1 else th.cat(parts, -1)

    def _flat_inputs(self, obs: dict[str, th.Tensor], lead: tuple[int, ...]) -> th.Tensor:
        """The MLP's input: the vector keys (the MLP applies symlog), or with discrete keys symlog of the vector keys
        and the one-hot encodings and bits, (*lead, vector_dim + discrete_dim)."""
        if self.discrete is None:
            return self.spec.vectors(obs, lead)
        parts = [symlog(self.spec.vectors(obs, lead))] if self.spec.vector_keys else []
        return th.cat([*parts, self.discrete.one_hot(obs, lead)], -1)


class FeaturesExtractorEncoder(nn.Module):
    """Embedding of o_t by a user's SB3 features extractor (``policy_kwargs`` ``features_extractor_class``).

    The extractor is built as SB3 builds it, ``features_extractor_class(observation_space, **kwargs)``, and receives
    what SB3's ``preprocess_obs`` gives an SB3 policy's extractor: a tensor (a dict of tensors for Dict spaces) with
    one batch dimension (the world model's (B, T) flattened), images as floats scaled to [0, 1] (as they are with
    ``normalize_images=False``), Box vectors as floats, ``Discrete`` / ``MultiDiscrete`` entries one-hot encoded and
    ``MultiBinary`` entries as float bits. Its ``features_dim`` outputs are the embedding the posterior reads.

    :param spec: the observation specification
    :param extractor_class: a ``BaseFeaturesExtractor`` subclass
    :param extractor_kwargs: its keywords besides the observation space
    """

    def __init__(
        self,
        spec: ObservationSpec,
        extractor_class: type[BaseFeaturesExtractor],
        extractor_kwargs: Mapping[str, Any] | None = None,
    ) -> None:
        super().__init__()
        self.spec = spec
        self.extractor = extractor_class(spec.space, **dict(extractor_kwargs or {}))
        if not isinstance(self.extractor, BaseFeaturesExtractor):
            raise ValueError(
                f"features_extractor_class must build a stable_baselines3 BaseFeaturesExtractor, got "
                f"{type(self.extractor).__name__}"
            )
        self.out_dim = int(self.extractor.features_dim)
        self.convs = nn.ModuleDict()  # no convolutions of the world model's own
        self.discrete = DiscreteLayout(spec) if spec.discrete_dim else None

    def forward(self, obs: dict[str, th.Tensor], lead: tuple[int, ...]) -> th.Tensor:
        """:param obs: dict from :meth:`ObservationSpec.as_dict`, entries (*lead, *shape); images as stored or
            already mapped by :meth:`ObservationSpec.preprocess`
        :param lead: batch shape
        :return: (*lead, features_dim) embedding
        """
        n = math.prod(lead)
        inputs = {}
        for key in self.spec.image_keys:
            images = obs[key].reshape(n, *self.spec.shapes[key])
            if self.spec.scale_images:  # uint8 pixels, or x / 255 - 0.5 after ObservationSpec.preprocess
                images = images.float() / 255.0 if images.dtype == th.uint8 else images + 0.5
            inputs[key] = images.float()
        for key in self.spec.vector_keys:
            inputs[key] = obs[key].reshape(n, *self.spec.shapes[key]).float()
        if self.discrete is not None:
            one_hot = self.discrete.one_hot(obs, (n,))
            widths = [self.spec.discrete_widths[k] for k in self.spec.discrete_keys]
            for key, part in zip(self.spec.discrete_keys, th.split(one_hot, widths, -1), strict=True):
                inputs[key] = part if key in self.spec.categorical_keys else part.reshape(n, *self.spec.shapes[key])
        features = self.extractor(inputs if self.spec.is_dict else inputs[SINGLE_KEY])
        return features.reshape(*lead, self.out_dim)


def make_observation_encoder(
    spec: ObservationSpec, config: WorldModelConfig, options: ObservationOptions | None = None
) -> ObservationEncoder | FeaturesExtractorEncoder:
    """The world model's encoder: :class:`ObservationEncoder`, or the user's features extractor in a
    :class:`FeaturesExtractorEncoder`.

    :param spec: the observation specification
    :param config: world-model hyperparameters
    :param options: SB3's observation keywords, or None
    :return: the encoder (``out_dim`` is the embedding size)
    """
    if options is not None and options.features_extractor_class is not None:
        return FeaturesExtractorEncoder(spec, options.features_extractor_class, options.features_extractor_kwargs)
    return ObservationEncoder(spec, config)


class ObservationDecoder(nn.Module):
    """p(o_t | h_t, z_t): a :class:`ConvDecoder` per image key (mean in x/255 - 0.5 space, or in the image's own
    units without image scaling; unit-variance Gaussian, i.e. MSE summed over pixels), one MLP predicting ``symlog``
    of all vector keys (symlog MSE) and one MLP predicting the logits of all discrete keys (a categorical per
    ``Discrete`` / ``MultiDiscrete`` entry, a Bernoulli per ``MultiBinary`` bit; :class:`DiscreteLayout`).

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
        self.discrete: DiscreteLayout | None = None
        if spec.discrete_dim:
            self.discrete_mlp = MLP(feat_dim, spec.discrete_dim, config.mlp_units, config.mlp_layers)
            self.discrete = DiscreteLayout(spec)

    def forward(self, feat: th.Tensor) -> dict[str, th.Tensor]:
        """:param feat: (..., feat_dim)
        :return: key -> prediction in model space (images (..., C, H, W) in x/255 - 0.5; the vector group under the
            key ``""`` as (..., vector_dim) in symlog space; the logits of the discrete keys under the key ``"."`` as
            (..., discrete_dim)), always float32
        """
        out = {k: conv(feat).float() for k, conv in self.convs.items()}
        if self.mlp is not None:
            out[_VECTORS] = self.mlp(feat).float()
        if self.discrete is not None:
            out[_LOGITS] = self.discrete_mlp(feat).float()
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
            target = preprocess_image(obs[key]) if self.spec.scale_images else obs[key].float()
            total = total + _SquaredError.apply(pred[key], target)
        if self.mlp is not None:
            total = total + symlog_mse(pred[_VECTORS], self.spec.vectors(obs, lead))
        if self.discrete is not None:
            total = total + self.discrete.nll(pred[_LOGITS], obs, lead)
        return total

    def mean(self, pred: dict[str, th.Tensor]) -> dict[str, th.Tensor]:
        """Predicted observations in the units of the observation space (for discrete keys the most likely value).

        :param pred: output of :meth:`forward`
        :return: key -> images as float pixels in [0, 255] (..., C, H, W) (in their own units without image
            scaling), vectors in raw units (..., *shape), discrete keys as values of their space (int64 indices,
            MultiBinary bits in its dtype)
        """
        if self.spec.scale_images:
            out = {k: ((pred[k] + 0.5) * 255.0).clamp(0.0, 255.0) for k in self.spec.image_keys}
        else:
            out = {k: pred[k] for k in self.spec.image_keys}
        if self.discrete is not None:
            out.update(self.discrete.mode(pred[_LOGITS]))
        if self.mlp is not None:
            vec = symexp(pred[_VECTORS])
            lead = vec.shape[:-1]
            for key, part in zip(self.spec.vector_keys, th.split(vec, self.spec.vector_sizes, -1), strict=True):
                out[key] = part.reshape(*lead, *self.spec.shapes[key])
        return out
