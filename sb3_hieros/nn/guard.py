"""Guard against numerical blow-ups: an optimiser step is taken only when its loss and gradient norms are finite.

A single batch with a non-finite loss (or a gradient that overflows) would otherwise write NaN into the parameters
and the Adam moments, and every later update would inherit it. :func:`step_if_finite` skips such a step instead and
leaves the optimiser state untouched; the caller counts the skips (see :class:`~sb3_hieros.HIEROS`'s
``max_nonfinite_updates``).
"""

from __future__ import annotations

from collections.abc import Mapping

import torch as th

__all__ = ["count_nonfinite", "nonfinite_error", "step_if_finite"]


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


#: metric prefix of each optimiser's loss and gradient norm (``wm/loss``, ``actor/grad_norm``, ...)
_METRIC_PREFIX = {"world_model": "wm", "actor": "actor", "critic": "critic", "autoencoder": "ae"}


def count_nonfinite(
    metrics: Mapping[str, float], level: int, skipped_updates: list[int], streak: list[int]
) -> list[str]:
    """Count an update of ``level`` whose metrics report a skipped optimiser step (``nonfinite/<name>`` = 1.0).

    :param metrics: the update's metrics (:meth:`~sb3_hieros.agent.subactor.Subactor.train_step`)
    :param level: the level that was updated
    :param skipped_updates: updates with a skipped step so far, per level (changed in place)
    :param streak: current run of such updates, per level (changed in place; reset by a clean update)
    :return: names of the optimisers whose step was skipped (empty for a clean update)
    """
    skipped = [key.split("/", 1)[1] for key, value in metrics.items() if key.startswith("nonfinite/") and value]
    if not skipped:
        streak[level] = 0
        return skipped
    skipped_updates[level] += 1
    streak[level] += 1
    return skipped


def nonfinite_error(
    metrics: Mapping[str, float], level: int, skipped: list[str], in_a_row: int, limit: int
) -> FloatingPointError:
    """The error that stops training after ``limit`` updates in a row with a skipped step, naming the losses.

    :param metrics: the last such update's metrics
    :param level: its level
    :param skipped: names of its skipped optimisers (:func:`count_nonfinite`)
    :param in_a_row: length of the run
    :param limit: ``HIEROS``'s ``max_nonfinite_updates``
    :return: the error to raise
    """
    details = []
    for name in skipped:
        prefix = _METRIC_PREFIX.get(name, name)
        values = [f"{key}={metrics[key]:.4g}" for key in (f"{prefix}/loss", f"{prefix}/grad_norm") if key in metrics]
        details.append(f"{name} loss ({', '.join(values)})" if values else f"{name} loss")
    return FloatingPointError(
        f"level {level}: {in_a_row} updates in a row had a non-finite loss or gradient "
        f"(max_nonfinite_updates={limit}); last skipped: {'; '.join(details)}. The "
        "parameters were left at their last finite values; check the environment's observations and rewards, "
        "or lower the learning rates"
    )
