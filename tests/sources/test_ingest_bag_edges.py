"""Bag edge cases written with rosbags' own ROS 1 writer: header stamps out of log order, duplicate
stamps, 32FC1 depth with NaN/inf, a static-transform chain, an undecodable image message."""
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.stage import StageContext
from sources.common import IngestError, pose_from_txyzq
from stages import ingest

W, H = 8, 6
K = np.array([[10.0, 0, 4.0], [0, 10.0, 3.0], [0, 0, 1]])
T0 = 1_000_000_000
DT = 66_000_000


class TinyBag:
    """Minimal RealSense-style ROS 1 bag; log time and header stamp can differ."""

    def __init__(self, path: Path):
        from rosbags.rosbag1 import Writer
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        self.ts = get_typestore(Stores.ROS1_NOETIC)
        self.ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms\n", "tf2_msgs/msg/TFMessage"))
        self.T = self.ts.types
        self.w = Writer(path)
        self.w.open()
        add = self.w.add_connection
        self.c = {"color": add("/camera/color/image_raw", "sensor_msgs/msg/Image", typestore=self.ts),
                  "depth": add("/camera/aligned_depth_to_color/image_raw", "sensor_msgs/msg/Image", typestore=self.ts),
                  "info": add("/camera/color/camera_info", "sensor_msgs/msg/CameraInfo", typestore=self.ts),
                  "odom": add("/odom", "nav_msgs/msg/Odometry", typestore=self.ts),
                  "tf_static": add("/tf_static", "tf2_msgs/msg/TFMessage", typestore=self.ts, latching=1)}

    def header(self, stamp: int, frame: str = "cam"):
        return self.T["std_msgs/msg/Header"](seq=0, stamp=self.T["builtin_interfaces/msg/Time"](
            sec=stamp // 1_000_000_000, nanosec=stamp % 1_000_000_000), frame_id=frame)

    def put(self, key: str, log_ns: int, msg) -> None:
        self.w.write(self.c[key], log_ns, self.ts.serialize_ros1(msg, msg.__msgtype__))

    def image(self, key: str, log_ns: int, stamp: int, img: np.ndarray, enc: str, truncate: bool = False) -> None:
        data = np.ascontiguousarray(img).view(np.uint8).ravel()
        step = len(data) // img.shape[0]
        self.put(key, log_ns, self.T["sensor_msgs/msg/Image"](
            header=self.header(stamp), height=img.shape[0], width=img.shape[1], encoding=enc, is_bigendian=0,
            step=step, data=data[: len(data) // 2] if truncate else data))

    def info(self, log_ns: int) -> None:
        T = self.T
        p = np.zeros((3, 4))
        p[:, :3] = K
        self.put("info", log_ns, T["sensor_msgs/msg/CameraInfo"](
            header=self.header(log_ns), height=H, width=W, distortion_model="plumb_bob", D=np.zeros(5),
            K=K.ravel(), R=np.eye(3).ravel(), P=p.ravel(), binning_x=0, binning_y=0,
            roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)))

    def static(self, parent: str, child: str, txyzq) -> None:
        T = self.T
        tr = T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=txyzq[0], y=txyzq[1], z=txyzq[2]),
            rotation=T["geometry_msgs/msg/Quaternion"](x=txyzq[3], y=txyzq[4], z=txyzq[5], w=txyzq[6]))
        self.put("tf_static", T0, T["tf2_msgs/msg/TFMessage"](transforms=[T["geometry_msgs/msg/TransformStamped"](
            header=self.header(T0, parent), child_frame_id=child, transform=tr)]))

    def odom(self, stamp: int, x: float) -> None:
        T = self.T
        v = T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
        pose = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=x, y=0.0, z=0.0),
                                           orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))
        self.put("odom", stamp, T["nav_msgs/msg/Odometry"](
            header=self.header(stamp, "odom"), child_frame_id="base_link",
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=T["geometry_msgs/msg/Twist"](linear=v, angular=v),
                                                             covariance=np.zeros(36))))

    def close(self) -> None:
        self.w.close()


OPTICAL_Q = Rotation.from_euler("xyz", [-90, 0, -90], degrees=True).as_quat()


def write_bag(raw: Path, header_order=(0, 1, 2, 3), duplicate=False, depth32=False, truncate=(), chain=False,
              odom_start=-2):
    """Colour+depth at T0 + i*DT for i in header_order, logged in file order; odometry x = 1 m/s * t."""
    raw.mkdir(parents=True)
    rng = np.random.default_rng(0)
    bag = TinyBag(raw / "t.bag")
    if chain:
        bag.static("base_link", "camera_link", (0.1, 0.0, 0.5, 0.0, 0.0, 0.0, 1.0))
        bag.static("camera_link", "camera_color_optical_frame", (0.0, 0.02, 0.0, *OPTICAL_Q))
    else:
        bag.static("base_link", "camera_color_optical_frame", (0.1, 0.0, 0.5, 0.0, 0.0, 0.0, 1.0))
    for i in range(odom_start, odom_start + 12):
        bag.odom(T0 + i * DT // 2, (i * DT // 2) / 1e9)
    images = {}
    order = list(header_order) + ([header_order[0]] if duplicate else [])
    for n, i in enumerate(order):
        log, stamp = T0 + n * DT, T0 + i * DT
        rgb = rng.integers(0, 255, (H, W, 3), dtype=np.uint8)
        images.setdefault(stamp, rgb)
        bag.info(log)
        bag.image("color", log, stamp, rgb, "rgb8", truncate=i in truncate)
        if depth32:
            d = np.full((H, W), 0.75, np.float32)
            d[0, :4] = [np.nan, np.inf, -1.0, 0.0]
            bag.image("depth", log, stamp, d, "32FC1")
        else:
            bag.image("depth", log, stamp, np.full((H, W), 750, np.uint16), "16UC1")
    bag.close()
    return images


def run(tmp_path: Path, **cfg):
    staging = tmp_path / f"stage{len(list(tmp_path.glob('stage*')))}"
    staging.mkdir()
    ctx = StageContext(stage="ingest", seq="t", data_root=tmp_path / "data", staging={"images": staging},
                       show_progress=False)
    out = ingest.run({"raw": tmp_path / "data" / "raw" / "t"}, ingest.Config(**cfg), ctx)
    return out, ctx, staging


def test_header_stamps_out_of_log_order_and_duplicates_are_sorted_and_counted(tmp_path):
    images = write_bag(tmp_path / "data" / "raw" / "t", header_order=(2, 0, 3, 1), duplicate=True)
    out, ctx, staging = run(tmp_path)
    f = out["frames"]
    assert f["stamp_ns"].tolist() == [T0 + i * DT for i in range(4)]
    assert ctx.summary["color_out_of_order"] == 2 and ctx.summary["color_duplicate_stamps"] == 1
    import cv2
    for row in f.itertuples():
        saved = cv2.cvtColor(cv2.imread(str(staging / "rgb" / Path(row.rgb_path).name)), cv2.COLOR_BGR2RGB)
        assert np.array_equal(saved, images[row.stamp_ns])  # the first message of a duplicated stamp wins


def test_32fc1_depth_nan_inf_and_non_positive_become_zero(tmp_path):
    write_bag(tmp_path / "data" / "raw" / "t", depth32=True)
    out, _, staging = run(tmp_path)
    import cv2
    d = cv2.imread(str(staging / "depth" / Path(out["frames"]["depth_path"].iloc[0]).name), cv2.IMREAD_UNCHANGED)
    assert d.dtype == np.uint16 and d[0, :4].tolist() == [0, 0, 0, 0] and d[1, 0] == 750
    assert out["frames"]["valid_depth_frac"].iloc[0] == pytest.approx(1 - 4 / (W * H))
    assert (out["frames"]["depth_scale_m"] == 0.001).all()


def test_static_transform_chain_is_composed(tmp_path):
    write_bag(tmp_path / "data" / "raw" / "t", chain=True)
    out, _, _ = run(tmp_path)
    fr = out["frames"].iloc[1]
    base = pose_from_txyzq(np.array([DT / 1e9, 0, 0, 0, 0, 0, 1]))
    t_rc = pose_from_txyzq(np.array([0.1, 0, 0.5, 0, 0, 0, 1])) @ pose_from_txyzq(np.array([0, 0.02, 0, *OPTICAL_Q]))
    cam = pose_from_txyzq(fr[["tx", "ty", "tz", "qx", "qy", "qz", "qw"]].to_numpy(float))
    assert np.allclose(cam, base @ t_rc, atol=1e-6)


def test_undecodable_image_message_is_skipped_or_an_error(tmp_path):
    write_bag(tmp_path / "data" / "raw" / "t", truncate=(1,))
    out, ctx, _ = run(tmp_path)
    assert len(out["frames"]) == 3 and ctx.summary["skipped_bad_image"] == 1
    assert T0 + DT not in out["frames"]["stamp_ns"].tolist() and "/camera/color/image_raw" in ctx.summary["notes"][0]
    with pytest.raises(IngestError, match="/camera/color/image_raw at 1066000000 ns"):
        run(tmp_path, on_bad_image="error")


def test_no_surviving_frame_is_an_error_with_the_stamp_ranges(tmp_path):
    write_bag(tmp_path / "data" / "raw" / "t", odom_start=20)  # odometry starts 0.46 s after the last frame
    with pytest.raises(IngestError, match=r"no frame has both .* odometry 1660000000\.\.2023000000 ns, "
                                          r"colour 1000000000\.\.1198000000 ns"):
        run(tmp_path)


def test_frames_on_odometry_samples_survive_a_tight_gap_tolerance(tmp_path):
    # odometry every 33 ms and a 0.1 ms gap tolerance: frames that fall on an odometry sample take its pose
    # exactly, however long the gaps beside it
    write_bag(tmp_path / "data" / "raw" / "t")
    out, ctx, _ = run(tmp_path, odom_tolerance_ms=0.1)
    assert out["frames"]["stamp_ns"].tolist() == [T0 + i * DT for i in range(4)]
    assert ctx.summary["skipped_no_odometry"] == 0
