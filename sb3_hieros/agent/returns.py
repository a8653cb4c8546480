"""Returns of an imagined trajectory and their normalisation (DreamerV3, as HIEROS adopts it; thesis 4.3.2)."""

from __future__ import annotations

import torch as th
from torch import nn

__all__ = ["ReturnNormalizer", "cumulative_discount", "lambda_returns", "replay_lambda_returns"]


def lambda_returns(
    rewards: th.Tensor,
    values: th.Tensor,
    continues: th.Tensor,
    bootstrap: th.Tensor,
    discount: float = 0.997,
    lambda_: float = 0.95,
    cut: th.Tensor | None = None,
) -> th.Tensor:
    r"""TD(lambda) returns of an imagined trajectory s_0 .. s_H, time-major (DreamerV3 definition).

    .. math::
        R_t = r_{t+1} + \gamma c_{t+1} \left[(1 - \lambda) v(s_{t+1}) + \lambda R_{t+1}\right], \qquad R_H = v(s_H)

    for t = 0 .. H-1. The reward and continue flag of a step are those of the state it *arrives at* (s_{t+1}); the
    reference implementation uses r(s_t), c(s_t) instead, which is off by one.

    Inputs are aligned with the returns, so the advantage is simply ``returns - values``:

    :param rewards: (H, *B) ``rewards[t]`` = r_{t+1}, the reward predicted for s_{t+1}
    :param values: (H, *B) ``values[t]`` = v(s_t); ``values[1:]`` enter the recursion, ``values[0]`` is only the
        baseline of R_0
    :param continues: (H, *B) ``continues[t]`` = c_{t+1} in [0, 1], the probability that the episode goes on at s_{t+1}
    :param bootstrap: (*B) v(s_H), the value of the last imagined state
    :param discount: gamma
    :param lambda_: lambda in [0, 1]; 0 gives one-step TD targets, 1 Monte-Carlo returns bootstrapped at s_H
    :param cut: (H, *B) bool or None; where ``cut[t]``, s_t does not lead to s_{t+1} (a replayed sequence that
        crosses an episode start) and R_t = ``values[t]``, which the earlier returns then bootstrap from
    :return: (H, *B) returns R_0 .. R_{H-1}
    """
    if rewards.dim() < 1 or rewards.shape[0] < 1:
        raise ValueError(f"rewards must have shape (H, *B) with H >= 1, got {tuple(rewards.shape)}")
    if values.shape != rewards.shape or continues.shape != rewards.shape:
        raise ValueError(
            f"rewards {tuple(rewards.shape)}, values {tuple(values.shape)} and continues {tuple(continues.shape)} "
            "must have the same (H, *B) shape"
        )
    if bootstrap.shape != rewards.shape[1:]:
        raise ValueError(f"bootstrap must have shape {tuple(rewards.shape[1:])}, got {tuple(bootstrap.shape)}")
    if not 0.0 <= lambda_ <= 1.0:
        raise ValueError(f"lambda_ must be in [0, 1], got {lambda_}")
    if cut is not None and cut.shape != rewards.shape:
        raise ValueError(f"cut must have the shape of rewards {tuple(rewards.shape)}, got {tuple(cut.shape)}")
    disc = discount * continues
    next_values = th.cat([values[1:], bootstrap.unsqueeze(0)], 0)
    inputs = rewards + disc * (1.0 - lambda_) * next_values
    last = bootstrap
    returns = []
    for t in reversed(range(rewards.shape[0])):
        last = inputs[t] + disc[t] * lambda_ * last
        if cut is not None:
            last = th.where(cut[t], values[t], last)
        returns.append(last)
    return th.stack(returns[::-1], 0)


def replay_lambda_returns(
    rewards: th.Tensor,
    continues: th.Tensor,
    is_first: th.Tensor,
    bootstrap: th.Tensor,
    discount: float = 0.997,
    lambda_: float = 0.95,
) -> tuple[th.Tensor, th.Tensor]:
    r"""TD(lambda) returns along replayed sequences s_0 .. s_{T-1}, bootstrapped with imagination's returns
    (DreamerV3's replay value loss; not in the thesis).

    .. math::
        R_t = r_{t+1} + \gamma c_{t+1} \left[(1 - \lambda) b_{t+1} + \lambda R_{t+1}\right], \qquad R_{T-1} = b_{T-1}

    where b_t is the bootstrap of s_t (DreamerV3: the imagined lambda-return R_0 of a rollout started at s_t). Where
    s_{t+1} starts a new episode, the sequence is cut: R_t = b_t, and such rows, like the last one, carry no target
    of their own (``valid`` is False there).

    :param rewards: (T, *B) ``rewards[t]`` = r_t, the reward received with s_t (index 0 unused)
    :param continues: (T, *B) ``continues[t]`` = c_t, 0 where s_t is terminal
    :param is_first: (T, *B) bool, episode starts
    :param bootstrap: (T, *B) b_t
    :param discount: gamma
    :param lambda_: lambda in [0, 1]
    :return: the returns (T, *B) and ``valid`` (T, *B) bool, the rows whose return reaches past their bootstrap
    """
    if rewards.dim() < 1 or rewards.shape[0] < 2:
        raise ValueError(f"rewards must have shape (T, *B) with T >= 2, got {tuple(rewards.shape)}")
    for name, x in (("continues", continues), ("is_first", is_first), ("bootstrap", bootstrap)):
        if x.shape != rewards.shape:
            raise ValueError(f"{name} must have the shape of rewards {tuple(rewards.shape)}, got {tuple(x.shape)}")
    crossing = is_first[1:].bool()  # (T-1, *B): s_{t+1} starts a new episode
    returns = lambda_returns(
        rewards[1:], bootstrap[:-1], continues[1:], bootstrap[-1], discount, lambda_, cut=crossing
    )  # R_0 .. R_{T-2}
    valid = th.cat([~crossing, th.zeros_like(crossing[:1])], 0)
    return th.cat([returns, bootstrap[-1:]], 0), valid


def cumulative_discount(continues: th.Tensor, discount: float = 0.997) -> th.Tensor:
    r"""Loss weights of the imagined states, ``w_t = c_0 \prod_{j=1}^{t} \gamma c_j`` (DreamerV3).

    A state after a predicted episode end gets (almost) zero weight; the start state s_0 has weight c_0.

    :param continues: (H+1, *B) continue probabilities of s_0 .. s_H
    :param discount: gamma
    :return: (H+1, *B) detached weights
    """
    if discount <= 0.0:
        raise ValueError(f"discount must be > 0, got {discount}")
    continues = continues.detach()
    return th.cumprod(discount * continues, 0) / discount


class ReturnNormalizer(nn.Module):
    """Return scale S = EMA(P_high) - EMA(P_low) of the lambda-returns, floored at ``min_scale`` (DreamerV3).

    The percentiles of each batch of returns are tracked with an exponential moving average (decay 0.99, started
    from 0 without bias correction, as in DreamerV3). Advantages are divided by ``max(min_scale, S)``, which shrinks
    large returns but never amplifies small ones. The EMAs are persistent float buffers, saved with the model.

    :param decay: EMA decay in [0, 1)
    :param percentiles: (low, high) percentiles in [0, 100]
    :param min_scale: floor of the scale (DreamerV3: 1)
    """

    low: th.Tensor
    high: th.Tensor

    def __init__(
        self, decay: float = 0.99, percentiles: tuple[float, float] = (5.0, 95.0), min_scale: float = 1.0
    ) -> None:
        super().__init__()
        if not 0.0 <= decay < 1.0:
            raise ValueError(f"decay must be in [0, 1), got {decay}")
        if not 0.0 <= percentiles[0] < percentiles[1] <= 100.0:
            raise ValueError(f"percentiles must satisfy 0 <= low < high <= 100, got {percentiles}")
        if min_scale <= 0.0:
            raise ValueError(f"min_scale must be > 0, got {min_scale}")
        self.decay = decay
        self.percentiles = (float(percentiles[0]), float(percentiles[1]))
        self.min_scale = min_scale
        self.register_buffer("low", th.zeros(()))
        self.register_buffer("high", th.zeros(()))

    @th.no_grad()
    def update(self, returns: th.Tensor) -> None:
        """Move the percentile EMAs towards the percentiles of ``returns`` (any shape, non-empty).

        :param returns: a batch of returns
        """
        if returns.numel() == 0:
            raise ValueError("returns must be non-empty")
        q = th.tensor([self.percentiles[0] / 100.0, self.percentiles[1] / 100.0], device=returns.device)
        low, high = th.quantile(returns.detach().reshape(-1).float(), q)
        self.low.mul_(self.decay).add_((1.0 - self.decay) * low.to(self.low.dtype))
        self.high.mul_(self.decay).add_((1.0 - self.decay) * high.to(self.high.dtype))

    def scale(self) -> th.Tensor:
        """0-d ``max(min_scale, high - low)`` (detached)."""
        return th.clamp(self.high - self.low, min=self.min_scale).detach()

    def forward(self, returns: th.Tensor, update: bool = True) -> tuple[th.Tensor, th.Tensor]:
        """Optionally update with ``returns``, then return the current statistics.

        :param returns: a batch of returns
        :param update: update the EMAs first
        :return: (offset = EMA of the low percentile, scale = max(min_scale, S)), both detached 0-d tensors
        """
        if update:
            self.update(returns)
        return self.low.detach().clone(), self.scale()
