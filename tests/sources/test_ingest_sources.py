import shutil
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
import yaml

from raw_helpers import copy_raw, shared_fixture
from pipeline.stage import StageContext
from sources.common import IngestError, pose_from_txyzq
from sources.rosbag import RosBag, Topics
from stages import ingest

TOPICS = Topics("/camera/color/image_raw", "/camera/aligned_depth_to_color/image_raw", "/camera/color/camera_info",
                "/odom", "/tf", "odom", "base_link", "camera_color_optical_frame")


def run_ingest(raw: Path, data_root: Path, tmp: Path, **cfg):
    staging = tmp / f"stage_{len(list(tmp.glob('stage_*')))}"
    staging.mkdir()
    ctx = StageContext(stage="ingest", seq="t", data_root=data_root, staging={"images": staging}, show_progress=False)
    out = ingest.run({"raw": raw}, ingest.Config(**cfg), ctx)
    return out, ctx, staging


def test_png_and_every_bag_format_give_identical_tables(tiny_raw, ros2_bags, tmp_path):
    data_root = tiny_raw.parents[1]
    ref, _, ref_dir = run_ingest(tiny_raw, data_root, tmp_path, source="png")
    gt = pd.read_parquet(tiny_raw / "gt" / "poses.parquet")
    assert len(ref["frames"]) == 8 and ref["frames"]["labelled"].sum() == 2
    for name, bag in [("ros1", "tiny.bag"), ("sqlite3", ros2_bags["sqlite3"]), ("mcap", ros2_bags["mcap"])]:
        out, ctx, out_dir = run_ingest(tiny_raw, data_root, tmp_path, source="bag", bag_path=str(bag))
        pd.testing.assert_frame_equal(out["frames"], ref["frames"], check_exact=False, atol=1e-6, rtol=0)
        pd.testing.assert_frame_equal(out["detections"], ref["detections"])
        for f in ref["frames"]["rgb_path"]:
            name_ = Path(f).name
            for sub in ("rgb", "depth"):
                a = cv2.imread(str(ref_dir / sub / name_), cv2.IMREAD_UNCHANGED)
                b = cv2.imread(str(out_dir / sub / name_), cv2.IMREAD_UNCHANGED)
                assert np.array_equal(a, b), (name, sub, name_)
    # odometry drifts, so compare the camera poses with what odometry.csv implies, not with gt;
    # but the first frame (0.2 s in) is still close to the truth.
    f0 = ref["frames"].iloc[0]
    assert abs(f0.tx - gt.tx.iloc[0]) < 0.01 and abs(f0.tz - gt.tz.iloc[0]) < 1e-6


def test_poses_are_odometry_times_extrinsic(tiny_raw, tmp_path):
    out, _, _ = run_ingest(tiny_raw, tiny_raw.parents[1], tmp_path, source="png")
    odo = pd.read_csv(tiny_raw / "odometry.csv")
    p = yaml.safe_load((tiny_raw / "params.yaml").read_text())
    fr = out["frames"].iloc[3]
    t = fr.stamp_ns
    i = np.searchsorted(odo.timestamp.to_numpy(), t)
    lo, hi = odo.iloc[i - 1], odo.iloc[i]
    a = (t - lo.timestamp) / (hi.timestamp - lo.timestamp)
    base_t = (1 - a) * lo[["tx", "ty", "tz"]].to_numpy(float) + a * hi[["tx", "ty", "tz"]].to_numpy(float)
    base = pose_from_txyzq(np.concatenate([base_t, lo[["qx", "qy", "qz", "qw"]].to_numpy(float)]))
    cam = base @ np.array(p["T_robot_camera"])
    assert np.allclose([fr.tx, fr.ty, fr.tz], cam[:3, 3], atol=1e-4)


# --- bad input -------------------------------------------------------------------------------------

@pytest.mark.parametrize("fixture, message", [
    ("rosbag_js/empty-file.bag", "empty file"),
    ("rosbag_js/no-messages.bag", "has no messages"),
    ("rosbag_js/example.bag", "not in bag; topics: ['/rosout"),
])
def test_real_bad_bags_give_clear_errors(fixture, message, tmp_path):
    raw = tmp_path / "raw"
    raw.mkdir()
    shutil.copy(shared_fixture(fixture), raw / "x.bag")
    with pytest.raises(IngestError, match=None) as err:
        run_ingest(raw, tmp_path, tmp_path)
    assert message in str(err.value) and "x.bag" in str(err.value)


def test_text_file_named_bag(tmp_path):
    raw = tmp_path / "raw"
    raw.mkdir()
    shutil.copy(shared_fixture("rosbag_js/asci-file.txt"), raw / "x.bag")
    with pytest.raises(IngestError, match="is not a readable ROS bag"):
        run_ingest(raw, tmp_path, tmp_path)


def test_unsorted_chunks_bag_reads_in_time_order():
    from sources.rosbag import open_reader
    with open_reader(shared_fixture("rosbag_js/example-unsorted-chunks.bag")) as r:
        stamps = [t for _, t, _ in r.messages()]
    assert stamps and stamps == sorted(stamps)


@pytest.mark.parametrize("dirname", ["images", "images.bag"])
def test_ros2_bag_without_type_definitions_and_with_bag_suffix(dirname, tmp_path):
    bag = tmp_path / dirname
    shutil.copytree(shared_fixture("ros2_images_bag"), bag)
    topics = Topics("/image", "/depth", "/info", "/odom", "/tf", "odom", "base_link", "cam")
    with pytest.raises(IngestError, match=r"topic\(s\) \['/depth'\] not in bag; topics: \['/image \(sensor_msgs/msg/Image, 3 msgs\)'\]"):
        RosBag(bag, topics)
    # the images themselves decode with the ROS 2 type store
    from sources.rosbag import header_stamp, image_to_array, open_reader
    with open_reader(bag) as r:
        imgs = [(header_stamp(m := r.deserialize(raw, c.msgtype), t), image_to_array(m, c.topic, t))
                for c, t, raw in r.messages()]
    assert [i[0] for i in imgs] == [0, 1_000_000_000, 2_000_000_000]
    assert all(np.array_equal(a, [[0, 128], [128, 255]]) for _, a in imgs)


def test_missing_depth_image_is_a_counted_skip(tiny_raw, tmp_path):
    raw = copy_raw(tiny_raw, tmp_path)
    victim = sorted((raw / "depth").iterdir())[2]
    victim.unlink()
    out, ctx, _ = run_ingest(raw, tmp_path, tmp_path, source="png")
    assert len(out["frames"]) == 7 and ctx.summary["skipped_no_depth"] == 1
    assert int(victim.stem) not in out["frames"]["stamp_ns"].tolist()


def test_truncated_png_is_skipped_and_named_or_an_error(tiny_raw, tmp_path):
    raw = copy_raw(tiny_raw, tmp_path)
    victim = sorted((raw / "rgb").iterdir())[1]
    victim.write_bytes(victim.read_bytes()[:60])
    out, ctx, _ = run_ingest(raw, tmp_path, tmp_path, source="png")
    assert ctx.summary["skipped_bad_image"] == 1 and victim.name in ctx.summary["notes"][0]
    assert list(out["frames"]["frame_id"]) == list(range(7))
    with pytest.raises(IngestError, match=f"{victim.name} is not a readable PNG"):
        run_ingest(raw, tmp_path, tmp_path, source="png", on_bad_image="error")


def test_zero_and_nan_depth_become_invalid(tiny_raw, tmp_path):
    raw = copy_raw(tiny_raw, tmp_path)
    first = sorted((raw / "depth").iterdir())[0]
    cv2.imwrite(str(first), np.zeros((32, 48), np.uint16))
    out, ctx, _ = run_ingest(raw, tmp_path, tmp_path, source="png")
    assert out["frames"]["valid_depth_frac"].iloc[0] == 0 and ctx.summary["frames_without_valid_depth"] == 1
    from sources.common import depth_to_mm
    assert depth_to_mm(np.array([[np.nan, np.inf, -1.0, 0.5]])).tolist() == [[0, 0, 0, 500]]


def test_non_monotonic_odometry_is_sorted_and_counted(tiny_raw, tmp_path):
    raw = copy_raw(tiny_raw, tmp_path)
    odo = pd.read_csv(raw / "odometry.csv")
    odo.iloc[::-1].to_csv(raw / "odometry.csv", index=False)
    ref, _, _ = run_ingest(tiny_raw, tiny_raw.parents[1], tmp_path, source="png")
    out, ctx, _ = run_ingest(raw, tmp_path, tmp_path, source="png")
    assert ctx.summary["odometry_out_of_order"] > 0
    assert np.allclose(out["frames"][["tx", "ty", "qw"]], ref["frames"][["tx", "ty", "qw"]])


def test_intrinsics_that_do_not_fit_the_image(tiny_raw, tmp_path):
    raw = copy_raw(tiny_raw, tmp_path)
    p = yaml.safe_load((raw / "params.yaml").read_text())
    p["width"], p["height"] = 640, 360
    (raw / "params.yaml").write_text(yaml.safe_dump(p))
    with pytest.raises(IngestError, match=r"are for 640x360 images but colour image at \d+ ns is 48x32"):
        run_ingest(raw, tmp_path, tmp_path, source="png")
    p["width"], p["height"] = 48, 32
    p["K"][0][2] = 100.0
    (raw / "params.yaml").write_text(yaml.safe_dump(p))
    with pytest.raises(IngestError, match="do not fit a 48x32 image"):
        run_ingest(raw, tmp_path, tmp_path, source="png")


def test_bag_only_folder_is_found_automatically(tiny_raw, tmp_path):
    raw = copy_raw(tiny_raw, tmp_path, drop_png_layout=True)
    out, ctx, _ = run_ingest(raw, tmp_path, tmp_path)
    assert "bag" in ctx.summary["source"] and len(out["frames"]) == 8


def test_missing_raw_layout_lists_what_exists(tmp_path):
    raw = tmp_path / "raw"
    raw.mkdir()
    (raw / "notes.txt").write_text("x")
    with pytest.raises(IngestError, match=r"no bag in .* has: \['notes.txt'\]"):
        run_ingest(raw, tmp_path, tmp_path)
