import numpy as np
from scipy.spatial.transform import Rotation

from nerf.metrics import ate_rmse, psnr, rotation_error_deg


def test_ate_is_invariant_to_a_rigid_transform_and_sees_noise():
    rng = np.random.default_rng(0)
    gt = np.cumsum(rng.normal(0, 0.05, (40, 3)), 0)
    r = Rotation.from_euler("xyz", [10, -20, 30], degrees=True).as_matrix()
    moved = gt @ r.T + [1.0, -2.0, 0.5]
    assert ate_rmse(moved, gt) < 1e-9
    noisy = moved + rng.normal(0, 0.01, moved.shape)
    assert 0.005 < ate_rmse(noisy, gt) < 0.02
    assert ate_rmse(moved * 2, gt, align="sim3") < 1e-9 and ate_rmse(moved * 2, gt) > 0.01


def test_rotation_error_after_alignment():
    rots = Rotation.random(10, random_state=1).as_matrix()
    common = Rotation.from_euler("z", 40, degrees=True).as_matrix()
    assert rotation_error_deg(np.einsum("ij,njk->nik", common, rots), rots) < 1e-6
    jitter = Rotation.from_rotvec(np.tile([0, 0, np.radians(2.0)], (10, 1))).as_matrix()
    perturbed = np.einsum("nij,njk->nik", rots, jitter)
    assert 0.5 < rotation_error_deg(perturbed, rots) < 2.5


def test_psnr():
    a = np.zeros((4, 4))
    assert psnr(a, a + 0.1) == 20.0
