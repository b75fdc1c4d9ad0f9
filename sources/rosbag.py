"""ROS 1 (.bag) and ROS 2 (sqlite3 / mcap) bags, read with the pure-Python rosbags package.

Two passes: the first reads only stamps, camera info, odometry and the static extrinsic; the second
decodes the paired colour/depth images one at a time, so memory stays bounded on long bags.
"""
from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from sources.common import (Camera, FrameSource, IngestError, Recording, Trajectory, depth_scale,
                            pose_from_txyzq, read_params, sort_unique)

TF_TYPES = ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage")


@dataclass(frozen=True)
class Topics:
    color: str
    depth: str
    camera_info: str
    odom: str
    tf: str
    odom_frame: str
    base_frame: str
    camera_frame: str


def is_ros2_dir(path: Path) -> bool:
    return path.is_dir() and (path / "metadata.yaml").is_file()


@contextlib.contextmanager
def open_reader(path: Path):
    """AnyReader on a ROS 1 file, a ROS 2 directory (whatever its name) or an .mcap file, with a ROS 2
    type store for bags that carry no type definitions."""
    from rosbags.highlevel import AnyReader, AnyReaderError
    from rosbags.typesys import Stores, get_typestore

    if not path.exists():
        raise IngestError(f"bag {path} does not exist")
    if path.is_file() and path.stat().st_size == 0:
        raise IngestError(f"bag {path} is an empty file (0 bytes)")
    with contextlib.ExitStack() as stack:
        target = path
        if is_ros2_dir(path) and path.suffix == ".bag":
            # AnyReader takes any path ending in .bag for a ROS 1 file: hand it a link without the suffix.
            tmp = Path(stack.enter_context(tempfile.TemporaryDirectory()))
            target = tmp / path.stem
            os.symlink(path.resolve(), target)
        try:
            reader = stack.enter_context(AnyReader([target], default_typestore=get_typestore(Stores.ROS2_HUMBLE)))
        except (AnyReaderError, OSError, ValueError, KeyError) as err:
            raise IngestError(f"{path} is not a readable ROS bag (expected a ROS 1 .bag file, a ROS 2 bag "
                              f"directory with metadata.yaml, or an .mcap file): {err}") from err
        yield reader


def image_to_array(msg, topic: str, stamp: int) -> np.ndarray:
    """sensor_msgs/Image -> [H, W] or [H, W, C] array honouring step and endianness."""
    enc = msg.encoding.lower()
    kinds = {"rgb8": (np.uint8, 3), "bgr8": (np.uint8, 3), "rgba8": (np.uint8, 4), "bgra8": (np.uint8, 4),
             "mono8": (np.uint8, 1), "8uc1": (np.uint8, 1), "8uc3": (np.uint8, 3), "16uc1": (np.uint16, 1),
             "mono16": (np.uint16, 1), "32fc1": (np.float32, 1)}
    if enc not in kinds:
        raise IngestError(f"topic {topic} at {stamp} ns: image encoding {msg.encoding!r} is not supported; "
                          f"supported: {sorted(kinds)}")
    dtype, ch = kinds[enc]
    dt = np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    row = w * ch * dt.itemsize
    data = np.asarray(msg.data, np.uint8)
    if step < row or len(data) < step * h:
        raise IngestError(f"topic {topic} at {stamp} ns: {h}x{w} {msg.encoding} image needs {row} bytes per row "
                          f"and {step * h} in all, got step {step} and {len(data)} bytes")
    arr = data[: step * h].reshape(h, step)[:, :row].copy().view(dt).reshape(h, w, ch) if h and w else \
        np.zeros((h, w, ch), dt)
    arr = arr.astype(dt.newbyteorder("="))
    if enc.startswith("bgr"):
        arr = arr[:, :, [2, 1, 0]]
    elif enc.startswith("rgba"):
        arr = arr[:, :, :3]
    elif enc.startswith("bgra"):
        arr = arr[:, :, [2, 1, 0]]
    return arr[:, :, 0] if ch == 1 else arr


def header_stamp(msg, fallback: int) -> int:
    h = getattr(msg, "header", None)
    if h is None:
        return fallback
    s = int(h.stamp.sec) * 1_000_000_000 + int(h.stamp.nanosec)
    return s if s > 0 else fallback


def _transform(tf) -> np.ndarray:
    t, q = tf.translation, tf.rotation
    return pose_from_txyzq(np.array([t.x, t.y, t.z, q.x, q.y, q.z, q.w]))


def chain_transform(tfs: dict[tuple[str, str], np.ndarray], parent: str, child: str) -> np.ndarray | None:
    """T_parent_child through a tree of static transforms keyed (parent, child), e.g. base_link ->
    camera_link -> camera_color_frame -> camera_color_optical_frame as a RealSense driver publishes it.
    Walks from `child` up its parents: T_parent_child = T_parent_a @ T_a_b @ ... @ T_z_child. None if the
    frames are not connected."""
    up = {c: (p, t) for (p, c), t in tfs.items()}
    out, frame, seen = np.eye(4), child, set()
    while frame != parent:
        if frame not in up or frame in seen:
            return None
        seen.add(frame)
        frame, t = up[frame]
        out = t @ out
    return out


class RosBag(FrameSource):
    def __init__(self, path: Path, topics: Topics, params_fallback: Path | None = None):
        """`params_fallback`: a params.yaml beside the bag, read for what the bag lacks (intrinsics, the
        extrinsic) and for its depth_scale_m (metres per unit of 16UC1 depth; without it millimetres, REP 118)."""
        self.path = path
        self.topics = topics
        self.depth_scale_m = 0.001
        if params_fallback is not None and params_fallback.is_file():
            try:
                params = yaml.safe_load(params_fallback.read_text())
            except yaml.YAMLError as err:
                raise IngestError(f"{params_fallback} is not valid YAML: {err}") from err
            self.depth_scale_m = depth_scale(params, params_fallback)
        counts: dict[str, int] = {}
        with open_reader(path) as reader:
            conns = {c.topic: c for c in reader.connections}
            available = sorted(f"{t} ({c.msgtype}, {c.msgcount} msgs)" for t, c in conns.items())
            if not conns or sum(c.msgcount for c in reader.connections) == 0:
                raise IngestError(f"bag {path} has no messages; expected {topics.color} and {topics.depth}")
            missing = [t for t in (topics.color, topics.depth) if t not in conns]
            if missing:
                raise IngestError(f"bag {path}: topic(s) {missing} not in bag; topics: {available or 'none'} "
                                  f"(set ingest.color_topic / ingest.depth_topic)")
            color, depth, info, tfs, odom = [], [], None, {}, []
            wanted = [c for c in reader.connections if c.topic in
                      (topics.camera_info, topics.odom, topics.tf, "/tf_static")]
            for conn, t, raw in reader.messages(connections=wanted):
                msg = reader.deserialize(raw, conn.msgtype)
                if conn.topic == topics.camera_info and info is None:
                    info = msg
                elif conn.topic == topics.odom and conn.msgtype.endswith("Odometry"):
                    p = msg.pose.pose
                    odom.append((header_stamp(msg, t), [p.position.x, p.position.y, p.position.z, p.orientation.x,
                                                        p.orientation.y, p.orientation.z, p.orientation.w]))
                elif conn.msgtype in TF_TYPES:
                    for tr in msg.transforms:
                        key = (tr.header.frame_id.lstrip("/"), tr.child_frame_id.lstrip("/"))
                        if key == (topics.odom_frame, topics.base_frame) and conn.topic != "/tf_static" \
                                and topics.odom not in conns:
                            odom.append((header_stamp(tr, t), [tr.transform.translation.x, tr.transform.translation.y,
                                                               tr.transform.translation.z, tr.transform.rotation.x,
                                                               tr.transform.rotation.y, tr.transform.rotation.z,
                                                               tr.transform.rotation.w]))
                        elif conn.topic == "/tf_static":
                            tfs[key] = _transform(tr.transform)
            # colour/depth stamps: headers, read without decoding pixel data beyond the header
            for conn, t, raw in reader.messages(connections=[conns[topics.color], conns[topics.depth]]):
                msg = reader.deserialize(raw, conn.msgtype)
                (color if conn.topic == topics.color else depth).append(header_stamp(msg, t))
        if info is not None:
            camera = Camera(np.array(info.K if hasattr(info, "K") else info.k, np.float64).reshape(3, 3),
                            int(info.width), int(info.height), f"topic {topics.camera_info} in {path}")
        elif params_fallback is not None and params_fallback.is_file():
            camera = read_params(params_fallback)[0]
        else:
            raise IngestError(f"bag {path}: no CameraInfo on {topics.camera_info} and no params.yaml beside it; "
                              f"topics: {available}")
        chained = chain_transform(tfs, topics.base_frame, topics.camera_frame)
        if chained is not None:
            t_rc = chained
        elif params_fallback is not None and params_fallback.is_file():
            t_rc = read_params(params_fallback)[1]
            counts["extrinsic_from_params_yaml"] = 1
        else:
            raise IngestError(f"bag {path}: no /tf_static transform {topics.base_frame} -> {topics.camera_frame} "
                              f"and no params.yaml beside it with T_robot_camera; static transforms: {sorted(tfs)}")
        if not odom:
            raise IngestError(f"bag {path}: no odometry: expected nav_msgs/Odometry on {topics.odom} or "
                              f"{topics.odom_frame} -> {topics.base_frame} on {topics.tf}; topics: {available}")
        st = np.array([s for s, _ in odom], np.int64)
        order = np.argsort(st, kind="stable")
        if np.any(np.diff(st) < 0):
            counts["odometry_out_of_order"] = int(np.sum(np.diff(st) < 0))
        st, vals = st[order], np.array([v for _, v in odom])[order]
        keep = np.concatenate([[True], np.diff(st) > 0])
        if not keep.all():
            counts["odometry_duplicate_stamps"] = int((~keep).sum())
        traj = Trajectory(st[keep], pose_from_txyzq(vals[keep]), f"{topics.odom} in {path}")
        cs = sort_unique(np.array(color, np.int64), "color", counts)
        ds = sort_unique(np.array(depth, np.int64), "depth", counts)
        self.recording = Recording(camera, t_rc, traj, cs, ds, [str(s) for s in cs], counts)

    def describe(self) -> str:
        return f"bag {self.path}"

    def frames(self, pairs: list[tuple[int, int]]) -> Iterator[tuple[int, np.ndarray | None, np.ndarray | None, str]]:
        rec = self.recording
        want_c = {int(rec.color_stamps[c]): c for c, _ in pairs}
        want_d: dict[int, list[int]] = {}
        for c, d in pairs:
            want_d.setdefault(int(rec.depth_stamps[d]), []).append(c)
        rgb_buf: dict[int, np.ndarray] = {}
        depth_buf: dict[int, np.ndarray] = {}
        done: set[int] = set()
        failed: dict[int, str] = {}
        with open_reader(self.path) as reader:
            conns = [c for c in reader.connections if c.topic in (self.topics.color, self.topics.depth)]
            for conn, t, raw in reader.messages(connections=conns):
                msg = reader.deserialize(raw, conn.msgtype)
                s = header_stamp(msg, t)
                if conn.topic == self.topics.color and s in want_c and want_c[s] not in done:
                    try:
                        arr = image_to_array(msg, conn.topic, s)
                        rgb_buf[want_c[s]] = np.repeat(arr[:, :, None], 3, 2) if arr.ndim == 2 else \
                            arr.astype(np.uint8)
                    except IngestError as err:
                        failed.setdefault(want_c[s], str(err))
                elif conn.topic == self.topics.depth and s in want_d:
                    users = [c for c in want_d[s] if c not in done]
                    try:
                        arr = image_to_array(msg, conn.topic, s) if users else None
                    except IngestError as err:
                        for c in users:
                            failed.setdefault(c, str(err))
                        users = []
                    if users:
                        if arr.dtype == np.uint16:
                            d = arr.astype(np.float32) * np.float32(self.depth_scale_m)
                        else:
                            d = np.where(np.isfinite(arr) & (arr > 0), arr, 0).astype(np.float32)
                        for c in users:
                            depth_buf[c] = d
                # a frame whose colour or depth message cannot be decoded comes back with the error (the
                # caller skips and counts it, or stops, per ingest.on_bad_image)
                for c in list(failed):
                    rgb_buf.pop(c, None)
                    depth_buf.pop(c, None)
                    done.add(c)
                    yield c, None, None, failed.pop(c)
                for c in [c for c in rgb_buf if c in depth_buf]:
                    yield c, rgb_buf.pop(c), depth_buf.pop(c), ""
                    done.add(c)
