"""Observations of a world model: which keys are images and which vectors, the encoder and the decoder (thesis 4.4).

A Box of rank 3 with uint8 pixels in [0, 255] is a channel-first (C, H, W) image, encoded by a CNN; every other Box
is a vector, and all vector keys together go through one symlog MLP. Non-dict spaces use the single key ``"obs"``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.preprocessing import is_image_space
from torch import nn

from sb3_hieros.config import WorldModelConfig
from sb3_hieros.nn.distributions import symexp, symlog_mse
from sb3_hieros.nn.networks import MLP, ConvDecoder, ConvEncoder, preprocess_image

__all__ = ["SINGLE_KEY", "ObservationDecoder", "ObservationEncoder", "ObservationSpec"]

#: The key of a non-dict observation inside the world model.
SINGLE_KEY = "obs"


class ObservationSpec:
    """Which observation keys are images (CNN) and which are vectors (symlog MLP).

    A Box of rank 3 with uint8 pixels in [0, 255] is a channel-first (C, H, W) image; any other Box is a vector
    (flattened). A Dict space may mix both. Non-dict spaces use the single key ``"obs"`` internally. The space is
    trusted (see :func:`sb3_hieros.spaces.check_observation_space`).

    :param observation_space: the level's observation space
    """

    def __init__(self, observation_space: spaces.Space) -> None:
        self.is_dict = isinstance(observation_space, spaces.Dict)
        items = list(observation_space.spaces.items()) if self.is_dict else [(SINGLE_KEY, observation_space)]
        self.shapes: dict[str, tuple[int, ...]] = {}
        self.image_keys: list[str] = []
        self.vector_keys: list[str] = []
        for key, space in items:
            self.shapes[key] = tuple(int(s) for s in space.shape)
            if is_image_space(space, check_channels=False):
                self.image_keys.append(key)
            else:
                self.vector_keys.append(key)
        self.vector_sizes = [int(np.prod(self.shapes[k])) for k in self.vector_keys]
        self.vector_dim = sum(self.vector_sizes)

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
            if tuple(value.shape) != expected:
                raise ValueError(f"{label} has shape {tuple(value.shape)}, expected {expected}")
        return obs

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
