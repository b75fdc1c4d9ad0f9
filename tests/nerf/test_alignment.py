"""One aligner (nerf.geometry.align_similarity) for trajectory errors, COLMAP poses, windows and depth tracks:
it gives what each of the aligners it replaced gave (their code kept here as the reference)."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from nerf.geometry import align_similarity, apply_similarity, similarity_matrix


# -- the former implementations, as they were -----------------------------------------------------------
def old_umeyama(src, dst, with_scale):
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    u, d, vt = np.linalg.svd(cov)
    sgn = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sgn[2, 2] = -1
    r = u @ sgn @ vt
    var = (xs ** 2).sum() / len(src)
    s = float(np.trace(np.diag(d) @ sgn) / var) if with_scale and var > 0 else 1.0
    return r, mu_d - s * r @ mu_s, s


def old_colmap_align(src, dst, src_rot=None, dst_rot=None, orientation_weight=1.0):
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    sig_s, sig_d = np.sqrt((xs ** 2).sum(1).mean()), np.sqrt((xd ** 2).sum(1).mean())
    m = xd.T @ xs / len(src) / (sig_s * sig_d)
    if src_rot is not None and dst_rot is not None and orientation_weight > 0:
        m = m + orientation_weight * np.einsum("nij,nkj->ik", dst_rot, src_rot) / len(src_rot)
    u, _, vt = np.linalg.svd(m)
    r = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt)) or 1.0]) @ vt
    s = float((xd * (xs @ r.T)).sum() / (xs ** 2).sum())
    return s, r, mu_d - s * r @ mu_s


def old_rigid_between(src, dst):
    m = np.einsum("nij,nkj->ik", dst[:, :3, :3], src[:, :3, :3])
    u, _, vt = np.linalg.svd(m)
    r = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
    out = np.eye(4)
    out[:3, :3] = r
    out[:3, 3] = (dst[:, :3, 3] - src[:, :3, 3] @ r.T).mean(0)
    return out


def random_case(seed, n, noise):
    rng = np.random.default_rng(seed)
    src = np.tile(np.eye(4), (n, 1, 1))
    src[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    src[:, :3, 3] = rng.normal(size=(n, 3))
    r = Rotation.random(random_state=seed + 100).as_matrix()
    s, t = float(rng.uniform(0.2, 3.0)), rng.normal(size=3)
    dst = apply_similarity(s, r, t, src)
    dst[:, :3, 3] += rng.normal(0, noise, (n, 3))
    dst[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, noise, (n, 3))).as_matrix() @ dst[:, :3, :3]
    return src, dst


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("n", [1, 2, 3, 10])
def test_same_results_as_the_replaced_aligners_on_random_data(seed, n):
    src, dst = random_case(seed, n, noise=0.05)
    ps, pd_, rs, rd = src[:, :3, 3], dst[:, :3, 3], src[:, :3, :3], dst[:, :3, :3]
    # windows onto each other (fusion) and depth tracks onto odometry: orientations only, no scale
    s, r, t = align_similarity(ps, pd_, rs, rd, with_scale=False, position_weight=0.0, orientation_weight=1.0)
    np.testing.assert_allclose(similarity_matrix(s, r, t), old_rigid_between(src, dst), atol=1e-12)
    if n < 2:
        return
    # COLMAP onto odometry: centres and orientations, with scale; and the plain Umeyama of its weight 0
    # (two centres alone leave the rotation about their line free: any answer is right, so weight 0 and the
    # plain Umeyama are compared from three points on)
    for w in (0.0, 1.0, 3.0) if n >= 3 else (1.0, 3.0):
        got = align_similarity(ps, pd_, rs, rd, orientation_weight=w)
        want = old_colmap_align(ps, pd_, rs, rd, orientation_weight=w)
        assert got[0] == pytest.approx(want[0], rel=1e-12)
        np.testing.assert_allclose(got[1], want[1], atol=1e-12)
        np.testing.assert_allclose(got[2], want[2], atol=1e-12)
    # trajectory error (ATE): Umeyama on positions, rigid and similarity
    for with_scale in (False, True) if n >= 3 else ():
        got = align_similarity(ps, pd_, with_scale=with_scale)
        r0, t0, s0 = old_umeyama(ps, pd_, with_scale)
        assert got[0] == pytest.approx(s0, rel=1e-12)
        np.testing.assert_allclose(got[1], r0, atol=1e-12)
        np.testing.assert_allclose(got[2], t0, atol=1e-12)


def test_exact_data_is_recovered_and_degenerate_data_is_refused():
    src, dst = random_case(3, 8, noise=0.0)
    s, r, t = align_similarity(src[:, :3, 3], dst[:, :3, 3], src[:, :3, :3], dst[:, :3, :3], orientation_weight=1.0)
    np.testing.assert_allclose(apply_similarity(s, r, t, src), dst, atol=1e-9)
    with pytest.raises(ValueError, match="coincide"):
        align_similarity(np.zeros((4, 3)), np.ones((4, 3)))
    with pytest.raises(ValueError, match="N >= 2"):
        align_similarity(np.zeros((1, 3)), np.zeros((1, 3)))
    with pytest.raises(ValueError, match="rotations"):
        align_similarity(src[:, :3, 3], dst[:, :3, 3], src[:2, :3, :3], dst[:, :3, :3], orientation_weight=1.0)
