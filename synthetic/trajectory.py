"""The robot's true path along the row, the drifting odometry it reports, and pose conversions.

Base frame (base_link): x forward, y left, z up, at `height_m` above the floor. The true path is
analytic in time: a straight drive along world +x with a small speed ripple and a slow lateral
sway; the heading follows the velocity (a wheeled robot does not slide sideways).

Odometry integrates the true body-frame increments (d_fwd, d_lat, d_yaw) between samples with
errors proportional to the distance driven:
    d_fwd' = d_fwd (1 + a),  d_lat' = d_lat + b d_fwd,  d_yaw' = d_yaw + c d_fwd
with (a, b) = drift_m_per_m (cos psi, sin psi) for a random psi, and c = +-yaw_drift_rad_per_m;
then adds white noise to x and y (none at the first sample, where odometry equals the truth).
Example: drift 0.03 m/m and yaw drift 2 deg/m over 1.6 m give about 5 cm of translation error
plus 0.5 * 1.6 m * 0.056 rad ~ 4.5 cm of sideways error from the heading.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

# Camera optical frame (x right, y down, z forward) looking left (+y) at the plants, in base_link.
R_BASE_CAMERA = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def camera_extrinsic(mast_m: float, lateral_m: float) -> np.ndarray:
    """T_robot_camera: 4x4 camera-to-robot (base_link) for a camera `mast_m` above base_link and
    `lateral_m` to its left, looking left at the row."""
    t = np.eye(4)
    t[:3, :3] = R_BASE_CAMERA
    t[:3, 3] = [0.0, lateral_m, mast_m]
    return t


def planar_poses(x: np.ndarray, y: np.ndarray, yaw: np.ndarray, z: float) -> np.ndarray:
    """[K] planar poses -> [K, 4, 4] base-to-world."""
    out = np.tile(np.eye(4), (len(x), 1, 1))
    c, s = np.cos(yaw), np.sin(yaw)
    out[:, 0, 0], out[:, 0, 1], out[:, 1, 0], out[:, 1, 1] = c, -s, s, c
    out[:, 0, 3], out[:, 1, 3], out[:, 2, 3] = x, y, z
    return out


@dataclass(frozen=True)
class BasePath:
    """x(t) = v t - v a T_v / (2 pi) (cos(2 pi t / T_v + phi_v) - cos phi_v)  (speed v (1 + a sin(...)))
    y(t) = A (sin(2 pi t / T_y + phi_y) - sin phi_y),  yaw = atan2(dy/dt, dx/dt);  t in s from the start."""

    speed_m_per_s: float
    height_m: float
    speed_ripple: float = 0.03
    speed_period_s: float = 5.0
    speed_phase: float = 0.0
    sway_m: float = 0.008
    sway_period_s: float = 9.0
    sway_phase: float = 0.0
    x0_m: float = 0.0

    @staticmethod
    def random(speed_m_per_s: float, height_m: float, x0_m: float, rng: np.random.Generator) -> BasePath:
        return BasePath(speed_m_per_s, height_m, speed_phase=rng.uniform(0, 2 * np.pi),
                        sway_phase=rng.uniform(0, 2 * np.pi), x0_m=x0_m)

    def xy_yaw(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        v, a = self.speed_m_per_s, self.speed_ripple
        wv, wy = 2 * np.pi / self.speed_period_s, 2 * np.pi / self.sway_period_s
        x = self.x0_m + v * t_s - v * a / wv * (np.cos(wv * t_s + self.speed_phase) - np.cos(self.speed_phase))
        y = self.sway_m * (np.sin(wy * t_s + self.sway_phase) - np.sin(self.sway_phase))
        dx = v * (1 + a * np.sin(wv * t_s + self.speed_phase))
        dy = self.sway_m * wy * np.cos(wy * t_s + self.sway_phase)
        return x, y, np.arctan2(dy, dx)

    def poses(self, t_s: np.ndarray) -> np.ndarray:
        """[K] seconds -> [K, 4, 4] true base-to-world."""
        x, y, yaw = self.xy_yaw(np.asarray(t_s, np.float64))
        return planar_poses(x, y, yaw, self.height_m)


@dataclass(frozen=True)
class OdometryErrors:
    drift_m_per_m: float
    yaw_drift_deg_per_m: float
    noise_m: float


def drifting_odometry(x: np.ndarray, y: np.ndarray, yaw: np.ndarray, z: float, err: OdometryErrors,
                      rng: np.random.Generator) -> np.ndarray:
    """True planar samples [K] -> [K, 4, 4] odometry base-to-world (see the module docstring)."""
    c, s = np.cos(yaw[:-1]), np.sin(yaw[:-1])
    dx, dy = np.diff(x), np.diff(y)
    fwd, lat = c * dx + s * dy, -s * dx + c * dy
    dyaw = np.angle(np.exp(1j * np.diff(yaw)))
    psi = rng.uniform(0, 2 * np.pi)
    a, b = err.drift_m_per_m * np.cos(psi), err.drift_m_per_m * np.sin(psi)
    cyaw = rng.choice([-1.0, 1.0]) * np.radians(err.yaw_drift_deg_per_m)
    fwd_o, lat_o, dyaw_o = fwd * (1 + a), lat + b * fwd, dyaw + cyaw * fwd
    yaw_o = yaw[0] + np.concatenate([[0.0], np.cumsum(dyaw_o)])
    co, so = np.cos(yaw_o[:-1]), np.sin(yaw_o[:-1])
    xo = x[0] + np.concatenate([[0.0], np.cumsum(co * fwd_o - so * lat_o)])
    yo = y[0] + np.concatenate([[0.0], np.cumsum(so * fwd_o + co * lat_o)])
    noise = rng.normal(0.0, err.noise_m, (len(x), 2))
    noise[0] = 0.0
    return planar_poses(xo + noise[:, 0], yo + noise[:, 1], yaw_o, z)


def to_txyzq(poses: np.ndarray) -> np.ndarray:
    """[K, 4, 4] -> [K, 7] tx, ty, tz, qx, qy, qz, qw (scalar last, qw >= 0)."""
    q = Rotation.from_matrix(poses[:, :3, :3]).as_quat()
    q[q[:, 3] < 0] *= -1
    return np.concatenate([poses[:, :3, 3], q], 1)
