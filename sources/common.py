"""What every source of a recorded row provides, and the shared pieces: stamps, pairing, pose
interpolation, intrinsics checks, depth conversion."""
from __future__ import annotations

import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

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
    notes: list[str] = field(default_factory=list)
    """what those skips were (files named), for the stage summary."""


StampUnit = Literal["auto", "ns", "us", "ms", "s"]
NS_PER_UNIT = {"ns": 1, "us": 1_000, "ms": 1_000_000, "s": 1_000_000_000}
# 'auto' reads an integer of exactly these digit counts in this unit, where the reading falls in
# [2000-01-01, 2100-01-01) UTC. Units are 1000 apart and that century spans a factor of 4.3, so no other
# unit puts the same integer in it. 18 and 19 digits are ns whatever the date: as us they would be
# thousands of years from 1970 or from any boot.
AUTO_DIGITS = {19: "ns", 18: "ns", 16: "us", 13: "ms", 10: "s"}
YEAR_2000_NS, YEAR_2100_NS = 946_684_800 * 10**9, 4_102_444_800 * 10**9
INT64_MAX = 2**63 - 1
# A clock counting nanoseconds from boot also writes 16 (11 days to 4 months up), 13 (17 min to 2.8 h) or
# 10 digits (1 s to 10 s), so a folder that 'auto' read as us, ms or s must hold frames or samples closer
# together than this, else its names were a boot clock's ns (read as ms they lie 18 hours apart at 15 fps).
AUTO_MAX_PERIOD_NS = 5 * 10**9


def read_stamp(name: str, unit: StampUnit = "auto") -> tuple[int, str]:
    """File stem (or a timestamp column's text) -> (stamp_ns, how it was read: the unit, or 'decimal s').

    unit 'ns', 'us', 'ms' or 's': the name's number in that unit (a decimal point allowed).
    unit 'auto' reads only names whose digits leave no doubt:
    - a decimal number is seconds (ROS `sec.nsec`, 100.033333333), before the year 2100;
    - an integer of 18 or 19 digits is ns (before 2100);
    - an integer of exactly 16, 13 or 10 digits is us, ms or s where that reading lies between 2000 and 2100
      (1600000000123 -> ms, 2020-09-13); `check_auto_period` then checks the folder's spacing;
    anything else (a boot clock's ns of 12 digits, a frame counter) is an IngestError saying to set
    ingest.stamp_unit. Example: read_stamp("1600000000.5") == (1_600_000_000_500_000_000, "decimal s")."""
    text = name.strip()
    if not re.fullmatch(r"\d+(\.\d+)?", text):
        raise IngestError(f"cannot read a timestamp from {name!r} (expected an integer, or a decimal "
                          f"number of seconds)")
    if unit != "auto":
        if unit not in NS_PER_UNIT:
            raise IngestError(f"stamp unit {unit!r} is not one of auto, {', '.join(NS_PER_UNIT)}")
        ns = _in_ns(text, unit)
        if ns > INT64_MAX:
            raise IngestError(f"timestamp {name!r} read in {unit} (ingest.stamp_unit) lies after the year 2262; "
                              f"is the unit right?")
        return ns, unit
    if "." in text:
        ns = _in_ns(text, "s")
        if ns >= YEAR_2100_NS:
            raise IngestError(f"cannot tell the unit of the timestamp {name!r}: as seconds it lies after 2100; "
                              f"set ingest.stamp_unit to ns, us, ms or s")
        return ns, "decimal s"
    digits = len(text.lstrip("0")) or 1
    guess = AUTO_DIGITS.get(digits)
    if guess is not None:
        ns = _in_ns(text, guess)
        if (guess == "ns" and ns < YEAR_2100_NS) or YEAR_2000_NS <= ns < YEAR_2100_NS:
            return ns, guess
    raise IngestError(f"cannot tell the unit of the integer timestamp {name!r} ({digits} digits): ingest.stamp_unit="
                      f"auto reads only 18-19 digits as ns, and 16, 13 or 10 digits as us, ms or s between 2000 and "
                      f"2100 (a clock counting from boot gives other names); set ingest.stamp_unit to ns, us, ms or s")


def _in_ns(text: str, unit: str) -> int:
    """'123.25' in `unit` -> ns, exactly (fraction digits finer than 1 ns dropped)."""
    whole, _, frac = text.partition(".")
    scale = NS_PER_UNIT[unit]
    return int(whole) * scale + int((frac + "0" * 9)[:9]) * scale // 10**9


def stamp_from_name(name: str, unit: StampUnit = "auto") -> int:
    """File stem -> ns, by the rule of `read_stamp`."""
    return read_stamp(name, unit)[0]


def check_auto_period(stamps_ns: np.ndarray, how: list[str], unit: StampUnit, where: str) -> None:
    """Under unit 'auto', names read as us, ms or s by their digit count (`how`, from read_stamp) must lie
    less than AUTO_MAX_PERIOD_NS apart (median gap): a boot clock's ns of the same digit count, read so, lie
    a thousand or more times farther apart. `where` names the folder or file for the error."""
    read_as = sorted(set(how) & {"us", "ms", "s"})
    if unit != "auto" or not read_as:
        return
    gaps = np.diff(np.unique(np.asarray(stamps_ns, np.int64)))
    if len(gaps) and np.median(gaps) > AUTO_MAX_PERIOD_NS:
        raise IngestError(f"{where}: the names read as {'/'.join(read_as)} by their digit count (ingest.stamp_unit="
                          f"auto) lie a median {np.median(gaps) / 1e9:.4g} s apart, too far for frames or odometry "
                          f"samples; they are likely ns of a clock counting from boot: set ingest.stamp_unit to the "
                          f"unit of the names (ns, us, ms or s)")


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


def read_params(path: Path) -> tuple[Camera, np.ndarray, float]:
    """params.yaml -> (camera, T_robot_camera, depth_scale_m: metres per unit of a 16-bit depth image,
    0.001 (millimetres) where the file does not say)."""
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
    return Camera(k, w, h, str(path)), t, depth_scale(p, path)


def depth_scale(params: dict, path: Path) -> float:
    """depth_scale_m of a parsed params.yaml: metres per unit of a 16-bit depth image (0.001 = millimetres,
    the default where the key is absent; 0.0001 for a sensor writing tenths of a millimetre)."""
    value = params.get("depth_scale_m", 0.001) if isinstance(params, dict) else 0.001
    try:
        scale = float(value)
    except (TypeError, ValueError):
        scale = float("nan")
    if not (np.isfinite(scale) and 0 < scale <= 1):
        raise IngestError(f"{path}: depth_scale_m must be metres per unit of the 16-bit depth images, in (0, 1] "
                          f"(0.001 for millimetres), got {value!r}")
    return scale


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
