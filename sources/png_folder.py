"""The BUP20-style PNG folder: rgb/<stamp>.png, depth/<stamp>.png (16-bit mm), odometry.csv, params.yaml."""
from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

from sources.common import FrameSource, IngestError, Recording, Trajectory, pose_from_txyzq, read_params, stamp_from_name

ODOM_COLUMNS = ["timestamp", "tx", "ty", "tz", "qx", "qy", "qz", "qw"]


def _is_stamp(text: str) -> bool:
    try:
        stamp_from_name(text)
    except IngestError:
        return False
    return True


def read_odometry_csv(path: Path, counts: dict[str, int]) -> Trajectory:
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
    try:
        stamps = np.array([stamp_from_name(str(s).strip()) for s in df["timestamp"]], np.int64)
    except IngestError:
        bad = next(n for n, s in enumerate(df["timestamp"]) if not _is_stamp(str(s).strip()))
        raise IngestError(f"{path}, data row {bad + 1}: timestamp {df['timestamp'].iloc[bad]!r} is not a time "
                          f"(expected integer ns or decimal seconds)") from None
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


def images_by_stamp(folder: Path, what: str, counts: dict[str, int]) -> dict[int, Path]:
    """{stamp_ns: file} of a folder of PNGs named by stamp; two names for one stamp (1600000000.5.png and
    1600000000500000000.png) keep the first by name and are counted."""
    out: dict[int, Path] = {}
    for p in sorted(folder.glob("*.png")):
        try:
            stamp = stamp_from_name(p.stem)
        except IngestError as err:
            raise IngestError(f"{p}: {err}; every PNG in {folder} must be named by its timestamp") from None
        if stamp in out:
            counts[f"{what}_duplicate_stamps"] = counts.get(f"{what}_duplicate_stamps", 0) + 1
            continue
        out[stamp] = p
    return out


class PngFolder(FrameSource):
    def __init__(self, root: Path, odometry_csv: str = "odometry.csv"):
        self.root = root
        rgb_dir, depth_dir = root / "rgb", root / "depth"
        if not rgb_dir.is_dir():
            raise IngestError(f"{rgb_dir} not found: a PNG-layout recording needs rgb/, depth/, odometry.csv "
                              f"and params.yaml (see data/README.md); {root} has: {sorted(p.name for p in root.iterdir())}")
        counts: dict[str, int] = {}
        camera, t_rc = read_params(root / "params.yaml")
        odom = read_odometry_csv(root / odometry_csv, counts)
        rgb = images_by_stamp(rgb_dir, "color", counts)
        if not rgb:
            raise IngestError(f"{rgb_dir} holds no PNG images")
        depth = images_by_stamp(depth_dir, "depth", counts) if depth_dir.is_dir() else {}
        # file names carry the stamps; their listing order means nothing
        color_stamps = np.array(sorted(rgb), np.int64)
        depth_stamps = np.array(sorted(depth), np.int64)
        self.rgb_files = [rgb[s] for s in color_stamps]
        self.depth_files = [depth[s] for s in depth_stamps]
        self.recording = Recording(camera, t_rc, odom, color_stamps, depth_stamps,
                                   [p.stem for p in self.rgb_files], counts)

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
            raise IngestError(f"colour image {rgb_path} is not a readable PNG (truncated or corrupt)")
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
            raise IngestError(f"depth image {depth_path}: expected 16-bit single-channel mm, got {d.dtype} {d.shape}")
        return rgb, d.astype(np.float32) * 0.001
