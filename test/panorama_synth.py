"""Synthetic frames for the panorama tests: a textured cylinder around the camera (pure
rotation, exact truth), a uniform wall, and a two-plane scene for a translating camera."""
from __future__ import annotations

import math

import cv2
import numpy as np

from ar_tracking.core.panorama.cylinder import CylinderGeometry, camera_rays

W, H = 320, 240
HFOV = math.radians(60.0)
F = W / 2 / math.tan(HFOV / 2)
K = np.array([[F, 0, (W - 1) / 2], [0, F, (H - 1) / 2], [0, 0, 1.0]])


def texture(seed: int, shape: tuple[int, int] = (1024, 4096)) -> np.ndarray:
    """Multi-scale noise with blocks: corners for FAST, structure for NCC (float32 0..255)."""
    rng = np.random.default_rng(seed)
    h, w = shape
    acc = np.zeros(shape, np.float32)
    for cell, amp in ((64, 60.0), (16, 40.0), (4, 25.0)):
        small = rng.standard_normal((h // cell + 1, w // cell + 1)).astype(np.float32)
        acc += amp * cv2.resize(small, (w + cell, h + cell), interpolation=cv2.INTER_CUBIC)[:h, :w]
    for _ in range(400):
        x, y = int(rng.integers(0, w - 40)), int(rng.integers(0, h - 40))
        acc[y:y + int(rng.integers(8, 40)), x:x + int(rng.integers(8, 40))] += float(rng.uniform(-60, 60))
    acc = acc - acc.mean() + 128
    return np.clip(acc, 5, 250).astype(np.float32)


def rot(axis: str, deg: float) -> np.ndarray:
    a = math.radians(deg)
    c, s = math.cos(a), math.sin(a)
    return {'x': np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
            'y': np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
            'z': np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])}[axis]


class CylinderWorld:
    """Renders R_world_cam views of a texture wrapped on a cylinder (its own 2x-resolution map)."""

    def __init__(self, seed: int = 1) -> None:
        self.tex = texture(seed)
        self.geo = CylinderGeometry(self.tex.shape[1], self.tex.shape[0])
        yy, xx = np.mgrid[0:H, 0:W]
        self.rays = camera_rays(K, xx.astype(float), yy.astype(float))

    def render(self, R_world_cam: np.ndarray, gain: float = 1.0, offset: float = 0.0,
               noise: float = 1.0, rng: np.random.Generator | None = None) -> np.ndarray:
        d = self.rays @ R_world_cam.T
        u, v = self.geo.project(d)
        img = cv2.remap(self.tex, u.astype(np.float32), v.astype(np.float32), cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_WRAP)
        img = img * gain + offset
        if noise > 0:
            img = img + (rng or np.random.default_rng(0)).normal(0, noise, img.shape)
        return np.clip(img + 0.5, 0, 255).astype(np.uint8)


#: Frame interval of the synthetic sequences, ns (30 Hz).
DT = 33_333_333


def render_all(world: CylinderWorld, Rs: list[np.ndarray], gains=None, offsets=None) -> list[np.ndarray]:
    """The views Rs of ``world``: frame k with ``gains[k]``, ``offsets[k]`` and noise seeded by k."""
    return [world.render(R, gain=1.0 if gains is None else float(gains[k]),
                         offset=0.0 if offsets is None else float(offsets[k]), rng=np.random.default_rng(k))
            for k, R in enumerate(Rs)]


def run_frames(mapper, frames: list[np.ndarray]) -> list:
    """Feed frames through a PanoramaMapper at 30 Hz, background step after each; its FrameResults."""
    out = []
    for k, img in enumerate(frames):
        out.append(mapper.process(img, K, (k + 1) * DT))
        mapper.background()
    return out


def run(mapper, world: CylinderWorld, Rs: list[np.ndarray], gains=None, offsets=None) -> list:
    """Feed the views Rs of ``world`` (frame k with ``gains[k]``, ``offsets[k]`` and noise seeded
    by k) through a PanoramaMapper at 30 Hz, background step after each; its FrameResults."""
    return run_frames(mapper, render_all(world, Rs, gains, offsets))


def sweep(n: int, step_deg: float, seed: int = 0) -> list[np.ndarray]:
    """R_world_cam of a pan about the vertical with a gentle pitch / roll wobble."""
    rng = np.random.default_rng(seed)
    ph = rng.uniform(0, 2 * math.pi, 2)
    return [rot('y', step_deg * k) @ rot('x', 6 * math.sin(0.05 * k + ph[0]))
            @ rot('z', 2 * math.sin(0.07 * k + ph[1])) for k in range(n)]


def two_plane_frame(tx: float, seed: int = 3) -> np.ndarray:
    """A camera at (tx, 0, 0) looking along +z at a near plane (z = 1 m, left half of the world)
    in front of a far plane (z = 6 m): translation makes parallax no rotation explains."""
    tex = texture(seed, (512, 2048))
    yy, xx = np.mgrid[0:H, 0:W]
    r = camera_rays(K, xx.astype(float), yy.astype(float))
    out = np.zeros((H, W), np.float32)
    t_near = 1.0 / r[..., 2]
    x_near = tx + t_near * r[..., 0]
    near = x_near < 0.0
    t_far = 6.0 / r[..., 2]
    xs = np.where(near, x_near, tx + t_far * r[..., 0])
    ys = np.where(near, t_near, t_far) * r[..., 1]
    scale = 300.0  # texture pixels per metre
    u = (xs * scale + 1024 + np.where(near, 0, 700)).astype(np.float32)
    v = (ys * scale + 256).astype(np.float32)
    out = cv2.remap(tex, u, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return np.clip(out + 0.5, 0, 255).astype(np.uint8)


def angle_deg(A: np.ndarray, B: np.ndarray) -> float:
    return math.degrees(math.acos(np.clip((np.trace(A.T @ B) - 1) / 2, -1, 1)))
