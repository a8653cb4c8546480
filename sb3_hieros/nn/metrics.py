"""Training metrics as Python floats with one device-to-host copy for all of them."""

from __future__ import annotations

from collections.abc import Mapping

import torch as th

__all__ = ["metric_floats"]


def metric_floats(tensors: Mapping[str, th.Tensor]) -> dict[str, float]:
    """0-d metric tensors as Python floats, with one device-to-host copy for all of them.

    :param tensors: name -> 0-d tensor
    :return: name -> float
    """
    names = list(tensors)
    if not names:
        return {}
    values = th.stack([tensors[k].detach().float().reshape(()) for k in names]).cpu().tolist()
    return dict(zip(names, values, strict=True))
