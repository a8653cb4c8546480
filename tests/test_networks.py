import pytest
import torch as th
from torch import nn

from sb3_hieros.nn.augment import random_shift
from sb3_hieros.nn.networks import (
    MLP,
    ConvDecoder,
    ConvEncoder,
    bf16_autocast,
    check_bf16,
    conv_stack_sizes,
    native_bf16,
    preprocess_image,
    trunc_normal_init_,
)


def test_mlp_leading_dims_and_structure():
    mlp = MLP(7, 3, hidden=16, layers=2)
    x = th.randn(2, 5, 4, 7)
    out = mlp(x)
    assert out.shape == (2, 5, 4, 3)
    assert th.allclose(out.reshape(-1, 3), mlp(x.reshape(-1, 7)), atol=1e-6)
    kinds = [type(m) for m in mlp.hidden]
    assert kinds == [nn.Linear, nn.LayerNorm, nn.SiLU] * 2
    assert mlp.hidden[0].bias is None  # no bias before a norm
    assert mlp.out_dim == 3


def test_mlp_variants():
    trunk = MLP(5, None, hidden=8, layers=1)
    assert trunk(th.randn(3, 5)).shape == (3, 8) and trunk.out_dim == 8
    linear = MLP(5, 2, layers=0)
    assert linear(th.randn(3, 5)).shape == (3, 2)
    zero_head = MLP(5, 4, hidden=8, layers=2, out_scale=0.0)
    assert th.equal(zero_head(th.randn(6, 5)), th.zeros(6, 4))
    no_norm = MLP(5, 4, hidden=8, layers=1, norm=False, act=nn.ELU)
    assert [type(m) for m in no_norm.hidden] == [nn.Linear, nn.ELU]
    sl = MLP(1, 1, hidden=4, layers=0, symlog_inputs=True)
    with th.no_grad():
        sl.out.weight.fill_(1.0)
    assert th.allclose(sl(th.tensor([[1e6]])), th.log1p(th.tensor([[1e6]])))


@pytest.mark.parametrize("norm", [True, False])
def test_mlp_forward_is_its_registered_layers_after_copy_and_load(norm):
    """MLP.forward calls its layers functionally; it must compute what its registered modules compute, also in a deep
    copy and after loading another MLP's weights."""
    import copy

    def chained(mlp: MLP, x: th.Tensor) -> th.Tensor:
        return mlp.out(mlp.hidden(x))

    source = MLP(5, 3, hidden=8, layers=2, norm=norm, act=nn.ELU)
    with th.no_grad():
        for p in source.parameters():
            p.normal_()
    mlp = copy.deepcopy(MLP(5, 3, hidden=8, layers=2, norm=norm, act=nn.ELU))
    mlp.load_state_dict(source.state_dict())
    x = th.randn(4, 5)
    assert th.equal(mlp(x), chained(mlp, x))
    assert th.equal(mlp(x), source(x))
    twin = copy.deepcopy(mlp)
    with th.no_grad():
        twin.hidden[0].weight.add_(1.0)
    assert th.equal(twin(x), chained(twin, x)) and not th.equal(twin(x), mlp(x))


def test_trunc_normal_init_statistics():
    layer = nn.Linear(400, 600)
    trunc_normal_init_(layer, scale=1.0)
    std = layer.weight.std().item()
    assert abs(std - (1.0 / 500) ** 0.5) / (1.0 / 500) ** 0.5 < 0.05
    bound = 2 * (1.0 / 500) ** 0.5 / 0.8796256610342398
    assert layer.weight.abs().max() <= bound + 1e-6
    assert th.equal(layer.bias, th.zeros(600))
    with pytest.raises(ValueError, match="scale"):
        trunc_normal_init_(layer, scale=-1.0)


@pytest.mark.parametrize(
    "shape, sizes",
    [
        ((3, 64, 64), [(64, 64), (32, 32), (16, 16), (8, 8), (4, 4)]),
        ((2, 40, 40), [(40, 40), (20, 20), (10, 10), (5, 5), (2, 2)]),
        ((1, 36, 36), [(36, 36), (18, 18), (9, 9), (4, 4)]),
        ((3, 37, 29), [(37, 29), (18, 14), (9, 7), (4, 3)]),
    ],
)
def test_conv_encoder_decoder_shapes(shape, sizes):
    _, h, w = shape
    assert conv_stack_sizes(h, w, 4) == sizes
    enc = ConvEncoder(shape, depth=4, min_res=4)
    n_conv = len(sizes) - 1
    assert enc.out_dim == 4 * 2 ** (n_conv - 1) * sizes[-1][0] * sizes[-1][1]
    obs = th.randint(0, 256, (2, 3, *shape), dtype=th.uint8)
    feat = enc(obs)
    assert feat.shape == (2, 3, enc.out_dim)
    # leading dims are only flattened: same result per image
    assert th.allclose(feat[1, 2], enc(obs[1, 2:3])[0], atol=1e-5)
    dec = ConvDecoder(enc.out_dim, shape, depth=4, min_res=4)
    img = dec(feat)
    assert img.shape == (2, 3, *shape)
    img.mean().backward()
    assert all(p.grad is not None for p in enc.parameters())


def test_preprocess_image():
    x = th.tensor([0, 255, 51], dtype=th.uint8)
    assert th.allclose(preprocess_image(x), th.tensor([-0.5, 0.5, 0.2 - 0.5]))
    f = th.rand(3) - 0.5
    assert preprocess_image(f) is f
    enc = ConvEncoder((1, 8, 8), depth=2)
    u8 = th.randint(0, 256, (2, 1, 8, 8), dtype=th.uint8)
    assert th.allclose(enc(u8), enc(u8.float() / 255 - 0.5))
    with pytest.raises(ValueError, match="uint8"):
        preprocess_image(th.zeros(3, dtype=th.int32))


def test_decoder_can_fit_an_image():
    th.manual_seed(0)
    shape = (2, 12, 10)
    dec = ConvDecoder(6, shape, depth=4, min_res=4)
    target = th.rand(4, *shape) - 0.5
    feat = th.randn(4, 6)
    opt = th.optim.Adam(dec.parameters(), lr=1e-2)
    first = None
    for _ in range(60):
        opt.zero_grad()
        loss = (dec(feat) - target).pow(2).mean()
        first = first if first is not None else loss.item()
        loss.backward()
        opt.step()
    assert loss.item() < 0.5 * first


def test_bad_inputs():
    mlp = MLP(4, 2, hidden=8)
    with pytest.raises(ValueError, match=r"\(\.\.\., 4\)"):
        mlp(th.zeros(3, 5))
    with pytest.raises(ValueError, match="in_dim"):
        MLP(0, 2)
    with pytest.raises(ValueError, match="layers"):
        MLP(3, 2, layers=-1)
    enc = ConvEncoder((3, 16, 16), depth=2)
    with pytest.raises(ValueError, match="ConvEncoder expected"):
        enc(th.zeros(2, 16, 16, 3, dtype=th.uint8))  # channel-last
    with pytest.raises(ValueError, match="in_shape"):
        ConvEncoder((16, 16))
    dec = ConvDecoder(5, (1, 8, 8), depth=2)
    with pytest.raises(ValueError, match="ConvDecoder expected"):
        dec(th.zeros(2, 6))
    with pytest.raises(ValueError, match="out_shape"):
        ConvDecoder(5, (1, 0, 8))


@pytest.mark.parametrize("value", [1, 0, "true", "on", None, "Auto"])
def test_check_bf16_names_a_value_it_does_not_take(value):
    with pytest.raises(ValueError, match=f"bf16 must be False, True or 'auto', got {value!r}"):
        check_bf16(value)
    assert [check_bf16(v) for v in (True, False, "auto")] == [True, False, "auto"]


def test_bf16_auto_autocasts_exactly_where_the_device_computes_bf16_natively():
    a, b = th.randn(4, 8), th.randn(8, 3)
    cpu = th.device("cpu")
    with bf16_autocast("auto", cpu):
        auto = (a @ b).dtype
    assert auto == (th.bfloat16 if native_bf16("cpu") else th.float32)
    with bf16_autocast(True, cpu):
        assert (a @ b).dtype == th.bfloat16
    with bf16_autocast(False, cpu):
        assert (a @ b).dtype == th.float32
    assert native_bf16("meta") is False


def test_random_shift_moves_each_sequence_as_one_crop_of_its_padded_frames():
    th.manual_seed(0)
    images = th.rand(6, 4, 3, 8, 8)  # (B, T, C, H, W)
    shifted = random_shift(images, 2)
    assert shifted.shape == images.shape
    assert shifted.reshape(-1, 3, 8, 8).is_contiguous(memory_format=th.channels_last)
    offsets = set()
    for b in range(6):
        padded = nn.functional.pad(images[b], (2, 2, 2, 2), mode="replicate")  # (T, C, 12, 12)
        # one offset for all frames of the sequence
        found = [(i, j) for i in range(5) for j in range(5) if th.equal(padded[..., i : i + 8, j : j + 8], shifted[b])]
        assert len(found) == 1, (b, found)
        offsets.add(found[0])
    assert len(offsets) > 1  # sequences move independently
    assert random_shift(images, 0) is images
    with pytest.raises(ValueError, match="pad must be >= 0, got -1"):
        random_shift(images, -1)
    with pytest.raises(ValueError, match=r"\(B, T, C, H, W\) images, got shape \(4, 3, 8, 8\)"):
        random_shift(images[0], 2)
