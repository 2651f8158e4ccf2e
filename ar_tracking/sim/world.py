"""A procedural 360-degree outdoor spot (a town square) for the simulator, with lighting.

The world is what a person standing at one spot sees all around: a ring of buildings with windows,
doors, shop signs and awnings, trees and lamp posts in front of them, a distant skyline, paved
ground and a cloudy sky. Everything except the sky is a set of textured planes in the ENU frame
(x east, y north, z up; the origin is the authoring spot at eye height, the ground is the plane
``z = -EYE_HEIGHT_M``), so that a panorama can be rendered from any nearby standing point with true
parallax, and so that shadows can be cast exactly (parallel projection between planes is affine).

Three steps, each cheap enough for a one-minute bag to be made in seconds:

* :func:`build_world` (seed only): geometry, albedo textures and the annotation anchors, so the
  authoring and the browsing session see the same spot.
* :func:`make_lighting` (seed and session): sun azimuth/elevation, sun and sky colours. The
  authoring session is late afternoon (low sun, long shadows, flare near the horizon), browsing is
  around midday, as in the experiments of Langlotz et al. 2011 (section 6.1).
* :func:`render_panorama`: an equirectangular radiance map (4096 x 2048 for 360 x 180 degrees)
  from a standing point under a lighting; :class:`FrameRenderer` turns it into 8-bit camera frames
  (pinhole, auto-exposure gain, white balance, glare, motion blur, noise, clipping).

Equirectangular convention: column ``u`` covers compass azimuth ``az = 2*pi*u/W`` (clockwise from
north, so turning right moves right in the map), row ``v`` covers elevation ``el = pi/2 - pi*v/H``.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Callable

import cv2
import numpy as np
from numpy.typing import NDArray

logger = logging.getLogger(__name__)

Array = NDArray[np.float64]
Image = NDArray[np.float32]

#: Height of the eyes (and the camera) above the ground, metres.
EYE_HEIGHT_M = 1.5
#: Size of the equirectangular panorama (360 x 180 degrees), pixels.
PANO_WIDTH = 4096
PANO_HEIGHT = 2048
#: Elevation band actually rendered (the camera never looks further up or down), radians.
PANO_MAX_ABS_EL = math.radians(72.0)
#: Texture resolution of the near objects, pixels per metre.
NEAR_PX_PER_M = 16.0
FAR_PX_PER_M = 4.0
#: Display gamma: textures are held gamma-encoded so that exposure is a plain multiplication.
GAMMA = 2.2

UP = np.array([0.0, 0.0, 1.0])

SIGN_WORDS = (
    'CAFE', 'BAKERY', 'HOTEL', 'PHARMACY', 'BANK', 'BOOKS', 'PIZZA', 'BAR', 'SHOES', 'MUSEUM',
    'POST', 'FLORIST', 'OPTIK', 'GELATO', 'TABAK', 'BIKES', 'DELI', 'KEBAB', 'TICKETS', 'SUSHI',
)


# --------------------------------------------------------------------------------------------
# Data


@dataclass
class Plane:
    """A textured vertical rectangle of the world (facade, tree, lamp post).

    The plane's foot point is ``distance_m`` from the origin at compass azimuth ``foot_az_rad``;
    its normal points back toward the origin. Texture column 0 is at ``s_min_m`` along the
    tangent (which points toward increasing azimuth, i.e. to the viewer's right), row 0 at the
    height ``z_max_m``. ``albedo`` is linear RGBA (alpha 0 where the plane is empty).
    """

    kind: str  # 'building', 'far', 'tree', 'pole'
    index: int  # building number used in labels (1-based), 0 for other objects
    foot_az_rad: float
    distance_m: float
    s_min_m: float
    z_max_m: float
    px_per_m: float
    albedo: Image  # (h, w, 4) float32, linear RGB + alpha
    windows: Array = field(default_factory=lambda: np.zeros((0, 5)))  # x0 y0 x1 y1 depth_m (px)
    awnings: Array = field(default_factory=lambda: np.zeros((0, 5)))  # x0 y0 x1 y1 depth_m (px)
    normals: Image | None = None  # (h, w, 3) local (tangent, up, out) normals for round objects
    features: list[tuple[str, float, float]] = field(default_factory=list)  # kind, col, row

    @property
    def tangent(self) -> Array:
        """Horizontal unit vector along the plane, toward increasing azimuth (viewer's right)."""
        return np.array([math.cos(self.foot_az_rad), -math.sin(self.foot_az_rad), 0.0])

    @property
    def normal(self) -> Array:
        """Horizontal unit normal, pointing back toward the origin."""
        return -np.array([math.sin(self.foot_az_rad), math.cos(self.foot_az_rad), 0.0])

    @property
    def foot(self) -> Array:
        return -self.distance_m * self.normal

    @property
    def shape(self) -> tuple[int, int]:
        return self.albedo.shape[0], self.albedo.shape[1]

    def world_point(self, col: Array, row: Array) -> Array:
        """World points (..., 3) of continuous texture coordinates (pixel i spans [i, i+1))."""
        s = self.s_min_m + np.asarray(col, dtype=float) / self.px_per_m
        z = self.z_max_m - np.asarray(row, dtype=float) / self.px_per_m
        return self.foot + s[..., None] * self.tangent + z[..., None] * UP

    def texture_coords(self, points: Array) -> tuple[Array, Array]:
        """Texture (col, row) of world points lying on the plane (continuous, pixel edges at 0)."""
        rel = np.asarray(points, dtype=float) - self.foot
        s = rel @ self.tangent
        return (s - self.s_min_m) * self.px_per_m, (self.z_max_m - rel[..., 2]) * self.px_per_m


@dataclass(frozen=True)
class Anchor:
    """A distinctive spot drawn into the world, the ground truth of an annotation."""

    label: str
    position_enu: Array  # metres, relative to the authoring spot (origin)

    @property
    def direction(self) -> Array:
        return self.position_enu / np.linalg.norm(self.position_enu)


@dataclass
class World:
    """Everything of the spot that does not depend on the session (derived from the seed only)."""

    seed: int
    planes: list[Plane]  # sorted far to near (painter's order from the origin)
    anchors: list[Anchor]
    ground_tile_m: float
    ground_grain: Image  # periodic fine texture of the paving, (n, n) float32 around 1
    ground_stains: Image  # periodic large-scale tint, (n, n) float32 around 1
    ground_base_rgb: Array
    crossings: Array  # (k, 4) azimuth, r0, r1, half-width (m): zebra crossings on the ground
    manholes: Array  # (k, 3) x, y, radius (m)
    clouds: Image  # (PANO_HEIGHT//2, PANO_WIDTH) float32 cloud density 0..1 of the upper half
    cloud_detail: Image  # same shape, detail around 1


@dataclass(frozen=True)
class Lighting:
    """Sun and sky of one session (from seed and session)."""

    sun_az_rad: float  # compass azimuth, clockwise from north
    sun_el_rad: float
    sun_rgb: Array  # irradiance of the sun on a surface facing it (linear, relative)
    ambient_rgb: Array  # sky light on any surface
    sky_zenith_rgb: Array
    sky_horizon_rgb: Array

    @property
    def sun_dir(self) -> Array:
        """Unit vector toward the sun in ENU."""
        ce = math.cos(self.sun_el_rad)
        return np.array([
            ce * math.sin(self.sun_az_rad), ce * math.cos(self.sun_az_rad),
            math.sin(self.sun_el_rad),
        ])


@dataclass
class Panorama:
    """An equirectangular rendering from one standing point.

    ``encoded`` holds gamma-encoded radiance (``L ** (1/GAMMA)``, 1.0 = a white wall in full sun
    at the reference exposure; the sun and its halo go far above 1), ``depth_m`` the distance of
    each pixel's surface (inf for sky).
    """

    encoded: Image  # (H, W, 3) float32
    depth_m: Image  # (H, W) float32
    viewpoint_enu: Array
    sun_visible: bool
    mean_radiance: float  # mean linear radiance in the band the camera sees


# --------------------------------------------------------------------------------------------
# Small helpers


def rng_stream(seed: int, *names: str | int) -> np.random.Generator:
    """An independent, reproducible random stream for one purpose (no salted hashing)."""
    import zlib

    keys = [int(seed) & 0xFFFFFFFF]
    for n in names:
        keys.append(zlib.crc32(n.encode()) if isinstance(n, str) else int(n) & 0xFFFFFFFF)
    return np.random.default_rng(np.random.SeedSequence(keys))


def _srgb_to_linear(rgb: Array) -> Array:
    return np.power(np.clip(np.asarray(rgb, dtype=np.float32), 0.0, 1.0), GAMMA)


def _noise(rng: np.random.Generator, shape: tuple[int, int], cell_px: float,
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


def _fbm(rng: np.random.Generator, shape: tuple[int, int], cell_px: float, octaves: int,
         gain: float = 0.5, wrap_x: bool = False) -> Image:
    """Fractal noise (sum of octaves), roughly in [-1, 1]."""
    out = np.zeros(shape, np.float32)
    amp, total = 1.0, 0.0
    for k in range(octaves):
        out += amp * _noise(rng, shape, max(1.5, cell_px / 2 ** k), wrap_x)
        total += amp
        amp *= gain
    return out / total


def _periodic_noise(rng: np.random.Generator, n: int, cells: int, octaves: int) -> Image:
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


def _smoothstep(e0: float, e1: float, x: Image) -> Image:
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _color(rng: np.random.Generator, palette: list[tuple[int, int, int]], jitter: int = 12
           ) -> tuple[int, int, int]:
    base = np.array(palette[int(rng.integers(len(palette)))], dtype=float)
    c = np.clip(base + rng.integers(-jitter, jitter + 1, 3), 0, 255)
    return int(c[0]), int(c[1]), int(c[2])


def pano_directions(rows: NDArray[np.int64] | Array, cols: NDArray[np.int64] | Array) -> Array:
    """Unit ENU directions (len(rows), len(cols), 3) of panorama pixel centres."""
    az = (np.asarray(cols, dtype=float) + 0.5) * (2 * math.pi / PANO_WIDTH)
    el = math.pi / 2 - (np.asarray(rows, dtype=float) + 0.5) * (math.pi / PANO_HEIGHT)
    ce, se = np.cos(el)[:, None], np.sin(el)[:, None]
    return np.stack([ce * np.sin(az)[None, :], ce * np.cos(az)[None, :],
                     np.broadcast_to(se, (len(el), len(az)))], axis=-1)


def direction_to_pano(d: Array) -> tuple[Array, Array]:
    """Continuous panorama (u, v) of ENU directions (..., 3); u in [0, W)."""
    d = np.asarray(d, dtype=float)
    az = np.arctan2(d[..., 0], d[..., 1]) % (2 * math.pi)
    el = np.arcsin(np.clip(d[..., 2] / np.linalg.norm(d, axis=-1), -1.0, 1.0))
    return az * (PANO_WIDTH / (2 * math.pi)), (math.pi / 2 - el) * (PANO_HEIGHT / math.pi)


# --------------------------------------------------------------------------------------------
# Facade textures


_WALL_COLOURS = [(214, 190, 150), (236, 226, 200), (176, 92, 70), (160, 160, 156),
                 (200, 214, 222), (206, 222, 196), (230, 200, 120), (190, 140, 110),
                 (240, 236, 228), (130, 120, 110), (222, 170, 150), (170, 190, 200)]
_TRIM_COLOURS = [(250, 250, 245), (60, 50, 45), (120, 110, 100), (210, 200, 180), (40, 60, 50)]
_ACCENT_COLOURS = [(180, 30, 30), (30, 90, 160), (30, 120, 60), (200, 150, 20), (120, 40, 120),
                   (20, 20, 20), (220, 90, 20), (0, 120, 130)]
_CURTAIN_COLOURS = [(230, 230, 220), (200, 60, 60), (240, 220, 160), (120, 140, 180),
                    (90, 60, 40), (250, 250, 250)]


@dataclass
class _FacadeDraw:
    """A facade being drawn (sRGB uint8 canvas) with the features found on the way."""

    img: NDArray[np.uint8]
    alpha: NDArray[np.uint8]
    ppm: float
    wall_top_px: int  # row of the top of the wall (roof items above it)
    windows: list[tuple[float, float, float, float, float]] = field(default_factory=list)
    awnings: list[tuple[float, float, float, float, float]] = field(default_factory=list)
    features: list[tuple[str, float, float]] = field(default_factory=list)  # kind, col, row

    def px(self, metres: float) -> int:
        return max(1, int(round(metres * self.ppm)))

    def row_of(self, height_above_ground_m: float) -> int:
        """Canvas row of a height above the ground."""
        return int(round(self.img.shape[0] - height_above_ground_m * self.ppm))


def _wall_texture(rng: np.random.Generator, h: int, w: int, ppm: float,
                  colour: tuple[int, int, int]) -> NDArray[np.uint8]:
    """Plaster, stone blocks or panels with dirt: never a flat area."""
    style = int(rng.integers(3))
    base = np.empty((h, w, 3), np.float32)
    base[:] = colour
    shade = 1.0 + 0.07 * _fbm(rng, (h, w), 2.0 * ppm, 4) + 0.05 * _fbm(rng, (h, w), 0.25 * ppm, 2)
    if style == 1:  # stone blocks in running bond, each block its own tint
        bh, bw = rng.uniform(0.3, 0.5), rng.uniform(0.6, 1.1)
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32) / ppm
        row_i = np.floor(yy / bh)
        xs = xx + 0.5 * bw * (row_i % 2)
        col_i = np.floor(xs / bw)
        tint = (np.sin(row_i * 12.9898 + col_i * 78.233) * 43758.5453) % 1.0
        shade *= 0.9 + 0.2 * tint
        joint = np.minimum(np.minimum(yy % bh, bh - yy % bh), np.minimum(xs % bw, bw - xs % bw))
        shade *= np.where(joint < 0.025, 0.72, 1.0)
    elif style == 2:  # large panels with dark joints
        ph, pw = rng.uniform(0.8, 1.6), rng.uniform(1.2, 2.5)
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32) / ppm
        joint = np.minimum(np.minimum(yy % ph, ph - yy % ph), np.minimum(xx % pw, pw - xx % pw))
        tint = (np.sin(np.floor(yy / ph) * 3.1 + np.floor(xx / pw) * 17.7) * 9137.3) % 1.0
        shade *= (0.94 + 0.12 * tint) * np.where(joint < 0.03, 0.65, 1.0)
    # Rain streaks: darker vertical stripes fading downwards.
    streaks = _noise(rng, (1, w), 0.4 * ppm)[0]
    fade = np.linspace(1.0, 0.3, h, dtype=np.float32)[:, None]
    shade *= 1.0 - 0.06 * np.clip(streaks, 0, 1)[None, :] * fade
    return np.clip(base * shade[..., None], 0, 255).astype(np.uint8)


def _draw_window(rng: np.random.Generator, f: _FacadeDraw, x0: int, y0: int, x1: int, y1: int,
                 trim: tuple[int, int, int], classic: bool, shutters: bool,
                 special: bool = False) -> None:
    img = f.img
    t = max(1, f.px(0.08))
    glass_top = np.array([90, 110, 140]) + rng.integers(-20, 20, 3)
    glass_bot = np.array([40, 45, 55]) + rng.integers(-10, 10, 3)
    ramp = np.linspace(0, 1, max(1, y1 - y0))[:, None, None]
    img[y0:y1, x0:x1] = (glass_top * (1 - ramp) + glass_bot * ramp).astype(np.uint8)
    if rng.random() < 0.55:  # curtain on one side or both
        c = _color(rng, _CURTAIN_COLOURS, 15)
        cw = int((x1 - x0) * rng.uniform(0.2, 0.5))
        if rng.random() < 0.5:
            cv2.rectangle(img, (x0, y0), (x0 + cw, y1 - 1), c, -1)
        else:
            cv2.rectangle(img, (x1 - cw, y0), (x1 - 1, y1 - 1), c, -1)
    if rng.random() < 0.15:  # a lit room
        cv2.rectangle(img, (x0 + t, y0 + t), (x1 - t, (y0 + y1) // 2), (235, 215, 150), -1)
    cv2.rectangle(img, (x0, y0), (x1 - 1, y1 - 1), trim, t)
    if classic:
        xm, ym = (x0 + x1) // 2, y0 + (y1 - y0) // 3
        cv2.line(img, (xm, y0), (xm, y1), trim, max(1, t // 2 + 1))
        cv2.line(img, (x0, ym), (x1, ym), trim, max(1, t // 2 + 1))
        # window head: a pediment or a flat lintel
        if rng.random() < 0.5:
            pts = np.array([[x0 - t, y0 - t], [x1 + t, y0 - t], [(x0 + x1) // 2, y0 - f.px(0.45)]])
            cv2.fillPoly(img, [pts.astype(np.int32)], trim)
        else:
            cv2.rectangle(img, (x0 - t, y0 - f.px(0.2)), (x1 + t, y0 - 1), trim, -1)
    cv2.rectangle(img, (x0 - t, y1), (x1 + t, y1 + f.px(0.1)), (200, 200, 195), -1)  # sill
    if shutters:
        sc = _color(rng, [(40, 90, 50), (120, 70, 40), (60, 80, 120), (150, 150, 140)], 10)
        sw = (x1 - x0) // 2
        for xa in (x0 - sw - t, x1 + t):
            cv2.rectangle(img, (xa, y0), (xa + sw, y1), sc, -1)
            for yy in range(y0 + 2, y1, max(2, f.px(0.12))):
                cv2.line(img, (xa, yy), (xa + sw, yy), tuple(int(v * 0.6) for v in sc), 1)
    if special:  # a flower box: the one window an author would label
        fc = [(200, 30, 60), (240, 200, 40), (230, 230, 240), (220, 80, 160)]
        cv2.rectangle(img, (x0 - t, y1 + f.px(0.1)), (x1 + t, y1 + f.px(0.35)), (90, 60, 40), -1)
        for _ in range(int((x1 - x0) * 1.5)):
            cx = int(rng.integers(x0 - t, x1 + t + 1))
            cy = int(rng.integers(y1 - f.px(0.15), y1 + f.px(0.15)))
            cv2.circle(img, (cx, cy), max(1, f.px(0.06)), fc[int(rng.integers(len(fc)))], -1)
    f.windows.append((x0, y0, x1, y1, float(rng.uniform(0.12, 0.3))))


def _draw_sign(rng: np.random.Generator, f: _FacadeDraw, x0: int, x1: int, y0: int, y1: int,
               word: str) -> None:
    bg = _color(rng, _ACCENT_COLOURS, 15)
    fg = (250, 245, 230) if sum(bg) < 400 else (20, 20, 20)
    cv2.rectangle(f.img, (x0, y0), (x1, y1), bg, -1)
    cv2.rectangle(f.img, (x0, y0), (x1, y1), tuple(int(c * 0.5) for c in bg), max(1, f.px(0.05)))
    font = cv2.FONT_HERSHEY_DUPLEX
    th = max(4, int((y1 - y0) * 0.6))
    (tw, tht), _ = cv2.getTextSize(word, font, 1.0, 2)
    scale = min(th / tht, 0.9 * (x1 - x0) / tw)
    (tw, tht), _ = cv2.getTextSize(word, font, scale, 1)
    org = ((x0 + x1 - tw) // 2, (y0 + y1 + tht) // 2)
    cv2.putText(f.img, word, org, font, scale, fg, max(1, int(round(scale * 1.5))), cv2.LINE_AA)


def _draw_ground_floor(rng: np.random.Generator, f: _FacadeDraw, bays: list[tuple[int, int]],
                       gf_h: float, trim: tuple[int, int, int], words: list[str]) -> None:
    """Shops, doors, signs and awnings along the ground floor."""
    img = f.img
    ground = img.shape[0]
    door_bays = set(rng.choice(len(bays), size=max(1, len(bays) // 3), replace=False).tolist())
    # Signs over runs of 1-3 bays.
    i = 0
    while i < len(bays):
        run = int(min(len(bays) - i, rng.integers(1, 4)))
        if words and rng.random() < 0.7:
            xa, xb = bays[i][0], bays[i + run - 1][1]
            ya, yb = f.row_of(gf_h - 0.3), f.row_of(gf_h - 1.1)
            word = words.pop()
            _draw_sign(rng, f, xa + f.px(0.2), xb - f.px(0.2), ya, yb, word)
            f.features.append((f'Sign "{word}"', (xa + xb) / 2, (ya + yb) / 2))
            if rng.random() < 0.6:  # striped awning under the sign
                ac = _color(rng, _ACCENT_COLOURS, 10)
                top, bot = yb + 1, f.row_of(gf_h - 1.8)
                stripe = max(2, f.px(0.3))
                for k, x in enumerate(range(xa + f.px(0.2), xb - f.px(0.2), stripe)):
                    col = ac if k % 2 == 0 else (240, 240, 235)
                    cv2.rectangle(img, (x, top), (min(x + stripe, xb - f.px(0.2)), bot), col, -1)
                f.awnings.append((xa + f.px(0.2), top, xb - f.px(0.2), bot,
                                  float(rng.uniform(1.0, 1.6))))
        i += run
    for k, (xa, xb) in enumerate(bays):
        if k in door_bays:
            dw = f.px(rng.uniform(1.0, 1.6))
            xc = (xa + xb) // 2
            x0, x1 = xc - dw // 2, xc + dw // 2
            y0 = f.row_of(rng.uniform(2.2, 2.7))
            dc = _color(rng, [(90, 55, 30), (40, 40, 45), (120, 30, 30), (30, 70, 50),
                              (60, 80, 110)], 10)
            cv2.rectangle(img, (x0 - f.px(0.15), y0 - f.px(0.15)), (x1 + f.px(0.15), ground),
                          trim, -1)
            cv2.rectangle(img, (x0, y0), (x1, ground), dc, -1)
            # panels, a glass pane and a handle
            cv2.rectangle(img, (x0 + f.px(0.12), y0 + f.px(0.12)), (x1 - f.px(0.12),
                          (y0 + ground) // 2), (70, 85, 100), -1)
            cv2.line(img, (xc, y0), (xc, ground), tuple(int(c * 0.6) for c in dc), 1)
            cv2.circle(img, (xc + f.px(0.15), f.row_of(1.0)), max(1, f.px(0.05)),
                       (210, 190, 90), -1)
            f.features.append(('Door', (x0 + x1) / 2, (y0 + ground) / 2))
        else:
            x0, x1 = xa + f.px(0.4), xb - f.px(0.4)
            y0, y1 = f.row_of(gf_h - 2.0), f.row_of(0.5)
            if x1 - x0 > 4:
                _draw_shop_window(rng, f, x0, y0, x1, y1, trim)


def _solid_rect(img: NDArray[np.uint8], alpha: NDArray[np.uint8], p0: tuple[int, int],
                p1: tuple[int, int], colour: tuple[int, int, int]) -> None:
    """A filled rectangle drawn into the colour image and marked opaque in the alpha mask."""
    cv2.rectangle(img, p0, p1, colour, -1)
    cv2.rectangle(alpha, p0, p1, 255, -1)


def _solid_poly(img: NDArray[np.uint8], alpha: NDArray[np.uint8], pts: NDArray[np.int32],
                colour: tuple[int, int, int]) -> None:
    cv2.fillPoly(img, [pts.astype(np.int32)], colour)
    cv2.fillPoly(alpha, [pts.astype(np.int32)], 255)


def _draw_shop_window(rng: np.random.Generator, f: _FacadeDraw, x0: int, y0: int, x1: int,
                      y1: int, trim: tuple[int, int, int]) -> None:
    img = f.img
    img[y0:y1, x0:x1] = (55, 60, 70)
    for _ in range(int(rng.integers(3, 9))):  # goods on display
        w, h = f.px(rng.uniform(0.1, 0.5)), f.px(rng.uniform(0.1, 0.6))
        cx = int(rng.integers(x0, max(x0 + 1, x1 - w)))
        cy = int(rng.integers(y0 + (y1 - y0) // 3, max(y0 + 1, y1 - h)))
        colour = _color(rng, _ACCENT_COLOURS + _CURTAIN_COLOURS, 30)
        cv2.rectangle(img, (cx, cy), (cx + w, cy + h), colour, -1)
    cv2.rectangle(img, (x0, y0), (x1, y1), trim, max(1, f.px(0.08)))
    if rng.random() < 0.5:
        xm = (x0 + x1) // 2
        cv2.line(img, (xm, y0), (xm, y1), trim, max(1, f.px(0.06)))
    f.windows.append((x0, y0, x1, y1, float(rng.uniform(0.08, 0.2))))


def _draw_roof(rng: np.random.Generator, f: _FacadeDraw, trim: tuple[int, int, int]) -> None:
    """Cornice at the wall top, and chimneys, antennas or a pitched roof above it."""
    img, a = f.img, f.alpha
    top = f.wall_top_px
    w = img.shape[1]
    cv2.rectangle(img, (0, top), (w, top + f.px(0.5)), trim, -1)
    step = max(3, f.px(0.35))
    for x in range(0, w, step):  # dentils
        cv2.rectangle(img, (x, top + f.px(0.5)), (x + step // 2, top + f.px(0.7)),
                      tuple(int(c * 0.7) for c in trim), -1)
    if rng.random() < 0.5:  # a pitched roof seen from below: a tiled band
        rh = f.px(rng.uniform(1.2, 2.6))
        rc = _color(rng, [(150, 60, 40), (80, 80, 85), (110, 70, 50)], 15)
        inset = f.px(rng.uniform(0.5, 2.0))
        pts = np.array([[0, top], [w - 1, top], [w - 1 - inset, top - rh], [inset, top - rh]])
        _solid_poly(img, a, pts, rc)
        for y in range(top - rh, top, max(2, f.px(0.25))):
            cv2.line(img, (0, y), (w, y), tuple(int(c * 0.75) for c in rc), 1)
        roof_top = top - rh
    else:
        roof_top = top
    for _ in range(int(rng.integers(1, 5))):  # chimneys
        cw, ch = f.px(rng.uniform(0.5, 1.0)), f.px(rng.uniform(0.8, 1.8))
        cx = int(rng.integers(0, max(1, w - cw)))
        col = _color(rng, [(150, 70, 50), (120, 120, 120), (180, 170, 150)], 15)
        _solid_rect(img, a, (cx, roof_top - ch), (cx + cw, roof_top + 2), col)
        _solid_rect(img, a, (cx - 1, roof_top - ch), (cx + cw + 1, roof_top - ch + f.px(0.15)),
                    (60, 60, 60))
    if rng.random() < 0.6:  # an antenna
        ax = int(rng.integers(0, w))
        ah = f.px(rng.uniform(1.5, 3.0))
        cv2.line(img, (ax, roof_top), (ax, roof_top - ah), (50, 50, 50), 1)
        cv2.line(a, (ax, roof_top), (ax, roof_top - ah), 255, 1)
        for k in range(3):
            y = roof_top - ah + k * f.px(0.4)
            hw = f.px(0.5 - 0.1 * k)
            cv2.line(img, (ax - hw, y), (ax + hw, y), (50, 50, 50), 1)
            cv2.line(a, (ax - hw, y), (ax + hw, y), 255, 1)


def _draw_clock(f: _FacadeDraw, xc: int, yc: int, r: int) -> None:
    img = f.img
    cv2.circle(img, (xc, yc), r + 2, (60, 50, 40), -1)
    cv2.circle(img, (xc, yc), r, (245, 240, 225), -1)
    for k in range(12):
        ang = k * math.pi / 6
        p0 = (int(xc + 0.8 * r * math.sin(ang)), int(yc - 0.8 * r * math.cos(ang)))
        p1 = (int(xc + 0.95 * r * math.sin(ang)), int(yc - 0.95 * r * math.cos(ang)))
        cv2.line(img, p0, p1, (20, 20, 20), 1 + (k % 3 == 0))
    cv2.line(img, (xc, yc), (int(xc + 0.5 * r), int(yc - 0.3 * r)), (10, 10, 10), 2)
    cv2.line(img, (xc, yc), (int(xc - 0.2 * r), int(yc - 0.8 * r)), (10, 10, 10), 1)
    f.features.append(('Clock', float(xc), float(yc)))


def draw_facade(rng: np.random.Generator, width_m: float, height_m: float, ppm: float,
                words: list[str], tower: bool = False) -> _FacadeDraw:
    """A building facade: wall texture, floors of windows, ground floor shops, roof items."""
    roof_m = 4.5
    h = int(round((height_m + roof_m) * ppm))
    w = max(8, int(round(width_m * ppm)))
    img = np.zeros((h, w, 3), np.uint8)
    alpha = np.zeros((h, w), np.uint8)
    wall_top = int(round(roof_m * ppm))
    f = _FacadeDraw(img, alpha, ppm, wall_top)
    wall_colour = _color(rng, _WALL_COLOURS, 14)
    trim = _color(rng, _TRIM_COLOURS, 10)
    img[wall_top:] = _wall_texture(rng, h - wall_top, w, ppm, wall_colour)
    alpha[wall_top:] = 255
    classic = rng.random() < 0.6
    shutters = classic and rng.random() < 0.4
    gf_h = rng.uniform(3.8, 4.8)
    fl_h = rng.uniform(3.0, 3.6)
    bay_w = rng.uniform(2.4, 3.6)
    n_bays = max(1, int(width_m / bay_w))
    margin = (width_m - n_bays * bay_w) / 2
    bays = [(f.px(margin + k * bay_w), f.px(margin + (k + 1) * bay_w)) for k in range(n_bays)]
    win_w, win_h = rng.uniform(0.9, 1.4), rng.uniform(1.4, 1.9)
    n_floors = max(0, int((height_m - gf_h - 0.8) / fl_h))
    special = (int(rng.integers(n_floors)), int(rng.integers(n_bays))) if n_floors else (-1, -1)
    clock_floor = n_floors - 1 if tower and n_floors >= 3 else -1
    for fl in range(n_floors):
        base = gf_h + fl * fl_h
        if classic:  # string course between floors
            y = f.row_of(base)
            cv2.rectangle(img, (0, y - f.px(0.12)), (w, y + f.px(0.12)), trim, -1)
        for b, (xa, xb) in enumerate(bays):
            if fl == clock_floor and b == n_bays // 2:
                continue
            xc = (xa + xb) // 2
            x0, x1 = xc - f.px(win_w / 2), xc + f.px(win_w / 2)
            y1 = f.row_of(base + 0.9)
            y0 = f.row_of(base + 0.9 + win_h)
            is_special = (fl, b) == special
            _draw_window(rng, f, x0, y0, x1, y1, trim, classic, shutters, is_special)
            if is_special:
                f.features.append(('Window', (x0 + x1) / 2, (y0 + y1) / 2))
    if clock_floor >= 0:
        xa, xb = bays[n_bays // 2]
        r = f.px(min(1.2, bay_w * 0.4))
        _draw_clock(f, (xa + xb) // 2, f.row_of(gf_h + clock_floor * fl_h + fl_h / 2), r)
    _draw_ground_floor(rng, f, bays, gf_h, trim, words)
    if rng.random() < 0.7:  # a drainpipe
        x = int(rng.integers(0, w))
        cv2.line(img, (x, wall_top), (x, h), (90, 90, 95), max(1, f.px(0.1)))
    for _ in range(int(rng.integers(0, 4))):  # posters and plates at street level
        pw, ph = f.px(rng.uniform(0.3, 0.8)), f.px(rng.uniform(0.4, 1.0))
        px, py = int(rng.integers(0, max(1, w - pw))), f.row_of(rng.uniform(1.2, 2.2))
        cv2.rectangle(img, (px, py), (px + pw, py + ph), _color(rng, _ACCENT_COLOURS, 40), -1)
        cv2.line(img, (px + 2, py + ph // 3), (px + pw - 2, py + ph // 3), (240, 240, 240), 1)
    _draw_roof(rng, f, trim)
    # ambient occlusion near the ground
    gh = f.px(0.5)
    img[h - gh:] = (img[h - gh:] * np.linspace(1.0, 0.75, gh)[:, None, None]).astype(np.uint8)
    return f


def draw_far_block(rng: np.random.Generator, width_m: float, height_m: float, ppm: float
                   ) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
    """A distant building: flat colour, a grid of window dots, sometimes a spire or crane."""
    extra = 12.0
    h, w = int(round((height_m + extra) * ppm)), max(4, int(round(width_m * ppm)))
    img = np.zeros((h, w, 3), np.uint8)
    a = np.zeros((h, w), np.uint8)
    top = int(round(extra * ppm))
    col = np.array(_color(rng, _WALL_COLOURS, 20), dtype=np.float32)
    tex = 1.0 + 0.08 * _fbm(rng, (h - top, w), 3 * ppm, 3)
    img[top:] = np.clip(col * tex[..., None], 0, 255).astype(np.uint8)
    a[top:] = 255
    dark = tuple(int(c * 0.45) for c in col)
    fy, fx = rng.uniform(3.0, 3.6), rng.uniform(2.5, 3.5)
    for y in np.arange(top + ppm * 1.5, h - ppm * 1.0, fy * ppm):
        for x in np.arange(ppm * 0.8, w - ppm * 0.8, fx * ppm):
            if rng.random() < 0.9:
                p1 = (int(x + 1.2 * ppm), int(y + 1.5 * ppm))
                cv2.rectangle(img, (int(x), int(y)), p1, dark, -1)
    if rng.random() < 0.25:  # spire or crane
        x = int(rng.integers(0, w))
        sh = int(rng.uniform(0.4, 1.0) * top)
        _solid_poly(img, a, np.array([[x - 3, top], [x + 3, top], [x, top - sh]]), dark)
    roof_c = tuple(int(c * 0.6) for c in col)
    cv2.rectangle(img, (0, top), (w, top + 2), roof_c, -1)
    return img, a


def draw_tree(rng: np.random.Generator, width_m: float, height_m: float, ppm: float
              ) -> tuple[NDArray[np.uint8], NDArray[np.uint8], Image]:
    """A deciduous tree: trunk and a crown of leaf clumps; returns rgb, alpha, local normals."""
    h, w = int(round(height_m * ppm)), int(round(width_m * ppm))
    img = np.zeros((h, w, 3), np.uint8)
    a = np.zeros((h, w), np.uint8)
    tw = max(2, int(0.35 * ppm))
    trunk_top = int(h * 0.45)
    _solid_rect(img, a, (w // 2 - tw // 2, trunk_top), (w // 2 + tw // 2, h), (70, 55, 40))
    cx, cy = w / 2, h * 0.36
    rx, ry = w * 0.48, h * 0.35
    greens = [(60, 100, 40), (80, 120, 50), (50, 85, 35), (100, 130, 60), (70, 110, 30)]
    n = int(rx * ry / (0.25 * ppm) ** 2 * 0.9)
    for _ in range(n):
        ang, rad = rng.uniform(0, 2 * math.pi), math.sqrt(rng.uniform(0, 1))
        px, py = cx + rx * rad * math.cos(ang), cy + ry * rad * math.sin(ang)
        r = int(rng.uniform(0.15, 0.45) * ppm)
        shade = 0.75 + 0.5 * (1 - rad)
        c = tuple(int(min(255, v * shade)) for v in _color(rng, greens, 12))
        cv2.circle(img, (int(px), int(py)), max(1, r), c, -1)
        cv2.circle(a, (int(px), int(py)), max(1, r), 255, -1)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    nx, ny = (xx - cx) / rx, (cy - yy) / ry
    nz = np.sqrt(np.clip(1 - nx ** 2 - ny ** 2, 0.05, 1))
    normals = np.stack([nx, ny, nz], -1)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    trunk = yy > trunk_top + 0.2 * ppm
    normals[trunk] = (0.0, 0.0, 1.0)
    return img, a, normals.astype(np.float32)


def draw_pole(rng: np.random.Generator, height_m: float, ppm: float
              ) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
    """A lamp post or a sign post."""
    w, h = int(1.2 * ppm), int(round(height_m * ppm))
    img = np.zeros((h, w, 3), np.uint8)
    a = np.zeros((h, w), np.uint8)
    col = _color(rng, [(40, 45, 40), (70, 70, 75), (30, 50, 40)], 8)
    pw = max(2, int(0.14 * ppm))
    xc = w // 2

    def dx(metres: float) -> int:
        return int(metres * ppm)

    _solid_rect(img, a, (xc - pw // 2, int(0.08 * h)), (xc + pw // 2, h), col)
    if rng.random() < 0.6:  # lamp head
        yl = int(0.12 * h)
        _solid_poly(img, a, np.array([[xc - dx(0.45), yl], [xc + dx(0.45), yl],
                                      [xc + dx(0.2), 0], [xc - dx(0.2), 0]]), col)
        _solid_rect(img, a, (xc - dx(0.3), yl), (xc + dx(0.3), yl + 3), (230, 230, 200))
    else:  # a street sign
        sc = _color(rng, [(20, 80, 160), (240, 240, 240), (200, 30, 30)], 5)
        y0 = int(0.1 * h)
        _solid_rect(img, a, (xc - dx(0.5), y0), (xc + dx(0.5), y0 + dx(0.5)), sc)
        cv2.rectangle(img, (xc - dx(0.4), y0 + 3), (xc + dx(0.4), y0 + dx(0.5) - 3),
                      (250, 250, 250) if sum(sc) < 600 else (30, 30, 30), 1)
    return img, a


def _to_albedo(img: NDArray[np.uint8], alpha: NDArray[np.uint8]) -> Image:
    """Linear RGBA albedo from an sRGB drawing and its coverage mask."""
    rgb = _srgb_to_linear(img.astype(np.float32) / 255.0)
    return np.dstack([rgb, alpha.astype(np.float32) / 255.0]).astype(np.float32)


# --------------------------------------------------------------------------------------------
# The world


def build_world(seed: int) -> World:
    """The spot of ``seed``: buildings, trees, posts, ground, clouds and 4-6 annotation anchors."""
    rng = rng_stream(seed, 'world')
    planes: list[Plane] = []
    planes += _far_ring(rng)
    buildings = _building_ring(rng)
    planes += buildings
    planes += _street_furniture(rng, buildings)
    planes.sort(key=lambda p: -p.distance_m)
    world = World(
        seed=seed, planes=planes, anchors=[], ground_tile_m=float(rng.uniform(0.4, 0.6)),
        ground_grain=_periodic_noise(rng, 256, 8, 4),
        ground_stains=_periodic_noise(rng, 256, 4, 3),
        ground_base_rgb=_srgb_to_linear(np.array(_color(rng, [(146, 140, 132), (156, 150, 140),
                                                              (132, 128, 124)], 6)) / 255.0),
        crossings=_crossings(rng, buildings), manholes=_manholes(rng),
        clouds=np.zeros((0, 0), np.float32), cloud_detail=np.zeros((0, 0), np.float32),
    )
    world.clouds, world.cloud_detail = _clouds(rng)
    world.anchors = _choose_anchors(rng, world, buildings)
    return world


def _building_ring(rng: np.random.Generator) -> list[Plane]:
    """11-15 buildings around the spot, each filling an azimuth sector (streets between some)."""
    n = int(rng.integers(11, 16))
    widths = rng.uniform(0.6, 1.4, n)
    widths *= 2 * math.pi / widths.sum()
    start = rng.uniform(0, 2 * math.pi)
    edges = start + np.concatenate([[0.0], np.cumsum(widths)])
    words = list(SIGN_WORDS)
    rng.shuffle(words)
    tower_at = int(rng.integers(n))
    out = []
    for i in range(n):
        gap = math.radians(rng.uniform(2.0, 6.0)) if rng.random() < 0.4 else 0.0
        a0, a1 = edges[i] + gap / 2, edges[i + 1] - gap / 2
        dist = rng.uniform(28.0, 75.0)
        skew = math.radians(rng.uniform(-18.0, 18.0))
        phi = (a0 + a1) / 2 + skew
        s0, s1 = dist * math.tan(a0 - phi), dist * math.tan(a1 - phi)
        tower = i == tower_at
        el_top = math.radians(rng.uniform(30.0, 40.0) if tower else rng.uniform(9.0, 32.0))
        height = float(np.clip(dist * math.tan(el_top) + EYE_HEIGHT_M, 7.0, 48.0))
        f = draw_facade(rng, s1 - s0, height, NEAR_PX_PER_M, words, tower=tower)
        out.append(Plane(
            kind='building', index=i + 1, foot_az_rad=phi % (2 * math.pi), distance_m=dist,
            s_min_m=s0, z_max_m=height + 4.5 - EYE_HEIGHT_M, px_per_m=NEAR_PX_PER_M,
            albedo=_to_albedo(f.img, f.alpha), windows=np.array(f.windows, float).reshape(-1, 5),
            awnings=np.array(f.awnings, float).reshape(-1, 5), features=f.features,
        ))
    return out


def _far_ring(rng: np.random.Generator) -> list[Plane]:
    """A closed ring of distant blocks so that the horizon is never empty."""
    out = []
    az = rng.uniform(0, 2 * math.pi)
    end = az + 2 * math.pi
    while az < end:
        span = math.radians(rng.uniform(6.0, 16.0))
        span = min(span, end - az + math.radians(0.5))
        dist = rng.uniform(180.0, 380.0)
        phi = az + span / 2 + math.radians(rng.uniform(-10, 10))
        s0, s1 = dist * math.tan(az - phi), dist * math.tan(az + span - phi)
        height = dist * math.tan(math.radians(rng.uniform(2.5, 9.0))) + EYE_HEIGHT_M
        img, a = draw_far_block(rng, s1 - s0, height, FAR_PX_PER_M)
        out.append(Plane(kind='far', index=0, foot_az_rad=phi % (2 * math.pi), distance_m=dist,
                         s_min_m=s0, z_max_m=height + 12.0 - EYE_HEIGHT_M, px_per_m=FAR_PX_PER_M,
                         albedo=_to_albedo(img, a)))
        az += span - math.radians(0.3)
    return out


def _building_distance_at(buildings: list[Plane], az: float) -> float:
    """Distance from the origin to the building ring in direction ``az`` (inf in a street)."""
    d = np.array([math.sin(az), math.cos(az), 0.0])
    best = math.inf
    for b in buildings:
        denom = d @ b.normal
        if denom >= -1e-6:
            continue
        lam = (b.foot @ b.normal) / denom
        s = (lam * d - b.foot) @ b.tangent
        w = b.albedo.shape[1] / b.px_per_m
        if lam > 0 and b.s_min_m <= s <= b.s_min_m + w:
            best = min(best, lam)
    return best


def _street_furniture(rng: np.random.Generator, buildings: list[Plane]) -> list[Plane]:
    """Trees and posts in front of the buildings (not too close, so parallax stays moderate)."""
    out = []
    for _ in range(int(rng.integers(5, 10))):
        az = rng.uniform(0, 2 * math.pi)
        dist = min(rng.uniform(17.0, 26.0), _building_distance_at(buildings, az) - 6.0)
        width, height = rng.uniform(4.0, 7.0), rng.uniform(6.0, 11.0)
        img, a, normals = draw_tree(rng, width, height, NEAR_PX_PER_M)
        out.append(Plane(kind='tree', index=0, foot_az_rad=az, distance_m=dist,
                         s_min_m=-width / 2, z_max_m=height - EYE_HEIGHT_M, px_per_m=NEAR_PX_PER_M,
                         albedo=_to_albedo(img, a), normals=normals))
    for _ in range(int(rng.integers(4, 8))):
        az = rng.uniform(0, 2 * math.pi)
        dist = rng.uniform(9.0, 20.0)
        height = rng.uniform(3.0, 5.5)
        img, a = draw_pole(rng, height, NEAR_PX_PER_M)
        out.append(Plane(kind='pole', index=0, foot_az_rad=az, distance_m=dist,
                         s_min_m=-0.6, z_max_m=height - EYE_HEIGHT_M, px_per_m=NEAR_PX_PER_M,
                         albedo=_to_albedo(img, a)))
    return out


def _crossings(rng: np.random.Generator, buildings: list[Plane]) -> Array:
    rows = []
    for _ in range(int(rng.integers(1, 3))):
        az = rng.uniform(0, 2 * math.pi)
        r1 = min(25.0, _building_distance_at(buildings, az) - 3.0)
        rows.append((az, max(4.0, r1 - rng.uniform(6, 10)), r1, rng.uniform(1.5, 2.5)))
    return np.array(rows, float)


def _manholes(rng: np.random.Generator) -> Array:
    n = int(rng.integers(3, 7))
    r = rng.uniform(3.0, 15.0, n)
    az = rng.uniform(0, 2 * math.pi, n)
    return np.stack([r * np.sin(az), r * np.cos(az), rng.uniform(0.3, 0.45, n)], 1)


def _clouds(rng: np.random.Generator) -> tuple[Image, Image]:
    """Cloud density of the upper panorama half: many cumulus with crisp edges, so that a camera
    looking up still sees structure (no big flat regions)."""
    h, w = PANO_HEIGHT // 2, PANO_WIDTH
    base = _fbm(rng, (h, w), 140.0, 6, gain=0.6, wrap_x=True)
    el = (math.pi / 2 - (np.arange(h) + 0.5) * math.pi / PANO_HEIGHT)[:, None]
    cover = rng.uniform(0.04, 0.12)
    dens = _smoothstep(0.0 - cover, 0.06 - cover, base)
    dens *= (0.8 + 0.2 * np.cos(el)).astype(np.float32)
    # Bright sunlit tops, grey bases and billows inside the clouds.
    detail = 1.0 + 0.45 * _fbm(rng, (h, w), 40.0, 4, gain=0.6, wrap_x=True)
    return dens.astype(np.float32), detail.astype(np.float32)


def _choose_anchors(rng: np.random.Generator, world: World, buildings: list[Plane]
                    ) -> list[Anchor]:
    """4-6 features (doors, signs, windows, a clock) of different buildings, seen from the spot."""
    cands = []
    for b in buildings:
        for kind, col, row in b.features:
            p = b.world_point(np.array(col), np.array(row))
            el = math.degrees(math.asin(p[2] / np.linalg.norm(p)))
            if not -6.0 < el < 32.0 or not _clear_view(world, b, p):
                continue
            label = f'{kind} of building {b.index}' if not kind.startswith('Sign') else \
                f'{kind} on building {b.index}'
            cands.append((math.atan2(p[0], p[1]) % (2 * math.pi), b.index, label, p))
    order = rng.permutation(len(cands))
    n_want = int(rng.integers(4, 7))
    chosen: list[tuple[float, int, str, Array]] = []
    for sep in (25.0, 12.0, 0.0):  # prefer anchors spread around the horizon
        for i in order:
            az, idx, label, p = cands[i]
            if len(chosen) >= n_want or any(c[1] == idx or c[2] == label for c in chosen):
                continue
            if all(abs((math.degrees(az - c[0]) + 180) % 360 - 180) >= sep for c in chosen):
                chosen.append(cands[i])
    chosen.sort(key=lambda c: c[0])
    return [Anchor(label=c[2], position_enu=c[3]) for c in chosen]


def _clear_view(world: World, plane: Plane, point: Array, margin_m: float = 0.6,
                radius_m: float = 1.5) -> bool:
    """Whether a spot and its surroundings on ``plane`` are unoccluded from the authoring spot
    and from anywhere a browsing user may stand (a circle of ``radius_m`` around it)."""
    offsets = np.array([(ds, dz) for ds in (-1, 0, 1) for dz in (-1, 0, 1)]) * margin_m
    points = point + offsets[:, :1] * plane.tangent + offsets[:, 1:] * UP
    ang = np.arange(8) * math.pi / 4
    views = np.vstack([np.zeros(3), radius_m * np.stack([np.sin(ang), np.cos(ang),
                                                          np.zeros(8)], 1)])
    q = np.repeat(points, len(views), axis=0)
    v = np.tile(views, (len(points), 1))
    return bool(np.all(_visible(world, q, v)))


def _visible_from(world: World, point: Array, viewpoint: Array) -> bool:
    """Whether nothing opaque lies between the viewpoint and a world point."""
    return bool(_visible(world, point[None], viewpoint[None])[0])


def _visible(world: World, points: Array, viewpoints: Array) -> NDArray[np.bool_]:
    """For pairs of points and viewpoints (n, 3): no opaque texel of any plane in between."""
    d = points - viewpoints
    dist = np.linalg.norm(d, axis=1)
    d = d / dist[:, None]
    free = np.ones(len(points), bool)
    for p in world.planes:
        denom = d @ p.normal
        safe = np.where(np.abs(denom) < 1e-9, 1e-9, denom)
        lam = ((p.foot - viewpoints) @ p.normal) / safe
        hit = (np.abs(denom) >= 1e-9) & (lam > 0) & (lam < dist - 0.5)
        if not hit.any():
            continue
        col, row = p.texture_coords(viewpoints[hit] + lam[hit, None] * d[hit])
        h, w = p.shape
        inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
        ci = np.clip(col, 0, w - 1).astype(int)
        ri = np.clip(row, 0, h - 1).astype(int)
        opaque = inside & (p.albedo[ri, ci, 3] > 0.5)
        idx = np.flatnonzero(hit)
        free[idx[opaque]] = False
    return free


# --------------------------------------------------------------------------------------------
# Lighting


def make_lighting(seed: int, session: str, world: World | None = None) -> Lighting:
    """Sun and sky for a session: low warm afternoon sun (authoring) or high midday sun (browsing).

    When ``world`` is given, the sun azimuth is chosen where the sun is not hidden behind a
    building (within the few tries), so that the session shows a sun glare somewhere.
    """
    rng = rng_stream(seed, 'lighting', session)
    if session == 'authoring':
        el = math.radians(rng.uniform(10.0, 20.0))
        sun_rgb = np.array([1.0, 0.82, 0.62]) * 2.0
        ambient = np.array([0.39, 0.44, 0.54])
        zenith, horizon = np.array([0.16, 0.28, 0.62]), np.array([0.85, 0.75, 0.62])
    else:
        el = math.radians(rng.uniform(34.0, 44.0))
        sun_rgb = np.array([1.0, 0.97, 0.92]) * 3.6
        ambient = np.array([0.62, 0.68, 0.80])
        zenith, horizon = np.array([0.20, 0.38, 0.82]), np.array([0.78, 0.84, 0.92])
    az = rng.uniform(0, 2 * math.pi)
    if world is not None:
        for _ in range(24):
            d = np.array([math.cos(el) * math.sin(az), math.cos(el) * math.cos(az), math.sin(el)])
            if _visible_from(world, 1e4 * d, np.zeros(3)):
                break
            az = rng.uniform(0, 2 * math.pi)
    return Lighting(sun_az_rad=float(az), sun_el_rad=float(el), sun_rgb=sun_rgb,
                    ambient_rgb=ambient, sky_zenith_rgb=zenith, sky_horizon_rgb=horizon)


def _plane_sun_terms(plane: Plane, sun: Array) -> tuple[float, float, float]:
    """Sun direction in the plane's frame: (along tangent, up, along the outward normal)."""
    return float(sun @ plane.tangent), float(sun[2]), float(sun @ plane.normal)


def _affine_between(src: Plane, project: Callable[[Array], Array],
                    dst_coords: Callable[[Array], tuple[Array, Array]]) -> Array:
    """The 2x3 affine map from ``src`` texture pixels to destination pixels of a projection."""
    pts = np.array([[0.5, 0.5], [1.5, 0.5], [0.5, 1.5]])
    world = src.world_point(pts[:, 0], pts[:, 1])
    dc, dr = dst_coords(project(world))
    dst = np.stack([dc - 0.5, dr - 0.5], 1).astype(np.float32)
    return cv2.getAffineTransform((pts - 0.5).astype(np.float32), dst)


def _splat_max(src: Image, M: Array, dst: Image) -> None:
    """``dst = max(dst, warp(src))`` computed only over the warped footprint of ``src``."""
    h, w = src.shape[:2]
    corners = np.array([[0, 0, 1], [w, 0, 1], [0, h, 1], [w, h, 1]], float) @ M.T
    x0, y0 = np.floor(corners.min(0)).astype(int)
    x1, y1 = np.ceil(corners.max(0)).astype(int) + 1
    x0, y0 = max(x0, 0), max(y0, 0)
    x1, y1 = min(x1, dst.shape[1]), min(y1, dst.shape[0])
    if x1 <= x0 or y1 <= y0:
        return
    M2 = M.copy()
    M2[:, 2] -= (x0, y0)
    warped = cv2.warpAffine(src, M2.astype(np.float32), (x1 - x0, y1 - y0), flags=cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    np.maximum(dst[y0:y1, x0:x1], warped, out=dst[y0:y1, x0:x1])


def _caster_alpha(caster: Plane, receiver_normal: Array, receiver_foot: Array, sun: Array
                  ) -> Image:
    """Alpha of a caster restricted to its part on the sun side of the receiver plane."""
    a = caster.albedo[..., 3]
    h, w = a.shape
    corners = caster.world_point(np.array([0.5, w - 0.5, 0.5]), np.array([0.5, 0.5, h - 0.5]))
    t = (corners - receiver_foot) @ receiver_normal
    if np.all(t > 0):
        return a
    if np.all(t <= 0):
        return np.zeros_like(a)
    # t is linear in (col, row): build it from the three corners.
    cols = np.arange(w, dtype=np.float32)[None, :] / max(1, w - 1)
    rows = np.arange(h, dtype=np.float32)[:, None] / max(1, h - 1)
    tt = t[0] + (t[1] - t[0]) * cols + (t[2] - t[0]) * rows
    return a * (tt > 0.05)


def _facade_shadow(receiver: Plane, casters: list[Plane], light: Lighting) -> Image:
    """Shadow mask (0 lit .. 1 shadow) on a facade from other planes and its own reliefs."""
    sun = light.sun_dir
    st, sz, sn = _plane_sun_terms(receiver, sun)
    h, w = receiver.shape
    shadow = np.zeros((h, w), np.float32)
    if sn <= 0.02:
        return np.ones((h, w), np.float32)
    ppm = receiver.px_per_m
    # Window recesses: the lintel and the jamb on the sun side shade the glass.
    for x0, y0, x1, y1, depth in receiver.windows:
        top = depth * sz / sn * ppm
        side = depth * abs(st) / sn * ppm
        yb = int(round(min(y1, y0 + top)))
        shadow[int(y0):max(int(y0), yb), int(x0):int(x1)] = 1.0
        if st > 0:
            shadow[int(y0):int(y1), max(int(x0), int(round(x1 - side))):int(x1)] = 1.0
        else:
            shadow[int(y0):int(y1), int(x0):int(round(min(x1, x0 + side)))] = 1.0
    # Awnings shade the wall below them, shifted away from the sun.
    for x0, y0, x1, y1, depth in receiver.awnings:
        drop = depth * sz / sn * ppm
        shift = -depth * st / sn * ppm
        xa, xb = int(round(x0 + shift)), int(round(x1 + shift))
        shadow[int(y1):int(min(h, y1 + drop)), max(0, xa):max(0, min(w, xb))] = 1.0
    # Cast shadows of other planes: parallel projection along the sun onto this plane.
    n, foot = receiver.normal, receiver.foot

    def project(p: Array) -> Array:
        return p - (((p - foot) @ n) / sn)[:, None] * sun

    for c in casters:
        if c is receiver:
            continue
        a = _caster_alpha(c, n, foot, sun)
        if not a.any():
            continue
        M = _affine_between(c, project, receiver.texture_coords)
        _splat_max(a, M, shadow)
    return shadow


GROUND_RASTER_HALF_M = 110.0
GROUND_RASTER_RES_M = 0.1


def _ground_shadow(casters: list[Plane], light: Lighting) -> Image:
    """Top-down shadow raster of the ground (rows north to south), 0 lit .. 1 shadow."""
    n = int(2 * GROUND_RASTER_HALF_M / GROUND_RASTER_RES_M)
    shadow = np.zeros((n, n), np.float32)
    sun = light.sun_dir

    def project(p: Array) -> Array:
        return p - ((p[:, 2] + EYE_HEIGHT_M) / sun[2])[:, None] * sun

    def coords(p: Array) -> tuple[Array, Array]:
        return ((p[:, 0] + GROUND_RASTER_HALF_M) / GROUND_RASTER_RES_M,
                (GROUND_RASTER_HALF_M - p[:, 1]) / GROUND_RASTER_RES_M)

    for c in casters:
        M = _affine_between(c, project, coords)
        _splat_max(c.albedo[..., 3], M, shadow)
    return cv2.GaussianBlur(shadow, (0, 0), 1.2)


def _light_plane(plane: Plane, shadow: Image | None, light: Lighting) -> Image:
    """Premultiplied linear RGBA radiance of a plane under the session's lighting."""
    alb = plane.albedo
    sun = light.sun_dir
    if plane.normals is not None:  # round object: per-pixel normal in (tangent, up, out)
        nrm = plane.normals
        world_n = (nrm[..., :1] * plane.tangent + nrm[..., 1:2] * UP + nrm[..., 2:] * plane.normal)
        cos_i = np.clip(world_n @ sun, 0, None).astype(np.float32)
        self_shadow = 0.35 + 0.65 * _smoothstep(0.0, 0.3, cos_i)
        direct = cos_i * self_shadow
    else:
        direct = np.full(plane.shape, max(0.0, float(sun @ plane.normal)), np.float32)
        if plane.kind == 'pole':
            direct[:] = 0.2 + 0.5 * max(0.0, float(np.hypot(sun[0], sun[1])))
    if shadow is not None:
        direct = direct * (1.0 - shadow)
    irr = light.ambient_rgb[None, None, :] + direct[..., None] * light.sun_rgb[None, None, :]
    rgb = alb[..., :3] * irr.astype(np.float32)
    if plane.kind == 'far':  # aerial perspective: distant blocks fade toward the horizon sky
        haze = 1.0 - math.exp(-plane.distance_m / 900.0)
        rgb = (1 - haze) * rgb + haze * (light.sky_horizon_rgb * 1.1).astype(np.float32)
    a = alb[..., 3:]
    return np.dstack([rgb * a, a]).astype(np.float32)


# --------------------------------------------------------------------------------------------
# Panorama rendering


def _band_rows() -> tuple[int, int]:
    r0 = int(math.floor((math.pi / 2 - PANO_MAX_ABS_EL) / math.pi * PANO_HEIGHT))
    return r0, PANO_HEIGHT - r0


ROW_CHUNK = 128  # rows of the panorama computed at once (bounds the memory of rendering)


def _render_sky(light: Lighting, world: World, out: Image) -> None:
    """Sky gradient, sun halo and disc, lit clouds into the upper half of ``out`` (linear)."""
    r0, _ = _band_rows()
    for a in range(r0, PANO_HEIGHT // 2, ROW_CHUNK):
        rows = np.arange(a, min(a + ROW_CHUNK, PANO_HEIGHT // 2))
        out[rows[0]:rows[-1] + 1] = _sky_rows(light, world, rows)


def _sky_rows(light: Lighting, world: World, rows: NDArray[np.int64]) -> Image:
    f32 = np.float32
    d = pano_directions(rows, np.arange(PANO_WIDTH)).astype(f32)
    t = np.sqrt(np.clip(d[..., 2:3], 0, 1))
    sky = light.sky_horizon_rgb.astype(f32) * (1 - t) + light.sky_zenith_rgb.astype(f32) * t
    cos_sun = np.clip(d @ light.sun_dir.astype(f32), -1, 1)[..., None]
    ang = np.arccos(cos_sun)
    halo = 1.0 + f32(1.6) * np.exp(-ang / f32(0.07)) + f32(0.5) * np.exp(-ang / f32(0.5))
    sky *= halo
    dens = world.clouds[rows][..., None]
    detail = world.cloud_detail[rows][..., None]
    cloud = (light.ambient_rgb.astype(f32) * f32(1.5)
             + f32(0.35) * light.sun_rgb.astype(f32) * (f32(0.6) + f32(0.4) * cos_sun)) * detail
    cloud *= (1.0 - f32(0.35) * dens) * np.sqrt(halo)  # grey bases, silver linings
    rgb = sky * (1 - f32(0.85) * dens) + cloud * f32(0.85) * dens
    rgb += ((ang < math.radians(0.6)) * (1 - f32(0.9) * dens) * f32(60.0))  # the sun's disc
    return rgb


def _ground_albedo(world: World, x: Image, y: Image, footprint: Image) -> Image:
    """Paving of the square at ground points (x, y) in metres, faded where it would alias."""
    tile = world.ground_tile_m
    row_i = np.floor(y / tile)
    xs = x + 0.5 * tile * (row_i % 2)
    col_i = np.floor(xs / tile)
    tint = (np.sin(row_i * 12.9898 + col_i * 78.233) * 43758.5453) % 1.0
    fy, fx = y - row_i * tile, xs - col_i * tile
    edge = np.minimum(np.minimum(fy, tile - fy), np.minimum(fx, tile - fx))
    soft = np.maximum(footprint, 0.01)
    grout = _smoothstep(0.0, 1.0, (edge - 0.015) / soft)
    fade = np.clip(1.0 - footprint / (0.35 * tile), 0.0, 1.0)
    pattern = (0.82 + 0.36 * tint) * (0.55 + 0.45 * grout)
    mean_pattern = 1.0 * (1 - 0.45 * 0.05 / tile)
    shade = fade * pattern + (1 - fade) * mean_pattern
    n = world.ground_grain.shape[0]
    gx = (x / 3.0 * n).astype(np.float32)
    gy = (y / 3.0 * n).astype(np.float32)
    grain = cv2.remap(world.ground_grain, gx, gy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
    m = world.ground_stains.shape[0]
    stains = cv2.remap(world.ground_stains, (x / 60.0 * m).astype(np.float32),
                       (y / 60.0 * m).astype(np.float32), cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_WRAP)
    grain_fade = np.clip(1.0 - footprint / 0.06, 0.0, 1.0)
    shade = shade * (1.0 + 0.25 * grain * grain_fade) * (1.0 + 0.18 * stains)
    paint = np.zeros_like(x)
    for caz, r0, r1, hw in world.crossings:  # zebra crossings: stripes across the walkway
        dx, dy = math.sin(caz), math.cos(caz)
        along = x * dx + y * dy
        across = -x * dy + y * dx
        inside = (along > r0) & (along < r1) & (np.abs(across) < hw)
        stripes = (np.floor(along / 0.5) % 2 == 0) & inside
        paint = np.maximum(paint, stripes.astype(np.float32) * np.clip(1 - footprint / 0.4, 0, 1))
    albedo = world.ground_base_rgb.astype(np.float32) * shade[..., None]
    albedo = albedo * (1 - paint[..., None]) + 0.75 * paint[..., None]
    for mx, my, mr in world.manholes:  # dark cast-iron covers with a grid
        dd = np.hypot(x - mx, y - my)
        cover = dd < mr
        if cover.any():
            grid = (np.floor((x[cover] - mx) / 0.08) + np.floor((y[cover] - my) / 0.08)) % 2
            albedo[cover] = (0.05 + 0.04 * grid)[:, None] * np.array([1.0, 1.0, 1.05], np.float32)
            albedo[cover & (dd > mr - 0.05)] = 0.02
    return albedo


def _render_ground(world: World, light: Lighting, viewpoint: Array, out: Image,
                   depth: Image) -> None:
    """Paved ground below the horizon, with the cast shadows of the session's sun."""
    _, r1 = _band_rows()
    casters = [p for p in world.planes if p.kind != 'far']
    shadow_raster = _ground_shadow(casters, light)
    for a in range(PANO_HEIGHT // 2, r1, ROW_CHUNK):  # every row here looks below the horizon
        rows = np.arange(a, min(a + ROW_CHUNK, r1))
        rgb, lam = _ground_rows(world, light, viewpoint, shadow_raster, rows)
        out[rows[0]:rows[-1] + 1] = rgb
        depth[rows[0]:rows[-1] + 1] = lam


def _ground_rows(world: World, light: Lighting, viewpoint: Array, shadow_raster: Image,
                 rows: NDArray[np.int64]) -> tuple[Image, Image]:
    d = pano_directions(rows, np.arange(PANO_WIDTH))
    h_eye = EYE_HEIGHT_M + viewpoint[2]
    lam = h_eye / np.maximum(-d[..., 2], 1e-4)
    x = (viewpoint[0] + lam * d[..., 0]).astype(np.float32)
    y = (viewpoint[1] + lam * d[..., 1]).astype(np.float32)
    lam = lam.astype(np.float32)
    footprint = lam * lam * np.float32(math.pi / PANO_HEIGHT / h_eye)
    albedo = _ground_albedo(world, x, y, footprint)
    sx = (x + GROUND_RASTER_HALF_M) / np.float32(GROUND_RASTER_RES_M) - np.float32(0.5)
    sy = (GROUND_RASTER_HALF_M - y) / np.float32(GROUND_RASTER_RES_M) - np.float32(0.5)
    shadow = cv2.remap(shadow_raster, sx, sy, cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    direct = np.float32(max(0.0, float(light.sun_dir[2]))) * (1.0 - shadow)
    irr = light.ambient_rgb + direct[..., None] * light.sun_rgb.astype(np.float32)
    rgb = albedo * irr.astype(np.float32)
    haze = (1.0 - np.exp(-lam / np.float32(900.0)))[..., None]
    return (1 - haze) * rgb + haze * light.sky_horizon_rgb.astype(np.float32), lam


def _plane_bbox(plane: Plane, viewpoint: Array) -> tuple[int, int, int, int] | None:
    """Panorama column and row range covered by a plane seen from ``viewpoint``."""
    h, w = plane.shape
    k = 17
    cols = np.concatenate([np.linspace(0, w, k), np.linspace(0, w, k), np.zeros(k), np.full(k, w)])
    rows = np.concatenate([np.zeros(k), np.full(k, h), np.linspace(0, h, k), np.linspace(0, h, k)])
    pts = plane.world_point(cols, rows) - viewpoint
    if np.any(pts @ plane.normal >= 0):  # seen from behind or edge-on: not drawn
        return None
    u, v = direction_to_pano(pts)
    uc, _ = direction_to_pano(plane.foot - viewpoint)
    du = (u - uc + PANO_WIDTH / 2) % PANO_WIDTH - PANO_WIDTH / 2
    return (int(math.floor(uc + du.min())) - 1, int(math.ceil(uc + du.max())) + 1,
            max(0, int(math.floor(v.min())) - 1), min(PANO_HEIGHT, int(math.ceil(v.max())) + 1))


def _prefilter(rgba: Image, plane: Plane, viewpoint: Array) -> Image:
    """Blur a plane's texture to the panorama's sampling at its distance (no aliasing)."""
    dist = float(np.linalg.norm(plane.foot - viewpoint))
    step = dist * (2 * math.pi / PANO_WIDTH) * plane.px_per_m  # texture px per panorama px
    if step <= 1.2:
        return rgba
    return cv2.GaussianBlur(rgba, (0, 0), 0.5 * step)


def _render_plane(plane: Plane, rgba: Image, viewpoint: Array, out: Image, depth: Image) -> None:
    """Composite a lit plane (premultiplied RGBA) over the panorama, painter's style."""
    box = _plane_bbox(plane, viewpoint)
    if box is None:
        return
    u0, u1, v0, v1 = box
    cols = np.arange(u0, u1)
    rows = np.arange(v0, v1)
    d = pano_directions(rows, cols)
    n = plane.normal
    denom = d @ n
    lam = np.where(denom < -1e-6, ((plane.foot - viewpoint) @ n) / np.minimum(denom, -1e-6), -1.0)
    pts = viewpoint + lam[..., None] * d
    tc, tr = plane.texture_coords(pts)
    sample = cv2.remap(rgba, (tc - 0.5).astype(np.float32), (tr - 0.5).astype(np.float32),
                       cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    a = sample[..., 3] * (lam > 0)
    wrap = cols % PANO_WIDTH
    dst = out[v0:v1][:, wrap]
    dst = sample[..., :3] * (lam > 0)[..., None] + (1 - a[..., None]) * dst
    out[v0:v1, wrap] = dst
    dep = depth[v0:v1][:, wrap]
    depth[v0:v1, wrap] = np.where(a > 0.5, lam, dep).astype(np.float32)


def _antialias(enc: Image) -> Image:
    """Blur for the camera's ~2x coarser sampling; wider horizontally toward the poles."""
    out = cv2.GaussianBlur(enc, (1, 0), sigmaX=0.01, sigmaY=0.85)
    bands = np.linspace(0, PANO_HEIGHT, 25).astype(int)
    for a, b in zip(bands[:-1], bands[1:]):
        el = abs(math.pi / 2 - (a + b) / 2 * math.pi / PANO_HEIGHT)
        sx = min(6.0, 0.85 / max(math.cos(el), 0.1))
        pad = int(math.ceil(4 * sx)) + 1
        strip = out[a:b]
        wrapped = np.concatenate([strip[:, -pad:], strip, strip[:, :pad]], axis=1)
        blurred = cv2.GaussianBlur(wrapped, (0, 0), sigmaX=sx, sigmaY=0.01)
        out[a:b] = blurred[:, pad:pad + PANO_WIDTH]
    return out


def render_panorama(world: World, light: Lighting, viewpoint_enu: Array) -> Panorama:
    """Render the world's equirectangular panorama from a standing point (eye height)."""
    viewpoint = np.asarray(viewpoint_enu, dtype=float)
    lin = np.zeros((PANO_HEIGHT, PANO_WIDTH, 3), np.float32)
    depth = np.full((PANO_HEIGHT, PANO_WIDTH), np.inf, np.float32)
    r0, r1 = _band_rows()
    lin[:r0] = light.sky_zenith_rgb
    lin[r1:] = world.ground_base_rgb * light.ambient_rgb
    _render_sky(light, world, lin)
    _render_ground(world, light, viewpoint, lin, depth)
    casters = [p for p in world.planes if p.kind != 'far']
    order = sorted(world.planes, key=lambda p: -float(np.linalg.norm(p.foot - viewpoint)))
    for plane in order:
        shadow = _facade_shadow(plane, casters, light) if plane.kind == 'building' else None
        rgba = _prefilter(_light_plane(plane, shadow, light), plane, viewpoint)
        _render_plane(plane, rgba, viewpoint, lin, depth)
    band = lin[PANO_HEIGHT // 2 - 500:PANO_HEIGHT // 2 + 400]
    mean_rad = float(np.mean(np.minimum(band, 4.0)))
    np.maximum(lin, 0.0, out=lin)
    enc = _antialias(np.power(lin, np.float32(1.0 / GAMMA), out=lin))
    sun_u, sun_v = direction_to_pano(light.sun_dir)
    sun_visible = bool(np.isinf(depth[int(sun_v) % PANO_HEIGHT, int(sun_u) % PANO_WIDTH]))
    logger.debug('panorama from %s: mean radiance %.3f, sun visible %s', viewpoint.round(2),
                 mean_rad, sun_visible)
    return Panorama(encoded=enc, depth_m=depth, viewpoint_enu=viewpoint, sun_visible=sun_visible,
                    mean_radiance=mean_rad)


# --------------------------------------------------------------------------------------------
# Camera frames


@dataclass(frozen=True)
class PinholeCamera:
    """An ideal pinhole camera (no distortion) in the camera_optical frame."""

    width: int = 320
    height: int = 240
    hfov_rad: float = math.radians(60.0)

    @property
    def fx(self) -> float:
        return self.width / 2 / math.tan(self.hfov_rad / 2)

    @property
    def cx(self) -> float:
        return (self.width - 1) / 2

    @property
    def cy(self) -> float:
        return (self.height - 1) / 2

    @property
    def K(self) -> Array:
        return np.array([[self.fx, 0, self.cx], [0, self.fx, self.cy], [0, 0, 1.0]])

    def rays(self) -> Array:
        """Unit rays (height*width, 3) of the pixel centres, in camera_optical."""
        u, v = np.meshgrid(np.arange(self.width), np.arange(self.height))
        r = np.stack([(u - self.cx) / self.fx, (v - self.cy) / self.fx, np.ones(u.shape)], -1)
        return (r / np.linalg.norm(r, axis=-1, keepdims=True)).reshape(-1, 3)


class FrameRenderer:
    """Camera frames from a panorama: exposure, white balance, glare, blur, noise, clipping.

    Per frame this costs a few milliseconds at 320 x 240: one ``cv2.remap`` per orientation
    sample, and sensor noise cut from a bank of pre-drawn noise (random offset per frame).
    """

    NOISE_BANK = 8
    NOISE_MARGIN = 32

    def __init__(self, pano: Panorama, light: Lighting, camera: PinholeCamera,
                 rng: np.random.Generator, noise_dn: float = 2.0) -> None:
        self.pano = pano
        self.camera = camera
        self.sun_dir = light.sun_dir
        self._rng = rng
        rays = camera.rays().astype(np.float32)
        self._rays = rays
        self._rx, self._ry, self._rz = (np.ascontiguousarray(rays[:, i]) for i in range(3))
        self._sun_visible = pano.sun_visible and light.sun_el_rad > 0
        m = self.NOISE_MARGIN
        self._noise = (rng.standard_normal(
            (self.NOISE_BANK, camera.height + m, camera.width + m, 3), dtype=np.float32)
            * np.float32(noise_dn))
        yy, xx = np.mgrid[0:camera.height, 0:camera.width]
        self._xx, self._yy = xx.astype(np.float32), yy.astype(np.float32)

    def _sample(self, R_enu_cam: Array) -> Image:
        """The panorama seen through the camera at one orientation (gamma-encoded, float)."""
        R = np.asarray(R_enu_cam, dtype=np.float32)
        dx = self._rx * R[0, 0] + self._ry * R[0, 1] + self._rz * R[0, 2]
        dy = self._rx * R[1, 0] + self._ry * R[1, 1] + self._rz * R[1, 2]
        dz = self._rx * R[2, 0] + self._ry * R[2, 1] + self._rz * R[2, 2]
        az = np.arctan2(dx, dy)
        az += np.float32(2 * math.pi) * (az < 0)
        u = az * np.float32(PANO_WIDTH / (2 * math.pi)) - np.float32(0.5)
        el = np.arcsin(np.clip(dz, -1.0, 1.0))
        v = (np.float32(math.pi / 2) - el) * np.float32(PANO_HEIGHT / math.pi) - np.float32(0.5)
        shape = (self.camera.height, self.camera.width)
        return cv2.remap(self.pano.encoded, u.reshape(shape), v.reshape(shape), cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_WRAP)

    def _glare(self, R_enu_cam: Array) -> Image | None:
        """Veiling glare and lens-flare ghosts when the visible sun is near the view (encoded)."""
        if not self._sun_visible:
            return None
        s_cam = (R_enu_cam.T @ self.sun_dir).astype(np.float32)
        off_axis = math.acos(max(-1.0, min(1.0, float(s_cam[2]))))
        if off_axis > math.radians(65):
            return None
        strength = math.exp(-off_axis / 0.35)
        cos_px = self._rx * s_cam[0] + self._ry * s_cam[1] + self._rz * s_cam[2]
        ang = np.arccos(np.clip(cos_px, -1, 1)).reshape(self.camera.height, self.camera.width)
        glare = np.float32(0.25 * strength) * np.exp(-ang / np.float32(0.25)) \
            + np.float32(0.05 * strength)
        out = glare[..., None] * np.array([1.0, 0.95, 0.85], np.float32)
        if s_cam[2] > 0.2:  # ghosts along the line from the sun's image through the centre
            ps = self.camera.K @ (s_cam / s_cam[2])
            c = np.array([self.camera.cx, self.camera.cy])
            tints = ([0.4, 0.9, 0.5], [0.9, 0.5, 0.9], [0.5, 0.7, 1.0])
            for k, (f, rad) in enumerate(((0.5, 14.0), (1.2, 24.0), (1.8, 9.0))):
                g = c + f * (c - ps[:2])
                r = np.hypot(self._xx - np.float32(g[0]), self._yy - np.float32(g[1]))
                blob = np.float32(0.12 * strength) * _smoothstep(rad, rad * 0.7, r)
                out += blob[..., None] * np.array(tints[k], np.float32)
        return out

    def render(self, R_enu_cam_samples: Array, gain: float, wb_rgb: Array) -> NDArray[np.uint8]:
        """An RGB8 frame; ``R_enu_cam_samples`` (n, 3, 3) spans the exposure (motion blur).

        ``gain`` multiplies linear radiance (so encoded values by ``gain ** (1/GAMMA)``).
        """
        acc = self._sample(R_enu_cam_samples[0])
        for R in R_enu_cam_samples[1:]:
            acc += self._sample(R)
        if len(R_enu_cam_samples) > 1:
            acc *= np.float32(1.0 / len(R_enu_cam_samples))
        glare = self._glare(R_enu_cam_samples[len(R_enu_cam_samples) // 2])
        if glare is not None:
            acc += glare
        scale = (gain ** (1.0 / GAMMA)) * 255.0 * np.asarray(wb_rgb, np.float64)
        acc *= scale.astype(np.float32)
        k = int(self._rng.integers(self.NOISE_BANK))
        oy, ox = (int(v) for v in self._rng.integers(0, self.NOISE_MARGIN, 2))
        h, w = self.camera.height, self.camera.width
        acc += self._noise[k, oy:oy + h, ox:ox + w]
        acc += np.float32(0.5)
        np.clip(acc, 0, 255, out=acc)
        return acc.astype(np.uint8)
