"""The data model of the two simulated scenes, and the constants that define them.

Street scene (rotation_sweep, Langlotz et al. 2011): the world a person standing at one spot sees
all around, as textured vertical planes in ENU (x east, y north, z up; the origin is the
authoring spot at eye height, the ground is the plane ``z = -EYE_HEIGHT_M``); the lighting of a
session; the equirectangular panorama rendered from a standing point; and the visibility queries
used to place annotation anchors and the sun.

Equirectangular convention: column ``u`` covers compass azimuth ``az = 2*pi*u/W`` (clockwise from
north, so turning right moves right in the map), row ``v`` covers elevation ``el = pi/2 - pi*v/H``.

Desk scene (handheld_desk, Klein & Murray 2009): textured rectangles (faces) of a desk, boxes on
it, a wall and a floor, in a ``world`` frame with z up and the desk top at z = 0, and their
mip-mapped texture atlas.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from numpy.typing import NDArray

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
# Street scene (rotation_sweep): data


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


def clear_view(world: World, plane: Plane, point: Array, margin_m: float = 0.6,
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
    return bool(np.all(visible(world, q, v)))


def visible_from(world: World, point: Array, viewpoint: Array) -> bool:
    """Whether nothing opaque lies between the viewpoint and a world point."""
    return bool(visible(world, point[None], viewpoint[None])[0])


def visible(world: World, points: Array, viewpoints: Array) -> NDArray[np.bool_]:
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
# Desk scene (handheld_desk): data



DESK_SIZE_M = (1.2, 0.8)
DESK_THICKNESS_M = 0.03
WALL_Y_M = 0.42
FLOOR_Z_M = -0.74
BACKGROUND = 80.0
#: Texture resolution of the desk and the boxes (texels per metre): 0.5 mm texels.
DESK_DENSITY = 2000.0
MIP_LEVELS = 4
ATLAS_GUTTER = 24


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
        return replace(self, atlas=mip_pyramid(level0))


def mip_pyramid(level0: NDArray[np.uint8]) -> tuple[NDArray[np.uint8], ...]:
    levels = [level0]
    for _ in range(MIP_LEVELS - 1):
        levels.append(cv2.pyrDown(levels[-1]))
    return tuple(levels)
