"""Checks of the arguments of the world model's public methods (the methods its owners call in their loops trust
their arguments)."""

from __future__ import annotations

from typing import Any

import torch as th

from sb3_hieros.agent.world_model.latent import LatentState

__all__ = ["check_actions", "check_is_first", "check_state"]


def check_is_first(is_first: Any, shape: tuple[int, ...], name: str = "is_first") -> th.Tensor:
    """``is_first`` of the given shape as a bool tensor (real tensors are compared with 0).

    :param is_first: the argument
    :param shape: expected shape
    :param name: argument name for the message
    :return: bool tensor
    """
    if not isinstance(is_first, th.Tensor):
        raise ValueError(f"{name} must be a torch.Tensor of shape {shape}, got {type(is_first).__name__}")
    if tuple(is_first.shape) != shape:
        raise ValueError(f"{name} has shape {tuple(is_first.shape)}, expected {shape}")
    if is_first.dtype == th.bool:
        return is_first
    if is_first.is_complex():
        raise ValueError(f"{name} must be bool or real, got dtype {is_first.dtype}")
    return is_first != 0


def check_actions(actions: Any, action_dim: int, ndim: int, name: str) -> th.Tensor:
    """Float action vectors of shape (B, T, A) (``ndim`` 3) or (N, A) (``ndim`` 2).

    :param actions: the argument
    :param action_dim: A
    :param ndim: 3 for chunks, 2 for one step
    :param name: argument name for the message
    :return: the actions as float32
    """
    layout = "(B, T, A)" if ndim == 3 else "(N, A)"
    if not isinstance(actions, th.Tensor):
        raise ValueError(f"{name} must be a torch.Tensor of shape {layout}, got {type(actions).__name__}")
    if actions.dim() != ndim or actions.shape[-1] != action_dim:
        raise ValueError(f"{name} must have shape {layout} with A={action_dim}, got shape {tuple(actions.shape)}")
    if not actions.is_floating_point():
        raise ValueError(f"{name} must be a float tensor (one-hot for discrete actions), got dtype {actions.dtype}")
    return actions.float()


def check_state(state: Any, lead: tuple[int, ...], stoch_dim: int, deter_dim: int, name: str = "state") -> LatentState:
    """A :class:`LatentState` of batch shape ``lead`` with the world model's sizes.

    :param state: the argument
    :param lead: expected batch shape
    :param stoch_dim: size of z
    :param deter_dim: size of h
    :param name: argument name for the message
    :return: the state
    """
    if not isinstance(state, LatentState):
        raise ValueError(f"{name} must be a LatentState, got {type(state).__name__}")
    if tuple(state.batch_shape) != lead:
        raise ValueError(f"{name} has batch shape {tuple(state.batch_shape)}, expected {lead}")
    if state.stoch.shape[-1] != stoch_dim or state.deter.shape[-1] != deter_dim:
        raise ValueError(
            f"{name} has stoch/deter sizes {state.stoch.shape[-1]}/{state.deter.shape[-1]}, expected "
            f"{stoch_dim}/{deter_dim}"
        )
    return state
