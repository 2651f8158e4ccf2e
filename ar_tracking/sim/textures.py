"""Texture primitives shared by both scenes: value and fractal noise, colours, a metric painter.

The street scene (:mod:`.street_textures`) paints facades in sRGB pixels with uniform value noise
(:func:`value_noise`, :func:`fbm`, :func:`periodic_noise`); the desk scene
(:mod:`.desk_textures`) paints grey-level face textures in metres with :class:`Painter` and
Gaussian :func:`smooth_noise`. Each function draws from the generator it is given, in a fixed
order, so textures are reproducible from the scene's random stream.
"""
from __future__ import annotations

import math
from contextlib import contextmanager
from typing import Any, Iterator

import cv2
import numpy as np
from numpy.typing import NDArray

from .model import GAMMA, Array, Image

def srgb_to_linear(rgb: Array) -> Array:
    return np.power(np.clip(np.asarray(rgb, dtype=np.float32), 0.0, 1.0), GAMMA)


def value_noise(rng: np.random.Generator, shape: tuple[int, int], cell_px: float,
           wrap_x: bool = False) -> Image:
    """Smooth value noise in [-1, 1] with features about ``cell_px`` pixels large."""
    h, w = shape
    gh = max(2, int(math.ceil(h / cell_px)) + 2)
    gw = max(2, int(math.ceil(w / cell_px)) + (0 if wrap_x else 2))
    grid = rng.uniform(-1.0, 1.0, size=(gh, gw)).astype(np.float32)
    if wrap_x:
        # Three copies side by side, resized, the middle one cut out: periodic in x.
        big = cv2.resize(np.hstack([grid, grid, grid]), (3 * w, int(round(gh * cell_px))),
                         interpolation=cv2.INTER_CUBIC)
        return big[:h, w:2 * w]
    big = cv2.resize(grid, (int(round(gw * cell_px)), int(round(gh * cell_px))),
                     interpolation=cv2.INTER_CUBIC)
    return big[:h, :w]


def fbm(rng: np.random.Generator, shape: tuple[int, int], cell_px: float, octaves: int,
         gain: float = 0.5, wrap_x: bool = False) -> Image:
    """Fractal noise (sum of octaves), roughly in [-1, 1]."""
    out = np.zeros(shape, np.float32)
    amp, total = 1.0, 0.0
    for k in range(octaves):
        out += amp * value_noise(rng, shape, max(1.5, cell_px / 2 ** k), wrap_x)
        total += amp
        amp *= gain
    return out / total


def periodic_noise(rng: np.random.Generator, n: int, cells: int, octaves: int) -> Image:
    """Noise that tiles in both directions (for textures looked up with wrap-around)."""
    out = np.zeros((n, n), np.float32)
    amp, total = 1.0, 0.0
    for k in range(octaves):
        c = cells * 2 ** k
        grid = rng.uniform(-1, 1, (c, c)).astype(np.float32)
        tiled = np.tile(grid, (3, 3))
        big = cv2.resize(tiled, (3 * n, 3 * n), interpolation=cv2.INTER_CUBIC)
        out += amp * big[n:2 * n, n:2 * n]
        total += amp
        amp *= 0.55
    return out / total


def smoothstep(e0: float, e1: float, x: Image) -> Image:
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def pick_colour(rng: np.random.Generator, palette: list[tuple[int, int, int]], jitter: int = 12
           ) -> tuple[int, int, int]:
    base = np.array(palette[int(rng.integers(len(palette)))], dtype=float)
    c = np.clip(base + rng.integers(-jitter, jitter + 1, 3), 0, 255)
    return int(c[0]), int(c[1]), int(c[2])

class Painter:
    """Draws shapes given in metres (local 2-D frames) into a uint8 face texture.

    ``density`` texels per metre; texel (row i, col j) covers ((j + 0.5) / density, (i + 0.5) /
    density). ``origin_m`` shifts the base frame: a point (x, y) is drawn at texture coordinates
    (x + origin_m[0], y + origin_m[1]). Shapes are antialiased with 4 bits of sub-texel precision."""

    def __init__(self, img: NDArray[np.uint8], density: float,
                 origin_m: tuple[float, float] = (0.0, 0.0)) -> None:
        self.img = img
        self.d = density
        self._T = [np.array([[1.0, 0.0, origin_m[0]], [0.0, 1.0, origin_m[1]], [0.0, 0.0, 1.0]])]

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


def smooth_noise(rng: np.random.Generator, shape: tuple[int, int], cells: tuple[int, int]) -> Array:
    """Smooth noise of unit-ish amplitude: random values on a coarse grid, cubic upsampling."""
    small = rng.normal(0, 1, (max(2, cells[1]), max(2, cells[0]))).astype(np.float32)
    return cv2.resize(small, (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC)
