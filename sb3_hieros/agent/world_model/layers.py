"""Layers of the sequence models: the input layer both use and the RSSM's GRU cell."""

from __future__ import annotations

import torch as th
import torch.nn.functional as F
from torch import nn

from sb3_hieros.nn.networks import layer_norm, trunc_normal_init_

__all__ = ["InputLayer", "LayerNormGRUCell"]


class InputLayer(nn.Module):
    """The sequence model's input from z_{t-1} and a_{t-1}, in one of two forms (``WorldModelConfig.action_input``):

    * ``separate=False``: ``SiLU(LayerNorm(W_z z + W_a a))``, one Linear over ``[z, a]`` (thesis, first DreamerV3);
    * ``separate=True``: ``[SiLU(LayerNorm(W_z z)), SiLU(LayerNorm(W_a a + b_a))]``, each half of ``out_dim`` wide
      (later DreamerV3 releases embed the action on its own): the action's half is normalised by itself, so a
      one-dimensional action is not one input among hundreds of stochastic ones.

    The action's part (:meth:`action_features`) depends on the action alone, so the RSSM computes it for a whole
    chunk outside its time loop and finishes with :meth:`join`.

    :param stoch_dim: size of the flattened z
    :param action_dim: size of the action vector
    :param out_dim: output width
    :param separate: embed z and a separately (see above)
    """

    def __init__(self, stoch_dim: int, action_dim: int, out_dim: int, separate: bool = False) -> None:
        super().__init__()
        if separate and out_dim < 2:
            raise ValueError(f"InputLayer with separate=True needs out_dim >= 2, got {out_dim}")
        action_width = out_dim // 2 if separate else out_dim
        stoch_width = out_dim - action_width if separate else out_dim
        self.stoch = nn.Linear(stoch_dim, stoch_width, bias=False)
        self.action = nn.Linear(action_dim, action_width, bias=separate)
        self.norm = nn.LayerNorm(stoch_width, eps=1e-3)
        self.action_norm = nn.LayerNorm(action_width, eps=1e-3) if separate else None
        trunc_normal_init_(self.stoch)
        trunc_normal_init_(self.action)

    def action_features(self, action: th.Tensor) -> th.Tensor:
        """The action's part of the input: ``W_a a`` (joint) or ``SiLU(LayerNorm(W_a a + b_a))`` (separate).

        :param action: (..., action_dim)
        :return: (..., out_dim) joint, (..., out_dim // 2) separate
        """
        pre = F.linear(action, self.action.weight, self.action.bias)
        if self.action_norm is None:
            return pre
        return F.silu(layer_norm(self.action_norm, pre))

    def join(self, stoch: th.Tensor, action_features: th.Tensor) -> th.Tensor:
        """The input from z and the action's part (:meth:`action_features`).

        :param stoch: (..., stoch_dim)
        :param action_features: from :meth:`action_features`
        :return: (..., out_dim)
        """
        if self.action_norm is None:
            return F.silu(layer_norm(self.norm, F.linear(stoch, self.stoch.weight) + action_features))
        stoch_features = F.silu(layer_norm(self.norm, F.linear(stoch, self.stoch.weight)))
        return th.cat([stoch_features, action_features.to(stoch_features.dtype)], -1)

    def forward(self, stoch: th.Tensor, action: th.Tensor) -> th.Tensor:
        """:param stoch: (..., stoch_dim)
        :param action: (..., action_dim)
        :return: (..., out_dim)
        """
        return self.join(stoch, self.action_features(action))


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
