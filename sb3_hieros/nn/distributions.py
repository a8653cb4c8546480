"""Output distributions and value transforms used by the world model and the actor-critic (DreamerV3 conventions).

Everything here is pure torch numerics:

* :func:`symlog` / :func:`symexp`: the squashing transform and its inverse.
* :class:`TwoHotSymlog`: 255-bin two-hot distribution over a scalar, bins uniformly spaced in symlog space on
  [-20, 20] (reward and value heads).
* :class:`OneHotCategoricalST`: one-hot categorical with a uniform mixture ("unimix", 1 %) and straight-through
  gradients, sampled by inverse CDF (the stochastic state z, discrete actions, subgoals).
* :func:`categorical_kl`: KL divergence between grouped categoricals (world-model KL, subgoal-AE KL).
* :class:`BoundedNormal`: Gaussian with ``tanh`` mean and sigmoid-bounded std for Box actions in [-1, 1].
* :class:`ContinueBernoulli`: Bernoulli head for the continue predictor.
* :func:`symlog_mse`: squared error in symlog space (vector observations).
"""

from __future__ import annotations

import math

import torch as th
import torch.nn.functional as F


def symlog(x: th.Tensor) -> th.Tensor:
    """Symmetric logarithm ``sign(x) * log(1 + |x|)``: compresses large magnitudes, identity-like near zero.

    :param x: any tensor
    :return: tensor of the same shape
    """
    return th.sign(x) * th.log1p(th.abs(x))


def symexp(x: th.Tensor) -> th.Tensor:
    """Inverse of :func:`symlog`: ``sign(x) * (exp(|x|) - 1)``.

    :param x: any tensor
    :return: tensor of the same shape
    """
    return th.sign(x) * th.expm1(th.abs(x))


def symlog_bins(
    num_bins: int = 255,
    low: float = -20.0,
    high: float = 20.0,
    device: th.device | str | None = None,
    dtype: th.dtype = th.float32,
) -> th.Tensor:
    """Bin centres of the two-hot encoding, uniformly spaced in symlog space.

    :param num_bins: number of bins (odd, so that 0 is a bin centre and a uniform distribution decodes to 0)
    :param low: lowest bin, in symlog space
    :param high: highest bin, in symlog space
    :param device: device of the result
    :param dtype: dtype of the result
    :return: (num_bins,) increasing bin centres in symlog space
    """
    if num_bins < 2 or num_bins % 2 == 0:
        raise ValueError(f"num_bins must be an odd integer >= 3, got {num_bins}")
    if not low < high:
        raise ValueError(f"need low < high, got low={low}, high={high}")
    bins = th.linspace(low, high, num_bins, device=device, dtype=th.float64)
    if low == -high:  # make the bins exactly antisymmetric, with an exact 0 in the centre
        bins = (bins - bins.flip(0)) / 2
    return bins.to(dtype)


def _check_bins(bins: th.Tensor) -> None:
    if bins.dim() != 1 or bins.numel() < 2:
        raise ValueError(f"bins must be a 1-d tensor with at least 2 entries, got shape {tuple(bins.shape)}")


def two_hot_neighbours(x: th.Tensor, bins: th.Tensor) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
    """The two bins around ``symlog(x)`` and the weight of the upper one (the sparse form of :func:`two_hot_encode`).

    :param x: (...) raw (not symlog'ed) scalars
    :param bins: (K,) increasing bin centres in symlog space, see :func:`symlog_bins`
    :return: (below, above, w_above), each (...): int64 indices of the lower and upper neighbour and the weight of
        the upper one in [0, 1] (the lower one gets ``1 - w_above``)
    """
    _check_bins(bins)
    y = symlog(x).clamp(bins[0], bins[-1])
    # index of the right neighbour, in [1, K-1]
    above = th.searchsorted(bins, y.detach().contiguous(), right=True).clamp(1, bins.numel() - 1)
    below = above - 1
    lo, hi = bins[below], bins[above]
    w_above = ((y - lo) / (hi - lo)).clamp(0.0, 1.0)
    return below, above, w_above


def two_hot_encode(x: th.Tensor, bins: th.Tensor) -> th.Tensor:
    """Two-hot encoding of ``symlog(x)`` on ``bins`` (which live in symlog space).

    The two neighbouring bins get weights that interpolate linearly, so ``(two_hot * bins).sum(-1) == symlog(x)``
    for every ``x`` whose symlog lies within ``[bins[0], bins[-1]]``; values outside are clamped to the end bins.

    :param x: (...) raw (not symlog'ed) scalars
    :param bins: (K,) increasing bin centres in symlog space, see :func:`symlog_bins`
    :return: (..., K) weights, two non-zero entries summing to 1
    """
    below, above, w_above = two_hot_neighbours(x, bins)
    out = th.zeros(*w_above.shape, bins.numel(), device=w_above.device, dtype=w_above.dtype)
    out.scatter_(-1, below.unsqueeze(-1), (1.0 - w_above).unsqueeze(-1))
    out.scatter_add_(-1, above.unsqueeze(-1), w_above.unsqueeze(-1))
    return out


def bins_are_antisymmetric(bins: th.Tensor) -> bool:
    """Whether ``bins[k] == -bins[K-1-k]`` for every k with an odd K (as :func:`symlog_bins` makes them).

    Reads the values (a host synchronisation on a GPU): modules check their constant bins once and hand the answer to
    :class:`TwoHotSymlog`.

    :param bins: (K,) bin centres
    :return: True for exactly antisymmetric bins around a centre bin of 0
    """
    num_bins = bins.numel()
    mid = (num_bins - 1) // 2
    return num_bins % 2 == 1 and th.equal(bins[mid + 1 :], -bins[:mid].flip(0))


def _symmetric_expectation(probs: th.Tensor, bins: th.Tensor, antisymmetric: bool | None = None) -> th.Tensor:
    """``(probs * bins).sum(-1)`` as one matrix-vector product, exactly 0 for a symmetric ``probs``.

    For antisymmetric bins (``bins[k] == -bins[K-1-k]``, as :func:`symlog_bins` makes them) the sum is computed as
    ``(p_right - flip(p_left)) @ bins_right``, so the uniform output of a zero-initialised head decodes to exactly
    0, which a plain left-to-right sum does not guarantee in floating point. Other bins use ``probs @ bins``.

    :param antisymmetric: :func:`bins_are_antisymmetric` of ``bins`` if known, or None to check it here
    """
    if antisymmetric is None:
        antisymmetric = bins_are_antisymmetric(bins)
    if antisymmetric:
        mid = (bins.numel() - 1) // 2
        return (probs[..., mid + 1 :] - probs[..., :mid].flip(-1)) @ bins[mid + 1 :]
    return probs @ bins


class TwoHotSymlog:
    """Categorical distribution over ``bins`` in symlog space, read out as a scalar by its expectation.

    Used by the reward and value heads (DreamerV3): the network outputs ``logits`` over the bins, the training target
    is the two-hot encoding of ``symlog(target)``, the prediction is ``symexp(E[bin])``.

    :param logits: (..., K) unnormalised log-probabilities over the bins (taken to float32, as in every distribution
        here, so that a bfloat16 network output is read out at full precision)
    :param bins: (K,) increasing bin centres in symlog space (:func:`symlog_bins`)
    :param antisymmetric: :func:`bins_are_antisymmetric` of ``bins`` if known (modules with constant bins check them
        once), or None to check it at each read-out
    """

    def __init__(self, logits: th.Tensor, bins: th.Tensor, antisymmetric: bool | None = None) -> None:
        _check_bins(bins)
        if logits.shape[-1:] != bins.shape:
            raise ValueError(
                f"logits must have last dim {bins.numel()} (the number of bins), got {tuple(logits.shape)}"
            )
        self.logits = logits.float()
        self.bins = bins
        self.antisymmetric = antisymmetric

    @property
    def probs(self) -> th.Tensor:
        """(..., K) bin probabilities."""
        return th.softmax(self.logits, -1)

    @property
    def mean(self) -> th.Tensor:
        """(...) decoded expectation ``symexp(sum_k p_k * bin_k)``, in raw (not symlog) units."""
        return symexp(_symmetric_expectation(self.probs, self.bins, self.antisymmetric))

    def mode(self) -> th.Tensor:
        """(...) same as :attr:`mean` (the DreamerV3 read-out)."""
        return self.mean

    def log_prob(self, target: th.Tensor) -> th.Tensor:
        """Log-likelihood of raw targets under the two-hot cross-entropy.

        :param target: (...) raw scalars (gradient is not propagated into them)
        :return: (...) ``sum_k two_hot(target)_k * log_softmax(logits)_k``
        """
        if target.shape != self.logits.shape[:-1]:
            raise ValueError(
                f"target shape {tuple(target.shape)} must equal the batch shape of logits "
                f"{tuple(self.logits.shape[:-1])}"
            )
        below, above, w_above = two_hot_neighbours(target.detach(), self.bins)
        log_probs = th.log_softmax(self.logits, -1)
        lp_below = log_probs.gather(-1, below.unsqueeze(-1)).squeeze(-1)
        lp_above = log_probs.gather(-1, above.unsqueeze(-1)).squeeze(-1)
        return lp_below + w_above * (lp_above - lp_below)


def unimix_probs(logits: th.Tensor, unimix: float) -> th.Tensor:
    """Softmax probabilities mixed with a uniform distribution: ``(1 - unimix) * softmax(logits) + unimix / K``.

    :param logits: (..., K)
    :param unimix: mixing fraction in [0, 1)
    :return: (..., K) probabilities
    """
    if not 0.0 <= unimix < 1.0:
        raise ValueError(f"unimix must be in [0, 1), got {unimix}")
    probs = th.softmax(logits, -1)
    if unimix > 0.0:
        probs = (1.0 - unimix) * probs + unimix / logits.shape[-1]
    return probs


def sample_categorical_index(probs: th.Tensor, generator: th.Generator | None = None) -> th.Tensor:
    """Draw one class index per row by inverse-CDF: ``(cumsum(p) < u).sum(-1)`` with ``u ~ U[0, 1)``.

    Same distribution as ``torch.multinomial`` but much faster for many small categoricals (no per-row kernel
    launch). The index is clamped to K-1 in case rounding leaves ``cumsum(p)[-1] < u``.

    :param probs: (..., K) probabilities (rows sum to 1)
    :param generator: optional torch generator for reproducible draws
    :return: (...) int64 indices
    """
    u = th.rand((*probs.shape[:-1], 1), device=probs.device, dtype=probs.dtype, generator=generator)
    index = (th.cumsum(probs, -1) < u).sum(-1)
    return index.clamp_(max=probs.shape[-1] - 1)


class OneHotCategoricalST:
    """One-hot categorical with uniform mixing and straight-through gradients (DreamerV2/V3).

    Samples and modes are exact one-hot vectors in the forward pass whose gradient is that of the probabilities
    (``one_hot + (probs - probs.detach())``). With ``event_ndims = 1`` and logits of shape (..., G, K) it is a
    product of G independent categoricals (e.g. z of 32 x 32 or a subgoal of 8 x 8): :meth:`log_prob` and
    :meth:`entropy` then sum over the G groups.

    :param logits: (..., K) or (..., G, K) unnormalised log-probabilities
    :param unimix: fraction of the uniform distribution mixed into the probabilities (DreamerV3: 0.01)
    :param event_ndims: number of dims left of K that belong to the event (summed in log_prob / entropy)
    """

    def __init__(self, logits: th.Tensor, unimix: float = 0.01, event_ndims: int = 0) -> None:
        if logits.dim() < 1 + event_ndims:
            raise ValueError(f"logits of shape {tuple(logits.shape)} have too few dims for event_ndims={event_ndims}")
        if event_ndims < 0:
            raise ValueError(f"event_ndims must be >= 0, got {event_ndims}")
        self.unimix, self.event_ndims = unimix, event_ndims
        self._raw_logits = logits = logits.float()
        self.probs = unimix_probs(logits, unimix)
        self._logits: th.Tensor | None = None

    @property
    def logits(self) -> th.Tensor:
        """(..., K) log of the (mixed) probabilities: normalised logits, usable in :func:`categorical_kl`."""
        if self._logits is None:  # computed lazily: sampling does not need it
            self._logits = th.log(self.probs) if self.unimix > 0.0 else th.log_softmax(self._raw_logits, -1)
        return self._logits

    @property
    def num_classes(self) -> int:
        """Number of classes K."""
        return self.probs.shape[-1]

    def _reduce(self, x: th.Tensor) -> th.Tensor:
        return x.sum(tuple(range(-self.event_ndims, 0))) if self.event_ndims > 0 else x

    def _straight_through(self, index: th.Tensor) -> th.Tensor:
        one_hot = th.zeros_like(self.probs).scatter_(-1, index.unsqueeze(-1), 1.0)
        if not self.probs.requires_grad:
            return one_hot
        # (probs - probs.detach()) is exactly 0 in the forward pass, so the value is an exact one-hot
        return one_hot + (self.probs - self.probs.detach())

    def sample(self, generator: th.Generator | None = None) -> th.Tensor:
        """One-hot sample with straight-through gradient to the probabilities.

        :param generator: optional torch generator
        :return: (..., K) or (..., G, K) one-hot
        """
        return self._straight_through(sample_categorical_index(self.probs.detach(), generator))

    rsample = sample

    def mode(self) -> th.Tensor:
        """One-hot of the most likely class, with straight-through gradient (the deterministic action)."""
        return self._straight_through(self.probs.argmax(-1))

    def log_prob(self, one_hot: th.Tensor) -> th.Tensor:
        """Log-probability of one-hot values.

        :param one_hot: same shape as the logits
        :return: batch-shaped log-probabilities (summed over the event dims)
        """
        if one_hot.shape != self.probs.shape:
            raise ValueError(f"one_hot shape {tuple(one_hot.shape)} must equal logits shape {tuple(self.probs.shape)}")
        return self._reduce((one_hot * self.logits).sum(-1))

    def entropy(self) -> th.Tensor:
        """Entropy (nats), summed over the event dims."""
        return self._reduce(-(self.probs * self.logits).sum(-1))


def categorical_kl(logits_p: th.Tensor, logits_q: th.Tensor, group_dims: int = 1) -> th.Tensor:
    """``KL(p || q)`` between categoricals given by logits, summed over the classes and ``group_dims`` group dims.

    The logits are normalised with ``log_softmax`` (no unimix is added here: pass ``OneHotCategoricalST(...).logits``,
    which already are the log of the mixed probabilities, to get the KL of the mixed distributions). For the world
    model's z of shape (..., 32, 32) the default ``group_dims = 1`` returns the KL of the joint (sum over 32 groups).
    ``logits_q`` broadcasts against ``logits_p`` (e.g. ``zeros(K)`` for a uniform prior).

    :param logits_p: (..., G, K)
    :param logits_q: broadcastable to ``logits_p``
    :param group_dims: number of dims left of K to sum over (0 for a single categorical)
    :return: (...) KL in nats, non-negative
    """
    if logits_p.dim() < 1 + group_dims:
        raise ValueError(f"logits_p of shape {tuple(logits_p.shape)} has too few dims for group_dims={group_dims}")
    if logits_q.shape[-1] != logits_p.shape[-1]:
        raise ValueError(f"class dims differ: logits_p {tuple(logits_p.shape)} vs logits_q {tuple(logits_q.shape)}")
    log_p = th.log_softmax(logits_p, -1)
    log_q = th.log_softmax(logits_q, -1)
    kl = (log_p.exp() * (log_p - log_q)).sum(-1)
    return kl.sum(tuple(range(-group_dims, 0))) if group_dims > 0 else kl


class BoundedNormal:
    """Diagonal Gaussian for Box actions in [-1, 1] (DreamerV3 ``normal`` actor).

    ``mean = tanh(mean_raw)`` and ``std = (max_std - min_std) * sigmoid(std_raw + 2) + min_std``. Samples are
    reparameterised and then clipped to [-1, 1] with a straight-through clip (the forward value is clipped, the gradient
    is that of the unclipped sample), so actions always lie in [-1, 1]; the policy rescales them to the env bounds.
    ``log_prob`` and ``entropy`` are those of the unclipped Gaussian, summed over the action dims.

    :param mean_raw: (..., A) unsquashed means
    :param std_raw: (..., A) unbounded std parameters
    :param min_std: lower std bound (DreamerV3: 0.1)
    :param max_std: upper std bound (DreamerV3: 1.0)
    """

    def __init__(self, mean_raw: th.Tensor, std_raw: th.Tensor, min_std: float = 0.1, max_std: float = 1.0) -> None:
        if mean_raw.shape != std_raw.shape:
            raise ValueError(f"mean_raw {tuple(mean_raw.shape)} and std_raw {tuple(std_raw.shape)} must match")
        if not 0.0 < min_std < max_std:
            raise ValueError(f"need 0 < min_std < max_std, got min_std={min_std}, max_std={max_std}")
        self.mean = th.tanh(mean_raw.float())
        self.std = (max_std - min_std) * th.sigmoid(std_raw.float() + 2.0) + min_std

    def rsample(self, generator: th.Generator | None = None) -> th.Tensor:
        """Reparameterised sample in [-1, 1] (straight-through clip).

        :param generator: optional torch generator
        :return: (..., A)
        """
        noise = th.randn(self.mean.shape, device=self.mean.device, dtype=self.mean.dtype, generator=generator)
        x = self.mean + self.std * noise
        return x.detach().clamp(-1.0, 1.0) + (x - x.detach())

    sample = rsample

    def mode(self) -> th.Tensor:
        """The mean ``tanh(mean_raw)``, in [-1, 1] (float rounding reaches the ends for large ``mean_raw``)."""
        return self.mean

    def log_prob(self, action: th.Tensor) -> th.Tensor:
        """Gaussian log-density of ``action``, summed over the last dim.

        :param action: (..., A)
        :return: (...)
        """
        if action.shape != self.mean.shape:
            raise ValueError(f"action shape {tuple(action.shape)} must equal {tuple(self.mean.shape)}")
        z = (action - self.mean) / self.std
        return (-0.5 * z.pow(2) - th.log(self.std) - 0.5 * math.log(2 * math.pi)).sum(-1)

    def entropy(self) -> th.Tensor:
        """Gaussian entropy, summed over the last dim: (...)."""
        return (0.5 + 0.5 * math.log(2 * math.pi) + th.log(self.std)).sum(-1)


class ContinueBernoulli:
    """Bernoulli distribution from logits, for the continue predictor (1 = episode continues).

    :param logits: (...) logits of the probability of 1
    """

    def __init__(self, logits: th.Tensor) -> None:
        self.logits = logits.float()

    @property
    def mean(self) -> th.Tensor:
        """(...) probability of 1."""
        return th.sigmoid(self.logits)

    def mode(self) -> th.Tensor:
        """(...) 1.0 where the probability is above 0.5, else 0.0."""
        return (self.logits > 0).to(self.logits.dtype)

    def log_prob(self, target: th.Tensor) -> th.Tensor:
        """Log-likelihood of targets in [0, 1] (soft targets allowed).

        :param target: (...) same shape as the logits
        :return: (...)
        """
        if target.shape != self.logits.shape:
            raise ValueError(f"target shape {tuple(target.shape)} must equal logits shape {tuple(self.logits.shape)}")
        return -F.binary_cross_entropy_with_logits(self.logits, target.to(self.logits.dtype), reduction="none")

    def entropy(self) -> th.Tensor:
        """(...) entropy in nats."""
        return F.binary_cross_entropy_with_logits(self.logits, self.mean, reduction="none")


def symlog_mse(prediction: th.Tensor, target: th.Tensor, event_ndims: int = 1) -> th.Tensor:
    """Squared error between a prediction in symlog space and ``symlog(target)``, summed over the event dims.

    This is the negative log-likelihood (up to a constant) of DreamerV3's symlog-MSE heads for vector observations;
    decode a prediction with :func:`symexp`.

    :param prediction: (..., *event) network output, in symlog space
    :param target: same shape, raw units
    :param event_ndims: number of trailing dims summed over
    :return: (...) per-sample loss
    """
    if prediction.shape != target.shape:
        raise ValueError(f"prediction {tuple(prediction.shape)} and target {tuple(target.shape)} must match")
    if not 0 <= event_ndims <= prediction.dim():
        raise ValueError(f"event_ndims must be in [0, {prediction.dim()}], got {event_ndims}")
    err = (prediction.float() - symlog(target)).pow(2)
    return err.sum(tuple(range(-event_ndims, 0))) if event_ndims > 0 else err
