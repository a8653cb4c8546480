"""The latent world state ``(h_t, z_t)`` shared by both world models (thesis 4.4)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import torch as th

__all__ = ["LatentState", "cat_states", "stack_states"]


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
    return _combine(th.stack, states, dim)


def cat_states(states: Sequence[LatentState], dim: int = 0) -> LatentState:
    """Concatenate states along an existing batch dim (``dim`` >= 0).

    :param states: states whose batch shapes agree except along ``dim``
    :param dim: batch dim to concatenate
    :return: concatenated state
    """
    return _combine(th.cat, states, dim)


def _combine(op: Callable[..., th.Tensor], states: Sequence[LatentState], dim: int) -> LatentState:
    """``op`` (``torch.stack`` or ``torch.cat``) applied field by field along the batch dim ``dim``."""
    if not states:
        raise ValueError("need at least one state")
    if dim < 0:
        raise ValueError(f"dim must be >= 0 (counted among the batch dims), got {dim}")
    return LatentState(*(op(fields, dim) for fields in zip(*states, strict=True)))
