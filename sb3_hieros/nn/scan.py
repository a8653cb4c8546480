"""The resettable scan of the S5 layer (thesis 4.4.2): x_t = (1 - d_t) * Lambda_bar * x_{t-1} + B_bar u_t.

:func:`resettable_scan` is what :class:`~sb3_hieros.nn.s5.S5Layer` runs in eager mode: the odd/even O(T) scan with a
hand-written backward (the adjoint of the recurrence is the same scan run backwards in time with
``conj(Lambda_bar)``). :func:`associative_scan_resettable` is the same scan under autograd,
:func:`associative_scan_resettable_real` and :func:`s5_parallel_real_split` its real-split form for ``torch.compile``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = [
    "associative_scan_resettable",
    "associative_scan_resettable_real",
    "resettable_scan",
    "s5_parallel_real_split",
]


def _interleave(even: torch.Tensor, odd: torch.Tensor, length: int) -> torch.Tensor:
    """Merge ``even`` (positions 0, 2, ...) and ``odd`` (positions 1, 3, ...) along dim 1 into ``length`` steps."""
    batch, rest = even.shape[0], even.shape[2:]
    if length % 2 == 0:
        return torch.stack((even, odd), dim=2).reshape(batch, length, *rest)
    pairs = torch.stack((even[:, :-1], odd), dim=2).reshape(batch, length - 1, *rest)
    return torch.cat((pairs, even[:, -1:]), dim=1)


def associative_scan_resettable(
    lambda_bar: torch.Tensor,
    keep: torch.Tensor,
    bu: torch.Tensor,
    initial_state: torch.Tensor | None = None,
) -> torch.Tensor:
    """All states of ``x_t = keep_t * lambda_bar ⊙ x_{t-1} + bu_t`` by a log-depth associative scan (thesis 2.4.3).

    This is the resettable S5 operator of Lu et al. (2024) with the reset folded into the transition:
    ``A_t = lambda_bar * (1 - reset_t)``. The scan follows the odd/even recursion of
    ``jax.lax.associative_scan`` (O(T) work, 2 log2(T) depth): adjacent pairs are combined, the half-length
    sequence is scanned recursively, and the even positions are filled in from their left neighbour.
    Because ``lambda_bar`` is the same at every step, a combined element spanning ``2^k`` steps has transition
    ``lambda_bar^(2^k)`` times the product of its ``keep`` flags, so only the flags ``(B, T, 1)`` are carried
    through the recursion instead of a full ``(B, T, P)`` complex transition tensor.

    :param lambda_bar: discretised diagonal transition ``(P,)`` complex
    :param keep: ``1 - reset`` as a real tensor ``(B, T, 1)``
    :param bu: the inputs ``B_bar u_t`` ``(B, T, P)`` complex
    :param initial_state: state before step 0 ``(B, P)`` complex, or None for zeros
    :return: the states ``x_0 .. x_{T-1}`` ``(B, T, P)`` complex
    """
    length = bu.shape[1]
    if length == 1:
        if initial_state is None:
            return bu
        return bu + lambda_bar * (initial_state.unsqueeze(1) * keep)
    keep_odd = keep[:, 1::2]
    # Pairs (0,1), (2,3), ...: transition lambda_bar^2 * keep_0 * keep_1, input lambda_bar * keep_1 * bu_0 + bu_1.
    pair_input = lambda_bar * (bu[:, 0:-1:2] * keep_odd) + bu[:, 1::2]
    odd = associative_scan_resettable(lambda_bar * lambda_bar, keep_odd * keep[:, 0:-1:2], pair_input, initial_state)
    # x_0 from the initial state; x_{2i} = lambda_bar * keep_{2i} * x_{2i-1} + bu_{2i} for i >= 1.
    first = bu[:, :1]
    if initial_state is not None:
        first = first + lambda_bar * (initial_state.unsqueeze(1) * keep[:, :1])
    n_even_rest = (length - 1) // 2
    even_rest = lambda_bar * (odd[:, :n_even_rest] * keep[:, 2::2]) + bu[:, 2::2]
    even = torch.cat((first, even_rest), dim=1)
    return _interleave(even, odd, length)


class _ResettableScanFunction(torch.autograd.Function):
    """:func:`associative_scan_resettable` with a hand-written backward (see :func:`resettable_scan`)."""

    @staticmethod
    def forward(
        ctx: torch.autograd.function.FunctionCtx,
        lambda_bar: torch.Tensor,
        keep: torch.Tensor,
        bu: torch.Tensor,
        initial_state: torch.Tensor | None,
    ) -> torch.Tensor:
        states = associative_scan_resettable(lambda_bar, keep, bu, initial_state)  # (B, T, P)
        ctx.save_for_backward(lambda_bar, keep, states, initial_state)
        return states

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(
        ctx: torch.autograd.function.FunctionCtx, grad_states: torch.Tensor
    ) -> tuple[torch.Tensor | None, None, torch.Tensor, torch.Tensor | None]:
        lambda_bar, keep, states, initial_state = ctx.saved_tensors
        # Adjoint recurrence G_t = g_t + conj(lambda_bar) keep_{t+1} G_{t+1}: the same scan on the time-reversed
        # sequence, whose step s carries the flag keep_{T-s} (the first reversed step has no carry-in).
        keep_reversed = torch.cat((torch.ones_like(keep[:, :1]), keep.flip(1)[:, :-1]), 1)
        grad_bu = associative_scan_resettable(lambda_bar.conj(), keep_reversed, grad_states.flip(1)).flip(1)
        grad_lambda = grad_initial = None
        if ctx.needs_input_grad[0]:
            first = torch.zeros_like(states[:, :1]) if initial_state is None else initial_state.unsqueeze(1)
            carried = torch.cat((first, states[:, :-1]), 1) * keep  # keep_t x_{t-1}, (B, T, P)
            grad_lambda = (grad_bu * carried.conj()).sum((0, 1))
        if initial_state is not None and ctx.needs_input_grad[3]:
            grad_initial = lambda_bar.conj() * keep[:, 0] * grad_bu[:, 0]
        return grad_lambda, None, grad_bu, grad_initial


def resettable_scan(
    lambda_bar: torch.Tensor,
    keep: torch.Tensor,
    bu: torch.Tensor,
    initial_state: torch.Tensor | None = None,
) -> torch.Tensor:
    """:func:`associative_scan_resettable` (same arguments and result) with a hand-written backward pass.

    The adjoint of the linear recurrence ``x_t = keep_t * lambda_bar * x_{t-1} + bu_t`` is the same recurrence run
    backwards in time with ``conj(lambda_bar)``: ``G_t = g_t + conj(lambda_bar) keep_{t+1} G_{t+1}`` gives the
    gradient of ``bu_t``; ``lambda_bar`` gets ``sum_t G_t conj(keep_t x_{t-1})`` and the initial state
    ``conj(lambda_bar) keep_0 G_0``. So the backward is one more log-depth scan, instead of autograd replaying every
    slice, product and concatenation of the recursion; the forward keeps no intermediates. Not twice differentiable.

    :param lambda_bar: discretised diagonal transition ``(P,)`` complex
    :param keep: ``1 - reset`` as a real tensor ``(B, T, 1)`` (no gradient)
    :param bu: the inputs ``B_bar u_t`` ``(B, T, P)`` complex
    :param initial_state: state before step 0 ``(B, P)`` complex, or None for zeros
    :return: the states ``x_0 .. x_{T-1}`` ``(B, T, P)`` complex
    """
    return _ResettableScanFunction.apply(lambda_bar, keep, bu, initial_state)


def _complex_mul(
    a_re: torch.Tensor, a_im: torch.Tensor, b_re: torch.Tensor, b_im: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(a_re + i a_im) * (b_re + i b_im)`` on real tensors."""
    return a_re * b_re - a_im * b_im, a_re * b_im + a_im * b_re


def associative_scan_resettable_real(
    lambda_re: torch.Tensor,
    lambda_im: torch.Tensor,
    keep: torch.Tensor,
    bu_re: torch.Tensor,
    bu_im: torch.Tensor,
    initial_re: torch.Tensor | None = None,
    initial_im: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``associative_scan_resettable`` on separate real and imaginary parts (no complex dtype anywhere).

    The same odd/even recursion; this layout is what ``torch.compile`` (Inductor) can generate code for.

    :param lambda_re: real part of ``lambda_bar`` ``(P,)``
    :param lambda_im: imaginary part of ``lambda_bar`` ``(P,)``
    :param keep: ``1 - reset`` ``(B, T, 1)``
    :param bu_re: real part of ``B_bar u`` ``(B, T, P)``
    :param bu_im: imaginary part of ``B_bar u`` ``(B, T, P)``
    :param initial_re: real part of the state before step 0 ``(B, P)``, or None (then ``initial_im`` is None too)
    :param initial_im: imaginary part of that state
    :return: real and imaginary parts of the states ``(B, T, P)`` each
    """
    length = bu_re.shape[1]
    first_re, first_im = bu_re[:, :1], bu_im[:, :1]
    if initial_re is not None and initial_im is not None:
        carry_re, carry_im = _complex_mul(
            lambda_re, lambda_im, initial_re.unsqueeze(1) * keep[:, :1], initial_im.unsqueeze(1) * keep[:, :1]
        )
        first_re, first_im = first_re + carry_re, first_im + carry_im
    if length == 1:
        return first_re, first_im
    keep_odd = keep[:, 1::2]
    pair_re, pair_im = _complex_mul(lambda_re, lambda_im, bu_re[:, 0:-1:2] * keep_odd, bu_im[:, 0:-1:2] * keep_odd)
    odd_re, odd_im = associative_scan_resettable_real(
        *_complex_mul(lambda_re, lambda_im, lambda_re, lambda_im),
        keep_odd * keep[:, 0:-1:2],
        pair_re + bu_re[:, 1::2],
        pair_im + bu_im[:, 1::2],
        initial_re,
        initial_im,
    )
    n_even_rest = (length - 1) // 2
    keep_even = keep[:, 2::2]
    rest_re, rest_im = _complex_mul(
        lambda_re, lambda_im, odd_re[:, :n_even_rest] * keep_even, odd_im[:, :n_even_rest] * keep_even
    )
    even_re = torch.cat((first_re, rest_re + bu_re[:, 2::2]), dim=1)
    even_im = torch.cat((first_im, rest_im + bu_im[:, 2::2]), dim=1)
    return _interleave(even_re, odd_re, length), _interleave(even_im, odd_im, length)


def s5_parallel_real_split(
    u: torch.Tensor,
    keep: torch.Tensor,
    state: torch.Tensor | None,
    log_neg_lambda_real: torch.Tensor,
    lambda_imag: torch.Tensor,
    b: torch.Tensor,
    c: torch.Tensor,
    d: torch.Tensor,
    log_step: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Parallel form of one S5 layer in real arithmetic only (ZOH + scan + readout, thesis 2.4.3).

    The same maths as ``S5Layer.forward`` with the parameters passed in, so that one ``torch.compile``d
    graph serves every layer of equal shape (see ``compile_s5``); Inductor does not generate code for complex
    dtypes.

    :param u: inputs ``(B, T, H)``
    :param keep: ``1 - reset`` ``(B, T, 1)``
    :param state: ``view_as_real`` of the state before step 0 ``(B, P, 2)``, or None
    :param log_neg_lambda_real: ``(P,)``, ``Re(Lambda) = -exp(.)``
    :param lambda_imag: ``(P,)``
    :param b: ``(P, H, 2)``
    :param c: ``(H, P, 2)``
    :param d: ``(H,)``
    :param log_step: ``(P,)``
    :return: outputs ``(B, T, H)`` and the states as (real, imaginary) pairs ``(B, T, P, 2)``
    """
    batch, length, d_model = u.shape
    d_state = b.shape[0]
    # ZOH: Lambda_bar = exp(Lambda Delta); B_bar = (Lambda_bar - 1) * conj(Lambda) / |Lambda|^2 * B.
    lam_re = -torch.exp(log_neg_lambda_real)
    step = torch.exp(log_step)
    magnitude, phase = torch.exp(lam_re * step), lambda_imag * step
    bar_re, bar_im = magnitude * torch.cos(phase), magnitude * torch.sin(phase)
    inv_norm = 1.0 / (lam_re * lam_re + lambda_imag * lambda_imag)
    scale_re, scale_im = _complex_mul(bar_re - 1.0, bar_im, lam_re * inv_norm, -lambda_imag * inv_norm)
    b_re, b_im = _complex_mul(scale_re.unsqueeze(-1), scale_im.unsqueeze(-1), b[..., 0], b[..., 1])
    w_in = torch.stack((b_re, b_im), dim=1).reshape(2 * d_state, d_model)
    w_out = torch.stack((c[..., 0], -c[..., 1]), dim=-1).reshape(d_model, 2 * d_state)

    bu = F.linear(u, w_in).view(batch, length, d_state, 2)
    states_re, states_im = associative_scan_resettable_real(
        bar_re,
        bar_im,
        keep,
        bu[..., 0],
        bu[..., 1],
        None if state is None else state[..., 0],
        None if state is None else state[..., 1],
    )
    states = torch.stack((states_re, states_im), dim=-1)  # (B, T, P, 2)
    y = F.linear(states.reshape(batch, length, 2 * d_state), w_out) + u * d
    return y, states
