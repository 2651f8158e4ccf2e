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
"""
from __future__ import annotations

import functools
import logging
import math
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Iterator

import cv2
import numpy as np
import yaml
from numpy.typing import NDArray

from ..core.rotations import matrix_to_quat_xyzw, trace_angle
from .world import rng_stream

logger = logging.getLogger(__name__)

Array = NDArray[np.float64]
PoseFn = Callable[[Array], tuple[Array, Array]]

RATE_HZ = 20.0
READOUT_S = 0.030
EXPOSURE_S = 0.012
HFOV_DEG = 50.0
IMAGE_SIZE = (640, 480)
GT_RATE_HZ = 100
IMU_RATE_HZ = 100
GRAVITY_M_S2 = 9.80665

DESK_SIZE_M = (1.2, 0.8)
DESK_THICKNESS_M = 0.03
WALL_Y_M = 0.42
FLOOR_Z_M = -0.74
BACKGROUND = 80.0
#: Texture resolution of the desk and the boxes (texels per metre): 0.5 mm texels.
DESK_DENSITY = 2000.0
MIP_LEVELS = 4
ATLAS_GUTTER = 24
OPTICAL_BLUR_SIGMA_PX = 0.5
PIXEL_NOISE = 2.0
VIGNETTING = 0.18
#: Largest image motion between two sub-exposure renders (px).
BLUR_STEP_PX = 2.5
MAX_SUBFRAMES = 6

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
# Camera and frames


@dataclass(frozen=True)
class DeskCamera:
    """The phone camera: pinhole intrinsics (pixels, OpenCV pixel centres), rate and shutter."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    rate_hz: float = RATE_HZ
    readout_s: float = READOUT_S
    exposure_s: float = EXPOSURE_S

    @property
    def K(self) -> Array:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def row_time_offset_s(self, v: Array) -> Array:
        """Capture time of row(s) ``v`` relative to the header stamp (centre row), as the SLAM."""
        return (np.asarray(v, dtype=float) - (self.height - 1) / 2.0) / self.height * self.readout_s

    def slam_camera(self) -> Any:
        """The same camera as ar_tracking.core.slam.camera.Camera (for core-only checks)."""
        from ..core.slam.camera import Camera

        return Camera(self.fx, self.fy, self.cx, self.cy, self.width, self.height, self.readout_s)


def desk_camera(width: int = IMAGE_SIZE[0], height: int = IMAGE_SIZE[1], *,
                readout_s: float = READOUT_S, exposure_s: float = EXPOSURE_S,
                rate_hz: float = RATE_HZ) -> DeskCamera:
    """The scenario's camera at a given image size (the field of view stays 50 deg wide)."""
    if width < 8 or height < 8:
        raise ValueError(f'image size {width}x{height} is too small')
    if readout_s < 0 or exposure_s < 0 or rate_hz <= 0:
        raise ValueError('readout_s and exposure_s must be >= 0, rate_hz > 0')
    f = width / 2.0 / math.tan(math.radians(HFOV_DEG) / 2.0)
    return DeskCamera(int(width), int(height), f, f, (width - 1) / 2.0, (height - 1) / 2.0,
                      float(rate_hz), float(readout_s), float(exposure_s))


@dataclass(frozen=True)
class DeskFrame:
    """One camera frame: stamp (ns from the start), the mono8 image, and the true camera pose
    (camera_optical in world) at the stamp, i.e. at the capture time of the centre row."""

    stamp_ns: int
    image: NDArray[np.uint8]
    R_w_c: Array
    p_w_c: Array
    index: int = 0
    subframes: int = 1


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
# Scene: textured rectangles and the texture atlas


@dataclass(frozen=True)
class Face:
    """A textured rectangle: points ``origin + a e_u + b e_v`` for a in [0, size_u], b in
    [0, size_v]; the outward normal is e_u x e_v. Texel (row i, col j) of its texture covers
    local (a, b) around ((j + 0.5) / density, (i + 0.5) / density)."""

    name: str
    origin: Array
    e_u: Array
    e_v: Array
    size: tuple[float, float]
    density: float
    atlas_xy: tuple[int, int] = (0, 0)

    @property
    def normal(self) -> Array:
        return np.cross(self.e_u, self.e_v)

    @property
    def corners(self) -> Array:
        u, v = self.e_u * self.size[0], self.e_v * self.size[1]
        return np.stack([self.origin, self.origin + u, self.origin + u + v, self.origin + v])

    def texture_shape(self) -> tuple[int, int]:
        return (max(1, int(math.ceil(self.size[1] * self.density))),
                max(1, int(math.ceil(self.size[0] * self.density))))

    def local(self, X: Array) -> Array:
        """Local (a, b) metres of world points (N, 3) on the face's plane."""
        d = np.atleast_2d(X) - self.origin
        return np.column_stack([d @ self.e_u, d @ self.e_v])


@dataclass(frozen=True)
class Box:
    """A box standing on the desk: centre of its footprint (x, y), yaw, size (lx, ly, h)."""

    kind: str
    centre: Array
    yaw: float
    size: tuple[float, float, float]


@dataclass(frozen=True)
class DeskScene:
    """Faces and the mip-mapped uint8 texture atlas (level k = cv2.pyrDown of level k - 1, so its
    texel i lies on texel 2^k i of level 0)."""

    seed: int
    faces: tuple[Face, ...]
    boxes: tuple[Box, ...]
    atlas: tuple[NDArray[np.uint8], ...] = field(repr=False)

    def face(self, name: str) -> Face:
        for f in self.faces:
            if f.name == name:
                return f
        raise KeyError(name)

    def texture(self, name: str) -> NDArray[np.uint8]:
        """A face's level-0 texture (a view into the atlas)."""
        f = self.face(name)
        h, w = f.texture_shape()
        x, y = f.atlas_xy
        return self.atlas[0][y:y + h, x:x + w]

    def with_dots(self, points_w: Array, radius_m: float = 0.004, value: int = 0) -> 'DeskScene':
        """A copy with filled dots painted at world points lying on faces (for tests/checks)."""
        level0 = self.atlas[0].copy()
        for X in np.atleast_2d(points_w):
            for f in self.faces:
                a, b = f.local(X)[0]
                if abs(float((X - f.origin) @ f.normal)) < 1e-6 and 0 <= a <= f.size[0] and 0 <= b <= f.size[1]:
                    c = ((f.atlas_xy[0] + a * f.density - 0.5) * 16, (f.atlas_xy[1] + b * f.density - 0.5) * 16)
                    cv2.circle(level0, (int(round(c[0])), int(round(c[1]))), int(round(radius_m * f.density * 16)),
                               int(value), -1, cv2.LINE_AA, 4)
                    break
        return replace(self, atlas=_pyramid(level0))


def _pyramid(level0: NDArray[np.uint8]) -> tuple[NDArray[np.uint8], ...]:
    levels = [level0]
    for _ in range(MIP_LEVELS - 1):
        levels.append(cv2.pyrDown(levels[-1]))
    return tuple(levels)


class _Painter:
    """Draws shapes given in metres (local 2-D frames) into a uint8 face texture."""

    def __init__(self, img: NDArray[np.uint8], density: float) -> None:
        self.img = img
        self.d = density
        self._T = [np.eye(3)]

    @contextmanager
    def at(self, x: float, y: float, angle: float = 0.0) -> Iterator[None]:
        c, s = math.cos(angle), math.sin(angle)
        self._T.append(self._T[-1] @ np.array([[c, -s, x], [s, c, y], [0, 0, 1.0]]))
        try:
            yield
        finally:
            self._T.pop()

    def _pts(self, pts: Any) -> NDArray[np.int32]:
        P = np.asarray(pts, float).reshape(-1, 2)
        T = self._T[-1]
        P = P @ T[:2, :2].T + T[:2, 2]
        return np.round((P * self.d - 0.5) * 16).astype(np.int32)

    def poly(self, pts: Any, val: float) -> None:
        cv2.fillPoly(self.img, [self._pts(pts)], int(np.clip(val, 0, 255)), cv2.LINE_AA, 4)

    def rect(self, x: float, y: float, w: float, h: float, val: float) -> None:
        self.poly([[x, y], [x + w, y], [x + w, y + h], [x, y + h]], val)

    def circle(self, x: float, y: float, r: float, val: float, width: float = 0.0) -> None:
        c = self._pts([[x, y]])[0]
        thick = -1 if width <= 0 else max(1, int(round(width * self.d)))
        cv2.circle(self.img, (int(c[0]), int(c[1])), int(round(r * self.d * 16)), int(np.clip(val, 0, 255)),
                   thick, cv2.LINE_AA, 4)

    def line(self, pts: Any, val: float, width: float, closed: bool = False) -> None:
        cv2.polylines(self.img, [self._pts(pts)], closed, int(np.clip(val, 0, 255)),
                      max(1, int(round(width * self.d))), cv2.LINE_AA, 4)


def _smooth_noise(rng: np.random.Generator, shape: tuple[int, int], cells: tuple[int, int]) -> Array:
    """Smooth noise of unit-ish amplitude: random values on a coarse grid, cubic upsampling."""
    small = rng.normal(0, 1, (max(2, cells[1]), max(2, cells[0]))).astype(np.float32)
    return cv2.resize(small, (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC)


# ---- texture pieces (all sizes in metres) -----------------------------------------------------


def _text(p: _Painter, rng: np.random.Generator, x: float, y: float, w: float, n_lines: int,
          size: float, val: float, pitch: float | None = None) -> None:
    """Lines of text-like word blobs (x-height bodies with a few ascenders)."""
    pitch = pitch or size * 1.7
    for i in range(n_lines):
        yy = y + i * pitch
        end = x + (w if i < n_lines - 1 else w * rng.uniform(0.3, 0.8))
        cx = x + (size * 2 if i == 0 and rng.random() < 0.3 else 0.0)
        while True:
            wl = int(rng.integers(1, 10)) * size * 0.55
            if cx + wl > end:
                break
            p.rect(cx, yy + size * 0.3, wl, size * 0.5, val)
            for _ in range(int(rng.integers(0, 3))):
                ax = cx + rng.uniform(0, max(wl - size * 0.15, 1e-4))
                p.rect(ax, yy, size * 0.15, size * 0.35, val)
            cx += wl + size * 0.5


def _picture(p: _Painter, rng: np.random.Generator, x: float, y: float, w: float, h: float,
             lo: float = 20, hi: float = 235) -> None:
    """An abstract 'photo': a background and overlapping random polygons and discs."""
    p.rect(x, y, w, h, rng.uniform(lo, hi))
    for _ in range(int(rng.integers(12, 25))):
        val = rng.uniform(lo, hi)
        cx, cy = x + rng.uniform(0, w), y + rng.uniform(0, h)
        r = rng.uniform(0.08, 0.35) * min(w, h)
        if rng.random() < 0.3:
            p.circle(cx, cy, r * 0.6, val)
        else:
            n = int(rng.integers(3, 6))
            ang = np.sort(rng.uniform(0, 2 * np.pi, n))
            rad = r * rng.uniform(0.5, 1.0, n)
            pts = np.column_stack([np.clip(cx + rad * np.cos(ang), x, x + w), np.clip(cy + rad * np.sin(ang), y, y + h)])
            p.poly(pts, val)


def _bar_chart(p: _Painter, rng: np.random.Generator, x: float, y: float, w: float, h: float) -> None:
    p.line([[x, y], [x, y + h], [x + w, y + h]], 40, 0.0008)
    n = int(rng.integers(4, 9))
    bw = w / (n * 1.5 + 0.5)
    for i in range(n):
        bh = rng.uniform(0.15, 0.95) * h
        p.rect(x + bw * (0.5 + 1.5 * i), y + h - bh, bw, bh, rng.choice([40.0, 90.0, 140.0]))


def _table(p: _Painter, rng: np.random.Generator, x: float, y: float, w: float, rows: int, cols: int) -> None:
    rh = 0.007
    cw = w / cols
    p.rect(x, y, w, rh, 70)
    for r in range(rows + 1):
        p.line([[x, y + r * rh], [x + w, y + r * rh]], 50, 0.0004)
    for c in range(cols + 1):
        p.line([[x + c * cw, y], [x + c * cw, y + rows * rh]], 50, 0.0004)
    for r in range(1, rows):
        for c in range(cols):
            p.rect(x + c * cw + 0.002, y + r * rh + 0.002, rng.uniform(0.3, 0.8) * (cw - 0.004), 0.0028, 30)


def _paper(p: _Painter, rng: np.random.Generator, x: float, y: float, angle: float) -> None:
    """An A4 sheet (its centre at x, y) with a title, paragraphs and a figure."""
    W, H = 0.210, 0.297
    with p.at(x, y, angle), p.at(-W / 2, -H / 2):
        p.rect(0, 0, W, H, rng.uniform(215, 235))
        m, yy = 0.022, 0.025
        _text(p, rng, m, yy, W * 0.6, 1, 0.007, 25, 0.012)
        yy += 0.018
        while yy < H - 0.03:
            kind = rng.random()
            if kind < 0.6:
                n = int(rng.integers(3, 8))
                _text(p, rng, m, yy, W - 2 * m, n, 0.0032, 35)
                yy += n * 0.0032 * 1.7 + 0.006
            elif kind < 0.75 and yy < H - 0.09:
                fw = rng.uniform(0.08, W - 2 * m)
                _bar_chart(p, rng, m + 0.005, yy, fw, 0.05)
                yy += 0.062
            elif kind < 0.88 and yy < H - 0.08:
                rows = int(rng.integers(3, 7))
                _table(p, rng, m, yy, W - 2 * m, rows, int(rng.integers(3, 6)))
                yy += rows * 0.007 + 0.008
            elif yy < H - 0.09:
                pw = rng.uniform(0.06, 0.12)
                _picture(p, rng, m, yy, pw, 0.06)
                _text(p, rng, m + pw + 0.006, yy, W - 2 * m - pw - 0.006, 6, 0.0032, 35)
                yy += 0.068
            else:
                break


def _sticky(p: _Painter, rng: np.random.Generator, x: float, y: float, angle: float) -> None:
    with p.at(x, y, angle):
        p.rect(-0.038, -0.038, 0.076, 0.076, rng.uniform(185, 210))
        for _ in range(int(rng.integers(2, 5))):
            n = int(rng.integers(3, 7))
            pts = np.column_stack([rng.uniform(-0.03, 0.03, n), rng.uniform(-0.03, 0.03, n)])
            p.line(pts, rng.uniform(30, 80), 0.0012)


def _keyboard(p: _Painter, rng: np.random.Generator, x: float, y: float, angle: float) -> None:
    with p.at(x, y, angle), p.at(-0.22, -0.07):
        p.rect(0, 0, 0.44, 0.14, 45)
        pitch, k = 0.019, 0.0155
        for r in range(5):
            c = 0.0
            while c < 0.42 - pitch:
                kw = k if rng.random() > 0.12 else k + pitch * int(rng.integers(1, 3))
                if c + kw > 0.43:
                    break
                p.rect(0.008 + c, 0.012 + r * pitch * 1.3 * 0.97, kw, k, 85)
                p.rect(0.011 + c, 0.015 + r * pitch * 1.3 * 0.97, 0.0025, 0.0035, 215)
                c += kw + pitch - k
        p.rect(0.12, 0.012 + 5 * pitch * 1.26, 0.2, 0.008, 85)


def _mousepad(p: _Painter, rng: np.random.Generator, x: float, y: float, angle: float) -> None:
    with p.at(x, y, angle):
        p.rect(-0.11, -0.09, 0.22, 0.18, 55)
        p.circle(0.04, 0.03, 0.03, 190)
        p.poly([[0.02, 0.045], [0.06, 0.045], [0.04, 0.01]], 55)
        _text(p, rng, -0.09, -0.07, 0.12, 1, 0.008, 200, 0.012)
        p.rect(-0.09, 0.06, 0.05, 0.012, 160)


def _calendar(p: _Painter, rng: np.random.Generator, x: float, y: float, angle: float, w: float, h: float,
              bg: float = 225) -> None:
    with p.at(x, y, angle), p.at(-w / 2, -h / 2):
        p.rect(0, 0, w, h, bg)
        p.rect(0, 0, w, h * 0.12, 70)
        _text(p, rng, w * 0.05, h * 0.025, w * 0.4, 1, h * 0.05, 220, h * 0.07)
        cols, rows = 7, 5
        cw, rh = w / cols, h * 0.88 / rows
        for r in range(rows + 1):
            p.line([[0, h * 0.12 + r * rh], [w, h * 0.12 + r * rh]], 90, 0.0006)
        for c in range(cols + 1):
            p.line([[c * cw, h * 0.12], [c * cw, h]], 90, 0.0006)
        for r in range(rows):
            for c in range(cols):
                x0, y0 = c * cw + cw * 0.08, h * 0.12 + r * rh + rh * 0.08
                n = int(rng.integers(1, 3))
                for i in range(n):
                    p.rect(x0 + i * cw * 0.1, y0, cw * 0.07, rh * 0.16, 40)
                if rng.random() < 0.25:
                    _text(p, rng, x0, y0 + rh * 0.35, cw * 0.8, 2, min(0.003, rh * 0.15), 60)


def _wood(rng: np.random.Generator, shape: tuple[int, int], density: float, base: float) -> NDArray[np.uint8]:
    """Wood grain: warped stripes along the texture's x axis plus low-frequency colour."""
    h, w = shape
    warp = _smooth_noise(rng, shape, (w // 240, h // 60)) * 1.2 + _smooth_noise(rng, shape, (w // 40, h // 20)) * 0.25
    yy = (np.arange(h, dtype=np.float32)[:, None] / density)
    period = 0.0035
    grain = np.sin(2 * np.pi * (yy / period + warp))
    low = _smooth_noise(rng, shape, (max(2, w // 400), max(2, h // 400)))
    img = base + 9.0 * grain + 10.0 * low + 3.0 * _smooth_noise(rng, shape, (w // 8, h // 8))
    return np.clip(img, 0, 255).astype(np.uint8)


def _desk_texture(rng: np.random.Generator) -> NDArray[np.uint8]:
    W, H = DESK_SIZE_M
    shape = (int(math.ceil(H * DESK_DENSITY)), int(math.ceil(W * DESK_DENSITY)))
    img = _wood(rng, shape, DESK_DENSITY, rng.uniform(135, 160))
    p = _Painter(img, DESK_DENSITY)
    # small stickers, screws, coins and scraps everywhere (corners on the bare wood too)
    for _ in range(90):
        x, y, s = rng.uniform(0, W), rng.uniform(0, H), rng.uniform(0.006, 0.03)
        val = rng.choice([rng.uniform(20, 80), rng.uniform(190, 245)])
        with p.at(x, y, rng.uniform(0, np.pi)):
            kind = rng.random()
            if kind < 0.4:
                p.rect(-s / 2, -s / 2 * rng.uniform(0.4, 1), s, s * rng.uniform(0.4, 1), val)
            elif kind < 0.7:
                p.poly([[0, -s / 2], [s / 2, s / 2], [-s / 2, s / 2]], val)
            else:
                p.circle(0, 0, s / 2, val)
                p.rect(-s / 4, -s / 10, s / 2, s / 5, 255 - val)
    _calendar(p, rng, rng.uniform(0.45, 0.75), rng.uniform(0.3, 0.42), rng.uniform(-0.08, 0.08), 0.42, 0.30)
    _keyboard(p, rng, rng.uniform(0.45, 0.7), rng.uniform(0.1, 0.15), rng.uniform(-0.1, 0.1))
    _mousepad(p, rng, rng.uniform(0.95, 1.05), rng.uniform(0.15, 0.3), rng.uniform(-0.3, 0.3))
    for x, y in ((rng.uniform(0.12, 0.3), rng.uniform(0.2, 0.45)), (rng.uniform(0.3, 0.5), rng.uniform(0.5, 0.68)),
                 (rng.uniform(0.8, 1.05), rng.uniform(0.45, 0.65)), (rng.uniform(0.55, 0.8), rng.uniform(0.2, 0.5))):
        _paper(p, rng, x, y, rng.uniform(-0.7, 0.7))
    for _ in range(5):
        _sticky(p, rng, rng.uniform(0.05, 1.15), rng.uniform(0.05, 0.75), rng.uniform(-0.5, 0.5))
    for _ in range(3):
        with p.at(rng.uniform(0.1, 1.1), rng.uniform(0.1, 0.7), rng.uniform(0, np.pi)):
            val = rng.uniform(20, 220)
            p.rect(-0.07, -0.0045, 0.14, 0.009, val)
            p.rect(0.045, -0.005, 0.03, 0.01, 255 - val)
            p.poly([[-0.07, -0.0045], [-0.085, 0], [-0.07, 0.0045]], 200)
    for _ in range(2):
        x, y = rng.uniform(0.1, 1.1), rng.uniform(0.1, 0.7)
        p.circle(x, y, 0.045, rng.uniform(60, 110))
        p.circle(x, y, 0.035, rng.uniform(170, 220), 0.004)
        p.circle(x, y, 0.012, 230)
    n = 8
    cable = np.column_stack([np.linspace(rng.uniform(0.2, 1.0), rng.uniform(0.2, 1.0), n) + rng.normal(0, 0.03, n),
                             np.linspace(0.8, rng.uniform(0.3, 0.6), n)])
    p.line(cable, 30, 0.006)
    return img


def _cardboard(rng: np.random.Generator, shape: tuple[int, int], density: float, w: float, h: float,
               top: bool) -> NDArray[np.uint8]:
    """Cardboard with tape (top) or shipping labels, a barcode, a printed logo and arrows (sides)."""
    img = np.clip(150 + 6 * _smooth_noise(rng, shape, (max(2, shape[1] // 6), max(2, shape[0] // 6)))
                  + 8 * _smooth_noise(rng, shape, (3, 3)), 0, 255).astype(np.uint8)
    p = _Painter(img, density)
    if top:
        p.rect(0, h / 2 - 0.025, w, 0.05, 178)
        _text(p, rng, 0.02, h / 2 - 0.015, w * 0.6, 2, 0.008, 60, 0.014)
        p.rect(rng.uniform(0.01, w * 0.4), rng.uniform(0.005, 0.02), 0.07, 0.035, 228)
        _picture(p, rng, w * 0.55, h * 0.7, w * 0.35, h * 0.25, 40, 120)
        return img
    lx, ly = rng.uniform(0.005, max(0.006, w - 0.105)), rng.uniform(0.005, max(0.006, h - 0.07))
    p.rect(lx, ly, 0.1, 0.065, 232)
    bx = lx + 0.008
    while bx < lx + 0.07:
        bw = rng.uniform(0.0005, 0.002)
        p.rect(bx, ly + 0.006, bw, 0.025, 20)
        bx += bw + rng.uniform(0.0005, 0.002)
    _text(p, rng, lx + 0.008, ly + 0.036, 0.08, 3, 0.004, 30)
    # printed logo and brand name, 'this side up' arrows, a glass and an umbrella-like icon
    cx, cy = rng.uniform(0.03, max(0.031, w - 0.03)), rng.uniform(0.03, max(0.031, h - 0.03))
    p.circle(cx, cy, 0.022, 60)
    p.poly([[cx - 0.012, cy + 0.01], [cx, cy - 0.014], [cx + 0.012, cy + 0.01]], 150)
    _text(p, rng, max(0.0, cx - 0.05), min(h - 0.02, cy + 0.028), 0.1, 1, 0.012, 60, 0.02)
    ax, ay = rng.uniform(0.005, max(0.006, w - 0.05)), rng.uniform(0.005, max(0.006, h - 0.05))
    for k in range(2):
        x0 = ax + k * 0.025
        p.poly([[x0, ay + 0.02], [x0 + 0.01, ay], [x0 + 0.02, ay + 0.02], [x0 + 0.013, ay + 0.02],
                [x0 + 0.013, ay + 0.045], [x0 + 0.007, ay + 0.045], [x0 + 0.007, ay + 0.02]], 60)
    gx, gy = rng.uniform(0.005, max(0.006, w - 0.03)), rng.uniform(0.005, max(0.006, h - 0.04))
    p.line([[gx, gy], [gx + 0.025, gy], [gx + 0.018, gy + 0.02], [gx + 0.007, gy + 0.02]], 60, 0.002, True)
    p.rect(gx + 0.011, gy + 0.02, 0.003, 0.015, 60)
    p.rect(gx + 0.004, gy + 0.033, 0.017, 0.003, 60)
    for _ in range(int(rng.integers(2, 5))):  # stamped lot numbers and scuffs
        _text(p, rng, rng.uniform(0, w * 0.7), rng.uniform(0, h - 0.01), w * 0.25, 1, 0.005, 70)
    return img


def _book_top(rng: np.random.Generator, shape: tuple[int, int], density: float, w: float, h: float) -> NDArray[np.uint8]:
    bg = rng.uniform(40, 200)
    img = np.full(shape, bg, np.uint8)
    p = _Painter(img, density)
    fg = 230 if bg < 120 else 25
    _text(p, rng, 0.02, 0.02, w - 0.04, 2, 0.012, fg, 0.02)
    _picture(p, rng, 0.03, 0.07, w - 0.06, h * 0.45)
    _text(p, rng, 0.02, h - 0.035, w * 0.5, 1, 0.008, fg)
    return img


def _book_side(rng: np.random.Generator, shape: tuple[int, int], density: float, w: float, h: float,
               bands: list[tuple[float, float]], spine: bool) -> NDArray[np.uint8]:
    img = np.full(shape, 215, np.uint8)
    p = _Painter(img, density)
    z = 0.0
    for thick, cover in bands:
        if spine:
            p.rect(0, z, w, thick, cover)
            _text(p, rng, 0.02, z + thick * 0.25, w * 0.6, 1, thick * 0.45, 255 - cover, thick)
        else:
            p.rect(0, z, w, thick, 220)
            for k in range(1, 6):
                p.line([[0, z + k * thick / 6], [w, z + k * thick / 6]], 195, 0.0004)
            p.rect(0, z, w, 0.0015, cover)
            p.rect(0, z + thick - 0.0015, w, 0.0015, cover)
        z += thick
    return img


def _pattern_box(rng: np.random.Generator, shape: tuple[int, int], density: float, w: float, h: float) -> NDArray[np.uint8]:
    img = np.full(shape, rng.uniform(170, 230), np.uint8)
    p = _Painter(img, density)
    step = rng.uniform(0.015, 0.025)
    val = rng.uniform(40, 110)
    for i, y in enumerate(np.arange(0, h, step)):
        for x in np.arange((i % 2) * step / 2, w, step):
            if rng.random() < 0.5:
                p.circle(x, y, step * 0.3, val)
            else:
                p.poly([[x - step * 0.3, y + step * 0.3], [x, y - step * 0.3], [x + step * 0.3, y + step * 0.3]], val)
    p.rect(w * 0.1, h * 0.35, w * 0.8, min(0.03, h * 0.3), 240)
    _text(p, rng, w * 0.14, h * 0.35 + 0.004, w * 0.7, 1, min(0.012, h * 0.15), 30)
    return img


def _wall_texture(rng: np.random.Generator, shape: tuple[int, int], density: float, w: float, h: float) -> NDArray[np.uint8]:
    """The wall from the floor up (local b = height above the floor); things hang above the desk."""
    img = np.clip(172 + 4 * _smooth_noise(rng, shape, (shape[1] // 4, shape[0] // 4))
                  + 8 * _smooth_noise(rng, shape, (4, 3)), 0, 255).astype(np.uint8)
    p = _Painter(img, density)
    p._T[0] = np.array([[1.0, 0, 0], [0, 1.0, -FLOOR_Z_M], [0, 0, 1.0]])  # origin at desk height
    px = rng.uniform(0.5, 0.9)
    p.rect(px - 0.01, 0.19, 0.37, 0.52, 40)
    _picture(p, rng, px, 0.2, 0.35, 0.4)
    _text(p, rng, px + 0.02, 0.62, 0.3, 2, 0.02, 220, 0.035)
    _calendar(p, rng, rng.uniform(1.3, 1.5), 0.45, 0.0, 0.3, 0.36)
    sx = rng.uniform(0.2, 0.4)
    p.rect(sx, 0.08, 0.08, 0.08, 235)
    p.rect(sx + 0.02, 0.11, 0.008, 0.02, 50)
    p.rect(sx + 0.05, 0.11, 0.008, 0.02, 50)
    return img


def _floor_texture(rng: np.random.Generator, shape: tuple[int, int], density: float) -> NDArray[np.uint8]:
    h, w = shape
    tile = 0.4
    ii, jj = np.mgrid[0:h, 0:w]
    checker = ((ii / density // tile + jj / density // tile) % 2).astype(np.float32)
    img = 95 + 20 * checker + 6 * _smooth_noise(rng, shape, (w // 3, h // 3))
    return np.clip(img, 0, 255).astype(np.uint8)


def _shade(normal: Array) -> float:
    """Lambertian shading by a light from above-front-left plus ambient light."""
    light = np.array([-0.3, -0.5, 1.0])
    light = light / np.linalg.norm(light)
    return float(0.45 + 0.55 * max(0.0, float(normal @ light)))


def _place_boxes(rng: np.random.Generator) -> list[Box]:
    kinds = [('cardboard', (0.16, 0.21), (0.12, 0.16), (0.15, 0.23), 0.14),
             ('books', (0.22, 0.26), (0.16, 0.19), (0.05, 0.09), -0.08),
             ('small', (0.09, 0.13), (0.07, 0.10), (0.06, 0.14), -0.1)]
    boxes: list[Box] = []
    for kind, lx, ly, hz, y_min in kinds:
        size = (rng.uniform(*lx), rng.uniform(*ly), rng.uniform(*hz))
        r = math.hypot(size[0], size[1]) / 2
        for _ in range(200):
            c = np.array([rng.uniform(-0.6 + r + 0.02, 0.6 - r - 0.02), rng.uniform(y_min, 0.4 - r - 0.02)])
            if all(np.linalg.norm(c - b.centre) > r + math.hypot(b.size[0], b.size[1]) / 2 + 0.03 for b in boxes):
                break
        boxes.append(Box(kind, c, float(rng.uniform(-0.6, 0.6)), size))
    return boxes


def _box_faces(box: Box, k: int) -> list[tuple[Face, str]]:
    c, s = math.cos(box.yaw), math.sin(box.yaw)
    ex, ey, ez = np.array([c, s, 0.0]), np.array([-s, c, 0.0]), np.array([0.0, 0.0, 1.0])
    lx, ly, h = box.size[0] / 2, box.size[1] / 2, box.size[2]
    C = np.array([box.centre[0], box.centre[1], 0.0])
    d = DESK_DENSITY
    return [
        (Face(f'box{k}_top', C - lx * ex - ly * ey + h * ez, ex, ey, (2 * lx, 2 * ly), d), 'top'),
        (Face(f'box{k}_px', C + lx * ex - ly * ey, ey, ez, (2 * ly, h), d), 'side0'),
        (Face(f'box{k}_nx', C - lx * ex + ly * ey, -ey, ez, (2 * ly, h), d), 'side1'),
        (Face(f'box{k}_py', C + lx * ex + ly * ey, -ex, ez, (2 * lx, h), d), 'side2'),
        (Face(f'box{k}_ny', C - lx * ex - ly * ey, ex, ez, (2 * lx, h), d), 'side3'),
    ]


def _box_texture(rng: np.random.Generator, box: Box, face: Face, role: str) -> NDArray[np.uint8]:
    shape = face.texture_shape()
    w, h = face.size
    if box.kind == 'cardboard':
        return _cardboard(rng, shape, face.density, w, h, role == 'top')
    if box.kind == 'books':
        if role == 'top':
            return _book_top(rng, shape, face.density, w, h)
        n = max(2, int(round(box.size[2] / 0.025)))
        cover_rng = np.random.default_rng(int(box.size[2] * 1e6))  # same bands on all four sides
        bands = [(box.size[2] / n, float(cover_rng.uniform(30, 200))) for _ in range(n)]
        return _book_side(rng, shape, face.density, w, h, bands, spine=role == 'side0')
    return _pattern_box(rng, shape, face.density, w, h)


def _pack(shapes: list[tuple[int, int]], width: int) -> tuple[list[tuple[int, int]], int]:
    """Shelf packing of (h, w) rectangles with a gutter; returns top-left (x, y) and the height."""
    g = ATLAS_GUTTER
    order = sorted(range(len(shapes)), key=lambda i: -shapes[i][0])
    pos: list[tuple[int, int]] = [(0, 0)] * len(shapes)
    x, y, shelf = g, g, 0
    for i in order:
        h, w = shapes[i]
        if x + w + g > width:
            x, y, shelf = g, y + shelf + 2 * g, 0
        pos[i] = (x, y)
        x += w + 2 * g
        shelf = max(shelf, h)
    return pos, y + shelf + g


@functools.lru_cache(maxsize=2)
def desk_scene(seed: int) -> DeskScene:
    """The seed's desk, boxes, wall and floor with their texture atlas (cached; ~1 s to make)."""
    rng = rng_stream(seed, 'handheld-desk-scene')
    W, H = DESK_SIZE_M
    faces: list[Face] = [
        Face('desk', np.array([-W / 2, -H / 2, 0.0]), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), (W, H), DESK_DENSITY),
        Face('desk_front', np.array([-W / 2, -H / 2, -DESK_THICKNESS_M]), np.array([1.0, 0, 0]), np.array([0, 0, 1.0]),
             (W, DESK_THICKNESS_M), 1000.0),
        Face('wall', np.array([-1.0, WALL_Y_M, FLOOR_Z_M]), np.array([1.0, 0, 0]), np.array([0, 0, 1.0]),
             (2.0, 1.7), 800.0),
        Face('floor', np.array([-2.0, -2.5, FLOOR_Z_M]), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), (4.0, 2.92), 150.0),
    ]
    textures: list[NDArray[np.uint8]] = [
        _desk_texture(rng),
        np.clip(70 + 10 * _smooth_noise(rng, faces[1].texture_shape(), (60, 2)), 0, 255).astype(np.uint8),
    ]
    wall_shape = faces[2].texture_shape()
    textures.append(_wall_texture(rng, wall_shape, faces[2].density, *faces[2].size))
    textures.append(_floor_texture(rng, faces[3].texture_shape(), faces[3].density))
    boxes = _place_boxes(rng)
    for k, box in enumerate(boxes):
        for face, role in _box_faces(box, k):
            faces.append(face)
            textures.append(_box_texture(rng, box, face, role))
    textures = [np.clip(t.astype(np.float32) * _shade(f.normal), 0, 255).astype(np.uint8)
                for f, t in zip(faces, textures)]
    width = 4096
    pos, height = _pack([t.shape for t in textures], width)
    atlas = np.zeros((height, width), np.uint8)
    g = ATLAS_GUTTER
    for (x, y), t in zip(pos, textures):
        atlas[y - g:y + t.shape[0] + g, x - g:x + t.shape[1] + g] = cv2.copyMakeBorder(t, g, g, g, g, cv2.BORDER_REPLICATE)
    faces = [replace(f, atlas_xy=xy) for f, xy in zip(faces, pos)]
    return DeskScene(int(seed), tuple(faces), tuple(boxes), _pyramid(atlas))


# --------------------------------------------------------------------------------------------
# Rendering


@dataclass
class _RayGrid:
    """Camera-frame ray components of a camera: x/z per column, y/z per row, |ray| per pixel."""

    xc: NDArray[np.float32]
    yc: Array
    norm: NDArray[np.float32]
    vignette: NDArray[np.float32]

    @staticmethod
    @functools.lru_cache(maxsize=4)
    def of(cam: DeskCamera) -> '_RayGrid':
        xc = ((np.arange(cam.width) - cam.cx) / cam.fx).astype(np.float32)
        yc = (np.arange(cam.height) - cam.cy) / cam.fy
        norm = np.sqrt(1.0 + xc[None, :].astype(np.float64) ** 2 + yc[:, None] ** 2).astype(np.float32)
        r2 = (xc[None, :] ** 2 + yc[:, None].astype(np.float32) ** 2)
        vig = (1.0 - VIGNETTING * r2 / r2.max()).astype(np.float32)
        return _RayGrid(xc, yc, norm, vig)


def _face_window(face: Face, cam: DeskCamera, R: Array, p: Array) -> tuple[int, int, int, int] | None:
    """Image rows/cols [r0, r1) x [c0, c1) that may see the face, from its corners projected with
    the poses of the first, middle and last rows; None when it cannot be seen."""
    idx = [0, len(p) // 2, len(p) - 1]
    n = face.normal
    if all(float(n @ (p[i] - face.origin)) <= 1e-9 for i in idx):
        return None  # the camera is behind the face's plane
    uvs = []
    for i in idx:
        Xc = (face.corners - p[i]) @ R[i]
        if np.any(Xc[:, 2] < 0.02):
            return 0, cam.height, 0, cam.width
        uvs.append(Xc[:, :2] / Xc[:, 2:3] * [cam.fx, cam.fy] + [cam.cx, cam.cy])
    uv = np.concatenate(uvs)
    c0, r0 = np.floor(uv.min(0)).astype(int) - 4
    c1, r1 = np.ceil(uv.max(0)).astype(int) + 5
    r0, r1, c0, c1 = max(r0, 0), min(r1, cam.height), max(c0, 0), min(c1, cam.width)
    if r1 <= r0 or c1 <= c0:
        return None
    return int(r0), int(r1), int(c0), int(c1)


def render_radiance(scene: DeskScene, cam: DeskCamera, R_rows: Array, p_rows: Array) -> NDArray[np.float32]:
    """One instantaneous render (float32 grey levels): row v seen from pose (R_rows[v], p_rows[v])."""
    H, W = cam.height, cam.width
    g = _RayGrid.of(cam)
    xc = g.xc[None, :]
    best_t = np.full((H, W), np.inf, np.float32)
    best_x = np.full((H, W), -100.0, np.float32)
    best_y = np.full((H, W), -100.0, np.float32)
    best_k = np.zeros((H, W), np.float32)  # density / sqrt(|n . d|): for the mip level
    for face in scene.faces:
        win = _face_window(face, cam, R_rows, p_rows)
        if win is None:
            continue
        r0, r1, c0, c1 = win
        R, p, yc = R_rows[r0:r1], p_rows[r0:r1], g.yc[r0:r1]
        xw = xc[:, c0:c1]

        def along(vec: Array) -> NDArray[np.float32]:
            vr = np.einsum('hij,i->hj', R, vec)  # vec . (R_h [x, y, 1]) = vr0 x + vr1 y + vr2
            return (vr[:, 0, None].astype(np.float32) * xw + (vr[:, 1] * yc + vr[:, 2])[:, None].astype(np.float32))

        n = face.normal
        dn = along(n)
        num = ((face.origin - p) @ n).astype(np.float32)[:, None]
        with np.errstate(divide='ignore', invalid='ignore'):
            t = num / dn
        a = ((p - face.origin) @ face.e_u).astype(np.float32)[:, None] + t * along(face.e_u)
        b = ((p - face.origin) @ face.e_v).astype(np.float32)[:, None] + t * along(face.e_v)
        bt = best_t[r0:r1, c0:c1]
        hit = (dn < -1e-6) & (t > 0) & (t < bt) & (a >= 0) & (a <= face.size[0]) & (b >= 0) & (b <= face.size[1])
        if not hit.any():
            continue
        np.copyto(bt, t, where=hit)
        np.copyto(best_x[r0:r1, c0:c1], face.atlas_xy[0] - 0.5 + a * np.float32(face.density), where=hit)
        np.copyto(best_y[r0:r1, c0:c1], face.atlas_xy[1] - 0.5 + b * np.float32(face.density), where=hit)
        np.copyto(best_k[r0:r1, c0:c1], np.float32(face.density) / np.sqrt(np.abs(dn)), where=hit)
    hit_any = np.isfinite(best_t)
    # footprint of a pixel in texels: distance / f / cos(incidence)^0.5 (area-like), as mip level
    with np.errstate(invalid='ignore', over='ignore'):
        fp = np.where(hit_any, best_t * g.norm * np.sqrt(g.norm) * best_k / np.float32(cam.fx), 1.0)
    lam = np.clip(np.log2(np.maximum(fp, 1.0)), 0, MIP_LEVELS - 1).astype(np.float32)
    out = np.zeros((H, W), np.float32)
    lo, hi = float(lam.min()), float(lam.max())
    for k in range(MIP_LEVELS):
        if k < math.floor(lo) or k > math.ceil(hi):
            continue
        s = np.float32(0.5 ** k)  # cv2.pyrDown centres texel i of level k on texel 2^k i of level 0
        mx = best_x * s
        my = best_y * s
        img = cv2.remap(scene.atlas[k], mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        wk = np.maximum(0.0, 1.0 - np.abs(lam - k))
        out += wk * img.astype(np.float32)
    out[~hit_any] = BACKGROUND
    return out


def subframe_count(cam: DeskCamera, pose_fn: PoseFn, t_s: float) -> int:
    """How many sub-exposure renders the motion during the exposure needs (1 .. MAX_SUBFRAMES)."""
    if cam.exposure_s <= 0:
        return 1
    R, p = pose_fn(np.array([t_s - cam.exposure_s / 2, t_s + cam.exposure_s / 2]))
    rel = R[0].T @ R[1]
    ang = float(trace_angle(rel))
    px = ang * cam.fx + float(np.linalg.norm(p[1] - p[0])) * cam.fx / 0.3
    return int(min(MAX_SUBFRAMES, max(1, math.ceil(px / BLUR_STEP_PX))))


def render_image(scene: DeskScene, cam: DeskCamera, pose_fn: PoseFn, t_s: float,
                 noise_rng: np.random.Generator | None = None, subframes: int | None = None,
                 optical_blur: bool = True) -> tuple[NDArray[np.uint8], int]:
    """The mono8 image whose centre row is captured at t_s, and the number of sub-exposures.

    ``pose_fn(times) -> (R_w_c (N, 3, 3), p_w_c (N, 3))`` gives the camera poses; each row is
    rendered at its own capture time (rolling shutter), averaged over the exposure (motion blur).
    ``noise_rng`` None renders without sensor noise."""
    n_sub = subframe_count(cam, pose_fn, t_s) if subframes is None else int(subframes)
    rows = cam.row_time_offset_s(np.arange(cam.height))
    acc = np.zeros((cam.height, cam.width), np.float32)
    for j in range(n_sub):
        dt = cam.exposure_s * ((j + 0.5) / n_sub - 0.5)
        R, p = pose_fn(t_s + rows + dt)
        acc += render_radiance(scene, cam, R, p)
    img = acc / np.float32(n_sub)
    if optical_blur and OPTICAL_BLUR_SIGMA_PX > 0:
        img = cv2.GaussianBlur(img, (0, 0), OPTICAL_BLUR_SIGMA_PX)
    img *= _RayGrid.of(cam).vignette
    if noise_rng is not None:
        img += noise_rng.normal(0.0, PIXEL_NOISE, img.shape).astype(np.float32)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8), n_sub


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
    from the closed-form motion, with phone-grade white noise and constant biases."""
    motion = desk_motion(int(seed), bool(pure_rotation_start))
    t = np.asarray(t_s, dtype=float)
    h = 1e-4
    Ra, _ = motion.pose(t - h)
    Rb, _ = motion.pose(t + h)
    R, p = motion.pose(t)
    rel = np.einsum('nji,njk->nik', Ra, Rb)  # R_a^T R_b ~ exp([w_c] 2h)
    w_c = np.stack([rel[:, 2, 1] - rel[:, 1, 2], rel[:, 0, 2] - rel[:, 2, 0], rel[:, 1, 0] - rel[:, 0, 1]], -1) / (4 * h)
    H = 1e-3
    _, pa = motion.pose(t - H)
    _, pb = motion.pose(t + H)
    acc_w = (pb - 2 * p + pa) / (H * H) + np.array([0.0, 0.0, GRAVITY_M_S2])
    f_c = np.einsum('nji,nj->ni', R, acc_w)
    rng = rng_stream(int(seed), 'handheld-desk-imu')
    bg, ba = rng.normal(0, 0.005, 3), rng.normal(0, 0.05, 3)
    gyro = w_c @ R_IMU_CAM.T + bg + rng.normal(0, GYRO_NOISE_RAD_S, (len(t), 3))
    accel = f_c @ R_IMU_CAM.T + ba + rng.normal(0, ACCEL_NOISE_M_S2, (len(t), 3))
    return gyro, accel


# --------------------------------------------------------------------------------------------
# The bag


def write_handheld_desk_bag(bag: Any, seed: int, duration_s: float, image_format: str = 'raw',
                            progress: Callable[[float], None] | None = None, *,
                            width: int = IMAGE_SIZE[0], height: int = IMAGE_SIZE[1],
                            pure_rotation_start: bool = False, imu: bool = True) -> None:
    """Write all messages of the scenario into an open BagWriter, in log-time order."""
    from ..io.bags import msg_class
    from .bagmaker import START_NS, _Msgs

    if image_format not in ('raw', 'compressed'):
        raise ValueError(f'unknown image format {image_format!r}')
    m = _Msgs()
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
