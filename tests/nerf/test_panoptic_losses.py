import torch

from nerf.panoptic.heads import integrate_probs as integrate
from nerf.panoptic.losses import consistency_loss, instance_loss, semantic_loss


def test_integration_example_and_detached_weights():
    logits = torch.tensor([[20.0, -20.0], [-20.0, 20.0]], requires_grad=True)
    w = torch.tensor([0.5, 0.25], requires_grad=True)
    p = integrate(logits, w, torch.tensor([0, 0]), 2)
    assert torch.allclose(p[0], torch.tensor([2 / 3, 1 / 3]), atol=1e-6)
    assert torch.allclose(p[1], torch.tensor([0.5, 0.5]))       # empty ray -> uniform
    p[0, 0].backward()
    assert w.grad is None and logits.grad is not None


def test_semantic_loss_ignores_void_and_weights_by_confidence():
    p = torch.tensor([[0.9, 0.1], [0.2, 0.8], [0.5, 0.5]])
    labels = torch.tensor([0, 0, 255])
    full = semantic_loss(p, labels, torch.tensor([1.0, 1.0, 1.0]))
    only_first = semantic_loss(p, labels, torch.tensor([1.0, 0.0, 1.0]))
    assert torch.isclose(only_first, -torch.log(torch.tensor(0.9)))
    assert full > only_first


def test_losses_stay_finite_on_zero_probabilities_and_empty_batches():
    p = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], requires_grad=True)
    for loss in (semantic_loss(p, torch.tensor([1, 1]), torch.tensor([1.0, float("nan")])),
                 instance_loss(p, torch.tensor([1, -1])),
                 consistency_loss(p, torch.tensor([0, 0]), 1),
                 instance_loss(p, torch.tensor([-1, -1])),
                 semantic_loss(p, torch.tensor([255, 255]), torch.ones(2))):
        assert torch.isfinite(loss)
        loss.backward(retain_graph=True)
    assert torch.isfinite(p.grad).all()


def test_consistency_is_zero_for_uniform_segments():
    p = torch.tensor([[0.2, 0.8], [0.2, 0.8], [0.9, 0.1]])
    assert consistency_loss(p, torch.tensor([0, 0, -1]), 1) == 0
    assert consistency_loss(p, torch.tensor([0, 0, 0]), 1) > 0


def test_panoptic_losses_move_neither_density_nor_poses():
    from nerf.config import preset
    from nerf.fields import RadianceField
    from nerf.panoptic.heads import PanopticField
    from nerf.poses import PoseCorrection
    from nerf.render import composite_weights

    cfg = preset("cpu", n_levels=4, log2_capacity=10)
    field = RadianceField(cfg, scene_scale_m=1.0)
    poses = PoseCorrection(1, scale_m=1.0)
    pan = PanopticField(cfg.n_levels, cfg.n_features, 8, cfg.coarsest_res_m, cfg.finest_res_m, n_classes=5, n_slots=8)
    c2w = poses.apply(torch.eye(4)[None], torch.tensor([0]))
    x = c2w[0, :3, 3] + torch.rand(32, 3)                         # positions depend on the pose
    d = torch.nn.functional.normalize(torch.rand(32, 3), dim=-1)
    sigma, rgb, g = field(x, d)
    ray = torch.arange(32) // 8
    w, _ = composite_weights(sigma, torch.full((32,), 0.1), ray, 4)
    sem, inst = pan(x, g)
    loss = semantic_loss(integrate(sem, w, ray, 4), torch.tensor([0, 1, 2, 3]), torch.ones(4)) + \
        instance_loss(integrate(inst, w, ray, 4), torch.tensor([1, 2, 0, 3]))
    loss.backward()
    assert field.grid.table.grad is None and all(p.grad is None for p in field.density_net.parameters())
    assert poses.rot6d.grad is None and poses.trans.grad is None
    assert pan.grid.table.grad is not None and pan.grid.table.grad.abs().sum() > 0
