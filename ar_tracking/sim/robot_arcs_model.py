"""The model of the ``robot_arcs`` scenario (Caarls et al. 2009, sec. 2.6, Fig. 9): the robot's
half-circle schedule and its closed-form motion, the exact IMU and its errors, the marker wall,
the ideal pinhole camera and the marker rendering, and the nodes' parameters for a bag.

Both profiles build on it: ``kind`` (:mod:`.robot_arcs`, which also writes the bags and
re-exports every name here) and ``hard`` (:mod:`.robot_arcs_real`); its own module so that the
two do not import each other. The scenario itself is described in :mod:`.robot_arcs`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import yaml
from numpy.typing import NDArray

from ..core.rotations import matrix_to_quat_xyzw, rot_z
from .world import rng_stream

Array = NDArray[np.float64]

ARC_SPEEDS_M_S: tuple[float, ...] = (0.32, 0.64, 0.96, 1.28, 1.60, 1.92, 2.24)
RADIUS_M = 0.55
ACCEL_TIME_S = 0.5
PAUSE_S = 0.5
CAMERA_HEIGHT_M = 1.0
#: Tool rotation about the vertical with the arc angle (rad at the ends of the half circle).
YAW_AMPLITUDE_RAD = 0.12
GRAVITY_M_S2 = 9.80665
IMU_RATE_HZ = 100
CAMERA_RATE_HZ = 15
PROCESSING_DELAY_NS = 80_000_000
IMAGE_SIZE = (640, 480)
HFOV_RAD = math.radians(60.0)
DICTIONARY = 'DICT_APRILTAG_36h11'
SUPERSAMPLING = 8
BLUR_SIGMA_PX = 0.6
PIXEL_NOISE = 2.0
BLACK, WHITE, WALL = 25.0, 225.0, 120.0

#: camera_optical -> imu (same device convention as rotation_sweep).
R_IMU_CAM = np.diag([1.0, -1.0, -1.0])
#: Camera looking north (+y), level: camera x -> east, y -> down, z -> north.
R0_ENU_CAM = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
#: A marker on the wall facing the robot: marker x -> east, y -> up, z (out of the marker) -> south.
R_ENU_WALL_MARKER = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])

FRAME_WORLD, FRAME_CAMERA, FRAME_IMU = 'enu', 'camera_optical', 'imu'


@dataclass(frozen=True)
class MarkerSpec:
    """One marker: ID, side length of the black square (m), pose of its centre in the world."""

    id: int
    size_m: float
    position: Array
    R_world_marker: Array

    def corners_world(self) -> Array:
        """The 4 outer corners of the black border in ArUco order (top-left, top-right,
        bottom-right, bottom-left seen from the front), world frame."""
        h = self.size_m / 2
        local = np.array([[-h, h, 0], [h, h, 0], [h, -h, 0], [-h, -h, 0]])
        return self.position + local @ self.R_world_marker.T


def wall_markers() -> tuple[list[MarkerSpec], list[MarkerSpec]]:
    """(the mapped markers: a 2x2 grid around x = 0.2 m at y = 3.2 m, the unmapped one)."""
    mapped = [MarkerSpec(i, 0.30, np.array([x, 3.2, z]), R_ENU_WALL_MARKER)
              for i, (x, z) in enumerate([(-0.25, 1.35), (0.65, 1.35), (-0.25, 0.65), (0.65, 0.65)])]
    unknown = [MarkerSpec(17, 0.20, np.array([1.35, 3.2, 1.0]), R_ENU_WALL_MARKER)]
    return mapped, unknown


@dataclass(frozen=True)
class Camera:
    width: int = IMAGE_SIZE[0]
    height: int = IMAGE_SIZE[1]
    hfov_rad: float = HFOV_RAD

    @property
    def K(self) -> Array:
        f = self.width / 2 / math.tan(self.hfov_rad / 2)
        return np.array([[f, 0, (self.width - 1) / 2], [0, f, (self.height - 1) / 2], [0, 0, 1.0]])


# --------------------------------------------------------------------------------------------
# Motion


@dataclass(frozen=True)
class ArcSchedule:
    """Start times of the half circles (each: pause, then the move) and their speeds."""

    starts_s: Array
    speeds_m_s: Array

    @staticmethod
    def make(duration_s: float, speeds: tuple[float, ...] = ARC_SPEEDS_M_S) -> 'ArcSchedule':
        L = math.pi * RADIUS_M
        starts, vs, t, k = [], [], 0.0, 0
        while t < duration_s + 10:
            v = speeds[k % len(speeds)]
            starts.append(t)
            vs.append(v)
            t += PAUSE_S + L / v + ACCEL_TIME_S
            k += 1
        return ArcSchedule(np.array(starts), np.array(vs))


def _ramp(tau: Array, v: Array) -> tuple[Array, Array, Array]:
    """Distance, speed, acceleration of a smooth start (cosine acceleration) over ACCEL_TIME_S."""
    Ta = ACCEL_TIME_S
    w = 2 * np.pi / Ta
    s = v * (tau ** 2 / (2 * Ta) + (np.cos(w * tau) - 1) / (w * w * Ta))
    sd = v * (tau / Ta - np.sin(w * tau) / (w * Ta))
    sdd = v / Ta * (1 - np.cos(w * tau))
    return s, sd, sdd


def arc_motion(sched: ArcSchedule, t_s: Array) -> tuple[Array, Array, Array]:
    """Arc angle theta (0 at x = +R, pi at x = -R), its rate and acceleration at times t."""
    t_s = np.asarray(t_s, dtype=float)
    k = np.searchsorted(sched.starts_s, t_s, side='right') - 1
    v = sched.speeds_m_s[k]
    L = math.pi * RADIUS_M
    T_move = L / v + ACCEL_TIME_S
    tau = t_s - sched.starts_s[k] - PAUSE_S
    s = np.zeros_like(t_s)
    sd = np.zeros_like(t_s)
    sdd = np.zeros_like(t_s)
    a = (tau > 0) & (tau < ACCEL_TIME_S)
    s[a], sd[a], sdd[a] = _ramp(tau[a], v[a])
    c = (tau >= ACCEL_TIME_S) & (tau <= T_move - ACCEL_TIME_S)
    s[c] = v[c] * ACCEL_TIME_S / 2 + v[c] * (tau[c] - ACCEL_TIME_S)
    sd[c] = v[c]
    d = (tau > T_move - ACCEL_TIME_S) & (tau < T_move)
    sr, sdr, sddr = _ramp(T_move[d] - tau[d], v[d])
    s[d], sd[d], sdd[d] = L - sr, sdr, -sddr
    s[tau >= T_move] = L
    forward = (k % 2) == 0  # even half circles go from x = +R to x = -R
    theta = np.where(forward, s / RADIUS_M, math.pi - s / RADIUS_M)
    sign = np.where(forward, 1.0, -1.0)
    return theta, sign * sd / RADIUS_M, sign * sdd / RADIUS_M


@dataclass(frozen=True)
class Truth:
    t_s: Array
    position: Array      # (N, 3) camera in the world
    velocity: Array
    accel: Array         # (N, 3) world acceleration of the camera (= IMU: no lever arm)
    R_enu_cam: Array     # (N, 3, 3)
    omega_world: Array   # (N, 3)
    speed_m_s: Array


def truth_at(sched: ArcSchedule, t_s: Array) -> Truth:
    th, thd, thdd = arc_motion(sched, t_s)
    R = RADIUS_M
    c, s = np.cos(th), np.sin(th)
    pos = np.stack([R * c, R * s, np.full_like(th, CAMERA_HEIGHT_M)], -1)
    vel = np.stack([-R * s * thd, R * c * thd, np.zeros_like(th)], -1)
    acc = np.stack([-R * (c * thd ** 2 + s * thdd), R * (-s * thd ** 2 + c * thdd), np.zeros_like(th)], -1)
    yaw = YAW_AMPLITUDE_RAD * np.cos(th)
    yaw_rate = -YAW_AMPLITUDE_RAD * np.sin(th) * thd
    Rz = np.stack([rot_z(y) for y in yaw])
    R_cam = Rz @ R0_ENU_CAM
    omega = np.stack([np.zeros_like(th), np.zeros_like(th), yaw_rate], -1)
    return Truth(np.asarray(t_s, float), pos, vel, acc, R_cam, omega, np.abs(thd) * R)


@dataclass(frozen=True)
class ImuErrors:
    gyro_bias_rad_s: Array
    accel_bias_m_s2: Array
    gyro_noise_rad_s: float = math.radians(0.3)
    accel_noise_m_s2: float = 0.013
    gyro_bias_walk_rad_s: float = math.radians(0.005)  # per sqrt(s)


def make_imu_errors(seed: int) -> ImuErrors:
    rng = rng_stream(seed, 'robot-arcs-imu-errors')
    sign = lambda: rng.choice([-1.0, 1.0], 3)  # noqa: E731
    return ImuErrors(np.radians(rng.uniform(0.2, 0.6, 3)) * sign(), rng.uniform(0.01, 0.03, 3) * sign())


def simulate_imu(truth: Truth, err: ImuErrors, seed: int) -> tuple[Array, Array]:
    """(gyro, accel) in the IMU frame: R_imu_enu (omega, a - g) + bias + noise."""
    rng = rng_stream(seed, 'robot-arcs-imu-noise')
    n = len(truth.t_s)
    R_enu_imu = truth.R_enu_cam @ R_IMU_CAM.T
    R_imu_enu = np.swapaxes(R_enu_imu, 1, 2)
    walk = np.cumsum(rng.normal(0, err.gyro_bias_walk_rad_s * math.sqrt(1 / IMU_RATE_HZ), (n, 3)), 0)
    gyro = np.einsum('nij,nj->ni', R_imu_enu, truth.omega_world) + err.gyro_bias_rad_s + walk
    gyro += rng.normal(0, err.gyro_noise_rad_s, (n, 3))
    f = truth.accel + np.array([0, 0, GRAVITY_M_S2])
    accel = np.einsum('nij,nj->ni', R_imu_enu, f) + err.accel_bias_m_s2
    accel += rng.normal(0, err.accel_noise_m_s2, (n, 3))
    return gyro, accel


# --------------------------------------------------------------------------------------------
# Rendering


def _dictionary(name: str = DICTIONARY) -> Any:
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))


def marker_plate(marker_id: int, dictionary: str = DICTIONARY, quiet_modules: int = 1) -> tuple[Array, float]:
    """The marker as an image of one pixel per module with a white quiet zone, and the fraction
    of the plate's half-size taken by the black square (for the plate corners)."""
    d = _dictionary(dictionary)
    modules = d.markerSize + 2
    img = cv2.aruco.generateImageMarker(d, int(marker_id), modules, borderBits=1)
    img = np.where(img > 127, WHITE, BLACK).astype(np.float32)
    plate = np.pad(img, quiet_modules, constant_values=WHITE)
    return plate, modules / (modules + 2 * quiet_modules)


def project(K: Array, R_world_cam: Array, p_world_cam: Array, X: Array) -> tuple[Array, Array]:
    """Pixel coordinates and depths of world points (ideal pinhole)."""
    Xc = (X - p_world_cam) @ R_world_cam  # = R^T (X - p)
    uv = Xc[:, :2] / Xc[:, 2:3] * K[[0, 1], [0, 1]] + K[:2, 2]
    return uv, Xc[:, 2]


def render_markers(image: Array, K: Array, R_world_cam: Array, p_world_cam: Array,
                   markers: list[MarkerSpec], dictionary: str = DICTIONARY,
                   supersampling: int = SUPERSAMPLING) -> dict[int, Array]:
    """Draw the markers into a float32 image in place; returns the exact pixel corners of the
    markers drawn (id -> (4, 2), OpenCV convention: pixel centres at integer coordinates)."""
    h_img, w_img = image.shape
    S = supersampling
    drawn: dict[int, Array] = {}
    for m in markers:
        plate, frac = marker_plate(m.id, dictionary)
        W = plate.shape[0]
        big = MarkerSpec(m.id, m.size_m / frac, m.position, m.R_world_marker)
        uv_plate, depth = project(K, R_world_cam, p_world_cam, big.corners_world())
        if np.any(depth < 0.05):
            continue
        lo = np.floor(uv_plate.min(0)).astype(int) - 2
        hi = np.ceil(uv_plate.max(0)).astype(int) + 3
        lo = np.maximum(lo, 0)
        hi = np.minimum(hi, [w_img, h_img])
        if np.any(hi - lo < 4):
            continue
        roi = image[lo[1]:hi[1], lo[0]:hi[0]]
        src = np.array([[-0.5, -0.5], [W - 0.5, -0.5], [W - 0.5, W - 0.5], [-0.5, W - 0.5]], np.float32)
        dst = ((uv_plate - lo) * S + (S - 1) / 2).astype(np.float32)
        H = cv2.getPerspectiveTransform(src, dst)
        hi_res = cv2.resize(roi, (roi.shape[1] * S, roi.shape[0] * S), interpolation=cv2.INTER_NEAREST)
        cv2.warpPerspective(plate, H, (hi_res.shape[1], hi_res.shape[0]), dst=hi_res,
                            flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_TRANSPARENT)
        roi[:] = cv2.resize(hi_res, (roi.shape[1], roi.shape[0]), interpolation=cv2.INTER_AREA)
        uv, _ = project(K, R_world_cam, p_world_cam, m.corners_world())
        if np.all((uv > 0) & (uv < [w_img - 1, h_img - 1])):
            drawn[m.id] = uv
    return drawn


def render_frame(cam: Camera, R_world_cam: Array, p_world_cam: Array, markers: list[MarkerSpec],
                 rng: np.random.Generator, blur_sigma_px: float = BLUR_SIGMA_PX,
                 noise: float = PIXEL_NOISE) -> tuple[NDArray[np.uint8], dict[int, Array]]:
    """One mono8 frame of the wall and the exact corners of the markers in it."""
    img = np.full((cam.height, cam.width), WALL, np.float32)
    corners = render_markers(img, cam.K, R_world_cam, p_world_cam, markers)
    if blur_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_sigma_px)
    if noise > 0:
        img = img + rng.normal(0, noise, img.shape).astype(np.float32)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8), corners


# --------------------------------------------------------------------------------------------
# The bag


def marker_map_doc(markers: list[MarkerSpec]) -> dict[str, Any]:
    """The marker map as the marker-map YAML document (frame, dictionary, markers)."""
    return {'frame_id': FRAME_WORLD, 'dictionary': DICTIONARY, 'markers': [
        {'id': int(m.id), 'size_m': float(m.size_m), 'position': [float(x) for x in m.position],
         'orientation_xyzw': [float(x) for x in matrix_to_quat_xyzw(m.R_world_marker)]}
        for m in markers]}


def sidecar_params(seed: int) -> dict[str, Any]:
    """marker_tracker and visual_inertial_filter parameters for a robot_arcs bag."""
    mapped, _ = wall_markers()
    err = make_imu_errors(seed)
    inline_map = yaml.safe_dump(marker_map_doc(mapped), default_flow_style=True, width=1 << 20).strip()
    return {
        'marker_tracker': {'ros__parameters': {
            'dictionary': DICTIONARY,
            'marker_map': inline_map,
        }},
        'visual_inertial_filter': {'ros__parameters': {
            'imu_to_camera_xyzw': [float(x) for x in matrix_to_quat_xyzw(R_IMU_CAM)],
            'gyro_noise_rad_s': float(round(err.gyro_noise_rad_s, 6)),
            'accel_noise_m_s2': float(err.accel_noise_m_s2),
        }},
    }
