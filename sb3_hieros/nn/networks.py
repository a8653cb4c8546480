"""Feed-forward building blocks in the DreamerV3 style: MLP, convolutional image encoder and decoder, initialisers.

All modules accept arbitrary leading batch dims, e.g. (B, T, ...) sequences: they flatten them internally and restore
them on the output. Images are channel-first (C, H, W), as produced by SB3's ``VecTransposeImage``.
"""

from __future__ import annotations

import contextlib
import functools
import math
from collections.abc import Iterator, Sequence

import torch as th
from torch import nn
from torch.nn import functional as F

from sb3_hieros.nn.distributions import symlog

# std of a unit normal truncated to [-2, 2]; dividing by it makes the truncated init have the requested std
_TRUNC_STD_CORRECTION = 0.8796256610342398


def trunc_normal_init_(module: nn.Module, scale: float = 1.0) -> None:
    """DreamerV3 initialiser for one ``Linear`` / ``Conv2d`` / ``ConvTranspose2d`` layer, in place.

    Weights ~ normal truncated at 2 std with variance ``scale / fan_avg`` (``fan_avg = (fan_in + fan_out) / 2``),
    biases zero. ``scale = 0`` gives an all-zero layer (used for reward and critic output layers).

    :param module: the layer (other modules are left untouched)
    :param scale: variance scale, >= 0
    """
    if scale < 0:
        raise ValueError(f"scale must be >= 0, got {scale}")
    if not isinstance(module, (nn.Linear, nn.Conv2d, nn.ConvTranspose2d)):
        return
    with th.no_grad():
        if scale == 0.0:
            module.weight.zero_()
        else:
            fan_in, fan_out = nn.init._calculate_fan_in_and_fan_out(module.weight)
            std = math.sqrt(scale / ((fan_in + fan_out) / 2.0)) / _TRUNC_STD_CORRECTION
            nn.init.trunc_normal_(module.weight, mean=0.0, std=std, a=-2.0 * std, b=2.0 * std)
        if module.bias is not None:
            module.bias.zero_()


def layer_norm(norm: nn.LayerNorm, x: th.Tensor) -> th.Tensor:
    """``norm(x)`` without the module call (hooks, tracing checks), which costs more than the norm itself on a small
    batch on a CPU; for the acting and imagination hot paths.

    :param norm: the LayerNorm module whose parameters are used
    :param x: (..., *norm.normalized_shape)
    :return: same shape as ``x``
    """
    return F.layer_norm(x, norm.normalized_shape, norm.weight, norm.bias, norm.eps)


class MLP(nn.Module):
    """``layers`` blocks of Linear -> LayerNorm -> activation, then an optional output Linear (DreamerV3).

    Hidden Linear layers have no bias when followed by a norm. Works on inputs of shape (..., in_dim).

    :param in_dim: input features
    :param out_dim: output features of the final Linear; ``None`` for no output layer (the last hidden block's
        activations are returned)
    :param hidden: hidden width
    :param layers: number of hidden blocks (0 gives a single Linear, or the identity if ``out_dim`` is None)
    :param norm: use LayerNorm (eps 1e-3) in the hidden blocks
    :param act: activation class
    :param out_scale: variance scale of the output layer init; 0.0 zero-initialises it (reward and critic heads)
    :param symlog_inputs: apply :func:`~sb3_hieros.nn.distributions.symlog` to the input first (vector observations)
    """

    def __init__(
        self,
        in_dim: int,
        out_dim: int | None,
        hidden: int = 256,
        layers: int = 2,
        norm: bool = True,
        act: type[nn.Module] = nn.SiLU,
        out_scale: float = 1.0,
        symlog_inputs: bool = False,
    ) -> None:
        super().__init__()
        for name, value in (("in_dim", in_dim), ("hidden", hidden)):
            if value < 1:
                raise ValueError(f"{name} must be >= 1, got {value}")
        if out_dim is not None and out_dim < 1:
            raise ValueError(f"out_dim must be >= 1 or None, got {out_dim}")
        if layers < 0:
            raise ValueError(f"layers must be >= 0, got {layers}")
        self.in_dim = in_dim
        self.symlog_inputs = symlog_inputs
        # (linear, norm or None, activation) per hidden block, called functionally in forward: the modules' own
        # __call__ (hooks, tracing checks) is a large part of a small-batch MLP's time on a CPU
        self._blocks: list[tuple[nn.Linear, nn.LayerNorm | None, nn.Module]] = []
        dim = in_dim
        for _ in range(layers):
            linear = nn.Linear(dim, hidden, bias=not norm)
            trunc_normal_init_(linear)
            self._blocks.append((linear, nn.LayerNorm(hidden, eps=1e-3) if norm else None, act()))
            dim = hidden
        self.hidden = nn.Sequential(*(m for block in self._blocks for m in block if m is not None))
        self.out: nn.Linear | None = None
        if out_dim is not None:
            self.out = nn.Linear(dim, out_dim)
            trunc_normal_init_(self.out, out_scale)
            dim = out_dim
        self.out_dim = dim

    def forward(self, x: th.Tensor) -> th.Tensor:
        """:param x: (..., in_dim)
        :return: (..., out_dim)
        """
        if x.dim() < 1 or x.shape[-1] != self.in_dim:
            raise ValueError(f"MLP expected input of shape (..., {self.in_dim}), got {tuple(x.shape)}")
        if self.symlog_inputs:
            x = symlog(x)
        for linear, norm, act in self._blocks:  # the layers of self.hidden, without their module calls
            x = F.linear(x, linear.weight, linear.bias)
            if norm is not None:
                x = layer_norm(norm, x)
            x = act.forward(x)
        return x if self.out is None else F.linear(x, self.out.weight, self.out.bias)


class ChannelLayerNorm(nn.Module):
    """LayerNorm over the channel dim of (N, C, H, W) maps, applied per pixel (DreamerV3's conv norm).

    :param channels: number of channels C
    :param eps: LayerNorm epsilon
    """

    def __init__(self, channels: int, eps: float = 1e-3) -> None:
        super().__init__()
        self.norm = nn.LayerNorm(channels, eps=eps)

    def forward(self, x: th.Tensor) -> th.Tensor:
        """:param x: (N, C, H, W)
        :return: (N, C, H, W)
        """
        return self.norm(x.permute(0, 2, 3, 1)).permute(0, 3, 1, 2)


def preprocess_image(obs: th.Tensor) -> th.Tensor:
    """Map images to the float space the encoder consumes and the decoder predicts.

    ``uint8`` pixels become ``x / 255 - 0.5`` in [-0.5, 0.5]. Floating-point inputs are taken as already in that
    space and returned unchanged (so decoder outputs and reconstruction targets can be passed back in). Other dtypes
    are refused.

    :param obs: (..., C, H, W) uint8 or floating-point images
    :return: float tensor of the same shape
    """
    if obs.dtype == th.uint8:
        return obs.float() / 255.0 - 0.5
    if obs.is_floating_point():
        return obs
    raise ValueError(f"images must be uint8 (0..255) or floating point (already x/255 - 0.5), got dtype {obs.dtype}")


def conv_stack_sizes(height: int, width: int, min_res: int) -> list[tuple[int, int]]:
    """Spatial sizes through stride-2 kernel-4 padding-1 convolutions, halving (floor) until ``max(h, w) <= min_res``.

    A dim of 1 cannot be halved further, so the stack also stops when ``min(h, w) < 2``.

    :param height: input height
    :param width: input width
    :param min_res: stop once the larger side is at most this
    :return: [(h_0, w_0) = (height, width), (h_1, w_1), ..., (h_n, w_n)] for a stack of n convolutions
    """
    if height < 1 or width < 1 or min_res < 1:
        raise ValueError(f"need positive sizes, got height={height}, width={width}, min_res={min_res}")
    sizes = [(height, width)]
    h, w = height, width
    while max(h, w) > min_res and min(h, w) >= 2:
        h, w = h // 2, w // 2
        sizes.append((h, w))
    return sizes


def _check_image_shape(name: str, shape: Sequence[int]) -> tuple[int, int, int]:
    if len(shape) != 3 or any(int(s) < 1 for s in shape):
        raise ValueError(f"{name} must be a channel-first (C, H, W) tuple of positive ints, got {tuple(shape)}")
    c, h, w = (int(s) for s in shape)
    return c, h, w


class ConvEncoder(nn.Module):
    """DreamerV3 image encoder: stride-2 4x4 convolutions doubling the channels (depth, 2 depth, 4 depth, ...).

    Convolutions halve the spatial size until the larger side is at most ``min_res`` (64 -> 32 -> 16 -> 8 -> 4,
    40 -> 20 -> 10 -> 5 -> 2, 36 -> 18 -> 9 -> 4), each followed by a per-pixel channel LayerNorm and SiLU; the final
    map is flattened. Inputs go through :func:`preprocess_image` (uint8 -> x/255 - 0.5; floats unchanged).

    :param in_shape: (C, H, W) of one image
    :param depth: channels of the first convolution
    :param min_res: stop halving once the larger spatial side is at most this
    """

    def __init__(self, in_shape: Sequence[int], depth: int = 32, min_res: int = 4) -> None:
        super().__init__()
        self.in_shape = _check_image_shape("in_shape", in_shape)
        if depth < 1:
            raise ValueError(f"depth must be >= 1, got {depth}")
        channels, height, width = self.in_shape
        sizes = conv_stack_sizes(height, width, min_res)
        layers: list[nn.Module] = []
        in_ch = channels
        for i in range(len(sizes) - 1):
            out_ch = depth * 2**i
            conv = nn.Conv2d(in_ch, out_ch, kernel_size=4, stride=2, padding=1, bias=False)  # the norm has a bias
            trunc_normal_init_(conv)
            layers += [conv, ChannelLayerNorm(out_ch), nn.SiLU()]
            in_ch = out_ch
        layers.append(nn.Flatten())
        self.net = nn.Sequential(*layers)
        # flatten size from a dummy forward (as SB3's NatureCNN does)
        with th.no_grad():
            self.out_dim = int(self.net(th.zeros(1, *self.in_shape)).shape[1])

    def forward(self, obs: th.Tensor) -> th.Tensor:
        """:param obs: (..., C, H, W) uint8 or float (see :func:`preprocess_image`)
        :return: (..., out_dim) features
        """
        if obs.dim() < 3 or tuple(obs.shape[-3:]) != self.in_shape:
            raise ValueError(f"ConvEncoder expected images of shape (..., {self.in_shape}), got {tuple(obs.shape)}")
        lead = obs.shape[:-3]
        x = preprocess_image(obs).reshape(-1, *self.in_shape)
        return self.net(x).reshape(*lead, self.out_dim)


class ConvDecoder(nn.Module):
    """Mirror of :class:`ConvEncoder`: Linear to the smallest map, then stride-2 4x4 transposed convolutions.

    Each transposed convolution doubles the spatial size, plus one where the encoder's floor-halving dropped a row or
    column (``output_padding``), so the output is exactly (C, H, W) for any image size. The output is the mean image
    in the same ``x/255 - 0.5`` space as :func:`preprocess_image` (no sigmoid).

    :param feat_dim: input features (e.g. the world-model state size)
    :param out_shape: (C, H, W) of the reconstructed image
    :param depth: channels of the encoder's first convolution (the decoder's last hidden map)
    :param min_res: as in :class:`ConvEncoder`
    """

    def __init__(self, feat_dim: int, out_shape: Sequence[int], depth: int = 32, min_res: int = 4) -> None:
        super().__init__()
        self.out_shape = _check_image_shape("out_shape", out_shape)
        if feat_dim < 1 or depth < 1:
            raise ValueError(f"feat_dim and depth must be >= 1, got feat_dim={feat_dim}, depth={depth}")
        self.feat_dim = feat_dim
        channels, height, width = self.out_shape
        sizes = conv_stack_sizes(height, width, min_res)
        n_conv = len(sizes) - 1
        hidden_ch = [depth * 2**i for i in range(n_conv)]
        bottom_ch = hidden_ch[-1] if n_conv > 0 else channels
        self._bottom = (bottom_ch, *sizes[-1])
        self.linear = nn.Linear(feat_dim, bottom_ch * sizes[-1][0] * sizes[-1][1])
        trunc_normal_init_(self.linear)
        layers: list[nn.Module] = []
        for i in reversed(range(n_conv)):
            in_ch = hidden_ch[i]
            last = i == 0
            out_ch = channels if last else hidden_ch[i - 1]
            (h_out, w_out), (h_in, w_in) = sizes[i], sizes[i + 1]
            padding = (h_out - 2 * h_in, w_out - 2 * w_in)  # 0 or 1: undo the encoder's floor division
            conv = nn.ConvTranspose2d(
                in_ch, out_ch, kernel_size=4, stride=2, padding=1, output_padding=padding, bias=last
            )
            trunc_normal_init_(conv)
            layers += [conv] if last else [conv, ChannelLayerNorm(out_ch), nn.SiLU()]
        self.net = nn.Sequential(*layers)

    def forward(self, feat: th.Tensor) -> th.Tensor:
        """:param feat: (..., feat_dim)
        :return: (..., C, H, W) mean image in x/255 - 0.5 space
        """
        if feat.dim() < 1 or feat.shape[-1] != self.feat_dim:
            raise ValueError(f"ConvDecoder expected input of shape (..., {self.feat_dim}), got {tuple(feat.shape)}")
        lead = feat.shape[:-1]
        x = self.linear(feat.reshape(-1, self.feat_dim)).reshape(-1, *self._bottom)
        x = self.net(x)
        return x.reshape(*lead, *self.out_shape)


@contextlib.contextmanager
def evaluation_mode(module: nn.Module) -> Iterator[None]:
    """Within the block ``module`` is in evaluation mode (no dropout); its previous mode is restored afterwards.

    Gradients still flow: this switches ``nn.Module.training`` only, unlike ``torch.no_grad``.

    :param module: the module (and its children)
    """
    was_training = module.training
    module.train(False)
    try:
        yield
    finally:
        module.train(was_training)


def check_bf16(value: object) -> bool | str:
    """Validate a ``bf16`` option.

    :param value: ``False``, ``True`` or ``"auto"``
    :return: the value
    :raises ValueError: for anything else (``1``, ``"true"``, ...), which is not coerced
    """
    if isinstance(value, bool) or value == "auto":
        return value  # type: ignore[return-value]
    raise ValueError(f"bf16 must be False, True or 'auto', got {value!r}")


@functools.cache
def native_bf16(device_type: str) -> bool:
    """Whether the device computes bfloat16 matrix products natively: a CPU with AVX512-BF16 or AMX-BF16, a CUDA GPU
    with bf16 support. Elsewhere a bf16 autocast is emulated and slower than float32.

    :param device_type: ``"cpu"``, ``"cuda"``, ...
    :return: True where native
    """
    if device_type == "cpu":
        # torch's own CPU feature table (private, hence guarded: without it, no native bf16 is assumed)
        get_capability = getattr(getattr(th._C, "_cpu", None), "_get_cpu_capability", None)
        capability = get_capability() if get_capability is not None else {}
        return bool(capability.get("avx512_bf16") or capability.get("amx_bf16"))
    if device_type == "cuda":
        return th.cuda.is_available() and th.cuda.is_bf16_supported()
    return False


def bf16_autocast(enabled: bool | str, device: th.device) -> contextlib.AbstractContextManager:
    """A bfloat16 ``torch.autocast`` block on ``device`` where ``enabled``, else a block that changes nothing.

    Under it, matrix products and convolutions run in bfloat16 (fast on CPUs with native bf16 instructions, e.g.
    AVX512-BF16 or AMX, and on recent GPUs); the distributions of :mod:`sb3_hieros.nn.distributions` take their
    parameters back to float32. Enter it around a forward pass and a loss, not around ``backward`` or an optimiser
    step: autocast caches the bf16 copies of the weights until the block ends, and an in-place update inside it would
    leave them stale.

    :param enabled: ``True``, ``False`` or ``"auto"`` (where :func:`native_bf16` holds for the device)
    :param device: device of the computation
    """
    if enabled == "auto":
        enabled = native_bf16(device.type)
    if not enabled:
        return contextlib.nullcontext()
    return th.autocast(device_type=device.type, dtype=th.bfloat16)


def without_autocast(device_type: str) -> contextlib.AbstractContextManager:
    """A block that runs outside any autocast: ``torch.autocast(enabled=False)`` where one is active, else nothing
    (entering the autocast context costs more than the single-step maths it would guard).

    :param device_type: ``"cpu"``, ``"cuda"``, ...
    """
    if th.is_autocast_enabled(device_type):
        return th.autocast(device_type=device_type, enabled=False)
    return contextlib.nullcontext()


__all__ = [
    "MLP",
    "ChannelLayerNorm",
    "ConvDecoder",
    "ConvEncoder",
    "bf16_autocast",
    "check_bf16",
    "conv_stack_sizes",
    "evaluation_mode",
    "native_bf16",
    "preprocess_image",
    "trunc_normal_init_",
    "without_autocast",
]
