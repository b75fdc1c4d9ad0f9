"""Write a synthetic recording in the formats a real one has: the BUP20-style PNG folder (data/README.md)
and a RealSense-style ROS 1 bag."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from pipeline.classes import DEFAULT_CLASSES, THING_IDS, VOID
from pipeline.images import write_png
from sources import coco

TF_MSG_DEF = "geometry_msgs/TransformStamped[] transforms\n"
POSE_COLUMNS = ["tx", "ty", "tz", "qx", "qy", "qz", "qw"]


def write_params(path: Path, k: np.ndarray, t_robot_camera: np.ndarray, width: int, height: int) -> None:
    path.write_text(yaml.safe_dump({
        "width": int(width), "height": int(height), "depth_scale_m": 0.001,
        "K": [[float(v) for v in row] for row in k],
        "T_robot_camera": [[float(v) for v in row] for row in t_robot_camera],
        "distortion": [0.0] * 5,
        "frame_ids": {"odom": "odom", "robot": "base_link", "camera": "camera_color_optical_frame"},
        "pixel_centre_offset_px": 0.5,
    }, sort_keys=False))


def write_odometry_csv(path: Path, stamps_ns: np.ndarray, txyzq: np.ndarray) -> None:
    df = pd.DataFrame(txyzq, columns=POSE_COLUMNS)
    df.insert(0, "timestamp", np.asarray(stamps_ns, np.int64))
    df.to_csv(path, index=False, float_format="%.9f")


def coco_annotations(labelled: list[tuple[int, np.ndarray, np.ndarray]], width: int, height: int) -> dict:
    """[(stamp_ns, semantic, instance)] -> COCO dict with an RLE mask per ground-truth fruit."""
    images, anns = [], []
    for img_id, (stamp, sem, inst) in enumerate(labelled, start=1):
        images.append({"id": img_id, "file_name": f"rgb/{stamp}.png", "width": int(width), "height": int(height),
                       "stamp_ns": int(stamp)})
        for fid in np.unique(inst[(inst > 0) & np.isin(sem, THING_IDS)]):
            mask = inst == fid
            ys, xs = np.nonzero(mask)
            anns.append({"id": len(anns) + 1, "image_id": img_id, "instance_id": int(fid),
                         "category_id": int(np.bincount(sem[mask]).argmax()), "iscrowd": 0,
                         "area": int(mask.sum()),
                         "bbox": [int(xs.min()), int(ys.min()), int(xs.max() - xs.min() + 1),
                                  int(ys.max() - ys.min() + 1)],
                         "segmentation": coco.encode(mask)})
    cats = [{"id": c.id, "name": c.name, "isthing": int(c.is_thing), "color": list(c.rgb)} for c in DEFAULT_CLASSES]
    return {"info": {"description": "synthetic glasshouse row (pag synth)"}, "images": images,
            "annotations": anns, "categories": cats}


def write_json(path: Path, obj: dict) -> None:
    path.write_text(json.dumps(obj, indent=None, sort_keys=False))


def write_frame_pngs(root: Path, stamp: int, rgb: np.ndarray, depth_mm: np.ndarray, gt_sem: np.ndarray,
                     gt_inst: np.ndarray) -> None:
    write_png(root / "rgb" / f"{stamp}.png", rgb)
    write_png(root / "depth" / f"{stamp}.png", depth_mm)
    write_png(root / "gt" / "semantic" / f"{stamp}.png", gt_sem)
    write_png(root / "gt" / "instance" / f"{stamp}.png", gt_inst)


STUFF_SEGMENT_ID_BASE = 1 << 16
"""Panoptic segment id of a stuff class = this + class id (never one of the 16-bit thing segment ids)."""


class DetectorWriter:
    """The synthetic detector's output in one of the formats real detectors write (docs/detector_formats.md):
    'png_pair' (pred_seg/semantic/, instance/, scores.csv), 'coco_panoptic' (pred_seg/panoptic.json +
    pred_seg/panoptic/<stamp>.png, pixel id = R + 256 G + 256^2 B) or 'coco_instances' (pred_seg/instances.json,
    a COCO results list with RLE masks, + pred_seg/images.json + pred_seg/semantic/ for the stuff).
    All three describe the same segments: thing segment ids, classes and scores are kept."""

    def __init__(self, root: Path, fmt: str, width: int, height: int):
        if fmt not in ("png_pair", "coco_panoptic", "coco_instances"):
            raise ValueError(f"detector format {fmt!r}; formats: png_pair, coco_panoptic, coco_instances")
        self.dir, self.fmt, self.width, self.height = root / "pred_seg", fmt, int(width), int(height)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.scores: list[tuple[int, int, int, float]] = []
        self.images: list[dict] = []
        self.entries: list[dict] = []

    def frame(self, stamp: int, semantic: np.ndarray, instance: np.ndarray,
              segments: list[tuple[int, int, float]]) -> None:
        """One frame: semantic [H, W] class ids (255 void), instance [H, W] segment ids, (id, class, score)."""
        image_id = len(self.images) + 1
        self.images.append({"id": image_id, "file_name": f"rgb/{stamp}.png", "width": self.width,
                            "height": self.height})
        if self.fmt == "png_pair":
            write_png(self.dir / "semantic" / f"{stamp}.png", semantic)
            write_png(self.dir / "instance" / f"{stamp}.png", instance)
            self.scores += [(stamp, sid, klass, score) for sid, klass, score in segments]
        elif self.fmt == "coco_panoptic":
            ids = np.where(instance > 0, instance.astype(np.int64), STUFF_SEGMENT_ID_BASE + semantic.astype(np.int64))
            ids[(instance == 0) & (semantic == VOID)] = 0
            rgb = np.stack([ids % 256, ids // 256 % 256, ids // 65536], -1).astype(np.uint8)
            write_png(self.dir / "panoptic" / f"{stamp}.png", rgb)
            info = [{"id": int(sid), "category_id": int(klass), "isthing": 1, "score": float(score)}
                    for sid, klass, score in segments]
            info += [{"id": STUFF_SEGMENT_ID_BASE + int(c), "category_id": int(c), "isthing": 0}
                     for c in np.unique(semantic[(instance == 0) & (semantic != VOID)])]
            self.entries.append({"image_id": image_id, "file_name": f"{stamp}.png", "segments_info": info})
        else:
            write_png(self.dir / "semantic" / f"{stamp}.png", semantic)
            self.entries += [{"image_id": image_id, "category_id": int(klass), "score": float(score),
                              "segmentation": coco.encode(instance == sid)} for sid, klass, score in segments]

    def close(self) -> None:
        cats = [{"id": c.id, "name": c.name, "isthing": int(c.is_thing)} for c in DEFAULT_CLASSES]
        if self.fmt == "png_pair":
            pd.DataFrame(self.scores, columns=["stamp_ns", "segment_id", "class_id", "score"]).to_csv(
                self.dir / "scores.csv", index=False)
        elif self.fmt == "coco_panoptic":
            write_json(self.dir / "panoptic.json", {"annotations": self.entries, "categories": cats})
        else:
            write_json(self.dir / "instances.json", self.entries)
            write_json(self.dir / "images.json", {"images": self.images, "categories": cats})


class Ros1BagWriter:
    """RealSense-style ROS 1 bag: colour, aligned depth, camera info, odometry and the static extrinsic.
    Messages must be written in time order; header stamps equal the bag record times."""

    def __init__(self, path: Path, topics: dict[str, str]):
        from rosbags.rosbag1 import Writer
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        self.ts = get_typestore(Stores.ROS1_NOETIC)
        if "tf2_msgs/msg/TFMessage" not in self.ts.types:
            self.ts.register(get_types_from_msg(TF_MSG_DEF, "tf2_msgs/msg/TFMessage"))
        self.T = self.ts.types
        self.writer = Writer(path)
        self.writer.open()
        kinds = {"color": "sensor_msgs/msg/Image", "depth": "sensor_msgs/msg/Image",
                 "info": "sensor_msgs/msg/CameraInfo", "odom": "nav_msgs/msg/Odometry",
                 "tf_static": "tf2_msgs/msg/TFMessage"}
        self.conn = {key: self.writer.add_connection(topics[key], kinds[key], typestore=self.ts,
                                                     **({"latching": 1} if key == "tf_static" else {}))
                     for key in kinds}
        self.seq = dict.fromkeys(kinds, 0)

    def _header(self, key: str, stamp_ns: int, frame: str):
        self.seq[key] += 1
        return self.T["std_msgs/msg/Header"](seq=self.seq[key], stamp=self.T["builtin_interfaces/msg/Time"](
            sec=int(stamp_ns // 1_000_000_000), nanosec=int(stamp_ns % 1_000_000_000)), frame_id=frame)

    def _write(self, key: str, stamp_ns: int, msg) -> None:
        self.writer.write(self.conn[key], int(stamp_ns), self.ts.serialize_ros1(msg, msg.__msgtype__))

    def _vec(self, v) -> object:
        return self.T["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))

    def _quat(self, q) -> object:
        return self.T["geometry_msgs/msg/Quaternion"](x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))

    def static_tf(self, stamp_ns: int, parent: str, child: str, txyzq: np.ndarray) -> None:
        T = self.T
        tr = T["geometry_msgs/msg/Transform"](translation=self._vec(txyzq[:3]), rotation=self._quat(txyzq[3:]))
        msg = T["geometry_msgs/msg/TransformStamped"](header=self._header("tf_static", stamp_ns, parent),
                                                      child_frame_id=child, transform=tr)
        self._write("tf_static", stamp_ns, T["tf2_msgs/msg/TFMessage"](transforms=[msg]))

    def odom(self, stamp_ns: int, txyzq: np.ndarray, linear: np.ndarray, angular: np.ndarray, frame: str,
             child: str) -> None:
        T = self.T
        cov = np.zeros(36)
        pose = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](
            x=float(txyzq[0]), y=float(txyzq[1]), z=float(txyzq[2])), orientation=self._quat(txyzq[3:]))
        msg = T["nav_msgs/msg/Odometry"](
            header=self._header("odom", stamp_ns, frame), child_frame_id=child,
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=cov),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](
                twist=T["geometry_msgs/msg/Twist"](linear=self._vec(linear), angular=self._vec(angular)),
                covariance=cov))
        self._write("odom", stamp_ns, msg)

    def image(self, key: str, stamp_ns: int, img: np.ndarray, encoding: str, frame: str) -> None:
        h, w = img.shape[:2]
        data = np.ascontiguousarray(img)
        if data.dtype.byteorder == ">":
            data = data.astype(data.dtype.newbyteorder("<"))
        data = data.view(np.uint8).ravel()
        msg = self.T["sensor_msgs/msg/Image"](header=self._header(key, stamp_ns, frame), height=h, width=w,
                                              encoding=encoding, is_bigendian=0, step=len(data) // h, data=data)
        self._write(key, stamp_ns, msg)

    def camera_info(self, stamp_ns: int, k: np.ndarray, width: int, height: int, frame: str) -> None:
        T = self.T
        p = np.zeros((3, 4))
        p[:, :3] = k
        msg = T["sensor_msgs/msg/CameraInfo"](
            header=self._header("info", stamp_ns, frame), height=int(height), width=int(width),
            distortion_model="plumb_bob", D=np.zeros(5), K=np.asarray(k, np.float64).ravel(), R=np.eye(3).ravel(),
            P=p.ravel(), binning_x=0, binning_y=0,
            roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
        self._write("info", stamp_ns, msg)

    def close(self) -> None:
        self.writer.close()
