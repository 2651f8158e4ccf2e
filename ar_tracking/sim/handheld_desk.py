"""Scenario ``handheld_desk``: a hand-held phone camera over a cluttered desk, for monocular SLAM.

What a PTAM user on a camera phone does (Klein & Murray 2009): hold the phone 0.4-0.6 m above
and in front of a desk, translate it sideways by ~10-15 cm for the stereo initialisation, then
explore the desk by hand (translations of a few dm, rotations up to ~30-40 deg). The camera is
the phone's: a narrow field of view, a low frame rate, a rolling shutter and motion blur.

Scene (seeded, ``world`` frame: z up, the desk top at z = 0, its centre at the origin):

* a 1.2 x 0.8 m desk top with a multi-scale texture: wood grain, printed sheets (text-like word
  blobs, bar charts, tables, pictures), a desk calendar pad, a keyboard, a mouse pad, sticky
  notes, pens, coasters and small stickers, so that Shi-Tomasi corners exist at full, half and
  quarter resolution; the desk's front edge;
* three boxes standing on it (a cardboard box 15-25 cm tall, a stack of books 5-9 cm, a small
  printed box 6-14 cm), with textured, differently lit faces;
* a wall behind the desk (poster, calendar, socket) and a tiled floor 0.74 m below the desk.

Rendering is per-pixel ray casting against these textured rectangles (vectorised numpy; each
face is processed only in its projected bounding box), with one camera pose per image ROW, so
the rolling shutter is exact: the header stamp is the capture time of the centre row, row ``v``
is captured ``(v - (H-1)/2) / H * readout_s`` later (ar_tracking.core.slam.camera). Each row's
exposure is centred on its capture time; motion blur averages 1-6 sub-exposure renders (as many
as the motion during the exposure needs, ~2.5 px apart). Textures are looked up in a mip-mapped
atlas (trilinear: bilinear ``cv2.remap`` per level, the level from the pixel footprint), so far
and oblique surfaces do not alias. Then a slight optical blur, mild vignetting and sensor noise.

Motion (seeded, closed form, so the ground truth is exact): smooth sums of sinusoids for the
position and for a look-at point on the desk, plus a roll about the optical axis, faded in after
the initialisation. The first ~2.3 s: still for 0.3 s, then a sideways translation of 10-15 cm
(the look-at point follows, so the rotation stays small). With ``pure_rotation_start`` the
camera first turns on the spot (~12 deg pan, 0.3-2.3 s) and only then translates (2.6-4.6 s).
Speeds are bounded by a time scaling of the exploration: <= 0.28 m/s and <= 55 deg/s. The motion
does not depend on the duration: a short bag is a prefix of a long one of the same seed.

Camera defaults: 640 x 480 mono8, horizontal field of view 50 deg, 20 Hz, rolling-shutter
readout 30 ms (top to bottom), exposure 12 ms, principal point at the image centre, no lens
distortion.

Bag topics (log time = header stamp), :func:`write_handheld_desk_bag`:
/camera/image_raw (sensor_msgs/Image mono8; or /camera/image_raw/compressed png),
/camera/camera_info (K, plumb_bob zeros), frame camera_optical; /ground_truth/pose (PoseStamped,
frame ``world``, the camera_optical pose) at 100 Hz and at every camera stamp; /imu/data_raw
(100 Hz, frame imu, phone-grade noise and biases) and /tf_static (imu -> camera_optical,
R_imu_cam = diag(1, -1, -1), as the other scenarios' device). The sidecar
``<stem>.params.yaml`` holds the keyframe_slam_mapper parameters (the readout time).

This module is the scenario (motion, frames, IMU, bag); the parts it shares with the street scene
live by concern: the faces and atlas in :mod:`.model`, the painters in :mod:`.desk_textures` and
:mod:`.textures`, the desk layout in :mod:`.layout`, the shading in :mod:`.lighting`, the ray
caster in :mod:`.render`, the camera in :mod:`.camera`, the IMU sensor model in :mod:`.imu`.
"""
from __future__ import annotations

import functools
import logging
import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable, Iterator

import cv2
import numpy as np
import yaml
from numpy.typing import NDArray

from ..core.rotations import matrix_to_quat_xyzw, trace_angle
from ..io.bags import msg_class
from .camera import DESK_EXPOSURE_S as EXPOSURE_S
from .camera import DESK_IMAGE_SIZE as IMAGE_SIZE
from .camera import DESK_RATE_HZ as RATE_HZ
from .camera import DESK_READOUT_S as READOUT_S
from .camera import DeskCamera, DeskFrame, desk_camera
from .imu import imu_samples
from .layout import desk_scene
from .messages import START_NS, Msgs
from .model import Array, DeskScene
from .render import render_image
from .rng import rng_stream
from .scenario import BagRequest

__all__ = ['DeskCamera', 'DeskFrame', 'DeskMotion', 'DeskScene', 'SCENARIO', 'desk_camera', 'desk_motion',
           'desk_scene', 'frame_stamps_ns', 'frames', 'look_at', 'render_image', 'sidecar_params',
           'simulate_imu', 'trajectory', 'write_handheld_desk_bag', 'write_sidecars']

logger = logging.getLogger(__name__)

GT_RATE_HZ = 100
IMU_RATE_HZ = 100
GRAVITY_M_S2 = 9.80665

MAX_SPEED_M_S = 0.28
MAX_RATE_DEG_S = 55.0

FRAME_WORLD, FRAME_CAMERA, FRAME_IMU = 'world', 'camera_optical', 'imu'
R_IMU_CAM = np.diag([1.0, -1.0, -1.0])
GYRO_NOISE_RAD_S = 0.004
ACCEL_NOISE_M_S2 = 0.03

TOPIC_IMAGE = '/camera/image_raw'
TOPIC_IMAGE_COMPRESSED = '/camera/image_raw/compressed'
TOPIC_CAMERA_INFO = '/camera/camera_info'
TOPIC_GT_POSE = '/ground_truth/pose'
TOPIC_IMU = '/imu/data_raw'


# --------------------------------------------------------------------------------------------
# Motion


def _smoothstep(x: Array) -> Array:
    """C2 ramp 0 -> 1 on [0, 1] (6x^5 - 15x^4 + 10x^3)."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (x * (6.0 * x - 15.0) + 10.0)


def _ramp(t: Array, t0: float, t1: float) -> Array:
    return _smoothstep((np.asarray(t, dtype=float) - t0) / (t1 - t0))


def _sines(t: Array, amp: Array, freq: Array, phase: Array) -> Array:
    """Sum over the last axis of amp * sin(2 pi f t + phase); t (N,), params (..., K) -> (N, ...)."""
    arg = 2.0 * np.pi * t[:, None, None] * freq[None] + phase[None]
    return np.sum(amp[None] * np.sin(arg), axis=-1)


def look_at(p: Array, q: Array, roll: Array) -> Array:
    """R_w_c (N, 3, 3) of cameras at p looking at q (world z up: no roll at roll = 0)."""
    f = q - p
    f = f / np.linalg.norm(f, axis=-1, keepdims=True)
    up = np.array([0.0, 0.0, 1.0])
    x = np.cross(f, up)
    x = x / np.linalg.norm(x, axis=-1, keepdims=True)
    y = np.cross(f, x)
    R = np.stack([x, y, f], axis=-1)
    c, s = np.cos(roll), np.sin(roll)
    Rz = np.zeros((len(roll), 3, 3))
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, -s, s, c, 1.0
    return R @ Rz


@dataclass(frozen=True)
class DeskMotion:
    """The closed-form hand-held motion of one seed (see the module docstring)."""

    p0: Array
    q0: Array
    init_shift: Array            # sideways translation of the initialisation (m)
    pan_shift: Array             # look-at shift of the pure-rotation start (m)
    pos_amp: Array               # (3, K)
    pos_freq: Array
    pos_phase: Array
    tgt_amp: Array               # (3, K) (z amplitude 0)
    tgt_freq: Array
    tgt_phase: Array
    roll0: float
    roll_amp: Array              # (1, K)
    roll_freq: Array
    roll_phase: Array
    pure_rotation_start: bool = False
    time_scale: float = 1.0

    @property
    def phases(self) -> dict[str, tuple[float, float]]:
        """Time windows (s): 'pan' (pure rotation), 'init' (sideways), 'explore' (fade-in)."""
        if self.pure_rotation_start:
            return {'pan': (0.3, 2.3), 'init': (2.6, 4.6), 'explore': (4.8, 7.8)}
        return {'pan': (0.0, 0.0), 'init': (0.3, 2.3), 'explore': (2.5, 5.5)}

    def pose(self, t_s: Array) -> tuple[Array, Array]:
        """(R_w_c (N, 3, 3), p_w_c (N, 3)) at times t_s (s from the start)."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        ph = self.phases
        s_init = _ramp(t, *ph['init'])[:, None]
        w = _ramp(t, *ph['explore'])[:, None]
        tau = t * self.time_scale
        p = self.p0 + s_init * self.init_shift + w * _sines(tau, self.pos_amp, self.pos_freq, self.pos_phase)
        q = self.q0 + 0.8 * s_init * self.init_shift + w * _sines(tau, self.tgt_amp, self.tgt_freq, self.tgt_phase)
        if self.pure_rotation_start:
            q = q + _ramp(t, *ph['pan'])[:, None] * self.pan_shift
        roll = self.roll0 + w[:, 0] * _sines(tau, self.roll_amp, self.roll_freq, self.roll_phase)[:, 0]
        return look_at(p, q, roll), p


def _rates(motion: DeskMotion, t: Array, h: float = 1e-3) -> tuple[Array, Array]:
    """Speed (m/s) and angular rate (rad/s) by central differences of the closed form."""
    Ra, pa = motion.pose(t - h)
    Rb, pb = motion.pose(t + h)
    v = np.linalg.norm(pb - pa, axis=1) / (2 * h)
    rel = np.einsum('nji,njk->nik', Ra, Rb)
    return v, trace_angle(rel) / (2 * h)


@functools.lru_cache(maxsize=8)
def desk_motion(seed: int, pure_rotation_start: bool = False) -> DeskMotion:
    """The seed's motion, its exploration slowed down where needed to respect the speed bounds
    (checked over the first 180 s; the motion is a bounded sum of sinusoids)."""
    rng = rng_stream(seed, 'handheld-desk-motion')
    sign = float(rng.choice([-1.0, 1.0]))
    shift = rng.uniform(0.10, 0.15)
    p0 = np.array([-sign * shift / 2 + rng.uniform(-0.03, 0.03), rng.uniform(-0.58, -0.52),
                   rng.uniform(0.42, 0.48)])
    q0 = np.array([rng.uniform(-0.05, 0.05), rng.uniform(0.0, 0.08), 0.0])
    base_f = np.array([rng.uniform(0.07, 0.11), rng.uniform(0.18, 0.28), rng.uniform(0.45, 0.70)])

    def harmonics(amps: list[list[float]]) -> tuple[Array, Array, Array]:
        a = np.asarray(amps, float) * rng.uniform(0.8, 1.2, (len(amps), 3))
        f = base_f[None, :] * rng.uniform(0.85, 1.15, (len(amps), 3))
        return a, f, rng.uniform(0, 2 * np.pi, (len(amps), 3))

    pos = harmonics([[0.13, 0.06, 0.02], [0.07, 0.035, 0.012], [0.05, 0.025, 0.01]])
    tgt = harmonics([[0.15, 0.07, 0.03], [0.09, 0.04, 0.02], [0.0, 0.0, 0.0]])
    roll = harmonics([[0.14, 0.06, 0.025]])
    motion = DeskMotion(p0, q0, np.array([sign * shift, 0.0, 0.0]),
                        np.array([-sign * 0.15, 0.0, 0.0]), *pos, *tgt,
                        float(rng.uniform(-0.05, 0.05)), *roll, pure_rotation_start=pure_rotation_start)
    t = np.arange(0.0, 180.0, 0.02)
    for _ in range(4):
        v, w = _rates(motion, t)
        factor = min(MAX_SPEED_M_S / max(v.max(), 1e-9), math.radians(MAX_RATE_DEG_S) / max(w.max(), 1e-9))
        if factor >= 1.0:
            break
        motion = replace(motion, time_scale=motion.time_scale * factor * 0.97)
    return motion


def trajectory(seed: int, duration_s: float, t_s: Array,
               pure_rotation_start: bool = False) -> tuple[Array, Array]:
    """True camera poses (R_w_c (N, 3, 3), p_w_c (N, 3)) at times t_s (s from the start).

    The motion does not depend on ``duration_s`` (kept for symmetry with :func:`frames`); times
    outside [0, duration_s] are allowed."""
    del duration_s
    return desk_motion(int(seed), bool(pure_rotation_start)).pose(np.asarray(t_s, dtype=float))



# --------------------------------------------------------------------------------------------
# Frames


def frame_stamps_ns(duration_s: float, rate_hz: float = RATE_HZ) -> NDArray[np.int64]:
    """Camera stamps (ns from the start) of a bag of that duration."""
    n = int(math.ceil(duration_s * rate_hz - 1e-9))
    return np.array([int(round(k * 1e9 / rate_hz)) for k in range(n)], dtype=np.int64)


def frames(seed: int, duration_s: float, width: int = IMAGE_SIZE[0], height: int = IMAGE_SIZE[1],
           pure_rotation_start: bool = False, *, readout_s: float = READOUT_S,
           exposure_s: float = EXPOSURE_S, rate_hz: float = RATE_HZ, noise: bool = True,
           start_index: int = 0) -> Iterator[DeskFrame]:
    """The camera frames of the scenario, rendered one at a time (~0.1 s each at 640x480).

    Same seed and arguments -> identical images (the pixel noise of frame k comes from its own
    stream). ``start_index`` skips the first frames without rendering them."""
    cam = desk_camera(width, height, readout_s=readout_s, exposure_s=exposure_s, rate_hz=rate_hz)
    scene = desk_scene(int(seed))
    motion = desk_motion(int(seed), bool(pure_rotation_start))
    stamps = frame_stamps_ns(duration_s, rate_hz)
    for k in range(int(start_index), len(stamps)):
        t = stamps[k] * 1e-9
        rng = rng_stream(int(seed), 'handheld-desk-pixels', k) if noise else None
        img, n_sub = render_image(scene, cam, motion.pose, t, rng)
        R, p = motion.pose(np.array([t]))
        yield DeskFrame(int(stamps[k]), img, R[0], p[0], k, n_sub)


# --------------------------------------------------------------------------------------------
# IMU


def simulate_imu(seed: int, t_s: Array, pure_rotation_start: bool = False) -> tuple[Array, Array]:
    """(gyro rad/s, accel m/s^2) in the IMU frame (R_imu_cam = diag(1, -1, -1)) at times t_s,
    from the closed-form motion (rates and acceleration by central differences), with
    phone-grade white noise and constant biases (:func:`.imu.imu_samples`)."""
    motion = desk_motion(int(seed), bool(pure_rotation_start))
    t = np.asarray(t_s, dtype=float)
    h = 1e-4
    Ra, _ = motion.pose(t - h)
    Rb, _ = motion.pose(t + h)
    R, p = motion.pose(t)
    rel = np.einsum('nji,njk->nik', Ra, Rb)  # R_a^T R_b ~ exp([w_c] 2h)
    w_c = np.stack([rel[:, 2, 1] - rel[:, 1, 2], rel[:, 0, 2] - rel[:, 2, 0],
                    rel[:, 1, 0] - rel[:, 0, 1]], -1) / (4 * h)
    H = 1e-3
    _, pa = motion.pose(t - H)
    _, pb = motion.pose(t + H)
    acc_w = (pb - 2 * p + pa) / (H * H) + np.array([0.0, 0.0, GRAVITY_M_S2])
    f_c = np.einsum('nji,nj->ni', R, acc_w)  # R^T (a + g) (this einsum form keeps the bags' bytes)
    rng = rng_stream(int(seed), 'handheld-desk-imu')
    bg, ba = rng.normal(0, 0.005, 3), rng.normal(0, 0.05, 3)
    return imu_samples(w_c, f_c, rng=rng, R_imu_cam=R_IMU_CAM, gyro_bias_rad_s=bg, accel_bias_m_s2=ba,
                       gyro_noise_rad_s=GYRO_NOISE_RAD_S, accel_noise_m_s2=ACCEL_NOISE_M_S2)


# --------------------------------------------------------------------------------------------
# The bag


def write_handheld_desk_bag(bag: Any, seed: int, duration_s: float, image_format: str = 'raw',
                            progress: Callable[[float], None] | None = None, *,
                            width: int = IMAGE_SIZE[0], height: int = IMAGE_SIZE[1],
                            pure_rotation_start: bool = False, imu: bool = True) -> None:
    """Write all messages of the scenario into an open BagWriter, in log-time order."""
    if image_format not in ('raw', 'compressed'):
        raise ValueError(f'unknown image format {image_format!r}')
    m = Msgs()
    cam = desk_camera(width, height)
    scene = desk_scene(int(seed))
    motion = desk_motion(int(seed), bool(pure_rotation_start))
    dur_ns = int(round(duration_s * 1e9))
    cam_ns = frame_stamps_ns(duration_s, cam.rate_hz)
    grid_ns = np.arange(0, dur_ns, 1_000_000_000 // GT_RATE_HZ, dtype=np.int64)
    gt_ns = np.union1d(grid_ns, cam_ns)
    R_gt, p_gt = motion.pose(gt_ns * 1e-9)
    q_gt = matrix_to_quat_xyzw(R_gt)
    imu_ns = np.arange(0, dur_ns, 1_000_000_000 // IMU_RATE_HZ, dtype=np.int64) if imu else np.zeros(0, np.int64)
    if imu:
        gyro, accel = simulate_imu(seed, imu_ns * 1e-9, pure_rotation_start)
        bag.write('/tf_static', START_NS, msg_class('tf2_msgs/msg/TFMessage')(transforms=[
            m.transform_stamped(START_NS, FRAME_IMU, FRAME_CAMERA, np.zeros(3), matrix_to_quat_xyzw(R_IMU_CAM))]))
    gv, av = GYRO_NOISE_RAD_S ** 2, ACCEL_NOISE_M_S2 ** 2

    K = cam.K
    P = np.hstack([K, np.zeros((3, 1))])
    Image = msg_class('sensor_msgs/msg/Image')
    Compressed = msg_class('sensor_msgs/msg/CompressedImage')
    CameraInfo = msg_class('sensor_msgs/msg/CameraInfo')
    Roi = msg_class('sensor_msgs/msg/RegionOfInterest')
    events = sorted([(int(s), 0, k) for k, s in enumerate(gt_ns)]
                    + [(int(s), 1, k) for k, s in enumerate(imu_ns)]
                    + [(int(s), 2, k) for k, s in enumerate(cam_ns)])
    n_cam = len(cam_ns)
    report_every = max(1, n_cam // 50)
    for stamp, kind, k in events:
        ns = START_NS + stamp
        if kind == 0:
            bag.write(TOPIC_GT_POSE, ns, m.pose_stamped(ns, FRAME_WORLD, p_gt[k], q_gt[k]))
            continue
        if kind == 1:
            bag.write(TOPIC_IMU, ns, m.imu(ns, gyro[k], accel[k], gv, av))
            continue
        rng = rng_stream(int(seed), 'handheld-desk-pixels', k)
        img, _ = render_image(scene, cam, motion.pose, stamp * 1e-9, rng)
        bag.write(TOPIC_CAMERA_INFO, ns, CameraInfo(
            header=m.header(ns, FRAME_CAMERA), height=cam.height, width=cam.width,
            distortion_model='plumb_bob', d=np.zeros(5), k=K.ravel(), r=np.eye(3).ravel(),
            p=P.ravel(), binning_x=0, binning_y=0,
            roi=Roi(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)))
        if image_format == 'raw':
            bag.write(TOPIC_IMAGE, ns, Image(
                header=m.header(ns, FRAME_CAMERA), height=cam.height, width=cam.width,
                encoding='mono8', is_bigendian=0, step=cam.width, data=img.reshape(-1)))
        else:
            ok, buf = cv2.imencode('.png', img)
            if not ok:  # pragma: no cover - OpenCV always encodes a valid uint8 image
                raise RuntimeError('PNG encoding failed')
            bag.write(TOPIC_IMAGE_COMPRESSED, ns, Compressed(
                header=m.header(ns, FRAME_CAMERA), format='png', data=buf.reshape(-1)))
        if progress is not None and (k % report_every == 0 or k == n_cam - 1):
            progress((k + 1) / n_cam)


def sidecar_params(seed: int) -> dict[str, Any]:
    """keyframe_slam_mapper parameters for a handheld_desk bag."""
    del seed
    return {'keyframe_slam_mapper': {'ros__parameters': {'readout_s': float(READOUT_S)}}}


def write_sidecars(params_path: Path, bag_path: Path, seed: int) -> None:
    """<stem>.params.yaml: the keyframe_slam_mapper parameters of the simulated camera."""
    head = (f'# Parameters for {Path(bag_path).name} (scenario handheld_desk, seed {seed}): the camera\'s\n'
            f'# rolling-shutter readout (top to bottom row, {READOUT_S * 1e3:.0f} ms) for keyframe_slam_mapper.\n')
    Path(params_path).write_text(head + yaml.safe_dump(sidecar_params(seed), sort_keys=False,
                                                       default_flow_style=None))


class HandheldDesk:
    """The :class:`.scenario.ScenarioBag` of handheld_desk (the session and profile are ignored)."""

    name = 'handheld_desk'

    def write_bag(self, bag: Any, req: BagRequest, progress: Callable[[float], None] | None) -> None:
        write_handheld_desk_bag(bag, req.seed, req.duration_s, req.image_format, progress)

    def write_sidecars(self, sidecar: Path, bag_path: Path, req: BagRequest) -> None:
        write_sidecars(sidecar, bag_path, req.seed)

    def summary(self, req: BagRequest) -> str:
        return f'handheld_desk, seed {req.seed}, {req.duration_s:.1f} s'


SCENARIO = HandheldDesk()
