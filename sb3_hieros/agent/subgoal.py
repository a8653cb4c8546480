"""Subgoal autoencoder and the two intrinsic rewards built on it (thesis 4.3.1 and 4.3.2, eq. 4.1, 4.2, 4.4, 4.5).

The autoencoder compresses a deterministic world state h into 8 one-hot categoricals of 8 classes (the subgoal space
the level above acts in) and decodes such a code back into h space. The subgoal reward compares the decoded subgoal
with the current h (max-cosine similarity), the novelty reward is the autoencoder's reconstruction error of h.

Deviations from the reference implementation: the encoder ends in a plain Linear layer producing
logits and the decoder in a plain Linear layer producing h (the reference passes both through LayerNorm + GELU, which
bounds the decoded values from below), and the reconstruction is compared with h in h's own units in the loss and in
both rewards (the reference compares a symlog'ed target with raw h in the novelty reward).
"""

from __future__ import annotations

import torch as th
from torch import nn

from sb3_hieros.nn.distributions import OneHotCategoricalST, categorical_kl
from sb3_hieros.nn.networks import MLP

#: Uniform mixture of the subgoal code distribution (DreamerV3's unimix).
CODE_UNIMIX = 0.01


class SubgoalAutoencoder(nn.Module):
    """G_psi = (encoder p_psi(g | h), decoder f_psi(g) ~ h) of eq. 4.1.

    The code g is ``n_cat`` one-hot categoricals of ``n_classes`` classes with unimix and straight-through gradients:
    sampled in training mode, the mode in eval mode (override with ``sample=``).

    :param h_dim: size of the deterministic world state h
    :param n_cat: number of categoricals (thesis: 8)
    :param n_classes: classes per categorical (thesis: 8)
    :param hidden: MLP width of encoder and decoder
    :param layers: hidden layers of encoder and decoder
    :param beta: weight of the KL to the uniform prior (thesis: 0.5)
    """

    def __init__(
        self, h_dim: int, n_cat: int = 8, n_classes: int = 8, hidden: int = 256, layers: int = 2, beta: float = 0.5
    ) -> None:
        super().__init__()
        if h_dim < 1 or n_cat < 1 or n_classes < 2:
            raise ValueError(f"need h_dim >= 1, n_cat >= 1, n_classes >= 2, got {h_dim}, {n_cat}, {n_classes}")
        if beta < 0:
            raise ValueError(f"beta must be >= 0, got {beta}")
        self.h_dim, self.n_cat, self.n_classes = h_dim, n_cat, n_classes
        self.beta, self.unimix = beta, CODE_UNIMIX
        self.encoder = MLP(h_dim, n_cat * n_classes, hidden, layers)
        self.decoder = MLP(n_cat * n_classes, h_dim, hidden, layers)

    @property
    def subgoal_shape(self) -> tuple[int, int]:
        """Shape (n_cat, n_classes) of one subgoal."""
        return (self.n_cat, self.n_classes)

    @property
    def subgoal_dim(self) -> int:
        """Flattened subgoal size n_cat * n_classes."""
        return self.n_cat * self.n_classes

    def _check_h(self, h: th.Tensor) -> None:
        if h.dim() < 1 or h.shape[-1] != self.h_dim:
            raise ValueError(f"h must have shape (*B, {self.h_dim}), got {tuple(h.shape)}")

    def dist(self, h: th.Tensor) -> OneHotCategoricalST:
        """Encoder distribution p_psi(g | h).

        :param h: (*B, h_dim)
        :return: categorical with batch shape *B and event shape (n_cat, n_classes)
        """
        self._check_h(h)
        logits = self.encoder(h).reshape(*h.shape[:-1], self.n_cat, self.n_classes)
        return OneHotCategoricalST(logits, self.unimix, event_ndims=1)

    def encode(self, h: th.Tensor, sample: bool | None = None) -> th.Tensor:
        """Subgoal code of h.

        :param h: (*B, h_dim)
        :param sample: sample the code (True) or take the mode (False); default: sample in training mode only
        :return: (*B, n_cat, n_classes) one-hot with straight-through gradient
        """
        dist = self.dist(h)
        if sample is None:
            sample = self.training
        return dist.sample() if sample else dist.mode()

    def decode(self, subgoal: th.Tensor) -> th.Tensor:
        """Decoder f_psi: subgoal code to h space.

        :param subgoal: (*B, n_cat, n_classes) or (*B, n_cat * n_classes) one-hot (or soft) codes
        :return: (*B, h_dim)
        """
        if subgoal.dim() >= 2 and tuple(subgoal.shape[-2:]) == self.subgoal_shape:
            flat = subgoal.reshape(*subgoal.shape[:-2], self.subgoal_dim)
        elif subgoal.dim() >= 1 and subgoal.shape[-1] == self.subgoal_dim:
            flat = subgoal
        else:
            raise ValueError(
                f"subgoal must have shape (*B, {self.n_cat}, {self.n_classes}) or (*B, {self.subgoal_dim}), "
                f"got {tuple(subgoal.shape)}"
            )
        return self.decoder(flat)

    def forward(self, h: th.Tensor, sample: bool | None = None) -> th.Tensor:
        """Reconstruction ``decode(encode(h))``.

        :param h: (*B, h_dim)
        :param sample: see :meth:`encode`
        :return: (*B, h_dim)
        """
        return self.decode(self.encode(h, sample))

    def loss(self, h: th.Tensor) -> tuple[th.Tensor, dict[str, th.Tensor]]:
        """Variational loss of eq. 4.2: ``mean((f(g^) - h)^2) + beta * KL(p(g | h) || uniform)``.

        ``h`` is detached (the autoencoder never trains the world model). The code g^ is sampled in training mode.
        The squared error is averaged over the h dims (the thesis' "L2 norm" is defined as a mean of squares), the KL
        is that of the joint code divided by ``n_cat`` (i.e. averaged over the categoricals, as in the reference, for
        which beta = 0.5 was tuned). Both are averaged over the batch.

        :param h: (*B, h_dim) world states
        :return: (scalar loss, metrics of detached 0-d tensors)
        """
        self._check_h(h)
        h = h.detach()
        dist = self.dist(h)
        code = dist.sample() if self.training else dist.mode()
        recon = self.decode(code)
        rec_loss = (recon - h).pow(2).mean(-1)  # (*B)
        uniform = th.zeros(self.n_classes, device=h.device, dtype=dist.logits.dtype)
        kl = categorical_kl(dist.logits, uniform, group_dims=1) / self.n_cat  # (*B)
        loss = (rec_loss + self.beta * kl).mean()
        metrics = {
            "subgoal_ae/loss": loss.detach(),
            "subgoal_ae/reconstruction": rec_loss.mean().detach(),
            "subgoal_ae/kl": kl.mean().detach(),
            "subgoal_ae/code_entropy": (dist.entropy() / self.n_cat).mean().detach(),
        }
        return loss, metrics


def max_cosine_subgoal_reward(h: th.Tensor, goal: th.Tensor, eps: float = 1e-8) -> th.Tensor:
    r"""Subgoal reward of eq. 4.4: max-cosine similarity of the world state and the decoded subgoal (Director).

    .. math:: r^g = \frac{g}{m} \cdot \frac{h}{m}, \qquad m = \max(\|g\|, \|h\|)

    The thesis prints the denominator as ``max(|g|, |h|)``; without the square the value would scale with the norms,
    so we follow Director and the reference in dividing by m^2. The result lies in [-1, 1], equals 1 exactly when
    g == h != 0, and is below 1 when the directions or the norms differ (the max penalises a shorter h). No clamp or
    symlog is applied (the reference clamps at 0 and symlogs).

    :param h: (*B, D) deterministic world states (e.g. (H+1, N, D) imagined)
    :param goal: decoded subgoals G_dec(g), broadcastable to ``h`` (e.g. (N, D), constant over the horizon)
    :param eps: guards the division when both vectors are zero (the reward is then 0)
    :return: (*B) rewards in [-1, 1]
    """
    if h.dim() < 1 or goal.dim() < 1 or h.shape[-1] != goal.shape[-1]:
        raise ValueError(f"h {tuple(h.shape)} and goal {tuple(goal.shape)} must share the last (feature) dim")
    m = th.maximum(goal.norm(dim=-1), h.norm(dim=-1)).clamp_min(eps)
    return (goal * h).sum(-1) / m.pow(2)


def novelty_reward(h: th.Tensor, autoencoder: SubgoalAutoencoder) -> th.Tensor:
    """Novelty reward of eq. 4.5: reconstruction error ``mean_j (h_j - G_dec(G_enc(h))_j)^2`` of h.

    The code is the encoder's mode (deterministic). States like those the autoencoder was trained on reconstruct well
    and earn little; unfamiliar states earn more. The result is differentiable w.r.t. h and the autoencoder's
    parameters: wrap the call in ``torch.no_grad()`` for a plain reward signal.

    :param h: (*B, h_dim) deterministic world states
    :param autoencoder: the level's subgoal autoencoder
    :return: (*B) non-negative rewards
    """
    recon = autoencoder(h, sample=False)
    return (h - recon).pow(2).mean(-1)


__all__ = ["SubgoalAutoencoder", "max_cosine_subgoal_reward", "novelty_reward"]
