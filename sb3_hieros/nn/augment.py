"""Image augmentation for world-model training."""

from __future__ import annotations

import torch as th
from torch.nn import functional as F


def random_shift(images: th.Tensor, pad: int) -> th.Tensor:
    """Random-shift augmentation of image sequences, one shift per sequence (DrQ's random shift, held over time).

    Each sequence is padded by ``pad`` pixels on every side by repeating its border pixels and cropped back to its
    size at an offset drawn uniformly from ``{0, ..., 2 pad}`` in each direction, the same offset for all of its
    frames: the scene moves by up to ``pad`` pixels while its motion from frame to frame stays what it was.

    :param images: (B, T, C, H, W) float images
    :param pad: largest shift in pixels, >= 0 (0 returns ``images`` unchanged)
    :return: (B, T, C, H, W) shifted images, laid out channels-last per frame (as the convolutions read them)
    """
    if pad < 0:
        raise ValueError(f"pad must be >= 0, got {pad}")
    if images.dim() != 5:
        raise ValueError(f"random_shift expected (B, T, C, H, W) images, got shape {tuple(images.shape)}")
    if pad == 0:
        return images
    batch, steps, channels, height, width = images.shape
    padded = F.pad(images.reshape(batch, steps * channels, height, width), (pad, pad, pad, pad), mode="replicate")
    offsets = th.randint(0, 2 * pad + 1, (2, batch), device=images.device)
    rows = offsets[0, :, None] + th.arange(height, device=images.device)  # (B, H)
    cols = offsets[1, :, None] + th.arange(width, device=images.device)  # (B, W)
    # advanced indices around a slice put their dims first: (B, H, W, T * C)
    crops = padded[th.arange(batch, device=images.device)[:, None, None], :, rows[:, :, None], cols[:, None, :]]
    crops = crops.reshape(batch, height, width, steps, channels).permute(0, 3, 1, 2, 4).contiguous()  # (B, T, H, W, C)
    return crops.permute(0, 1, 4, 2, 3)
