"""Guard against numerical blow-ups: an optimiser step is taken only when its loss and gradient norms are finite.

A single batch with a non-finite loss (or a gradient that overflows) would otherwise write NaN into the parameters
and the Adam moments, and every later update would inherit it. :func:`step_if_finite` skips such a step instead and
leaves the optimiser state untouched; the caller counts the skips (see :class:`~sb3_hieros.HIEROS`'s
``max_nonfinite_updates``).
"""

from __future__ import annotations

import torch as th

__all__ = ["step_if_finite"]


def step_if_finite(optimizer: th.optim.Optimizer, loss: th.Tensor, *grad_norms: th.Tensor | float) -> bool:
    """``optimizer.step()`` if ``loss`` and every gradient norm are finite; otherwise drop the gradients.

    Call it after ``backward`` and gradient clipping, in place of ``optimizer.step()``. The norms are those that
    ``torch.nn.utils.clip_grad_norm_`` returned: a NaN or inf gradient anywhere makes the total norm non-finite, so
    the gradients themselves need not be scanned. One host synchronisation per call.

    :param optimizer: the optimiser to step
    :param loss: the 0-d loss that was back-propagated
    :param grad_norms: total gradient norms of the parameters the optimiser updates (one per clipped group)
    :return: True if the step was taken, False if it was skipped (gradients set to None, no state changed)
    """
    values = [loss.detach().float().reshape(())]
    values += [th.as_tensor(n, device=loss.device).detach().float().reshape(()) for n in grad_norms]
    if bool(th.isfinite(th.stack(values)).all()):
        optimizer.step()
        return True
    optimizer.zero_grad(set_to_none=True)
    return False
