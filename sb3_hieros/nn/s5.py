"""Resettable S5 sequence model (thesis sections 2.4.3, 4.1.2 and 4.4.2).

S5 (Smith et al., 2022) is a linear state space layer with a diagonal complex state of size P,
discretised with zero-order hold (ZOH) and evaluated with a log-depth parallel scan in training and one
step at a time in acting and imagination. The reset of Lu et al. (2024) zeroes the state carried into a
step that starts a new episode, so a training chunk may span episode borders without information leaking
across them (thesis 4.4.2). HIEROS uses the per-layer internal states as the deterministic world-model
state h_t (thesis 4.1.2, 5.3.5), so every forward pass returns them.

Recurrence of one layer, for t = 0..T-1 with input u_t in R^H, state x_t in C^P and reset flag d_t::

    x_t = (1 - d_t) * Lambda_bar ⊙ x_{t-1} + B_bar u_t        (x_{-1} = given state, or 0)
    y_t = Re(C x_t) + D ⊙ u_t

Differences to the public reference implementation:

* Re(Lambda) is parameterised as ``-exp(log_neg_lambda_real)`` so it stays strictly negative under any
  optimiser step (the reference trains the complex Lambda unconstrained and may become unstable).
* C is initialised with standard deviation ``1/sqrt(P)`` per real and imaginary part as in S5; the
  reference's initialiser treats C like a convolution kernel and makes it more than ten times too small.
* B is drawn with its true fan-in H (the reference uses P) before the eigenbasis change.
* Complex parameters are stored as real tensors (``(..., 2)`` pairs, or separate real and imaginary parts
  for Lambda), so state_dicts are all-real and survive ``torch.load(weights_only=True)``, fused optimisers,
  AMP gradient scalers and gradient clipping unchanged.
* The ZOH discretisation is computed once per call, not once per batch element.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Iterator

import torch
import torch.nn.functional as F
from torch import nn

from sb3_hieros.nn.networks import layer_norm, without_autocast
from sb3_hieros.nn.scan import (
    associative_scan_resettable,
    associative_scan_resettable_real,
    resettable_scan,
    s5_parallel_real_split,
)

__all__ = [
    "S5Block",
    "S5Layer",
    "S5Stack",
    "associative_scan_resettable",
    "associative_scan_resettable_real",
    "compile_s5",
    "hippo_n_eigendecomposition",
    "resettable_scan",
    "s5_parallel_real_split",
    "ssm_parameter_names",
]

# Names of the S5Layer parameters that S5 keeps out of weight decay (Smith et al., 2022).
_SSM_PARAMETER_NAMES = ("log_neg_lambda_real", "lambda_imag", "B", "log_step")


def hippo_n_eigendecomposition(n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Eigenvalues and eigenvectors of HiPPO-N, the normal part of HiPPO-LegS (S5 initialisation, thesis 2.4.3).

    HiPPO-LegS is ``A[i, k] = -sqrt(2i+1) sqrt(2k+1)`` below the diagonal, ``-(i+1)`` on it and 0 above.
    Adding ``p p^T`` with ``p_i = sqrt(i + 1/2)`` gives ``S = -I/2 + K`` with K skew-symmetric, which is normal
    and diagonalised by a unitary V: ``S = V diag(Lambda) V^H`` with ``Re(Lambda) = -1/2``.

    :param n: size of the HiPPO matrix (one initialisation block)
    :return: eigenvalues ``(n,)`` and unitary eigenvectors ``(n, n)``, both complex128
    """
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    idx = torch.arange(n, dtype=torch.float64)
    q = torch.sqrt(2.0 * idx + 1.0)
    legs = -torch.tril(torch.outer(q, q), diagonal=-1) - torch.diag(idx + 1.0)
    p = torch.sqrt(idx + 0.5)
    normal = legs + torch.outer(p, p)  # (n, n), = -I/2 + skew-symmetric
    skew = normal + 0.5 * torch.eye(n, dtype=torch.float64)
    # -i K is Hermitian: K V = i V diag(w) with real w.
    w, v = torch.linalg.eigh(-1j * skew.to(torch.complex128))
    eigenvalues = torch.complex(torch.full_like(w, -0.5), w)
    return eigenvalues, v


def _check_call(
    x: object,
    reset: object,
    state: object,
    d_model: int,
    state_shape: tuple[int, ...],
    sequence: bool,
) -> None:
    """Checks of the public ``forward`` (``sequence``: x (B, T, H), reset (B, T)) and ``step`` (x (B, H), reset (B,)
    or None) of the S5 modules; ``state_shape`` is a state's shape without the batch dim."""
    ndim = 3 if sequence else 2
    _check_input(x, d_model, ndim)
    assert isinstance(x, torch.Tensor)
    if sequence or reset is not None:
        _check_reset(reset, tuple(x.shape[: ndim - 1]), tuple(x.shape))
    if state is not None:
        layout = "(B, P)" if len(state_shape) == 1 else "(B, L, P)"
        _check_state(state, (x.shape[0], *state_shape), layout)


def _check_input(x: object, d_model: int, ndim: int, name: str = "x") -> torch.Tensor:
    shape_text = "(B, T, H)" if ndim == 3 else "(B, H)"
    if not isinstance(x, torch.Tensor):
        raise ValueError(f"{name} must be a torch.Tensor of shape {shape_text}, got {type(x).__name__}")
    if x.ndim != ndim:
        raise ValueError(f"{name} must have shape {shape_text} (rank {ndim}), got shape {tuple(x.shape)}")
    if not x.is_floating_point():
        raise ValueError(f"{name} must be a real floating point tensor, got dtype {x.dtype}")
    if x.shape[-1] != d_model:
        raise ValueError(f"{name} has feature size {x.shape[-1]} (shape {tuple(x.shape)}), expected H={d_model}")
    if ndim == 3 and x.shape[1] < 1:
        raise ValueError(f"{name} must have at least one time step, got shape {tuple(x.shape)}")
    return x


def _check_reset(reset: object, expected_shape: tuple[int, ...], x_shape: tuple[int, ...]) -> torch.Tensor:
    if not isinstance(reset, torch.Tensor):
        raise ValueError(f"reset must be a bool torch.Tensor of shape {expected_shape}, got {type(reset).__name__}")
    if reset.dtype != torch.bool:
        raise ValueError(f"reset must have dtype torch.bool, got {reset.dtype} (shape {tuple(reset.shape)})")
    if tuple(reset.shape) != expected_shape:
        raise ValueError(
            f"reset has shape {tuple(reset.shape)}, expected {expected_shape} to match x of shape {x_shape}"
        )
    return reset


def _check_state(state: object, expected_shape: tuple[int, ...], layout: str) -> torch.Tensor:
    if not isinstance(state, torch.Tensor):
        raise ValueError(f"state must be a complex torch.Tensor of shape {layout}, got {type(state).__name__}")
    if not state.is_complex():
        raise ValueError(f"state must be complex (complex64), got dtype {state.dtype} (shape {tuple(state.shape)})")
    if tuple(state.shape) != expected_shape:
        raise ValueError(f"state has shape {tuple(state.shape)}, expected {layout} = {expected_shape}")
    return state


class S5Layer(nn.Module):
    """One resettable S5 layer: diagonal complex SSM with ZOH discretisation (thesis 2.4.3, eq. 2.4-2.5).

    Parameters (all stored as real tensors; the complex ones are assembled in ``forward``):

    * ``log_neg_lambda_real`` ``(P,)`` and ``lambda_imag`` ``(P,)``: ``Lambda = -exp(log_neg_lambda_real)
      + i lambda_imag``. The exponential keeps ``Re(Lambda) < 0`` (a stable, contracting state) whatever
      the optimiser does; the reference implementation has no such constraint.
    * ``B`` ``(P, H, 2)``: input matrix in the eigenbasis, (real, imaginary) pairs.
    * ``C`` ``(H, P, 2)``: output matrix in the eigenbasis, (real, imaginary) pairs.
    * ``D`` ``(H,)``: real skip connection.
    * ``log_step`` ``(P,)``: log of the per-state ZOH time step Delta.

    Initialisation: HiPPO-N eigendecomposition per block (``Lambda``: ``Re = -1/2``, V unitary) repeated
    ``n_blocks`` times (the thesis' J); ``B = V^H B_0`` with real ``B_0 ~ N(0, 1/H)``;
    ``C = C_0 V`` with complex ``C_0`` of std ``1/sqrt(P)`` per part; ``D ~ N(0, 1)``;
    ``log_step ~ U[log dt_min, log dt_max]``.

    The scan and the state run in the parameters' precision (float32 / complex64) even under autocast; the input
    and output projections (``B_bar u`` and ``Re(C x)``, the layer's matmuls) follow an enclosing autocast, so a bf16
    autocast runs them in bf16 (the compiled real-split scan of :func:`compile_s5` stays in fp32 throughout).

    :param d_model: input and output width H
    :param d_state: complex state size P
    :param n_blocks: number of HiPPO-N initialisation blocks J; must divide ``d_state``
    :param dt_min: smallest initial time step
    :param dt_max: largest initial time step
    """

    def __init__(
        self,
        d_model: int,
        d_state: int,
        n_blocks: int = 1,
        dt_min: float = 1e-3,
        dt_max: float = 1e-1,
    ) -> None:
        super().__init__()
        if d_model < 1 or d_state < 1 or n_blocks < 1:
            raise ValueError(
                f"d_model, d_state and n_blocks must be >= 1, got d_model={d_model}, d_state={d_state}, "
                f"n_blocks={n_blocks}"
            )
        if d_state % n_blocks != 0:
            raise ValueError(f"d_state={d_state} must be divisible by n_blocks={n_blocks}")
        if not 0.0 < dt_min <= dt_max:
            raise ValueError(f"need 0 < dt_min <= dt_max, got dt_min={dt_min}, dt_max={dt_max}")
        self.d_model, self.d_state, self.n_blocks = d_model, d_state, n_blocks
        self.dt_min, self.dt_max = dt_min, dt_max

        block_eigenvalues, block_vectors = hippo_n_eigendecomposition(d_state // n_blocks)
        eigenvalues = block_eigenvalues.repeat(n_blocks)  # (P,)
        v = torch.block_diag(*([block_vectors] * n_blocks))  # (P, P), unitary

        b0 = torch.randn(d_state, d_model, dtype=torch.float64) / math.sqrt(d_model)
        b_tilde = v.conj().T @ b0.to(torch.complex128)  # (P, H)
        c0 = torch.complex(
            torch.randn(d_model, d_state, dtype=torch.float64), torch.randn(d_model, d_state, dtype=torch.float64)
        ) / math.sqrt(d_state)
        c_tilde = c0 @ v  # (H, P)
        log_step = torch.empty(d_state).uniform_(math.log(dt_min), math.log(dt_max))

        self.log_neg_lambda_real = nn.Parameter(torch.log(-eigenvalues.real).float())
        self.lambda_imag = nn.Parameter(eigenvalues.imag.float())
        self.B = nn.Parameter(torch.view_as_real(b_tilde).float().contiguous())
        self.C = nn.Parameter(torch.view_as_real(c_tilde).float().contiguous())
        self.D = nn.Parameter(torch.randn(d_model))
        self.log_step = nn.Parameter(log_step)
        # Opt-in alternative computation path (see ``compile_s5``); not part of the state_dict.
        self.real_split = False
        self._compiled_core: Callable[..., tuple[torch.Tensor, torch.Tensor]] | None = None
        # Step weights held by ``reuse_step_weights`` (not part of the state_dict).
        self._held_step_weights: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None
        # Step weights of the last gradient-free step and what they were computed from (see ``_step_weights``).
        self._no_grad_step_weights: tuple[tuple[tuple[torch.Tensor, int], ...], tuple[torch.Tensor, ...]] | None = None

    def extra_repr(self) -> str:
        return f"d_model={self.d_model}, d_state={self.d_state}, n_blocks={self.n_blocks}"

    @property
    def state_dtype(self) -> torch.dtype:
        """Complex dtype of the state (complex64 for float32 parameters)."""
        return torch.complex128 if self.B.dtype == torch.float64 else torch.complex64

    def ssm_parameters(self) -> Iterator[nn.Parameter]:
        """Parameters S5 trains without weight decay: Lambda (both parts), B and log_step.

        :return: iterator over those parameters
        """
        for name in _SSM_PARAMETER_NAMES:
            yield getattr(self, name)

    def eigenvalues(self) -> torch.Tensor:
        """Continuous-time diagonal state matrix ``Lambda`` ``(P,)`` complex, with ``Re(Lambda) < 0``.

        :return: Lambda
        """
        return torch.complex(-torch.exp(self.log_neg_lambda_real), self.lambda_imag)

    def discretize(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Zero-order-hold discretisation (thesis 2.4.3): ``Lambda_bar = exp(Lambda Delta)``,
        ``B_bar = (Lambda_bar - 1) / Lambda * B``.

        :return: ``Lambda_bar`` ``(P,)`` complex and ``B_bar`` ``(P, H)`` complex
        """
        lam = self.eigenvalues()
        lambda_bar = torch.exp(lam * torch.exp(self.log_step))
        b_bar = ((lambda_bar - 1.0) / lam).unsqueeze(-1) * torch.view_as_complex(self.B)
        return lambda_bar, b_bar

    def _real_weights(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Discretised system as real matrices acting on interleaved (re, im) features.

        :return: ``Lambda_bar`` ``(P,)`` complex, input weight ``(2P, H)`` with rows (Re B_bar_p, Im B_bar_p),
            output weight ``(H, 2P)`` with columns (Re C_p, -Im C_p) so that ``W_out @ [Re x; Im x] = Re(C x)``
        """
        lambda_bar, b_bar = self.discretize()
        w_in = torch.view_as_real(b_bar).transpose(1, 2).reshape(2 * self.d_state, self.d_model)
        w_out = torch.stack((self.C[..., 0], -self.C[..., 1]), dim=-1).reshape(self.d_model, 2 * self.d_state)
        return lambda_bar, w_in, w_out

    def _step_weights(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """:meth:`_real_weights`, or the ones held by :meth:`reuse_step_weights` inside its block.

        Without autograd (acting) the weights of the last call are reused while the parameters they came from are
        unchanged: the same tensors (held, so their memory cannot be reused by others) at the same version counter,
        which every in-place write (optimiser steps, ``load_state_dict``) advances.

        :return: ``Lambda_bar`` ``(P,)`` complex, input weight ``(2P, H)``, output weight ``(H, 2P)``
        """
        if self._held_step_weights is not None:
            return self._held_step_weights
        if torch.is_grad_enabled():
            return self._real_weights()
        cached = self._no_grad_step_weights
        params = (self.log_neg_lambda_real, self.lambda_imag, self.B, self.C, self.log_step)
        if cached is not None and all(
            p.data_ptr() == held.data_ptr() and p._version == version
            for p, (held, version) in zip(params, cached[0], strict=True)
        ):
            return cached[1]  # type: ignore[return-value]
        weights = self._real_weights()
        self._no_grad_step_weights = (tuple((p.detach(), p._version) for p in params), weights)
        return weights

    @contextlib.contextmanager
    def reuse_step_weights(self) -> Iterator[None]:
        """Discretise once and reuse the step weights for every :meth:`step` inside the block (a rollout of many
        steps: imagination). The parameters must not change inside it. Under autograd the held weights stay in the
        graph, so gradients still reach the parameters. Nested blocks keep the outermost block's weights.
        """
        if self._held_step_weights is not None:
            yield
            return
        with torch.autocast(device_type=self.B.device.type, enabled=False):
            self._held_step_weights = self._real_weights()
        try:
            yield
        finally:
            self._held_step_weights = None

    def _forward(
        self, x: torch.Tensor, reset: torch.Tensor, state: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``forward`` without input checks (used by the block and the stack, which check once)."""
        batch, length, _ = x.shape
        with torch.autocast(device_type=x.device.type, enabled=False):
            u = x.to(self.B.dtype)
            if self.real_split:
                core = s5_parallel_real_split if self._compiled_core is None else self._compiled_core
                y, states = core(
                    u,
                    (~reset).to(u.dtype).unsqueeze(-1),
                    None if state is None else torch.view_as_real(state),
                    self.log_neg_lambda_real,
                    self.lambda_imag,
                    self.B,
                    self.C,
                    self.D,
                    self.log_step,
                )
                return y, torch.view_as_complex(states)
            lambda_bar, w_in, w_out = self._real_weights()
            keep = (~reset).to(u.dtype).unsqueeze(-1)  # (B, T, 1)
        bu = F.linear(u, w_in).to(u.dtype)  # (B, T, 2P), in an enclosing autocast's dtype, then back
        with torch.autocast(device_type=x.device.type, enabled=False):
            bu = torch.view_as_complex(bu.view(batch, length, self.d_state, 2))  # (B, T, P)
            states = resettable_scan(lambda_bar, keep, bu, state)  # (B, T, P)
        real_states = torch.view_as_real(states).reshape(batch, length, 2 * self.d_state)
        y = F.linear(real_states, w_out).to(u.dtype) + u * self.D
        return y, states

    def forward(
        self, x: torch.Tensor, reset: torch.Tensor, state: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Parallel (training) form over a whole sequence.

        Where ``reset[b, t]`` is true the state carried into step t is zero, so ``x_t = B_bar u_t`` and nothing
        before t reaches t or later steps; a reset at t=0 discards ``state``.

        :param x: inputs ``(B, T, H)``, real
        :param reset: ``(B, T)`` bool, true where a new episode starts
        :param state: state before the first step ``(B, P)`` complex, or None for zeros
        :return: outputs ``y`` ``(B, T, H)`` and all states ``(B, T, P)`` complex
        """
        _check_call(x, reset, state, self.d_model, (self.d_state,), sequence=True)
        return self._forward(x, reset, state)

    def _step(
        self, x: torch.Tensor, state: torch.Tensor | None, reset: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``step`` without input checks."""
        with without_autocast(x.device.type):
            u = x.to(self.B.dtype)
            lambda_bar, w_in, w_out = self._step_weights()
        bu = F.linear(u, w_in).to(u.dtype)  # (B, 2P), in an enclosing autocast's dtype, then back
        with without_autocast(x.device.type):
            new_state = torch.view_as_complex(bu.view(x.shape[0], self.d_state, 2))  # (B, P)
            if state is not None:
                carried = lambda_bar * state
                if reset is not None:
                    carried = carried * (~reset).to(u.dtype).unsqueeze(-1)
                new_state = carried + new_state
        real_state = torch.view_as_real(new_state).reshape(x.shape[0], 2 * self.d_state)
        y = F.linear(real_state, w_out).to(u.dtype) + u * self.D
        return y, new_state

    def step(
        self, x: torch.Tensor, state: torch.Tensor | None, reset: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Recurrent (acting / imagination) form: one time step, the same maths as ``forward``.

        :param x: inputs ``(B, H)``, real
        :param state: previous state ``(B, P)`` complex, or None for zeros
        :param reset: ``(B,)`` bool, true where the previous state is to be dropped, or None
        :return: outputs ``(B, H)`` and the new state ``(B, P)`` complex
        """
        _check_call(x, reset, state, self.d_model, (self.d_state,), sequence=False)
        return self._step(x, state, reset)


class S5Block(nn.Module):
    """S5 block (thesis 4.4.2): ``x + Dropout(SiLU(S5(LayerNorm(x))))``.

    The thesis adapts the deep S5 block of Smith et al. (2022) with Layer Normalisation instead of Batch
    Normalisation, SiLU instead of GELU, and dropout. (The reference code instead uses GELU and an extra
    linear layer; this follows the thesis.)

    :param d_model: width H
    :param d_state: complex state size P
    :param n_blocks: HiPPO-N initialisation blocks J
    :param dropout: dropout probability after the activation
    """

    def __init__(self, d_model: int, d_state: int, n_blocks: int = 1, dropout: float = 0.0) -> None:
        super().__init__()
        if not 0.0 <= dropout < 1.0:
            raise ValueError(f"dropout must be in [0, 1), got {dropout}")
        self.norm = nn.LayerNorm(d_model)
        self.s5 = S5Layer(d_model, d_state, n_blocks)
        self.dropout = nn.Dropout(dropout)

    @property
    def d_model(self) -> int:
        return self.s5.d_model

    @property
    def d_state(self) -> int:
        return self.s5.d_state

    def ssm_parameters(self) -> Iterator[nn.Parameter]:
        """SSM parameters of the inner layer (see ``S5Layer.ssm_parameters``).

        :return: iterator over those parameters
        """
        return self.s5.ssm_parameters()

    def _forward(
        self, x: torch.Tensor, reset: torch.Tensor, state: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        y, states = self.s5._forward(self.norm(x), reset, state)
        return x + self.dropout(F.silu(y)), states

    def forward(
        self, x: torch.Tensor, reset: torch.Tensor, state: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Parallel form, see ``S5Layer.forward``.

        :param x: ``(B, T, H)``
        :param reset: ``(B, T)`` bool
        :param state: ``(B, P)`` complex or None
        :return: ``(B, T, H)`` outputs and ``(B, T, P)`` complex states
        """
        _check_call(x, reset, state, self.d_model, (self.d_state,), sequence=True)
        return self._forward(x, reset, state)

    def _step(
        self, x: torch.Tensor, state: torch.Tensor | None, reset: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        y, new_state = self.s5._step(layer_norm(self.norm, x), state, reset)
        y = F.silu(y)
        if self.training and self.dropout.p > 0.0:  # otherwise dropout returns its input
            y = self.dropout(y)
        return x + y, new_state

    def step(
        self, x: torch.Tensor, state: torch.Tensor | None, reset: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Recurrent form, see ``S5Layer.step``.

        :param x: ``(B, H)``
        :param state: ``(B, P)`` complex or None
        :param reset: ``(B,)`` bool or None
        :return: ``(B, H)`` outputs and the new ``(B, P)`` complex state
        """
        _check_call(x, reset, state, self.d_model, (self.d_state,), sequence=False)
        return self._step(x, state, reset)


class S5Stack(nn.Module):
    """Stack of ``n_layers`` S5 blocks: the sequence model of the S5 world model (thesis 4.4.2, Figure 4.6).

    The states of all layers together, ``(B, L, P)`` complex, are the recurrent state; the world model uses
    them as its deterministic state h_t (thesis 4.1.2, 5.3.5). The reset applies to every layer.

    :param n_layers: number of S5 blocks L (thesis: 8)
    :param d_model: width H (thesis: 256)
    :param d_state: complex state size P per layer (thesis: 128)
    :param n_blocks: HiPPO-N initialisation blocks J (thesis: 4)
    :param dropout: dropout probability inside each block
    """

    def __init__(self, n_layers: int, d_model: int, d_state: int, n_blocks: int = 1, dropout: float = 0.0) -> None:
        super().__init__()
        if n_layers < 1:
            raise ValueError(f"n_layers must be >= 1, got {n_layers}")
        self.n_layers = n_layers
        self.d_model = d_model
        self.d_state = d_state
        self.blocks = nn.ModuleList(S5Block(d_model, d_state, n_blocks, dropout) for _ in range(n_layers))

    @property
    def state_size(self) -> int:
        """Number of complex state entries, ``L * P``."""
        return self.n_layers * self.d_state

    @property
    def state_dtype(self) -> torch.dtype:
        """Complex dtype of the state (complex64 for float32 parameters)."""
        return self.blocks[0].s5.state_dtype

    def initial_state(self, batch_size: int, device: torch.device | str | None = None) -> torch.Tensor:
        """Zero state before the first step of an episode.

        :param batch_size: B
        :param device: device of the state; default: the device of the parameters
        :return: zeros ``(B, L, P)`` complex64
        """
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        if device is None:
            device = self.blocks[0].s5.B.device
        return torch.zeros(batch_size, self.n_layers, self.d_state, dtype=self.state_dtype, device=device)

    def ssm_parameters(self) -> Iterator[nn.Parameter]:
        """SSM parameters of all layers (for an optimiser group with ``weight_decay=0``).

        :return: iterator over those parameters
        """
        for block in self.blocks:
            yield from block.ssm_parameters()

    @contextlib.contextmanager
    def reuse_step_weights(self) -> Iterator[None]:
        """:meth:`S5Layer.reuse_step_weights` for every layer: discretise once for a rollout of many steps."""
        with contextlib.ExitStack() as stack:
            for block in self.blocks:
                stack.enter_context(block.s5.reuse_step_weights())
            yield

    def forward(
        self, x: torch.Tensor, reset: torch.Tensor, state: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Parallel form over a sequence (thesis 4.4.2, training).

        :param x: ``(B, T, H)``
        :param reset: ``(B, T)`` bool, true where a new episode starts (the state into that step is zeroed)
        :param state: ``(B, L, P)`` complex state before the first step, or None for zeros
        :return: outputs ``(B, T, H)`` and the states of all layers at every step ``(B, T, L, P)`` complex
        """
        _check_call(x, reset, state, self.d_model, (self.n_layers, self.d_state), sequence=True)
        return self._forward(x, reset, state)

    def _forward(
        self, x: torch.Tensor, reset: torch.Tensor, state: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``forward`` without input checks."""
        layer_states = []
        for i, block in enumerate(self.blocks):
            x, states = block._forward(x, reset, None if state is None else state[:, i])
            layer_states.append(states)
        return x, torch.stack(layer_states, dim=2)

    def step(
        self, x: torch.Tensor, state: torch.Tensor | None, reset: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Recurrent form, one step (thesis 4.4.2, acting and imagination).

        :param x: ``(B, H)``
        :param state: ``(B, L, P)`` complex, or None for zeros
        :param reset: ``(B,)`` bool, true where the previous state is to be dropped, or None
        :return: outputs ``(B, H)`` and the new state ``(B, L, P)`` complex
        """
        _check_call(x, reset, state, self.d_model, (self.n_layers, self.d_state), sequence=False)
        return self._step(x, state, reset)

    def _step(
        self, x: torch.Tensor, state: torch.Tensor | None, reset: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``step`` without input checks."""
        new_states = []
        for i, block in enumerate(self.blocks):
            x, layer_state = block._step(x, None if state is None else state[:, i], reset)
            new_states.append(layer_state)
        return x, torch.stack(new_states, dim=1)


def ssm_parameter_names(module: nn.Module) -> list[str]:
    """Qualified names of all S5 SSM parameters inside ``module`` (for a ``weight_decay=0`` optimiser group).

    :param module: any module that may contain ``S5Layer``s
    :return: names as in ``module.named_parameters()``
    """
    names = []
    for prefix, sub in module.named_modules():
        if isinstance(sub, S5Layer):
            names.extend(f"{prefix}.{name}" if prefix else name for name in _SSM_PARAMETER_NAMES)
    return names


def compile_s5(module: nn.Module, **compile_kwargs: object) -> nn.Module:
    """Opt-in ``torch.compile`` of the parallel form of every ``S5Layer`` inside ``module`` (in place).

    The layers switch to the real-split computation (Inductor does not generate code for complex
    operators) and compile it with ``torch.compile(**compile_kwargs)`` (``dynamic=False`` unless given).
    Results equal the default path up to float rounding. One compiled graph per input shape is shared by all
    layers; compiling costs tens of seconds to minutes per new shape on a CPU, past torch's recompile limit
    (8 shapes) calls fall back to eager, and the measured CPU gain is small
    (``python -m benchmarks.speed s5 --compile``). So this is for long runs with a fixed chunk length;
    ``step`` stays eager. Pickling the whole compiled module is not supported; save the ``state_dict``.

    :param module: a module containing ``S5Layer``s (e.g. ``S5Stack``)
    :param compile_kwargs: passed to ``torch.compile`` (e.g. ``mode``, ``dynamic``)
    :return: ``module`` itself
    """
    layers = [sub for sub in module.modules() if isinstance(sub, S5Layer)]
    if not layers:
        raise ValueError(f"module {type(module).__name__} contains no S5Layer to compile")
    # The scan's recursion is unrolled for each sequence length, so shapes are static: with dynamic shapes
    # (torch's automatic choice after a second length) the backward failed to compile in torch 2.13.
    compile_kwargs.setdefault("dynamic", False)
    compiled = torch.compile(s5_parallel_real_split, **compile_kwargs)  # one graph per shape, shared by layers
    for layer in layers:
        layer.real_split = True
        layer._compiled_core = compiled
    return module
