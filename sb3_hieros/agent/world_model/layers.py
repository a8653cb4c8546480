"""Layers of the sequence models: the input layer both use and the RSSM's GRU cell."""

from __future__ import annotations

import torch as th
import torch.nn.functional as F
from torch import nn

from sb3_hieros.nn.networks import layer_norm, trunc_normal_init_

__all__ = ["InputLayer", "LayerNormGRUCell"]


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
        return F.silu(layer_norm(self.norm, pre))

    def forward(self, stoch: th.Tensor, action: th.Tensor) -> th.Tensor:
        """:param stoch: (..., stoch_dim)
        :param action: (..., action_dim)
        :return: (..., out_dim)
        """
        return self.combine(F.linear(stoch, self.stoch.weight) + F.linear(action, self.action.weight))


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
