"""The BUP20-style folder: rgb/<stamp>.png or .jpg, depth/<stamp>.png (16-bit, params.yaml's depth_scale_m
metres per unit), odometry.csv, params.yaml."""
from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

from sources.common import (FrameSource, IngestError, Recording, StampUnit, Trajectory, check_auto_period,
                            pose_from_txyzq, read_params, read_stamp)

ODOM_COLUMNS = ["timestamp", "tx", "ty", "tz", "qx", "qy", "qz", "qw"]
IMAGE_KINDS = {".png": "PNG", ".jpg": "JPEG", ".jpeg": "JPEG"}
COLOR_SUFFIXES = (".png", ".jpg", ".jpeg")
DEPTH_SUFFIXES = (".png",)  # 16-bit and lossless: a JPEG cannot hold depth


def read_odometry_csv(path: Path, counts: dict[str, int], stamp_unit: StampUnit = "auto") -> Trajectory:
    if not path.is_file():
        raise IngestError(f"{path} not found: expected odometry.csv with columns {ODOM_COLUMNS}")
    try:
        df = pd.read_csv(path, dtype={"timestamp": str})
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as err:
        raise IngestError(f"{path} is not a readable CSV: {err}") from err
    missing = [c for c in ODOM_COLUMNS if c not in df.columns]
    if missing:
        raise IngestError(f"{path}: columns {missing} missing; columns present: {list(df.columns)}")
    if df.empty:
        raise IngestError(f"{path} has no odometry rows")
    read, how = [], []
    for n, text in enumerate(df["timestamp"]):
        try:
            stamp, unit = read_stamp(str(text), stamp_unit)
        except IngestError as err:
            raise IngestError(f"{path}, data row {n + 1}: timestamp {text!r} is not a time: {err}") from None
        read.append(stamp)
        how.append(unit)
    stamps = np.array(read, np.int64)
    check_auto_period(stamps, how, stamp_unit, f"{path}, column timestamp")
    values = df[ODOM_COLUMNS[1:]].to_numpy(np.float64)
    bad = ~np.isfinite(values).all(1)
    if bad.any():
        counts["odometry_rows_non_finite"] = int(bad.sum())
        stamps, values = stamps[~bad], values[~bad]
    order = np.argsort(stamps, kind="stable")
    if np.any(np.diff(stamps) < 0):
        counts["odometry_out_of_order"] = int(np.sum(np.diff(stamps) < 0))
    stamps, values = stamps[order], values[order]
    keep = np.concatenate([[True], np.diff(stamps) > 0])
    if not keep.all():
        counts["odometry_duplicate_stamps"] = int((~keep).sum())
    try:
        poses = pose_from_txyzq(values[keep])
    except IngestError as err:
        raise IngestError(f"{path}: {err}") from err
    return Trajectory(stamps[keep], poses, str(path))


def images_by_stamp(folder: Path, what: str, suffixes: tuple[str, ...], counts: dict[str, int],
                    notes: list[str], stamp_unit: StampUnit = "auto") -> dict[int, Path]:
    """{stamp_ns: file} of a folder of images named by stamp, with one of `suffixes` (any case). Two names for
    one stamp (1600000000.5.png and 1600000000500000000.png) keep the first by name and are counted; other
    files are counted (`files_not_images`) and named in `notes`."""
    out: dict[int, Path] = {}
    how: list[str] = []
    others = []
    for p in sorted(folder.iterdir()):
        if not (p.is_file() and p.suffix.lower() in suffixes):
            others.append(p.name)
            continue
        try:
            stamp, unit = read_stamp(p.stem, stamp_unit)
        except IngestError as err:
            raise IngestError(f"{p}: {err}; every image in {folder} must be named by its timestamp") from None
        how.append(unit)
        if stamp in out:
            counts[f"{what}_duplicate_stamps"] = counts.get(f"{what}_duplicate_stamps", 0) + 1
            continue
        out[stamp] = p
    check_auto_period(np.array(sorted(out), np.int64), how, stamp_unit, str(folder))
    if others:
        counts["files_not_images"] = counts.get("files_not_images", 0) + len(others)
        kinds = " or ".join(dict.fromkeys(IMAGE_KINDS[s] for s in suffixes))
        shown = ", ".join(others[:5]) + (f" and {len(others) - 5} more" if len(others) > 5 else "")
        notes.append(f"{folder}: {len(others)} entr{'y' if len(others) == 1 else 'ies'} not {kinds} images "
                     f"ignored: {shown}")
    return out


class PngFolder(FrameSource):
    def __init__(self, root: Path, odometry_csv: str = "odometry.csv", stamp_unit: StampUnit = "auto"):
        self.root = root
        rgb_dir, depth_dir = root / "rgb", root / "depth"
        if not rgb_dir.is_dir():
            raise IngestError(f"{rgb_dir} not found: a PNG-layout recording needs rgb/, depth/, odometry.csv "
                              f"and params.yaml (see data/README.md); {root} has: {sorted(p.name for p in root.iterdir())}")
        counts: dict[str, int] = {}
        notes: list[str] = []
        camera, t_rc, self.depth_scale_m = read_params(root / "params.yaml")
        odom = read_odometry_csv(root / odometry_csv, counts, stamp_unit)
        rgb = images_by_stamp(rgb_dir, "color", COLOR_SUFFIXES, counts, notes, stamp_unit)
        if not rgb:
            raise IngestError(f"{rgb_dir} holds no PNG or JPEG images")
        depth = {}
        if depth_dir.is_dir():
            lossy = sorted(p.name for p in depth_dir.iterdir() if p.suffix.lower() in (".jpg", ".jpeg"))
            if lossy:
                raise IngestError(f"{depth_dir / lossy[0]}: depth images must be 16-bit PNGs (a JPEG holds 8 bits, "
                                  f"lossy); {len(lossy)} JPEG file(s) in {depth_dir}")
            depth = images_by_stamp(depth_dir, "depth", DEPTH_SUFFIXES, counts, notes, stamp_unit)
        # file names carry the stamps; their listing order means nothing
        color_stamps = np.array(sorted(rgb), np.int64)
        depth_stamps = np.array(sorted(depth), np.int64)
        self.rgb_files = [rgb[s] for s in color_stamps]
        self.depth_files = [depth[s] for s in depth_stamps]
        self.recording = Recording(camera, t_rc, odom, color_stamps, depth_stamps,
                                   [p.stem for p in self.rgb_files], counts, notes)

    def describe(self) -> str:
        return f"PNG folder {self.root}"

    def where(self, ci: int, di: int) -> str:
        return f"{self.rgb_files[ci]} and {self.depth_files[di]}"

    def frames(self, pairs: list[tuple[int, int]]) -> Iterator[tuple[int, np.ndarray | None, np.ndarray | None, str]]:
        for ci, di in pairs:
            try:
                rgb, depth = self._load(ci, di)
                yield ci, rgb, depth, ""
            except IngestError as err:
                yield ci, None, None, str(err)

    def _load(self, ci: int, di: int) -> tuple[np.ndarray, np.ndarray]:
        rgb_path, depth_path = self.rgb_files[ci], self.depth_files[di]
        img = cv2.imread(str(rgb_path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise IngestError(f"colour image {rgb_path} is not a readable {IMAGE_KINDS[rgb_path.suffix.lower()]} "
                              f"(truncated or corrupt)")
        if img.ndim == 2:
            rgb = cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
        elif img.shape[2] == 4:
            rgb = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
        else:
            rgb = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
        if rgb.dtype != np.uint8:
            raise IngestError(f"colour image {rgb_path}: expected 8-bit, got {rgb.dtype}")
        d = cv2.imread(str(depth_path), cv2.IMREAD_UNCHANGED)
        if d is None:
            raise IngestError(f"depth image {depth_path} is not a readable PNG (truncated or corrupt)")
        if d.ndim != 2 or d.dtype != np.uint16:
            raise IngestError(f"depth image {depth_path}: expected 16-bit single-channel, got {d.dtype} {d.shape}")
        return rgb, d.astype(np.float32) * np.float32(self.depth_scale_m)  # [H, W] metres, 0 = invalid
