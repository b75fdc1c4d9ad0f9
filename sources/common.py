"""What every source of a recorded row provides, and the shared pieces: stamps, pairing, pose
interpolation, intrinsics checks, depth conversion."""
from __future__ import annotations

import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml
from scipy.spatial.transform import Rotation, Slerp


class IngestError(ValueError):
    """A recording cannot be read as expected; the message names the file, topic or frame."""


@dataclass
class Camera:
    k: np.ndarray
    """[3, 3] intrinsics."""
    width: int
    height: int
    origin: str
    """where the intrinsics came from (file or topic), for errors."""

    def check(self, width: int, height: int, where: str) -> None:
        """Intrinsics must fit the image they describe."""
        fx, fy, cx, cy = self.k[0, 0], self.k[1, 1], self.k[0, 2], self.k[1, 2]
        if (self.width, self.height) != (width, height):
            raise IngestError(f"intrinsics from {self.origin} are for {self.width}x{self.height} images but "
                              f"{where} is {width}x{height}")
        if not (fx > 0 and fy > 0 and 0 < cx < width and 0 < cy < height) or not np.isfinite(self.k).all():
            raise IngestError(f"intrinsics from {self.origin} do not fit a {width}x{height} image: "
                              f"fx={fx:g} fy={fy:g} cx={cx:g} cy={cy:g} (expected fx, fy > 0, 0 < cx < width, "
                              f"0 < cy < height)")


@dataclass
class Trajectory:
    stamps_ns: np.ndarray
    """[K] increasing."""
    poses: np.ndarray
    """[K, 4, 4] base-to-world."""
    origin: str


@dataclass
class Recording:
    """Metadata of a recording, before any image is decoded."""

    camera: Camera
    t_robot_camera: np.ndarray
    """[4, 4] camera-to-robot extrinsic."""
    odometry: Trajectory
    color_stamps: np.ndarray
    """[N] colour image stamps (sorted, unique)."""
    depth_stamps: np.ndarray
    """[M] depth image stamps (sorted, unique)."""
    color_names: list[str]
    """per colour image: the name used to find its detector / annotation files (file stem or stamp)."""
    counts: dict[str, int] = field(default_factory=dict)
    """skips and repairs found while reading metadata."""


def stamp_from_name(name: str) -> int:
    """File stem -> ns: integer names are ns (or us/ms/s by digit count), decimal names are seconds."""
    if re.fullmatch(r"\d+\.\d+", name):
        sec, frac = name.split(".")
        return int(sec) * 1_000_000_000 + int((frac + "000000000")[:9])
    if re.fullmatch(r"\d+", name):
        v = int(name)
        digits = len(name)
        if digits >= 18:
            return v
        if digits >= 15:
            return v * 1_000
        if digits >= 12:
            return v * 1_000_000
        return v * 1_000_000_000
    raise IngestError(f"cannot read a timestamp from the file name {name!r} (expected integer ns or decimal s)")


def sort_unique(stamps: np.ndarray, what: str, counts: dict[str, int]) -> np.ndarray:
    """Sorted unique stamps; non-monotonic and duplicate stamps are counted."""
    stamps = np.asarray(stamps, np.int64)
    if len(stamps) > 1 and np.any(np.diff(stamps) < 0):
        counts[f"{what}_out_of_order"] = int(np.sum(np.diff(stamps) < 0))
    uniq = np.unique(stamps)
    if len(uniq) < len(stamps):
        counts[f"{what}_duplicate_stamps"] = len(stamps) - len(uniq)
    return uniq


def pair_nearest(a: np.ndarray, b: np.ndarray, tol_ns: int) -> np.ndarray:
    """For each stamp of sorted `a`, the index of the nearest stamp of sorted `b` within tol, else -1."""
    if len(b) == 0:
        return np.full(len(a), -1)
    j = np.clip(np.searchsorted(b, a), 1, len(b) - 1) if len(b) > 1 else np.zeros(len(a), int)
    if len(b) > 1:
        left_better = np.abs(a - b[j - 1]) <= np.abs(b[j] - a)
        j = np.where(left_better, j - 1, j)
    return np.where(np.abs(b[j] - a) <= tol_ns, j, -1)


def interpolate_poses(traj: Trajectory, at_ns: np.ndarray, tol_ns: int) -> tuple[np.ndarray, np.ndarray]:
    """Poses at `at_ns` (linear translation, slerp rotation). Returns ([M, 4, 4], ok [M]); not ok where
    the stamp is outside the trajectory by more than tol or falls in a gap longer than 2 * tol."""
    s = traj.stamps_ns
    if len(s) == 0:
        raise IngestError(f"odometry from {traj.origin} has no samples")
    at = np.asarray(at_ns, np.int64)
    ok = (at >= s[0] - tol_ns) & (at <= s[-1] + tol_ns)
    if len(s) > 1:
        i = np.clip(np.searchsorted(s, at), 1, len(s) - 1)
        gap = s[i] - s[i - 1]
        inside = (at > s[0]) & (at < s[-1]) & (s[i] != at)  # a stamp on a sample needs no interpolation
        ok &= ~(inside & (gap > 2 * tol_ns))
    t = (s - s[0]) / 1e9
    q = np.clip((at - s[0]) / 1e9, t[0], t[-1])
    out = np.tile(np.eye(4), (len(at), 1, 1))
    if len(s) == 1:
        out[:] = traj.poses[0]
        return out, ok
    out[:, :3, :3] = Slerp(t, Rotation.from_matrix(traj.poses[:, :3, :3]))(q).as_matrix()
    for k in range(3):
        out[:, k, 3] = np.interp(q, t, traj.poses[:, k, 3])
    return out, ok


def pose_from_txyzq(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, np.float64)
    q = v[..., 3:7]
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(~np.isfinite(v)) or np.any(norm < 1e-9):
        raise IngestError("pose with a non-finite value or a zero quaternion")
    out = np.tile(np.eye(4), v.shape[:-1] + (1, 1))
    out[..., :3, :3] = Rotation.from_quat((q / norm).reshape(-1, 4)).as_matrix().reshape(v.shape[:-1] + (3, 3))
    out[..., :3, 3] = v[..., :3]
    return out


def txyzq_from_pose(p: np.ndarray) -> np.ndarray:
    q = Rotation.from_matrix(p[..., :3, :3].reshape(-1, 3, 3)).as_quat()
    q[q[:, 3] < 0] *= -1
    return np.concatenate([p[..., :3, 3].reshape(-1, 3), q], 1)


def depth_to_mm(depth_m: np.ndarray) -> np.ndarray:
    """Metres (NaN/inf/<= 0 invalid) -> uint16 mm, 0 = invalid."""
    d = np.asarray(depth_m, np.float64)
    mm = np.where(np.isfinite(d) & (d > 0), np.round(d * 1000.0), 0)
    return np.where(mm < 65535, mm, 0).astype(np.uint16)


def read_params(path: Path) -> tuple[Camera, np.ndarray]:
    """params.yaml -> (camera, T_robot_camera)."""
    if not path.is_file():
        raise IngestError(f"{path} not found: expected params.yaml with K (3x3), T_robot_camera (4x4), width, height")
    try:
        p = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as err:
        raise IngestError(f"{path} is not valid YAML: {err}") from err
    try:
        k = np.array(p["K"], np.float64)
        t = np.array(p["T_robot_camera"], np.float64)
        w, h = int(p["width"]), int(p["height"])
    except (KeyError, TypeError, ValueError) as err:
        raise IngestError(f"{path}: expected keys K (3x3), T_robot_camera (4x4), width, height; "
                          f"problem with {err}; keys present: {sorted(p) if isinstance(p, dict) else p!r}") from err
    if k.shape == (9,):
        k = k.reshape(3, 3)
    if k.shape != (3, 3) or not np.isfinite(k).all() or not np.allclose(k[2], [0, 0, 1]):
        raise IngestError(f"{path}: K must be a 3x3 intrinsics matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] "
                          f"(nested lists or 9 values row-major), got shape {k.shape}: {k.tolist()}")
    if t.shape == (16,):
        t = t.reshape(4, 4)
    if t.shape != (4, 4) or not np.isfinite(t).all():
        raise IngestError(f"{path}: T_robot_camera must be a 4x4 matrix, got shape {t.shape}")
    r = t[:3, :3]
    if not np.allclose(t[3], [0, 0, 0, 1]):
        raise IngestError(f"{path}: T_robot_camera is not a rigid transform: its last row is {t[3].tolist()}, "
                          f"expected [0, 0, 0, 1]")
    if not np.allclose(r @ r.T, np.eye(3), atol=1e-4) or np.linalg.det(r) < 0:
        raise IngestError(f"{path}: T_robot_camera is not a rigid transform: its rotation part is not orthonormal "
                          f"with determinant +1 (R R^T deviates from I by {np.abs(r @ r.T - np.eye(3)).max():.3g}, "
                          f"det R = {np.linalg.det(r):.4g}); scale or shear does not belong in the extrinsics")
    return Camera(k, w, h, str(path)), t


class FrameSource:
    """A recording whose frames can be decoded in stamp order."""

    recording: Recording

    def describe(self) -> str:
        raise NotImplementedError

    def where(self, ci: int, di: int) -> str:
        """The files or messages of colour image ci and depth image di, for errors."""
        return f"colour image {ci} and depth image {di} of {self.describe()}"

    def frames(self, pairs: list[tuple[int, int]]) -> Iterator[tuple[int, np.ndarray | None, np.ndarray | None, str]]:
        """Yield (colour index, rgb [H, W, 3] uint8, depth [H, W] float32 metres with 0 = invalid, error)
        for each (colour index, depth index) pair; a frame that cannot be decoded comes with None images
        and the error text, so the caller can skip it and count it."""
        raise NotImplementedError
