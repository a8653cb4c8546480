"""Optimisers under SB3's policy keywords ``optimizer_class`` and ``optimizer_kwargs``.

Without them every learner of HIEROS has its own AdamW (built where the learner is). With them,
:func:`user_optimizer` builds each of those optimisers from the user's class and keywords, keeping what the
configuration says per learner (learning rate, epsilon, which parameters decay).
"""

from __future__ import annotations

import inspect
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import torch as th
from torch import nn

__all__ = ["check_optimizer_options", "user_optimizer"]


def check_optimizer_options(
    optimizer_class: type[th.optim.Optimizer] | None, optimizer_kwargs: Mapping[str, Any] | None
) -> None:
    """Raise ``ValueError`` unless ``optimizer_class`` is None or a ``torch.optim.Optimizer`` subclass and
    ``optimizer_kwargs`` is None or a dict without ``lr`` and ``params``.

    :param optimizer_class: SB3's policy keyword
    :param optimizer_kwargs: SB3's policy keyword
    """
    if optimizer_class is not None and not (
        isinstance(optimizer_class, type) and issubclass(optimizer_class, th.optim.Optimizer)
    ):
        raise ValueError(f"optimizer_class must be a torch.optim.Optimizer subclass, got {optimizer_class!r}")
    if optimizer_kwargs is not None and not isinstance(optimizer_kwargs, Mapping):
        raise ValueError(f"optimizer_kwargs must be a dict or None, got {type(optimizer_kwargs).__name__}")
    for name in ("lr", "params"):
        if name in (optimizer_kwargs or {}):
            raise ValueError(
                f"optimizer_kwargs must not contain {name!r}: the learning rates are learning_rate (the world "
                "models) and the config fields actor_critic.actor_lr, actor_critic.critic_lr and subgoal.lr "
                "(config_overrides)"
            )


def user_optimizer(
    groups: Sequence[tuple[Iterable[nn.Parameter], bool]],
    lr: float,
    eps: float,
    weight_decay: float,
    optimizer_class: type[th.optim.Optimizer] | None,
    optimizer_kwargs: Mapping[str, Any] | None,
) -> th.optim.Optimizer:
    """One learner's optimiser under ``optimizer_class`` (default ``torch.optim.AdamW``) and ``optimizer_kwargs``.

    It is ``optimizer_class(groups, lr=lr, eps=eps, **optimizer_kwargs)``: the configuration's learning rate, its
    ``eps`` for classes whose constructor takes one, and the user's keywords over them. Each parameter group carries
    its weight decay: ``optimizer_kwargs["weight_decay"]`` if given, else ``weight_decay``, for the groups that decay;
    0 for the others (norms, biases, S5 parameters). Classes without weight decay ignore it.

    :param groups: (parameters, whether they decay) per parameter group
    :param lr: the learner's learning rate
    :param eps: the learner's epsilon from the configuration
    :param weight_decay: the learner's weight decay from the configuration
    :param optimizer_class: a ``torch.optim.Optimizer`` subclass, or None for AdamW
    :param optimizer_kwargs: keywords of its constructor (not ``lr``), or None
    :return: the optimiser
    """
    check_optimizer_options(optimizer_class, optimizer_kwargs)
    cls = th.optim.AdamW if optimizer_class is None else optimizer_class
    kwargs = dict(optimizer_kwargs or {})
    decay = float(kwargs.pop("weight_decay", weight_decay))
    param_groups = [{"params": list(params), "weight_decay": decay if decays else 0.0} for params, decays in groups]
    if "eps" in inspect.signature(cls.__init__).parameters:
        kwargs.setdefault("eps", eps)
    return cls(param_groups, lr=lr, **kwargs)
