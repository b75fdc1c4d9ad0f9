"""Write a synthetic recording in the real formats: the BUP20-style PNG folder and a ROS 1 bag."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from pipeline.classes import DEFAULT_CLASSES
from pipeline.images import write_png
from sources import coco

TF_MSG_DEF = "geometry_msgs/TransformStamped[] transforms\n"


def depth_to_mm(depth_m: np.ndarray) -> np.ndarray:
    mm = np.round(depth_m * 1000.0)
    return np.where((mm > 0) & (mm < 65535), mm, 0).astype(np.uint16)


def write_params(path: Path, k: np.ndarray, t_robot_camera: np.ndarray, width: int, height: int) -> None:
    path.write_text(yaml.safe_dump({
        "width": int(width), "height": int(height), "depth_scale_m": 0.001,
        "K": [[float(v) for v in row] for row in k],
        "T_robot_camera": [[float(v) for v in row] for row in t_robot_camera],
    }, sort_keys=False))


def write_odometry_csv(path: Path, stamps_ns: np.ndarray, txyzq: np.ndarray) -> None:
    df = pd.DataFrame(txyzq, columns=["tx", "ty", "tz", "qx", "qy", "qz", "qw"])
    df.insert(0, "timestamp", stamps_ns.astype(np.int64))
    df.to_csv(path, index=False, float_format="%.9f")


def coco_annotations(labelled: list[tuple[int, np.ndarray, np.ndarray]], width: int, height: int) -> dict:
    """[(stamp_ns, semantic, instance)] -> COCO dict with RLE masks of every thing instance."""
    images, anns = [], []
    things = [c.id for c in DEFAULT_CLASSES if c.is_thing]
    for img_id, (stamp, sem, inst) in enumerate(labelled, start=1):
        images.append({"id": img_id, "file_name": f"rgb/{stamp}.png", "width": width, "height": height})
        for fid in np.unique(inst[(inst > 0) & np.isin(sem, things)]):
            mask = inst == fid
            ys, xs = np.nonzero(mask)
            anns.append({"id": len(anns) + 1, "image_id": img_id, "instance_id": int(fid),
                         "category_id": int(np.bincount(sem[mask]).argmax()), "iscrowd": 0,
                         "area": int(mask.sum()), "bbox": [int(xs.min()), int(ys.min()),
                                                          int(xs.max() - xs.min() + 1), int(ys.max() - ys.min() + 1)],
                         "segmentation": coco.encode(mask)})
    cats = [{"id": c.id, "name": c.name, "isthing": int(c.is_thing)} for c in DEFAULT_CLASSES]
    return {"images": images, "annotations": anns, "categories": cats}


def write_frame_pngs(root: Path, stamp: int, frame: dict, det: tuple) -> None:
    write_png(root / "rgb" / f"{stamp}.png", frame["rgb"])
    write_png(root / "depth" / f"{stamp}.png", depth_to_mm(frame["depth"]))
    write_png(root / "gt" / "semantic" / f"{stamp}.png", frame["semantic"])
    write_png(root / "gt" / "instance" / f"{stamp}.png", frame["instance"])
    write_png(root / "pred_seg" / "semantic" / f"{stamp}.png", det[0])
    write_png(root / "pred_seg" / "instance" / f"{stamp}.png", det[1])


def write_json(path: Path, obj: dict) -> None:
    path.write_text(json.dumps(obj))


class Ros1BagWriter:
    """RealSense-style ROS 1 bag: colour, aligned depth, camera info, odometry and the static extrinsic."""

    def __init__(self, path: Path, color_topic: str, depth_topic: str, info_topic: str, odom_topic: str):
        from rosbags.rosbag1 import Writer
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        self.ts = get_typestore(Stores.ROS1_NOETIC)
        self.ts.register(get_types_from_msg(TF_MSG_DEF, "tf2_msgs/msg/TFMessage"))
        self.writer = Writer(path)
        self.writer.open()
        t = self.ts.types
        self.T = t
        self.conn = {
            "color": self.writer.add_connection(color_topic, "sensor_msgs/msg/Image", typestore=self.ts),
            "depth": self.writer.add_connection(depth_topic, "sensor_msgs/msg/Image", typestore=self.ts),
            "info": self.writer.add_connection(info_topic, "sensor_msgs/msg/CameraInfo", typestore=self.ts),
            "odom": self.writer.add_connection(odom_topic, "nav_msgs/msg/Odometry", typestore=self.ts),
            "tf_static": self.writer.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=self.ts,
                                                    latching=1),
        }
        self.seq = 0

    def header(self, stamp_ns: int, frame: str):
        self.seq += 1
        return self.T["std_msgs/msg/Header"](seq=self.seq, stamp=self.T["builtin_interfaces/msg/Time"](
            sec=int(stamp_ns // 1_000_000_000), nanosec=int(stamp_ns % 1_000_000_000)), frame_id=frame)

    def _write(self, key: str, stamp_ns: int, msg) -> None:
        self.writer.write(self.conn[key], int(stamp_ns), self.ts.serialize_ros1(msg, msg.__msgtype__))

    def _pose(self, txyzq: np.ndarray):
        T = self.T
        return T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=float(txyzq[0]), y=float(txyzq[1]), z=float(txyzq[2])),
            orientation=T["geometry_msgs/msg/Quaternion"](x=float(txyzq[3]), y=float(txyzq[4]),
                                                          z=float(txyzq[5]), w=float(txyzq[6])))

    def static_tf(self, stamp_ns: int, parent: str, child: str, txyzq: np.ndarray) -> None:
        T = self.T
        tr = T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=float(txyzq[0]), y=float(txyzq[1]), z=float(txyzq[2])),
            rotation=T["geometry_msgs/msg/Quaternion"](x=float(txyzq[3]), y=float(txyzq[4]),
                                                       z=float(txyzq[5]), w=float(txyzq[6])))
        ts = T["geometry_msgs/msg/TransformStamped"](header=self.header(stamp_ns, parent), child_frame_id=child,
                                                     transform=tr)
        self._write("tf_static", stamp_ns, T["tf2_msgs/msg/TFMessage"](transforms=[ts]))

    def odom(self, stamp_ns: int, txyzq: np.ndarray) -> None:
        T = self.T
        cov = np.zeros(36)
        msg = T["nav_msgs/msg/Odometry"](
            header=self.header(stamp_ns, "odom"), child_frame_id="base_link",
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=self._pose(txyzq), covariance=cov),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](
                twist=T["geometry_msgs/msg/Twist"](linear=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                                                   angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)),
                covariance=cov))
        self._write("odom", stamp_ns, msg)

    def image(self, key: str, stamp_ns: int, img: np.ndarray, encoding: str, frame: str) -> None:
        h, w = img.shape[:2]
        data = np.ascontiguousarray(img).view(np.uint8).ravel()
        msg = self.T["sensor_msgs/msg/Image"](header=self.header(stamp_ns, frame), height=h, width=w,
                                              encoding=encoding, is_bigendian=0, step=len(data) // h, data=data)
        self._write(key, stamp_ns, msg)

    def camera_info(self, stamp_ns: int, k: np.ndarray, width: int, height: int, frame: str) -> None:
        T = self.T
        p = np.zeros((3, 4))
        p[:, :3] = k
        msg = T["sensor_msgs/msg/CameraInfo"](
            header=self.header(stamp_ns, frame), height=height, width=width, distortion_model="plumb_bob",
            D=np.zeros(5), K=k.ravel().astype(np.float64), R=np.eye(3).ravel(), P=p.ravel(), binning_x=0,
            binning_y=0, roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                                  do_rectify=False))
        self._write("info", stamp_ns, msg)

    def close(self) -> None:
        self.writer.close()
