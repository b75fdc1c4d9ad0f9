"""Textures, meshes and exact ray casting of the synthetic row, on tiny hand-built scenes."""
import numpy as np
import open3d as o3d

from synthetic import meshes, render
from synthetic import scene as S
from synthetic.textures import fbm, value_noise
from synthetic.trajectory import R_BASE_CAMERA

K = np.array([[40.0, 0.0, 24.0], [0.0, 40.0, 16.0], [0.0, 0.0, 1.0]])
W, H = 48, 32


def test_value_noise_is_deterministic_bounded_and_smooth():
    p = np.random.default_rng(0).uniform(-3, 3, (2000, 3))
    a, b = value_noise(p, 0.05, seed=4), value_noise(p, 0.05, seed=4)
    assert np.array_equal(a, b) and a.dtype == np.float32
    assert 0.0 <= a.min() and a.max() <= 1.0 and a.std() > 0.05
    assert not np.array_equal(a, value_noise(p, 0.05, seed=5))
    step = value_noise(p + [1e-4, 0, 0], 0.05, seed=4) - a  # 1/500 of a feature: tiny change
    assert np.abs(step).max() < 0.02
    f = fbm(p, 0.05, 3, seed=1)
    assert 0.0 <= f.min() and f.max() <= 1.0


def test_pepper_is_closed_outward_and_of_the_asked_size():
    m = meshes.pepper(0.08, 0.1, 4, 0.3)
    legacy = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(m.vertices.astype(float)),
                                       o3d.utility.Vector3iVector(m.triangles))
    assert legacy.is_watertight()
    ext = m.vertices.max(0) - m.vertices.min(0)
    assert 0.07 < ext[0] < 0.09 and 0.07 < ext[1] < 0.09 and 0.085 < ext[2] < 0.105
    centroids = m.vertices[m.triangles].mean(1)
    normals = m.corner_normals().mean(1)
    assert np.mean(np.sum(normals * centroids, 1) > 0) > 0.97


def test_calipers_measure_widths_across_the_axis():
    ang = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    circle = np.stack([0.03 * np.cos(ang), 0.03 * np.sin(ang), np.linspace(-1, 1, 720)], 1)
    mean, widest = meshes.calipers(circle)
    assert abs(mean - 0.06) < 1e-4 and abs(widest - 0.06) < 1e-4          # z does not count
    ellipse = circle * [2.0, 1.0, 1.0]                                     # semi-axes 6 and 3 cm
    mean, widest = meshes.calipers(ellipse)
    assert abs(widest - 0.12) < 1e-4 and 0.06 < mean < 0.12
    # a lobed pepper is narrower than its shape parameter on average; its widest reading is close to it
    for lobes in (3, 4):
        mean, widest = meshes.calipers(meshes.pepper(0.08, 0.1, lobes, 0.3).vertices)
        assert 0.93 * 0.08 < mean < 0.97 * 0.08 and mean < widest < 1.01 * 0.08


def test_box_normals_point_out_and_tube_follows_its_polyline():
    b = meshes.box([0, 0, 0], [1, 2, 3])
    c = b.vertices[b.triangles].mean(1) - [0.5, 1.0, 1.5]
    assert np.all(np.sum(b.corner_normals()[:, 0] * c, 1) > 0)
    t = meshes.tube(np.array([[0, 0, 0], [0, 0, 1.0]]), 0.1, res=8)
    assert np.allclose(np.hypot(t.vertices[:, 0], t.vertices[:, 1]), 0.1, atol=1e-6)


def _wall_scene(distance_m: float, with_fruit: bool) -> S.Scene:
    """A textured wall at y = distance_m and, optionally, a pepper (fruit id 1, red) 0.3 m in front of it."""
    b = S.SceneBuilder()
    b.add(meshes.box([-5, distance_m, -5], [5, distance_m + 0.1, 5]), np.eye(3), np.zeros(3), S.WALL, S.BACKGROUND)
    fruits = []
    if with_fruit:
        c = np.array([0.0, distance_m - 0.3, 0.0])
        b.add(meshes.pepper(0.08, 0.09, 4, 0.0), np.eye(3), c, S.FRUIT, S.RED, 1, param=(0.5, 0.09, 0.08, 4.0))
        fruits.append(S.Fruit(1, S.RED, tuple(c), 0.08, 0.09, True))
    return b.build(fruits, seed=0)


def _camera(x: float) -> np.ndarray:
    c2w = np.eye(4)
    c2w[:3, :3] = R_BASE_CAMERA  # looking along world +y, image x along world +x, image y down
    c2w[:3, 3] = [x, 0.0, 0.0]
    return c2w


def test_depth_is_z_depth_not_ray_length_and_labels_are_exact():
    sc = _wall_scene(1.0, with_fruit=True)
    out = render.render(sc, _camera(0.0), K, W, H, supersample=2)
    d = out["depth"]
    wall = out["instance"] == 0
    assert np.allclose(d[wall], 1.0, atol=1e-5)  # a plane facing the camera has one z-depth everywhere
    fruit = out["instance"] == 1
    assert fruit.any() and np.all(out["semantic"][fruit] == S.RED) and np.all(out["semantic"][wall] == 0)
    # the pepper's front is ~ its radius in front of its centre (0.7 m)
    assert abs(d[H // 2, W // 2] - (0.7 - 0.04)) < 0.01
    assert d[fruit].max() < 0.72


def test_colour_is_view_independent_image_shifts_by_whole_pixels():
    sc = _wall_scene(2.0, with_fruit=False)
    shift_px = 5
    a = render.render(sc, _camera(0.0), K, W, H, supersample=2)["rgb"].astype(int)
    b = render.render(sc, _camera(shift_px * 2.0 / K[0, 0]), K, W, H, supersample=2)["rgb"].astype(int)
    # moving the camera right by 5 pixel footprints moves the wall 5 pixels left
    assert np.abs(a[:, shift_px:] - b[:, :-shift_px]).max() <= 1
    assert a.std() > 3  # textured


def test_supersampling_modes_agree_on_labels():
    sc = _wall_scene(1.0, with_fruit=True)
    outs = [render.render(sc, _camera(0.0), K, W, H, supersample=s) for s in (1, 2, 3)]
    for o in outs[1:]:
        assert np.array_equal(o["instance"], outs[0]["instance"]) and np.array_equal(o["depth"], outs[0]["depth"])
        assert np.abs(o["rgb"].astype(int) - outs[0]["rgb"]).mean() < 12
