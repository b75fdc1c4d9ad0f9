import pytest
import torch

from nerf.poses import PoseCorrection, rotation_6d


def test_identity_at_init_and_orthonormal_after_noise():
    p = PoseCorrection(3, scale_m=2.0)
    c2w = torch.eye(4).repeat(3, 1, 1)
    assert torch.allclose(p.apply(c2w, torch.arange(3)), c2w)
    r = rotation_6d(torch.randn(50, 6))
    assert torch.allclose(r @ r.transpose(1, 2), torch.eye(3).expand(50, 3, 3), atol=1e-5)
    assert torch.allclose(torch.det(r), torch.ones(50), atol=1e-5)


def test_degenerate_6d_inputs_give_no_nan_and_finite_gradients():
    a = torch.tensor([[0.0, 0, 0, 0, 0, 0], [1.0, 0, 0, 2.0, 0, 0], [1e-20, 0, 0, 0, 1e-20, 0]], requires_grad=True)
    r = rotation_6d(a)
    r.sum().backward()
    assert torch.isfinite(r).all() and torch.isfinite(a.grad).all()


def test_translation_is_in_scene_units_times_scale():
    p = PoseCorrection(1, scale_m=2.0)
    with torch.no_grad():
        p.trans[0] = torch.tensor([0.01, 0.0, 0.0])
    out = p.apply(torch.eye(4)[None], torch.tensor([0]))
    assert torch.allclose(out[0, :3, 3], torch.tensor([0.02, 0.0, 0.0]))


def test_shift_is_how_far_the_camera_centre_moves_in_metres():
    from nerf.trainer import shift_cost

    p = PoseCorrection(3, scale_m=2.0)
    with torch.no_grad():
        p.trans[:] = torch.tensor([[0.01, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.03, 0.04]])
        p.rot6d[0] = torch.tensor([0.0, 1.0, 0.0, -1.0, 0.0, 0.0])   # a turn: the shift stays the centre's move
    c2w = torch.eye(4).repeat(3, 1, 1)
    c2w[:, :3, 3] = torch.tensor([1.0, 2.0, 3.0])
    moved = (p.apply(c2w, torch.arange(3))[:, :3, 3] - c2w[:, :3, 3]).norm(dim=-1)
    assert torch.allclose(p.shift_m(torch.arange(3)).norm(dim=-1), moved)
    assert torch.allclose(moved, torch.tensor([0.02, 0.0, 0.1]))
    assert float(shift_cost(p, torch.tensor([0, 2])).detach()) == pytest.approx((0.02 ** 2 + 0.1 ** 2) / 2)


def test_a_negative_shift_penalty_is_refused():
    from nerf.config import preset

    with pytest.raises(ValueError, match="pose_shift_penalty must be >= 0"):
        preset("cpu", pose_shift_penalty=-1.0)
