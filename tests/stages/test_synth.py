"""The synth stage end to end on tiny rows: layout, determinism, ground truth, odometry, detections, bag."""
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from pipeline.images import read_depth_m, read_label, read_rgb
from pipeline.stage import StageContext
from sources import coco
from sources.common import pose_from_txyzq
from stages import synth

TINY = dict(n_frames=8, width=64, height=36, n_labelled=2)


def make(tmp_path: Path, name: str = "a", **kw) -> tuple[Path, StageContext]:
    out = tmp_path / name
    out.mkdir()
    ctx = StageContext(stage="synth", seq="t", data_root=tmp_path, staging={"raw": out}, show_progress=False)
    assert synth.run({}, synth.Config(**{**TINY, **kw}), ctx) == {}
    return out, ctx


@pytest.fixture(scope="module")
def row(tmp_path_factory):
    return make(tmp_path_factory.mktemp("synth"), workers=2)


def stamps_of(root: Path, sub: str = "rgb") -> list[int]:
    return sorted(int(p.stem) for p in (root / sub).glob("*.png"))


def test_layout_matches_data_readme(row):
    root, ctx = row
    stamps = stamps_of(root)
    assert len(stamps) == 8 and stamps[0] == synth.FIRST_STAMP_NS
    assert stamps == [synth.FIRST_STAMP_NS + round(i * 1e9 / 15) for i in range(8)]
    for sub in ("depth", "gt/semantic", "gt/instance", "pred_seg/semantic", "pred_seg/instance"):
        assert stamps_of(root, sub) == stamps, sub
    assert len(stamps_of(root, "seg")) == 2 and set(stamps_of(root, "seg")) < set(stamps[1:-1])
    assert read_rgb(root / "rgb" / f"{stamps[0]}.png").shape == (36, 64, 3)
    assert read_label(root / "gt" / "semantic" / f"{stamps[0]}.png", "gt").max() <= 4
    odo = pd.read_csv(root / "odometry.csv")
    assert list(odo.columns) == ["timestamp", "tx", "ty", "tz", "qx", "qy", "qz", "qw"]
    assert odo["timestamp"].dtype == np.int64
    assert odo["timestamp"].iloc[0] < stamps[0] < stamps[-1] < odo["timestamp"].iloc[-1]
    assert np.all(np.diff(odo["timestamp"]) == 20_000_000)  # 50 Hz
    params = yaml.safe_load((root / "params.yaml").read_text())
    assert {"K", "T_robot_camera", "width", "height", "depth_scale_m"} <= set(params)
    assert np.array(params["K"]).shape == (3, 3) and np.array(params["T_robot_camera"]).shape == (4, 4)
    assert (params["width"], params["height"], params["depth_scale_m"]) == (64, 36, 0.001)
    scores = pd.read_csv(root / "pred_seg" / "scores.csv")
    assert list(scores.columns) == ["stamp_ns", "segment_id", "class_id", "score"]
    for s in stamps:  # every segment of an instance PNG has exactly one score row, and no more
        inst = read_label(root / "pred_seg" / "instance" / f"{s}.png", "det")
        rows = scores[scores.stamp_ns == s]
        assert sorted(rows.segment_id) == sorted(set(np.unique(inst)) - {0}) == list(range(1, len(rows) + 1))
        assert rows.class_id.isin([2, 3, 4]).all() and rows.score.between(0.3, 0.99).all()
    poses = pd.read_parquet(root / "gt" / "poses.parquet")
    assert list(poses.columns) == ["frame_id", "stamp_ns", "tx", "ty", "tz", "qx", "qy", "qz", "qw"]
    assert poses["stamp_ns"].tolist() == stamps
    fruits = pd.read_parquet(root / "gt" / "fruits.parquet")
    assert {"fruit_id", "class_id", "x_m", "y_m", "z_m", "diameter_m", "length_m", "near_row"} <= set(fruits.columns)
    assert fruits["fruit_id"].tolist() == list(range(1, len(fruits) + 1)) and fruits["class_id"].isin([2, 3, 4]).all()
    assert fruits["diameter_nominal_m"].between(0.06, 0.09).all() and fruits["length_m"].between(0.07, 0.11).all()
    # diameter_m is the mesh's mean caliper width: below the widest reading and the shape parameter
    assert (fruits.diameter_m < fruits.diameter_max_m).all()
    assert (fruits.diameter_max_m <= 1.01 * fruits.diameter_nominal_m).all()
    assert (fruits.diameter_m / fruits.diameter_nominal_m).between(0.93, 0.97).all()
    assert yaml.safe_load((root / "gt" / "synth_config.yaml").read_text())["n_frames"] == 8
    assert (root / "t.bag").is_file() and ctx.summary["frames"] == 8 and ctx.summary["fruits_near"] > 5


def test_coco_annotations_round_trip_to_ground_truth(row):
    root, _ = row
    ann = json.loads((root / "annotations.json").read_text())
    assert len(ann["images"]) == 2 and {c["id"] for c in ann["categories"]} == {0, 1, 2, 3, 4}
    for img in ann["images"]:
        stamp = Path(img["file_name"]).stem
        assert img["file_name"] == f"rgb/{stamp}.png"
        gt = read_label(root / "gt" / "instance" / f"{stamp}.png", "gt")
        sem = read_label(root / "gt" / "semantic" / f"{stamp}.png", "gt")
        assert np.array_equal(read_label(root / "seg" / f"{stamp}.png", "seg"), gt)
        mine = [a for a in ann["annotations"] if a["image_id"] == img["id"]]
        assert sorted(a["instance_id"] for a in mine) == sorted(set(np.unique(gt)) - {0})
        for a in mine:
            assert isinstance(a["segmentation"]["counts"], str) and a["segmentation"]["size"] == [36, 64]
            m = coco.decode(a["segmentation"])
            assert np.array_equal(m, gt == a["instance_id"]) and a["area"] == m.sum()
            assert a["category_id"] == np.bincount(sem[m]).argmax() and a["iscrowd"] == 0


def test_depth_agrees_with_fruit_geometry_and_far_fruits_are_far(row):
    root, _ = row
    fruits = pd.read_parquet(root / "gt" / "fruits.parquet").set_index("fruit_id")
    poses = pd.read_parquet(root / "gt" / "poses.parquet")
    assert fruits["near_row"].any() and (~fruits["near_row"]).any()
    checked = {True: 0, False: 0}
    for p in poses.itertuples():
        c2w = pose_from_txyzq(np.array([p.tx, p.ty, p.tz, p.qx, p.qy, p.qz, p.qw]))
        inst = read_label(root / "gt" / "instance" / f"{p.stamp_ns}.png", "gt")
        depth = read_depth_m(root / "depth" / f"{p.stamp_ns}.png", 0.001)
        for fid in set(np.unique(inst)) - {0}:
            f = fruits.loc[fid]
            m = inst == fid
            assert np.all(depth[m] > 0)
            assert (depth[m].min() > 1.5) == (not f.near_row)
            if m.sum() < 30:
                continue
            centre_cam = c2w[:3, :3].T @ (np.array([f.x_m, f.y_m, f.z_m]) - c2w[:3, 3])
            # the nearest visible point of a pepper is about its radius in front of its centre
            assert abs(depth[m].min() - (centre_cam[2] - f.diameter_m / 2)) < 0.02, (fid, p.frame_id)
            checked[bool(f.near_row)] += 1
    assert checked[True] > 5


def test_odometry_starts_true_and_drifts_with_distance(tmp_path):
    root, _ = make(tmp_path, n_frames=4, fps=1.0, width=16, height=12, n_labelled=0, odom_noise_m=0.0,
                   write_bag=False, speed_m_per_s=0.3)
    odo = pd.read_csv(root / "odometry.csv")
    gt = pd.read_parquet(root / "gt" / "poses.parquet")
    t_rc = np.array(yaml.safe_load((root / "params.yaml").read_text())["T_robot_camera"])
    errors = []
    for p in gt.itertuples():
        base = pose_from_txyzq(np.array([p.tx, p.ty, p.tz, p.qx, p.qy, p.qz, p.qw])) @ np.linalg.inv(t_rc)
        xy = [np.interp(p.stamp_ns, odo.timestamp, odo[c]) for c in ("tx", "ty")]
        errors.append(float(np.hypot(*(base[:2, 3] - xy))))
        assert np.interp(p.stamp_ns, odo.timestamp, odo.tz) == pytest.approx(base[2, 3])
    assert errors[0] < 0.003 and np.all(np.diff(errors) > 0)
    driven = gt.tx.iloc[-1] - gt.tx.iloc[0] + 0.06
    assert 0.01 * driven < errors[-1] < 0.15 * driven


def test_same_seed_same_bytes_whatever_the_threads_other_seed_differs(tmp_path):
    a, _ = make(tmp_path, "a", n_frames=3, n_labelled=1, workers=1)
    b, _ = make(tmp_path, "b", n_frames=3, n_labelled=1, workers=3)
    c, _ = make(tmp_path, "c", n_frames=3, n_labelled=1, seed=5, write_bag=False)
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    for rel in files:
        assert (a / rel).read_bytes() == (b / rel).read_bytes(), rel
    for rel in ("odometry.csv", "gt/fruits.parquet", f"rgb/{synth.FIRST_STAMP_NS}.png",
                f"pred_seg/instance/{synth.FIRST_STAMP_NS}.png"):
        assert (a / rel).read_bytes() != (c / rel).read_bytes(), rel


def test_knobs_change_the_row(tmp_path):
    root, ctx = make(tmp_path, n_frames=2, n_labelled=0, write_bag=False, fruits_per_m=0.0, det_false_pos_rate=0.0)
    assert len(pd.read_parquet(root / "gt" / "fruits.parquet")) == 0
    assert read_label(root / "gt" / "instance" / f"{synth.FIRST_STAMP_NS}.png", "gt").max() == 0
    assert pd.read_csv(root / "pred_seg" / "scores.csv").empty


def test_bag_matches_the_png_folder(row):
    from rosbags.highlevel import AnyReader

    root, _ = row
    stamps = stamps_of(root)
    odo = pd.read_csv(root / "odometry.csv")
    params = yaml.safe_load((root / "params.yaml").read_text())
    seen: dict[str, list] = {}
    with AnyReader([root / "t.bag"]) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        assert types == {"/camera/color/image_raw": "sensor_msgs/msg/Image",
                         "/camera/aligned_depth_to_color/image_raw": "sensor_msgs/msg/Image",
                         "/camera/color/camera_info": "sensor_msgs/msg/CameraInfo",
                         "/odom": "nav_msgs/msg/Odometry", "/tf_static": "tf2_msgs/msg/TFMessage"}
        last = 0
        for conn, t, raw in reader.messages():
            assert t >= last
            last = t
            msg = reader.deserialize(raw, conn.msgtype)
            stamp = msg.transforms[0].header.stamp if conn.topic == "/tf_static" else msg.header.stamp
            assert stamp.sec * 1_000_000_000 + stamp.nanosec == t
            seen.setdefault(conn.topic, []).append((t, msg))
    assert [t for t, _ in seen["/camera/color/image_raw"]] == stamps
    assert [t for t, _ in seen["/camera/aligned_depth_to_color/image_raw"]] == stamps
    assert [t for t, _ in seen["/camera/color/camera_info"]] == stamps
    for (t, c), (_, d) in zip(seen["/camera/color/image_raw"], seen["/camera/aligned_depth_to_color/image_raw"]):
        assert c.encoding == "rgb8" and d.encoding == "16UC1" and c.header.frame_id == "camera_color_optical_frame"
        rgb = np.frombuffer(c.data, np.uint8).reshape(c.height, c.width, 3)
        assert np.array_equal(rgb, read_rgb(root / "rgb" / f"{t}.png"))
        mm = np.frombuffer(d.data, "<u2").reshape(d.height, d.width)
        assert np.array_equal(mm, read_label(root / "depth" / f"{t}.png", "depth"))
    info = seen["/camera/color/camera_info"][0][1]
    assert np.allclose(np.array(info.K).reshape(3, 3), params["K"]) and (info.width, info.height) == (64, 36)
    assert info.distortion_model == "plumb_bob" and not np.any(info.D)
    odom = seen["/odom"]
    assert [t for t, _ in odom] == odo["timestamp"].tolist()
    m = odom[-1][1]
    assert (m.header.frame_id, m.child_frame_id) == ("odom", "base_link")
    assert np.allclose([m.pose.pose.position.x, m.pose.pose.position.y, m.pose.pose.orientation.w],
                       odo[["tx", "ty", "qw"]].iloc[-1], atol=1e-8)
    (t_tf, tf), = seen["/tf_static"]
    tr = tf.transforms[0]
    assert t_tf == odo["timestamp"].iloc[0]
    assert (tr.header.frame_id, tr.child_frame_id) == ("base_link", "camera_color_optical_frame")
    q = tr.transform.rotation
    v = tr.transform.translation
    assert np.allclose(pose_from_txyzq(np.array([v.x, v.y, v.z, q.x, q.y, q.z, q.w])), params["T_robot_camera"])


def test_detector_ids_change_between_frames_but_ground_truth_ids_do_not(row):
    root, _ = row
    stamps = stamps_of(root)
    fruits = pd.read_parquet(root / "gt" / "fruits.parquet")
    changed, shared = 0, 0
    prev = None
    for s in stamps:
        gt = read_label(root / "gt" / "instance" / f"{s}.png", "gt")
        det = read_label(root / "pred_seg" / "instance" / f"{s}.png", "det")
        # the detector segment covering most of each ground-truth fruit
        cur = {int(f): int(np.bincount(det[gt == f]).argmax()) for f in set(np.unique(gt)) - {0}}
        cur = {f: d for f, d in cur.items() if d}
        if prev is not None:
            common = set(cur) & set(prev)
            shared += len(common)
            changed += sum(cur[f] != prev[f] for f in common)
        prev = cur
        assert set(np.unique(gt)) - {0} <= set(fruits["fruit_id"])
    assert shared > 10 and changed > shared / 3
    vis = fruits.set_index("fruit_id")["n_frames_visible"]
    assert vis.max() == len(stamps)  # some fruit keeps its ground-truth id in every frame


@pytest.mark.parametrize("bad, message", [
    (dict(det_miss_rate=1.5), "det_miss_rate must be in"),
    (dict(n_frames=0), "n_frames must be > 0"),
    (dict(n_frames=4, n_labelled=3), "n_labelled"),
    (dict(far_row_distance_m=0.8), "far_row_distance_m"),
    (dict(ripeness_mix=(0.0, 0.0, 0.0)), "ripeness_mix"),
])
def test_bad_knobs_are_clear_errors(bad, message):
    with pytest.raises(ValueError, match=message):
        synth.Config(**bad)


def test_presets_fill_unset_sizes_and_explicit_settings_win():
    small, bup = synth.Config(), synth.Config(preset="bup20")
    assert (small.width, small.height, small.n_frames, small.n_labelled) == (320, 180, 120, 3)
    assert (bup.width, bup.height, bup.fps, bup.speed_m_per_s) == (1280, 720, 15.0, 0.2)
    row_m = bup.n_frames / bup.fps * bup.speed_m_per_s
    assert bup.n_frames >= 450 and row_m >= 6.0
    gaps_m = np.diff([0, *synth.labelled_frames(bup), bup.n_frames - 1]) / bup.fps * bup.speed_m_per_s
    assert np.all(np.abs(gaps_m - 1.0) < 0.02)  # a labelled frame every metre, a metre from either end
    over = synth.Config(preset="bup20", width=640, height=360, n_frames=60, n_labelled=1)
    assert (over.width, over.height, over.n_frames, over.n_labelled, over.fps) == (640, 360, 60, 1, 15.0)
    with pytest.raises(ValueError, match="preset must be one of"):
        synth.Config(preset="huge")


def test_preset_through_the_config_layer_and_set_overrides():
    from pipeline import config as cfgmod

    cfg = cfgmod.build(synth.Config, cfgmod.parse_set(["synth.preset=bup20", "synth.n_frames=30"])["synth"], "synth")
    assert (cfg.width, cfg.n_frames, cfg.n_labelled) == (1280, 30, 5)
    # the resolved config round-trips (the runner writes and hashes it)
    again = cfgmod.build(synth.Config, cfgmod.to_dict(cfg), "synth")
    assert again == cfg
