"""The decoders' MLP: chunk by chunk on the CPU, the same values and gradients as layer by layer."""
import pytest
import torch
from torch import nn

from nerf.fields.base import CHUNK_ROWS, MLP, mlp


def layer_by_layer(m: MLP) -> nn.Sequential:
    """The reference: the same layers, run one after another by a plain nn.Sequential."""
    return nn.Sequential(*m)


def grads(module: nn.Module, x: torch.Tensor) -> list[torch.Tensor]:
    return [p.grad.clone() for p in module.parameters()] + ([x.grad.clone()] if x.grad is not None else [])


@pytest.mark.parametrize("n_in,n_hidden,n_out", [(32, 1, 16), (25, 1, 3), (32, 2, 6), (32, 3, 46)])
def test_chunked_forward_and_backward_match_the_layer_by_layer_products(n_in, n_hidden, n_out):
    torch.manual_seed(0)
    m = mlp(n_in, 64, n_hidden, n_out)
    x = torch.randn(2 * CHUNK_ROWS + 123, n_in, requires_grad=True)   # two full chunks and a short one
    go = torch.randn(x.shape[0], n_out)
    y = m(x)
    assert y.grad_fn is not None and "ChunkedMLP" in type(y.grad_fn).__name__
    y.backward(go)
    chunked = grads(m, x)
    m.zero_grad()
    x.grad = None
    y_ref = layer_by_layer(m)(x)
    y_ref.backward(go)
    for a, b in zip([y] + chunked, [y_ref] + grads(m, x)):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5 * float(b.detach().abs().max()))


def test_frozen_parameters_and_inputs_without_gradient():
    torch.manual_seed(1)
    m = mlp(32, 64, 2, 6)
    x = torch.randn(CHUNK_ROWS + 7, 32)
    for p in m[0].parameters():     # a frozen first layer: only the later layers get gradients
        p.requires_grad_(False)
    m(x).square().sum().backward()
    assert m[0].weight.grad is None and m[2].weight.grad is not None and m[4].bias.grad is not None
    got = [p.grad.clone() for p in m.parameters() if p.requires_grad]
    m.zero_grad()
    layer_by_layer(m)(x).square().sum().backward()
    for a, p in zip(got, [p for p in m.parameters() if p.requires_grad]):
        torch.testing.assert_close(a, p.grad, rtol=1e-5, atol=1e-5 * float(p.grad.abs().max()))
    with torch.no_grad():
        torch.testing.assert_close(m(x), layer_by_layer(m)(x))


def test_same_parameters_and_state_dict_keys_as_a_sequential():
    m = mlp(25, 64, 1, 3)
    assert list(m.state_dict()) == ["0.weight", "0.bias", "2.weight", "2.bias"]
    ref = nn.Sequential(nn.Linear(25, 64), nn.ReLU(), nn.Linear(64, 3))
    ref.load_state_dict(m.state_dict())
    x = torch.randn(CHUNK_ROWS * 2, 25)
    with torch.no_grad():
        torch.testing.assert_close(m(x), ref(x))
