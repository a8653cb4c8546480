"""World model of one HIEROS level (thesis 4.4): S5WM and DreamerV3's RSSM behind one interface.

* :mod:`~sb3_hieros.agent.world_model.latent`: the world state :class:`LatentState` ``(h_t, z_t)``;
* :mod:`~sb3_hieros.agent.world_model.observations`: image and vector keys, encoder and decoder;
* :mod:`~sb3_hieros.agent.world_model.base`: :class:`WorldModel`, the part both share (heads, loss, replay context,
  the imagination rollout);
* :mod:`~sb3_hieros.agent.world_model.s5wm` and :mod:`~sb3_hieros.agent.world_model.rssm`: the sequence models,
  :mod:`~sb3_hieros.agent.world_model.layers` their layers;
* here: the factory :func:`make_world_model` and the optimiser with its warm-up.
"""

from __future__ import annotations

from typing import Any

import torch as th
from gymnasium import spaces

from sb3_hieros.agent.world_model.base import REWARD_BINS, WorldModel
from sb3_hieros.agent.world_model.latent import LatentState, cat_states, stack_states
from sb3_hieros.agent.world_model.observations import ObservationOptions, ObservationSpec
from sb3_hieros.agent.world_model.rssm import RSSMWorldModel
from sb3_hieros.agent.world_model.s5wm import S5WorldModel
from sb3_hieros.config import WorldModelConfig
from sb3_hieros.nn.optim import user_optimizer

__all__ = [
    "REWARD_BINS",
    "LatentState",
    "ObservationOptions",
    "ObservationSpec",
    "RSSMWorldModel",
    "S5WorldModel",
    "WorldModel",
    "cat_states",
    "make_world_model",
    "set_world_model_lr",
    "stack_states",
    "world_model_lr_scheduler",
    "world_model_optimizer",
]

_KINDS: dict[str, type[WorldModel]] = {"s5": S5WorldModel, "rssm": RSSMWorldModel}


def make_world_model(
    observation_space: spaces.Space, action_dim: int, config: WorldModelConfig, **options: Any
) -> WorldModel:
    """The world model selected by ``config.kind`` (``"s5"``: S5WM, ``"rssm"``: DreamerV3's RSSM).

    :param observation_space: observation space of the level
    :param action_dim: size of the action vector
    :param config: world-model hyperparameters
    :param options: ``bf16`` and ``compile`` opt-ins and ``observation_options`` (see :class:`WorldModel`)
    :return: the world model
    """
    return _KINDS[config.kind](observation_space, action_dim, config, **options)


def world_model_optimizer(
    model: WorldModel,
    config: WorldModelConfig | None = None,
    optimizer_class: type[th.optim.Optimizer] | None = None,
    optimizer_kwargs: dict[str, Any] | None = None,
) -> th.optim.Optimizer:
    """AdamW for a world model with two groups: weight decay ``config.weight_decay`` for weight matrices, none for
    :meth:`WorldModel.no_weight_decay_parameters` (S5 SSM parameters, norms, biases).

    With SB3's ``optimizer_class`` / ``optimizer_kwargs`` (policy keywords) the same groups go to the user's class
    (:func:`~sb3_hieros.nn.optim.user_optimizer`).

    :param model: the world model
    :param config: hyperparameters (``lr``, ``eps``, ``weight_decay``); default ``model.config``
    :param optimizer_class: a ``torch.optim.Optimizer`` subclass, or None
    :param optimizer_kwargs: its keywords (not ``lr``), or None
    :return: the optimiser
    """
    cfg = model.config if config is None else config
    no_decay = model.no_weight_decay_parameters()
    no_decay_ids = {id(p) for p in no_decay}
    decay = [p for p in model.parameters() if id(p) not in no_decay_ids]
    if optimizer_class is not None or optimizer_kwargs:
        groups = [(decay, True), (no_decay, False)]
        return user_optimizer(groups, cfg.lr, cfg.eps, cfg.weight_decay, optimizer_class, optimizer_kwargs)
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


def set_world_model_lr(
    optimizer: th.optim.Optimizer, scheduler: th.optim.lr_scheduler.LambdaLR | None, lr: float, updates: int
) -> None:
    """Set a world model's learning rate for its next update: ``lr`` (the value of the SB3 schedule) times the warm-up
    factor of :func:`world_model_lr_scheduler` after ``updates`` updates.

    :param optimizer: the world model's optimiser
    :param scheduler: its warm-up scheduler, or None
    :param lr: the scheduled learning rate
    :param updates: updates the world model has made so far
    """
    factor = 1.0
    if scheduler is not None:
        factor = float(scheduler.lr_lambdas[0](updates))  # type: ignore[attr-defined]
        scheduler.base_lrs = [lr] * len(optimizer.param_groups)
        scheduler.last_epoch = updates
    for group in optimizer.param_groups:
        group["lr"] = lr * factor
