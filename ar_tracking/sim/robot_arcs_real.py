"""Profile ``hard`` of the ``robot_arcs`` scenario: the same robot half circles in front of the
marker wall, seen by a camera with the effects of a real one (the default of ``make-bag
robot_arcs``; ``--profile kind`` is the ideal-pinhole simulator of :mod:`.robot_arcs`).

What the real camera adds, each because it changes the corners or the fusion:

* **lens**: radial-tangential (plumb_bob) distortion, k1 = -0.25, published in camera_info. The
  image is rendered on a 2x supersampled *ideal* canvas and resampled through the distortion
  map: every output pixel averages the canvas at 2x2 points of its area, each looked up at its
  undistorted position.
* **photometry**: the scene is rendered in linear radiance; vignetting (1 - 0.25 r^2), a slowly
  changing auto-exposure gain, defocus (Gaussian, sigma 0.9 px), shot + read noise, then the
  *display gamma* 1/2.2 and 8-bit quantisation. Edges in the published image are therefore not
  erf-shaped: the bright side is stretched and the dark side compressed.
* **motion**: quick pans of the tool (a raised-cosine yaw excursion of 12 deg in 0.243 s:
  peak ~155 deg/s) every ~2.5 s on top of the arcs; the 12 ms exposure integrates the motion
  (sub-frames averaged in linear radiance): ~18 px of blur at the peak of a pan.
* **occlusion**: a thin pole between the robot and the wall covers parts of the lower right
  marker as the camera moves (parallax); plus the unknown ID 17 at the side.
* **timing**: camera at 20 Hz stamped at mid-exposure, images published 80 ms late; the
  camera_info of each frame is logged 1 ms *after* its image (the first image must wait).
* **IMU**: 100 Hz, larger gyro and accelerometer bias random walks, mounted with a non-identity
  rotation and a lever arm (the IMU sees the centripetal and tangential acceleration of the
  pans); the mount is only on ``/tf_static`` (imu -> camera_optical, rotation and translation),
  *not* in the sidecar's parameters, as a user's bag has it.

Ground truth as in the kind profile (``/ground_truth/pose``, ``/ground_truth/orientation`` of
the camera at the IMU stamps) plus ``/ground_truth/marker_corners`` (visualization_msgs/
MarkerArray at each image stamp: one LINE_STRIP per mapped marker whose corners are in the
image, points = the exact distorted pixel corners (u, v, 0) at mid-exposure; ns ``visible`` or
``occluded`` when the pole covers part of it), read only by ``evaluate`` and the benches.
"""
from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from ..core.rotations import matrix_to_quat_xyzw, rot_x, rot_z
from . import robot_arcs_model as ra
from .world import rng_stream

Array = NDArray[np.float64]

CAMERA_RATE_HZ = 20
EXPOSURE_S = 0.012
#: plumb_bob k1, k2, p1, p2, k3 (camera_info.d)
DISTORTION = np.array([-0.25, 0.07, 0.0008, -0.0005, 0.0])
DISPLAY_GAMMA = 2.2
DEFOCUS_SIGMA_PX = 0.9
VIGNETTING = 0.25
CANVAS_SCALE = 2
#: Marker plates are drawn at this many sub-pixels per canvas pixel: edge positions on a grid of
#: 1 / (CANVAS_SCALE * CANVAS_SUPERSAMPLING) = 1/16 output px (was 1/8: a 0.036 px rms edge
#: error, steady while the camera stands still, so the pose error did not average out).
CANVAS_SUPERSAMPLING = 8
#: Quick pans: yaw amplitude, duration, period, first start.
PAN_AMPLITUDE_RAD = math.radians(12.0)
PAN_DURATION_S = 0.243
PAN_PERIOD_S = 2.5
PAN_FIRST_S = 1.7
#: IMU mount: camera_optical -> imu rotation and the camera origin in the IMU frame (m).
R_IMU_CAM = rot_z(math.pi / 2) @ rot_x(math.radians(4.0)) @ np.diag([1.0, -1.0, -1.0])
T_IMU_CAM = np.array([0.03, -0.05, 0.02])
#: A pole between robot and wall (x, y of its axis; width; bottom and top height), m.
POLE = (0.48, 2.45, 0.04, 0.0, 0.74)
POLE_RADIANCE = 0.12
GYRO_BIAS_WALK_RAD_S = math.radians(0.03)     # per sqrt(s)
ACCEL_BIAS_WALK_M_S2 = 0.004                  # per sqrt(s)
CAMERA_INFO_LAG_NS = 1_000_000
TOPIC_CORNERS = '/ground_truth/marker_corners'


# --------------------------------------------------------------------------------------------
# Motion: the arcs plus quick pans


def pan_yaw(t_s: Array) -> tuple[Array, Array, Array]:
    """Yaw excursion of the quick pans, its rate and acceleration (raised-cosine bumps,
    alternating direction; peak rate PAN_AMPLITUDE_RAD * pi / PAN_DURATION_S ~ 155 deg/s)."""
    t = np.asarray(t_s, dtype=float)
    k = np.floor((t - PAN_FIRST_S) / PAN_PERIOD_S)
    tau = t - PAN_FIRST_S - k * PAN_PERIOD_S
    on = (k >= 0) & (tau < PAN_DURATION_S)
    sign = np.where(k % 2 == 0, 1.0, -1.0)
    w = 2 * math.pi / PAN_DURATION_S
    A = PAN_AMPLITUDE_RAD
    y = np.where(on, sign * A / 2 * (1 - np.cos(w * tau)), 0.0)
    yd = np.where(on, sign * A / 2 * w * np.sin(w * tau), 0.0)
    ydd = np.where(on, sign * A / 2 * w * w * np.cos(w * tau), 0.0)
    return y, yd, ydd


@dataclass(frozen=True)
class HardTruth:
    """Camera truth plus what the IMU at its lever arm feels."""

    cam: ra.Truth
    imu_accel: Array       # (N, 3) world acceleration of the IMU point
    R_enu_imu: Array       # (N, 3, 3)
    omega_world: Array     # (N, 3)


def truth_at(sched: ra.ArcSchedule, t_s: Array) -> HardTruth:
    """Camera pose (arcs + pans) and the IMU point's acceleration (closed form)."""
    t_s = np.asarray(t_s, dtype=float)
    th, thd, thdd = ra.arc_motion(sched, t_s)
    R = ra.RADIUS_M
    c, s = np.cos(th), np.sin(th)
    pos = np.stack([R * c, R * s, np.full_like(th, ra.CAMERA_HEIGHT_M)], -1)
    vel = np.stack([-R * s * thd, R * c * thd, np.zeros_like(th)], -1)
    acc = np.stack([-R * (c * thd ** 2 + s * thdd), R * (-s * thd ** 2 + c * thdd), np.zeros_like(th)], -1)
    A = ra.YAW_AMPLITUDE_RAD
    py, pyd, pydd = pan_yaw(t_s)
    yaw = A * c + py
    yaw_rate = -A * s * thd + pyd
    yaw_acc = -A * (c * thd ** 2 + s * thdd) + pydd
    R_cam = np.stack([rot_z(y) for y in yaw]) @ ra.R0_ENU_CAM
    zero = np.zeros_like(th)
    omega = np.stack([zero, zero, yaw_rate], -1)
    alpha = np.stack([zero, zero, yaw_acc], -1)
    # IMU point: p_imu = p_cam + R_enu_cam p_cam_imu, p_cam_imu = -R_imu_cam^T t_imu_cam.
    r = np.einsum('nij,j->ni', R_cam, -R_IMU_CAM.T @ T_IMU_CAM)
    a_imu = acc + np.cross(alpha, r) + np.cross(omega, np.cross(omega, r))
    cam = ra.Truth(t_s, pos, vel, acc, R_cam, omega, np.abs(thd) * R)
    return HardTruth(cam, a_imu, R_cam @ R_IMU_CAM.T, omega)


def simulate_imu(truth: HardTruth, err: ra.ImuErrors, seed: int) -> tuple[Array, Array]:
    """(gyro, accel) in the IMU frame with bias random walks (gyro and accelerometer)."""
    rng = rng_stream(seed, 'robot-arcs-hard-imu-noise')
    n = len(truth.cam.t_s)
    R_imu_enu = np.swapaxes(truth.R_enu_imu, 1, 2)
    dt = 1.0 / ra.IMU_RATE_HZ
    gwalk = np.cumsum(rng.normal(0, GYRO_BIAS_WALK_RAD_S * math.sqrt(dt), (n, 3)), 0)
    awalk = np.cumsum(rng.normal(0, ACCEL_BIAS_WALK_M_S2 * math.sqrt(dt), (n, 3)), 0)
    gyro = np.einsum('nij,nj->ni', R_imu_enu, truth.omega_world) + err.gyro_bias_rad_s + gwalk
    gyro += rng.normal(0, err.gyro_noise_rad_s, (n, 3))
    f = truth.imu_accel + np.array([0, 0, ra.GRAVITY_M_S2])
    accel = np.einsum('nij,nj->ni', R_imu_enu, f) + err.accel_bias_m_s2 + awalk
    accel += rng.normal(0, err.accel_noise_m_s2, (n, 3))
    return gyro, accel


# --------------------------------------------------------------------------------------------
# Rendering


@dataclass(frozen=True)
class RealCamera:
    """The distorted camera and the ideal canvas it is resampled from."""

    width: int = ra.IMAGE_SIZE[0]
    height: int = ra.IMAGE_SIZE[1]

    @property
    def K(self) -> Array:
        return ra.Camera(self.width, self.height).K

    @property
    def D(self) -> Array:
        return DISTORTION.copy()


#: Where each output pixel samples the canvas (a 2x2 grid over its area: the pixel integrates
#: light over its whole area; a single point sample of the finer canvas would alias the edges).
_PIXEL_SUBSAMPLES = ((-0.25, -0.25), (0.25, -0.25), (-0.25, 0.25), (0.25, 0.25))


@functools.lru_cache(maxsize=2)
def _canvas(width: int, height: int) -> tuple[Array, list[tuple[NDArray[np.float32], NDArray[np.float32]]], tuple[int, int], NDArray[np.float32]]:
    """(canvas K, [(map_x, map_y)] per pixel sub-sample, canvas size, vignetting)."""
    K = ra.Camera(width, height).K
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-12)
    norms = []
    for du, dv in _PIXEL_SUBSAMPLES:
        px = np.stack([u.ravel() + du, v.ravel() + dv], -1).reshape(-1, 1, 2)
        norms.append(cv2.undistortPoints(px, K, DISTORTION, criteria=crit).reshape(-1, 2))
    allnorm = np.concatenate(norms)
    f = K[0, 0] * CANVAS_SCALE
    lo = allnorm.min(0) * f - 4
    hi = allnorm.max(0) * f + 4
    size = (math.ceil(hi[0] - lo[0]), math.ceil(hi[1] - lo[1]))
    Kc = np.array([[f, 0, -lo[0]], [0, f, -lo[1]], [0, 0, 1.0]])
    maps = [((n[:, 0] * f - lo[0]).reshape(height, width).astype(np.float32),
             (n[:, 1] * f - lo[1]).reshape(height, width).astype(np.float32)) for n in norms]
    r2 = ((u - K[0, 2]) ** 2 + (v - K[1, 2]) ** 2) / (K[0, 2] ** 2 + K[1, 2] ** 2)
    vig = (1.0 - VIGNETTING * r2).astype(np.float32)
    return Kc, maps, size, vig


def _pole_corners() -> Array:
    x, y, w, z0, z1 = POLE
    return np.array([[x - w / 2, y, z1], [x + w / 2, y, z1], [x + w / 2, y, z0], [x - w / 2, y, z0]])


def _render_canvas(Kc: Array, size: tuple[int, int], R: Array, p: Array, markers: list[ra.MarkerSpec]) -> Array:
    """Reflectance (0..1) of the wall, markers and pole on the ideal canvas for one pose."""
    img = np.full((size[1], size[0]), ra.WALL, np.float32)
    ra.render_markers(img, Kc, R, p, markers, supersampling=CANVAS_SUPERSAMPLING)
    img *= 1.0 / 255.0
    uv, depth = ra.project(Kc, R, p, _pole_corners())
    if np.all(depth > 0.05):
        cv2.fillConvexPoly(img, np.rint(uv * 16).astype(np.int32), POLE_RADIANCE, cv2.LINE_8, shift=4)
    return img


def exposure_gain(t_s: float) -> float:
    """Auto exposure: a slow gain change (the camera re-metering)."""
    return 1.0 + 0.12 * math.sin(2 * math.pi * t_s / 9.0) + 0.05 * math.sin(2 * math.pi * t_s / 2.3)


def blur_length_px(truth: HardTruth, k: int, f_px: float) -> float:
    """Approximate motion-blur length over the exposure at sample k, px."""
    w = float(np.linalg.norm(truth.omega_world[k]))
    v = float(np.linalg.norm(truth.cam.velocity[k]))
    return (w * f_px + v * f_px / 2.5) * EXPOSURE_S


def render_real_frame(cam: RealCamera, sched: ra.ArcSchedule, t_s: float, markers: list[ra.MarkerSpec],
                      rng: np.random.Generator) -> tuple[NDArray[np.uint8], float]:
    """One mono8 frame exposed around t_s (mid-exposure) with every effect of the module
    docstring; returns (image, blur length in px)."""
    Kc, maps, size, vig = _canvas(cam.width, cam.height)
    mid = truth_at(sched, np.array([t_s]))
    blur = blur_length_px(mid, 0, cam.K[0, 0])
    n_sub = min(max(math.ceil(blur / 1.2) + 1, 1), 24) if blur > 0.3 else 1
    ts = t_s + (np.arange(n_sub) + 0.5) / n_sub * EXPOSURE_S - EXPOSURE_S / 2 if n_sub > 1 else np.array([t_s])
    tr = truth_at(sched, ts)
    # The exposure (sub-frames) and the defocus are summed and blurred on the ideal canvas, and
    # only then resampled through the distortion: the lens blurs light before the pixels
    # integrate it, and a band-limited canvas is what makes the bilinear resampling (and the
    # 2x2 points per pixel) an accurate area integral. Blurring after the resampling instead
    # left a sharp canvas edge interpolated linearly: edge positions off by up to 0.09 px
    # depending on their phase to the canvas grid, about 0.2 cm of camera pose at 3 m.
    acc_canvas = np.zeros((size[1], size[0]), np.float32)
    for j in range(len(ts)):
        acc_canvas += _render_canvas(Kc, size, tr.cam.R_enu_cam[j], tr.cam.position[j], markers)
    canvas = cv2.GaussianBlur(acc_canvas * np.float32(1.0 / len(ts)), (0, 0), DEFOCUS_SIGMA_PX * CANVAS_SCALE)
    acc = np.zeros((cam.height, cam.width), np.float32)
    for mx, my in maps:
        acc += cv2.remap(canvas, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    radiance = acc / len(maps) * vig * np.float32(0.95 * exposure_gain(t_s))
    sigma = np.sqrt(np.maximum(radiance, 0) * 2.5e-4 + 2.0e-5).astype(np.float32)
    radiance = radiance + rng.standard_normal(radiance.shape).astype(np.float32) * sigma
    out = 255.0 * np.power(np.clip(radiance, 0.0, 1.0), 1.0 / DISPLAY_GAMMA)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8), blur


def true_corners(cam: RealCamera, R: Array, p: Array, markers: list[ra.MarkerSpec]) -> dict[int, tuple[Array, bool]]:
    """Exact distorted pixel corners of the markers fully in the image, and whether the pole
    covers part of the marker (id -> ((4, 2), occluded))."""
    K, D = cam.K, cam.D
    R_cam_w = R.T
    rvec, _ = cv2.Rodrigues(R_cam_w)
    tvec = -R_cam_w @ p
    pole_uv = None
    pc = _pole_corners()
    if np.all((pc - p) @ R[:, 2] > 0.05):
        pole_uv, _ = cv2.projectPoints(pc, rvec, tvec, K, D)
        pole_uv = pole_uv.reshape(-1, 2)
    out: dict[int, tuple[Array, bool]] = {}
    for m in markers:
        X = m.corners_world()
        if np.any((X - p) @ R[:, 2] < 0.05):
            continue
        uv, _ = cv2.projectPoints(X, rvec, tvec, K, D)
        uv = uv.reshape(-1, 2)
        if not np.all((uv > 1) & (uv < [cam.width - 2, cam.height - 2])):
            continue
        occluded = False
        if pole_uv is not None:
            # The plate (with its quiet zone) against the pole's quad, both convex.
            _, plate_frac = ra.marker_plate(m.id)
            c = uv.mean(0)
            plate = c + (uv - c) / plate_frac
            inter, _ = cv2.intersectConvexConvex(plate.astype(np.float32), pole_uv.astype(np.float32))
            occluded = inter > 1.0
        out[m.id] = (uv, bool(occluded))
    return out


# --------------------------------------------------------------------------------------------
# The bag


def write_bag(bag: Any, seed: int, duration_s: float, image_format: str,
              progress: Callable[[float], None] | None = None,
              speeds: tuple[float, ...] = ra.ARC_SPEEDS_M_S, mount_on_tf_static: bool = True) -> None:
    """Write all messages of the hard profile into an open BagWriter, in log-time order.
    ``mount_on_tf_static`` False leaves /tf_static out (the same bag otherwise: for comparing
    the mount from /tf_static with the mount from parameters, :func:`mount_params`)."""
    from ..io.bags import msg_class
    from .messages import START_NS
    from .messages import Msgs as _Msgs

    m = _Msgs()
    cam = RealCamera()
    sched = ra.ArcSchedule.make(duration_s, speeds)
    mapped, unknown = ra.wall_markers()
    dur_ns = round(duration_s * 1e9)
    imu_ns = np.arange(0, dur_ns, 1_000_000_000 // ra.IMU_RATE_HZ, dtype=np.int64)
    n_cam = math.ceil(dur_ns * CAMERA_RATE_HZ / 1e9)
    cam_ns = (np.arange(n_cam, dtype=np.int64) * 1_000_000_000) // CAMERA_RATE_HZ + 5_000_000
    truth = truth_at(sched, imu_ns * 1e-9)
    err = ra.make_imu_errors(seed)
    gyro, accel = simulate_imu(truth, err, seed)
    q_gt = matrix_to_quat_xyzw(truth.cam.R_enu_cam)
    cam_truth = truth_at(sched, cam_ns * 1e-9)
    pixel_rng = rng_stream(seed, 'robot-arcs-hard-pixels')
    gv, av = err.gyro_noise_rad_s ** 2, err.accel_noise_m_s2 ** 2

    if mount_on_tf_static:
        bag.write('/tf_static', START_NS, msg_class('tf2_msgs/msg/TFMessage')(transforms=[
            m.transform_stamped(START_NS, ra.FRAME_IMU, ra.FRAME_CAMERA, T_IMU_CAM, matrix_to_quat_xyzw(R_IMU_CAM))]))
    events = sorted([(int(s), 0, k) for k, s in enumerate(imu_ns)]
                    + [(int(s) + ra.PROCESSING_DELAY_NS, 1, k) for k, s in enumerate(cam_ns)])
    K = cam.K
    P = np.hstack([K, np.zeros((3, 1))])
    Image = msg_class('sensor_msgs/msg/Image')
    Marker = msg_class('visualization_msgs/msg/Marker')
    MarkerArray = msg_class('visualization_msgs/msg/MarkerArray')
    report_every = max(1, n_cam // 50)
    for log_ns, kind, k in events:
        if kind == 0:
            ns = START_NS + log_ns
            bag.write('/imu/data_raw', ns, m.imu(ns, gyro[k], accel[k], gv, av))
            bag.write('/ground_truth/orientation', ns, m.transform_stamped(
                ns, ra.FRAME_WORLD, ra.FRAME_CAMERA, truth.cam.position[k], q_gt[k]))
            bag.write('/ground_truth/pose', ns, m.pose_stamped(ns, ra.FRAME_WORLD, truth.cam.position[k], q_gt[k]))
            continue
        stamp = START_NS + int(cam_ns[k])
        log = START_NS + log_ns
        img, _ = render_real_frame(cam, sched, cam_ns[k] * 1e-9, mapped + unknown, pixel_rng)
        if image_format == 'raw':
            bag.write('/camera/image_raw', log, Image(
                header=m.header(stamp, ra.FRAME_CAMERA), height=cam.height, width=cam.width,
                encoding='mono8', is_bigendian=0, step=cam.width, data=img.reshape(-1)))
        else:
            _, buf = cv2.imencode('.png', img)
            bag.write('/camera/image_raw/compressed', log, msg_class('sensor_msgs/msg/CompressedImage')(
                header=m.header(stamp, ra.FRAME_CAMERA), format='png', data=buf.reshape(-1)))
        info = msg_class('sensor_msgs/msg/CameraInfo')(
            header=m.header(stamp, ra.FRAME_CAMERA), height=cam.height, width=cam.width,
            distortion_model='plumb_bob', d=cam.D, k=K.ravel(), r=np.eye(3).ravel(),
            p=P.ravel(), binning_x=0, binning_y=0,
            roi=msg_class('sensor_msgs/msg/RegionOfInterest')(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
        bag.write('/camera/camera_info', log + CAMERA_INFO_LAG_NS, info)
        corners = true_corners(cam, cam_truth.cam.R_enu_cam[k], cam_truth.cam.position[k], mapped)
        items = []
        for mid, (uv, occluded) in sorted(corners.items()):
            items.append(Marker(
                header=m.header(stamp, ra.FRAME_CAMERA), ns='occluded' if occluded else 'visible', id=int(mid),
                type=Marker.LINE_STRIP, action=Marker.ADD,
                pose=m.Pose(position=m.Point(x=0.0, y=0.0, z=0.0), orientation=m.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)),
                scale=m.Vector3(x=1.0, y=0.0, z=0.0),
                color=msg_class('std_msgs/msg/ColorRGBA')(r=0.0, g=0.0, b=1.0, a=1.0),
                lifetime=msg_class('builtin_interfaces/msg/Duration')(sec=0, nanosec=0), frame_locked=False,
                points=[m.Point(x=float(u), y=float(v), z=0.0) for u, v in uv], colors=[], texture_resource='',
                texture=msg_class('sensor_msgs/msg/CompressedImage')(header=m.header(0, ''), format='', data=np.zeros(0, np.uint8)),
                uv_coordinates=[], text='', mesh_resource='',
                mesh_file=msg_class('visualization_msgs/msg/MeshFile')(filename='', data=np.zeros(0, np.uint8)),
                mesh_use_embedded_materials=False))
        bag.write(TOPIC_CORNERS, stamp, MarkerArray(markers=items))
        if progress is not None and (k % report_every == 0 or k == n_cam - 1):
            progress((k + 1) / n_cam)


def sidecar_params(seed: int) -> dict[str, Any]:
    """marker_tracker and visual_inertial_filter parameters: the marker map and the IMU noise;
    the mount is deliberately absent (it is on /tf_static only)."""
    params = ra.sidecar_params(seed)
    # The printed marker's white/black reflectance (the renderer's WHITE / BLACK), as a site
    # documents its markers: marker_tracker estimates the camera's gamma from it.
    params['marker_tracker']['ros__parameters']['marker_print_contrast'] = float(ra.WHITE / ra.BLACK)
    vi = params['visual_inertial_filter']['ros__parameters']
    vi.pop('imu_to_camera_xyzw', None)
    vi['gyro_bias_walk_rad_s'] = float(GYRO_BIAS_WALK_RAD_S)
    vi['accel_bias_walk_m_s2'] = float(ACCEL_BIAS_WALK_M_S2)
    return params


def mount_params() -> dict[str, Any]:
    """The IMU mount as visual_inertial_filter parameters (what /tf_static carries)."""
    return {'imu_to_camera_xyzw': [float(x) for x in matrix_to_quat_xyzw(R_IMU_CAM)],
            'camera_in_imu_m': [float(x) for x in T_IMU_CAM]}
