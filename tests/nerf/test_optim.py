import torch

from nerf.optim import adam


def test_fused_adam_takes_the_same_steps_as_plain_adam():
    torch.manual_seed(0)
    a = [torch.nn.Parameter(torch.randn(4096, 2)), torch.nn.Parameter(torch.randn(16, 8))]
    b = [torch.nn.Parameter(p.detach().clone()) for p in a]
    groups = lambda ps: [{"params": [ps[0]], "eps": 1e-15}, {"params": [ps[1]], "weight_decay": 1e-6}]  # noqa: E731
    fast, plain = adam(groups(a), lr=1e-2), torch.optim.Adam(groups(b), lr=1e-2)
    assert fast.defaults.get("fused") is True  # the fused kernel exists for CPU tensors
    for step in range(5):
        g = [torch.randn_like(p) for p in a]
        g[0][::3] = 0  # most table rows see no gradient in a step
        for ps, opt in ((a, fast), (b, plain)):
            for p, gi in zip(ps, g):
                p.grad = gi.clone()
            opt.step()
        for p, q in zip(a, b):
            torch.testing.assert_close(p, q, rtol=1e-5, atol=1e-6)
