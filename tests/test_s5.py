import io

import pytest
import torch
from stable_baselines3.common.save_util import load_from_zip_file, save_to_zip_file

from sb3_hieros.nn.s5 import (
    S5Block,
    S5Layer,
    S5Stack,
    associative_scan_resettable,
    associative_scan_resettable_real,
    compile_s5,
    hippo_n_eigendecomposition,
    resettable_scan,
    ssm_parameter_names,
)

H, P, J = 12, 8, 2
ATOL = 1e-4


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)


def _inputs(batch=3, length=9, reset_prob=0.25):
    x = torch.randn(batch, length, H)
    reset = torch.rand(batch, length) < reset_prob
    return x, reset


def _random_state(*shape):
    return torch.randn(*shape, dtype=torch.complex64)


def _step_loop(module, x, reset, state):
    ys, states = [], []
    for x_t, r_t in zip(x.unbind(1), reset.unbind(1), strict=True):
        y_t, state = module.step(x_t, state, r_t)
        ys.append(y_t)
        states.append(state)
    return torch.stack(ys, dim=1), torch.stack(states, dim=1)


def _max_abs(a, b):
    return (a - b).abs().max().item()


@pytest.mark.parametrize("length", [1, 2, 3, 8, 13, 64])
@pytest.mark.parametrize("with_state", [False, True])
def test_layer_parallel_matches_step(length, with_state):
    layer = S5Layer(H, P, J)
    x, reset = _inputs(length=length)
    state = _random_state(3, P) if with_state else None
    y, states = layer(x, reset, state)
    assert y.shape == (3, length, H) and y.dtype == torch.float32
    assert states.shape == (3, length, P) and states.dtype == torch.complex64
    y_step, states_step = _step_loop(layer, x, reset, state)
    assert _max_abs(y, y_step) <= ATOL
    assert _max_abs(states, states_step) <= ATOL


@pytest.mark.parametrize("length", [1, 5, 16, 33])
def test_scan_matches_sequential_recurrence(length):
    lambda_bar = torch.exp(torch.complex(-torch.rand(P), torch.randn(P)))
    keep = (torch.rand(2, length, 1) > 0.3).float()
    bu = torch.randn(2, length, P, dtype=torch.complex64)
    x0 = _random_state(2, P)
    out = associative_scan_resettable(lambda_bar, keep, bu, x0)
    state, expected = x0, []
    for t in range(length):
        state = keep[:, t] * lambda_bar * state + bu[:, t]
        expected.append(state)
    assert _max_abs(out, torch.stack(expected, dim=1)) <= ATOL


def _scan_inputs(length, dtype=torch.complex64):
    lambda_bar = torch.exp(torch.complex(-torch.rand(P), torch.randn(P))).to(dtype).requires_grad_()
    keep = (torch.rand(2, length, 1) > 0.3).to(lambda_bar.real.dtype)
    bu = torch.randn(2, length, P, dtype=dtype, requires_grad=True)
    x0 = torch.randn(2, P, dtype=dtype, requires_grad=True)
    return lambda_bar, keep, bu, x0


@pytest.mark.parametrize("length", [1, 2, 5, 16, 33])
@pytest.mark.parametrize("with_state", [False, True])
def test_resettable_scan_backward_matches_autograd_through_the_recursion(length, with_state):
    lambda_bar, keep, bu, x0 = _scan_inputs(length)
    state = x0 if with_state else None
    weights = torch.randn(2, length, P, dtype=torch.complex64)  # a loss that weighs every state differently
    inputs = [lambda_bar, bu, x0] if with_state else [lambda_bar, bu]
    expected_states = associative_scan_resettable(lambda_bar, keep, bu, state)
    # (length 1 without a state: the recursion returns bu as it is and lambda_bar gets no gradient, i.e. zero)
    expected = torch.autograd.grad(
        torch.view_as_real(expected_states * weights).sum(), inputs, allow_unused=True, materialize_grads=True
    )
    states = resettable_scan(lambda_bar, keep, bu, state)
    assert torch.equal(states, expected_states)
    grads = torch.autograd.grad(torch.view_as_real(states * weights).sum(), inputs)
    for got, want in zip(grads, expected, strict=True):
        assert _max_abs(got, want) <= 1e-4 * max(1.0, want.abs().max().item())


def test_resettable_scan_passes_gradcheck():
    lambda_bar, keep, bu, x0 = _scan_inputs(7, dtype=torch.complex128)
    assert torch.autograd.gradcheck(resettable_scan, (lambda_bar, keep, bu, x0))
    assert torch.autograd.gradcheck(lambda lam, b: resettable_scan(lam, keep, b), (lambda_bar, bu))


def test_resettable_scan_skips_gradients_nobody_asked_for():
    lambda_bar, keep, bu, x0 = _scan_inputs(6)
    states = resettable_scan(lambda_bar.detach(), keep, bu, x0.detach())
    states.abs().sum().backward()
    assert bu.grad is not None and lambda_bar.grad is None and x0.grad is None


@pytest.mark.parametrize("length", [1, 6, 13])
def test_real_split_scan_matches_complex_scan(length):
    lambda_bar = torch.exp(torch.complex(-torch.rand(P), torch.randn(P)))
    keep = (torch.rand(2, length, 1) > 0.3).float()
    bu = torch.randn(2, length, P, dtype=torch.complex64)
    x0 = _random_state(2, P)
    expected = associative_scan_resettable(lambda_bar, keep, bu, x0)
    re, im = associative_scan_resettable_real(
        lambda_bar.real, lambda_bar.imag, keep, bu.real, bu.imag, x0.real, x0.imag
    )
    assert _max_abs(torch.complex(re, im), expected) <= 1e-5


def test_real_split_layer_path_matches_default():
    stack = S5Stack(2, H, P, J)
    x, reset = _inputs(length=11)
    state = _random_state(3, 2, P)
    y, states = stack(x, reset, state)
    y.square().mean().backward()
    grads = {n: p.grad.clone() for n, p in stack.named_parameters()}
    stack.zero_grad()
    for block in stack.blocks:
        block.s5.real_split = True  # what compile_s5 switches on, here without compiling
    y_rs, states_rs = stack(x, reset, state)
    assert states_rs.dtype == torch.complex64
    assert _max_abs(y_rs, y) <= 1e-5 and _max_abs(states_rs, states) <= 1e-5
    y_rs.square().mean().backward()
    for name, param in stack.named_parameters():
        assert torch.allclose(param.grad, grads[name], atol=1e-5, rtol=1e-4), name


def test_compile_s5_needs_a_layer():
    with pytest.raises(ValueError, match="no S5Layer"):
        compile_s5(torch.nn.Linear(2, 2))


@pytest.mark.parametrize("module_cls", [S5Layer, S5Block])
def test_reset_makes_suffix_independent_of_prefix(module_cls):
    module = module_cls(H, P, J)
    x, _ = _inputs(length=10)
    reset = torch.zeros(3, 10, dtype=torch.bool)
    t0 = 4
    reset[:, t0] = True
    state = _random_state(3, P)
    y, states = module(x, reset, state)
    y_fresh, states_fresh = module(x[:, t0:], reset[:, t0:])
    assert _max_abs(y[:, t0:], y_fresh) <= 1e-5
    assert _max_abs(states[:, t0:], states_fresh) <= 1e-5
    # Without the reset the prefix does leak into the suffix.
    y_no_reset, _ = module(x, torch.zeros_like(reset), state)
    assert _max_abs(y_no_reset[:, t0:], y_fresh) > 1e-4
    # The prefix before the reset is unaffected by the reset.
    assert _max_abs(y[:, :t0], y_no_reset[:, :t0]) <= 1e-6


def test_reset_at_zero_ignores_given_state():
    layer = S5Layer(H, P, J)
    x, reset = _inputs(length=7)
    reset[:, 0] = True
    y_a, s_a = layer(x, reset, _random_state(3, P))
    y_b, s_b = layer(x, reset, None)
    assert _max_abs(y_a, y_b) <= 1e-6
    assert _max_abs(s_a, s_b) <= 1e-6
    # and the step form agrees
    y_step, _ = layer.step(x[:, 0], _random_state(3, P), reset[:, 0])
    assert _max_abs(y_step, y_b[:, 0]) <= 1e-6


@pytest.mark.parametrize("split", [1, 6, 10])
def test_chunked_equals_whole_layer(split):
    layer = S5Layer(H, P, J)
    x, reset = _inputs(length=11)
    y, states = layer(x, reset)
    y1, s1 = layer(x[:, :split], reset[:, :split])
    y2, s2 = layer(x[:, split:], reset[:, split:], s1[:, -1])
    assert _max_abs(torch.cat([y1, y2], 1), y) <= ATOL
    assert _max_abs(torch.cat([s1, s2], 1), states) <= ATOL


def test_chunked_equals_whole_stack():
    stack = S5Stack(3, H, P, J)
    x, reset = _inputs(length=12)
    initial = _random_state(3, 3, P)
    y, states = stack(x, reset, initial)
    y1, s1 = stack(x[:, :5], reset[:, :5], initial)
    y2, s2 = stack(x[:, 5:], reset[:, 5:], s1[:, -1])
    assert _max_abs(torch.cat([y1, y2], 1), y) <= ATOL
    assert _max_abs(torch.cat([s1, s2], 1), states) <= ATOL


def test_stack_shapes_and_step_agreement():
    stack = S5Stack(3, H, P, J, dropout=0.1).eval()
    assert stack.state_size == 3 * P
    init = stack.initial_state(4)
    assert init.shape == (4, 3, P) and init.dtype == torch.complex64 and not init.any()
    x, reset = _inputs(batch=4, length=9)
    state = _random_state(4, 3, P)
    y, states = stack(x, reset, state)
    assert y.shape == (4, 9, H) and states.shape == (4, 9, 3, P) and states.dtype == torch.complex64
    y_step, states_step = _step_loop(stack, x, reset, state)
    assert _max_abs(y, y_step) <= ATOL
    assert _max_abs(states, states_step) <= ATOL
    # state None == zeros; reset None == no reset
    y0, s0 = stack.step(x[:, 0], None, None)
    y0b, s0b = stack.step(x[:, 0], init, torch.zeros(4, dtype=torch.bool))
    assert torch.equal(y0, y0b) and torch.equal(s0, s0b)


def test_block_shapes_and_step_agreement():
    block = S5Block(H, P, J)
    x, reset = _inputs(length=6)
    y, states = block(x, reset)
    assert y.shape == x.shape and states.shape == (3, 6, P)
    y_step, states_step = _step_loop(block, x, reset, None)
    assert _max_abs(y, y_step) <= ATOL
    assert _max_abs(states, states_step) <= ATOL


def test_gradients_reach_every_parameter():
    stack = S5Stack(2, H, P, J)
    x, reset = _inputs(length=9)
    x.requires_grad_(True)
    state = _random_state(3, 2, P).requires_grad_(True)
    y, states = stack(x, reset, state)
    (y.square().mean() + torch.view_as_real(states).square().mean()).backward()
    for name, param in stack.named_parameters():
        assert param.grad is not None, name
        assert torch.isfinite(param.grad).all(), name
        assert param.grad.abs().sum() > 0, name
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
    assert torch.isfinite(torch.view_as_real(state.grad)).all() and state.grad.abs().sum() > 0


def test_step_gradients_match_parallel_form():
    # the step form (one step at a time, weights as used by imagination) differentiates like the parallel scan
    stack = S5Stack(2, H, P, J)
    x, reset = _inputs(length=5)
    state = _random_state(3, 2, P)

    def grads(run):
        stack.zero_grad()
        y, states = run()
        (y.square().mean() + torch.view_as_real(states).square().mean()).backward()
        return {name: p.grad.clone() for name, p in stack.named_parameters()}

    parallel = grads(lambda: stack(x, reset, state))
    stepped = grads(lambda: _step_loop(stack, x, reset, state))
    for name, grad in parallel.items():
        assert torch.allclose(grad, stepped[name], atol=1e-4, rtol=1e-3), name


def test_reuse_step_weights_gives_the_same_steps_and_gradients():
    stack = S5Stack(2, H, P, J)
    x, reset = _inputs(length=6)
    state = _random_state(3, 2, P)

    def run():
        stack.zero_grad()
        y, states = _step_loop(stack, x, reset, state)
        (y.square().mean() + torch.view_as_real(states).square().mean()).backward()
        return y.detach(), states.detach(), {name: p.grad.clone() for name, p in stack.named_parameters()}

    y_fresh, s_fresh, g_fresh = run()
    with stack.reuse_step_weights():
        assert all(block.s5._held_step_weights is not None for block in stack.blocks)
        y_held, s_held, g_held = run()
    assert all(block.s5._held_step_weights is None for block in stack.blocks)
    assert torch.equal(y_fresh, y_held) and torch.equal(s_fresh, s_held)
    for name, grad in g_fresh.items():
        assert torch.allclose(grad, g_held[name], atol=1e-6, rtol=1e-5), name


def test_reuse_step_weights_nests_and_releases_on_error():
    layer = S5Layer(H, P, J)
    with layer.reuse_step_weights():
        held = layer._held_step_weights
        with layer.reuse_step_weights():
            assert layer._held_step_weights is held  # the outer block's weights stay
        assert layer._held_step_weights is held
    assert layer._held_step_weights is None
    with pytest.raises(RuntimeError, match="inside"):
        with layer.reuse_step_weights():
            raise RuntimeError("inside")
    assert layer._held_step_weights is None
    # outside a block a parameter change shows in the next step at once
    x, state = torch.randn(3, H), _random_state(3, P)
    y_before, _ = layer.step(x, state)
    with torch.no_grad():
        layer.log_step.add_(0.5)
    y_after, _ = layer.step(x, state)
    assert not torch.equal(y_before, y_after)


def test_long_sequence_stays_finite():
    stack = S5Stack(2, H, P, J)
    x = 3.0 * torch.randn(2, 2048, H)
    reset = torch.zeros(2, 2048, dtype=torch.bool)
    y, states = stack(x, reset)
    assert torch.isfinite(y).all()
    assert torch.isfinite(torch.view_as_real(states)).all()
    y.mean().backward()
    assert all(torch.isfinite(p.grad).all() for p in stack.parameters())


def test_state_dict_is_real_without_constant_buffers():
    stack = S5Stack(2, H, P, J)
    sd = stack.state_dict()
    assert all(v.is_floating_point() for v in sd.values())
    assert set(sd) == {name for name, _ in stack.named_parameters()}  # no persistent buffers


def test_save_load_roundtrip_torch(tmp_path):
    stack = S5Stack(2, H, P, J)
    x, reset = _inputs()
    expected, expected_states = stack(x, reset)
    buffer = io.BytesIO()
    torch.save(stack.state_dict(), buffer)
    buffer.seek(0)
    other = S5Stack(2, H, P, J)
    other.load_state_dict(torch.load(buffer, weights_only=True))
    y, states = other(x, reset)
    assert torch.equal(y, expected) and torch.equal(states, expected_states)


def test_save_load_roundtrip_sb3_zip(tmp_path):
    stack = S5Stack(2, H, P, J)
    optimizer = torch.optim.AdamW(stack.parameters(), lr=1e-3, weight_decay=0.1)
    x, reset = _inputs()
    stack(x, reset)[0].sum().backward()
    optimizer.step()
    expected, _ = stack(x, reset)
    path = tmp_path / "model.zip"
    save_to_zip_file(path, data={}, params={"policy": stack.state_dict(), "policy.optimizer": optimizer.state_dict()})
    _, params, _ = load_from_zip_file(path, device="cpu")
    other = S5Stack(2, H, P, J)
    other.load_state_dict(params["policy"])
    other_opt = torch.optim.AdamW(other.parameters(), lr=1e-3, weight_decay=0.1)
    other_opt.load_state_dict(params["policy.optimizer"])
    y, _ = other(x, reset)
    assert torch.equal(y, expected)
    y.sum().backward()
    other_opt.step()  # the restored optimizer keeps working


def test_adamw_weight_decay_and_clipping_keep_lambda_stable():
    stack = S5Stack(2, H, P, J)
    ssm_names = set(ssm_parameter_names(stack))
    named = dict(stack.named_parameters())
    assert ssm_names <= set(named)
    assert {id(p) for p in stack.ssm_parameters()} == {id(named[n]) for n in ssm_names}
    groups = [
        {"params": [p for n, p in named.items() if n in ssm_names], "weight_decay": 0.0},
        {"params": [p for n, p in named.items() if n not in ssm_names]},
    ]
    optimizer = torch.optim.AdamW(groups, lr=0.5, weight_decay=0.1)
    x, reset = _inputs()
    for _ in range(5):
        optimizer.zero_grad()
        y, _ = stack(x, reset)
        # Push Re(Lambda) upwards as hard as possible, besides a normal loss.
        lam_real = sum(block.s5.eigenvalues().real.sum() for block in stack.blocks)
        (y.square().mean() - 100.0 * lam_real).backward()
        norm = torch.nn.utils.clip_grad_norm_(stack.parameters(), max_norm=1.0)
        assert torch.isfinite(norm)
        optimizer.step()
    for block in stack.blocks:
        assert (block.s5.eigenvalues().real < 0).all()
    y, states = stack(x, reset)
    assert torch.isfinite(y).all() and torch.isfinite(torch.view_as_real(states)).all()


def test_ssm_parameter_names_in_nested_module():
    outer = torch.nn.Sequential(torch.nn.Linear(2, 2), S5Layer(H, P, J))
    assert ssm_parameter_names(outer) == ["1.log_neg_lambda_real", "1.lambda_imag", "1.B", "1.log_step"]


def test_hippo_n_initialisation():
    eigenvalues, v = hippo_n_eigendecomposition(8)
    assert torch.allclose(eigenvalues.real, torch.full((8,), -0.5, dtype=torch.float64))
    assert torch.allclose(v.conj().T @ v, torch.eye(8, dtype=torch.complex128), atol=1e-10)
    n = torch.arange(8, dtype=torch.float64)
    legs = -torch.tril(torch.outer(torch.sqrt(2 * n + 1), torch.sqrt(2 * n + 1)), -1) - torch.diag(n + 1)
    normal = legs + torch.outer(torch.sqrt(n + 0.5), torch.sqrt(n + 0.5))
    rebuilt = v @ torch.diag(eigenvalues) @ v.conj().T
    assert torch.allclose(rebuilt, normal.to(torch.complex128), atol=1e-9)
    layer = S5Layer(16, 16, n_blocks=2)
    lam = layer.eigenvalues().detach()
    assert torch.allclose(lam[:8], lam[8:])  # J identical blocks
    assert (lam.real < 0).all()


def test_initialisation_scales():
    layer = S5Layer(64, 64, 4, dt_min=1e-3, dt_max=1e-1)
    step = torch.exp(layer.log_step.detach())
    assert (step >= 1e-3 * 0.999).all() and (step <= 1e-1 * 1.001).all()
    c_std = layer.C.detach().std().item()
    assert 0.5 / 64**0.5 < c_std < 2.0 / 64**0.5  # not the reference's accidentally tiny C
    lambda_bar, _ = layer.discretize()
    assert (lambda_bar.abs() < 1).all()


def test_autocast_keeps_complex64_state():
    stack = S5Stack(2, H, P, J)
    x, reset = _inputs()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        y, states = stack(x, reset)
    assert states.dtype == torch.complex64 and torch.isfinite(y).all()


def test_bf16_autocast_runs_the_projections_in_bf16_and_keeps_step_and_scan_alike():
    torch.manual_seed(0)
    layer = S5Layer(H, P, J)
    x, reset = _inputs()
    y32, states32 = layer(x, reset)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        y, states = layer(x, reset)
        state, steps = None, []
        for t in range(x.shape[1]):
            y_t, state = layer.step(x[:, t], state, reset[:, t])
            steps.append(y_t)
    assert states.dtype == torch.complex64 and y.dtype == torch.float32
    assert not torch.equal(y, y32)  # the matmuls ran in bf16
    torch.testing.assert_close(y, y32, rtol=0.05, atol=0.05)
    torch.testing.assert_close(torch.stack(steps, 1), y, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(states, states32, rtol=0.05, atol=0.05)


def test_bad_d_state_blocks():
    with pytest.raises(ValueError, match="divisible"):
        S5Layer(H, 10, n_blocks=3)


def _bad_calls():
    layer = S5Layer(H, P, J)
    stack = S5Stack(2, H, P, J)
    x, reset = _inputs()
    return [
        ("x", lambda: layer(x[0], reset)),
        ("x", lambda: layer(x[..., :-1], reset)),
        ("x", lambda: layer(x.long(), reset)),
        ("reset", lambda: layer(x, reset[:, :-1])),
        ("reset", lambda: layer(x, reset[:2])),
        ("reset", lambda: layer(x, reset.float())),
        ("state", lambda: layer(x, reset, _random_state(3, P + 1))),
        ("state", lambda: layer(x, reset, torch.zeros(3, P))),
        ("x", lambda: layer.step(x, None, None)),
        ("reset", lambda: layer.step(x[:, 0], None, reset)),
        ("state", lambda: layer.step(x[:, 0], _random_state(2, P), None)),
        ("state", lambda: stack(x, reset, _random_state(3, P))),
        ("state", lambda: stack.step(x[:, 0], _random_state(3, 3, P))),
    ]


@pytest.mark.parametrize("index", range(13))
def test_bad_inputs_raise_value_error(index):
    name, call = _bad_calls()[index]
    with pytest.raises(ValueError, match=rf"^{name}\b"):
        call()


def test_nonfinite_inputs_propagate_without_raising():
    """Like torch's own layers, S5 passes NaN through (no device sync per call); the optimiser guard skips the step."""
    stack = S5Stack(2, H, P, J)
    x, reset = _inputs()
    x[0, 1, 2] = float("nan")
    y, _ = stack(x, reset)
    assert torch.isnan(y[0, 1:]).any() and torch.isfinite(y[1:]).all()
    y_step, _ = stack.step(x[:, 1], None)
    assert torch.isnan(y_step[0]).any() and torch.isfinite(y_step[1:]).all()


def test_gradient_free_steps_reuse_weights_only_while_the_parameters_are_unchanged():
    torch.manual_seed(0)
    layer = S5Layer(H, P, J)
    x = torch.randn(3, H)
    state = torch.randn(3, P, dtype=torch.complex64)

    def gradient_free() -> torch.Tensor:
        with torch.no_grad():
            return layer.step(x, state)[0]

    def with_autograd() -> torch.Tensor:  # discretises afresh at every call
        return layer.step(x, state)[0].detach()

    first = gradient_free()
    assert torch.equal(first, with_autograd()) and torch.equal(gradient_free(), first)
    optimizer = torch.optim.SGD(layer.parameters(), lr=0.1)
    layer.step(x, state)[0].square().sum().backward()
    optimizer.step()  # in place, as in training
    stepped = gradient_free()
    assert not torch.equal(stepped, first) and torch.equal(stepped, with_autograd())
    layer.load_state_dict({k: v * 1.5 for k, v in layer.state_dict().items()})
    loaded = gradient_free()
    assert not torch.equal(loaded, stepped) and torch.equal(loaded, with_autograd())
    layer.log_step.data = layer.log_step.data + 0.25  # new storage, version counter of its own
    replaced = gradient_free()
    assert not torch.equal(replaced, loaded) and torch.equal(replaced, with_autograd())
