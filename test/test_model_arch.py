"""Forward-model architecture (3.1, Fig. 4-5): shapes, equal-length scales, attention, functorch."""

import pytest
import torch
from torch.func import functional_call

from peel_model.config import ModelConfig
from peel_model.model import ConvAttentionLSTM
from peel_model.predictor import ForcePredictor, Normalization
from peel_msgs_py.errors import ParameterError

ARCHS = ("ours", "mlp", "cnn-lstm")


@pytest.mark.parametrize("arch", ARCHS)
@pytest.mark.parametrize("batch", [1, 7])
def test_output_shape(arch, batch):
    torch.manual_seed(0)
    p = ForcePredictor(ModelConfig(arch=arch))
    out = p.predict(torch.randn(batch, p.h, 4), torch.randn(batch))
    assert out.shape == (batch, 2)
    assert out.dtype == torch.float32
    assert torch.isfinite(out).all()


@pytest.mark.parametrize("h", [6, 10, 16])
def test_multiscale_outputs_have_equal_length(h):
    cfg = ModelConfig(h=h, conv_channels=5)
    body = ConvAttentionLSTM(cfg)
    scales = body.conv(torch.randn(3, h, 4))
    assert [tuple(s.shape) for s in scales] == [(3, h - 1, 5)] * 3
    assert [c.kernel_size[0] for c in body.conv.convs] == [2, 4, 6]
    assert [c.padding[0] for c in body.conv.convs] == [0, 1, 2]
    assert all(c.in_channels == 4 for c in body.conv.convs)


def test_unequal_paddings_refused():
    with pytest.raises(ParameterError, match="unequal"):
        ModelConfig(kernels=(2, 4, 6), paddings=(0, 0, 2)).check()


@pytest.mark.parametrize("arch", ["ours", "cnn-lstm"])
def test_attention_weights_sum_to_one(arch):
    torch.manual_seed(1)
    p = ForcePredictor(ModelConfig(arch=arch))
    w = p.attention_weights(torch.randn(9, p.h, 4) * 3)
    assert w.shape == (9, p.h - 1, 3)
    assert torch.allclose(w.sum(-1), torch.ones(9, p.h - 1), atol=1e-6)
    assert (w > 0).all() and (w < 1).all()
    # the weights depend on the input (they are not a constant)
    w2 = p.attention_weights(torch.randn(9, p.h, 4) * 3)
    assert not torch.allclose(w, w2)


def test_mlp_has_no_attention():
    with pytest.raises(ValueError):
        ForcePredictor(ModelConfig(arch="mlp")).attention_weights(torch.zeros(1, 10, 4))


def test_increment_head_and_units():
    """Output = F_k + out_mean + out_std * body(normalised input) (predictor docstring)."""
    torch.manual_seed(2)
    norm = Normalization(in_mean=(10.0, 2.0, 3.0, 1.0), in_std=(5.0, 1.0, 2.0, 0.5),
                         out_mean=(0.1, -0.2), out_std=(0.5, 0.25))
    p = ForcePredictor(ModelConfig(), norm)
    hist = torch.randn(4, 10, 4) * 3 + 5
    v = torch.rand(4) * 4
    d = p.body((hist - p.in_mean) / p.in_std, (v - 2.0) / 1.0)
    expected = hist[:, -1, 2:4] + torch.tensor([0.1, -0.2]) + torch.tensor([0.5, 0.25]) * d
    assert torch.allclose(p(hist, v), expected, atol=1e-6)


def test_future_velocity_matters():
    torch.manual_seed(3)
    p = ForcePredictor(ModelConfig())
    hist = torch.randn(5, 10, 4)
    v = torch.zeros(5, requires_grad=True)
    p(hist, v).sum().backward()
    assert v.grad.abs().sum() > 0


def test_bad_input_shape_refused():
    p = ForcePredictor(ModelConfig())
    with pytest.raises(ValueError, match="hist"):
        p(torch.zeros(2, 9, 4), torch.zeros(2))
    with pytest.raises(ValueError, match="v_next"):
        p(torch.zeros(2, 10, 4), torch.zeros(3))


@pytest.mark.parametrize("arch", ARCHS)
def test_functional_call_and_second_order_grad(arch):
    """MAML (Eq. 26-27) runs the module through torch.func.functional_call with new weights."""
    torch.manual_seed(4)
    p = ForcePredictor(ModelConfig(arch=arch))
    hist, v = torch.randn(6, 10, 4), torch.randn(6)
    params = {k: t.detach().clone().requires_grad_() for k, t in p.named_parameters()}
    assert torch.equal(functional_call(p, params, (hist, v)), p(hist, v))
    loss = functional_call(p, params, (hist, v)).pow(2).mean()
    grads = torch.autograd.grad(loss, list(params.values()), create_graph=True)
    fast = {k: t - 0.1 * g for (k, t), g in zip(params.items(), grads, strict=True)}
    meta = functional_call(p, fast, (hist, v)).pow(2).mean()
    meta_grads = torch.autograd.grad(meta, list(params.values()))
    assert all(torch.isfinite(g).all() for g in meta_grads)
    assert sum(float(g.abs().sum()) for g in meta_grads) > 0
