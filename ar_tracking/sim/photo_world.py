"""A real photo sequence as the world of ``rotation_sweep``: the other renderer.

The street of :mod:`.layout` is textures this project drew; a tracker tuned on it may lean on
what those textures have (crisp edges everywhere, no empty walls, no repeated shelves). Here the
world is a real scene instead: the photos of a camera turned a full circle about its centre
(e.g. ../shared/data/pano_grail, an office, and pano_parrington, a lawn with bare trees), laid
into the simulator's equirectangular :class:`.model.Panorama`, from which the camera frames are
then cut exactly as from the rendered street (motion blur, rolling shutter, noise, exposure,
vignetting). The sensors, the motion and the ground truth are unchanged: the truth is the
rotation the frames were cut at, whatever the panorama shows.

How the photos are laid: photo ``i`` is a pinhole view at azimuth ``i * 360 / n`` (the
sequences were shot in equal steps, SOURCE.md) plus a correction measured between neighbours by
phase correlation of their overlap, and the loop's residual is shared over the steps (a turn is
360 degrees). Each map pixel takes the photos that see it, weighted toward their centres, so
that exposure steps between photos fade instead of standing as edges. Photos cover only a band
of elevations (about +-20 degrees for these); above and below, each column fades from its
edge's colour, smoothed along the horizon, into the band's mean: the featureless ceiling, sky
and floor a phone also sees when pitched up or down.

Only the layout is approximate: a seam a pixel or two off is part of this world's texture, the
same in every frame, so it costs the truth nothing.
"""
from __future__ import annotations

import functools
import math
import re
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from ..core.rotations import align_directions
from .model import GAMMA, PANO_HEIGHT, PANO_MAX_ABS_EL, PANO_WIDTH, Panorama, pano_directions
from .scenario import SimError

Array = NDArray[np.float64]

#: The photo files read; their 8-bit values (sRGB-like, display-encoded) are the map's encoded
#: radiance as they are.
PHOTO_SUFFIXES = ('.jpg', '.jpeg', '.png')
#: Elevations the fade above and below the photos spans, radians.
FADE_RAD = math.radians(10.0)
#: Width of the horizontal smoothing of the band's edge rows before the fade, map pixels.
EDGE_SMOOTH_PX = 61


class PhotoWorldError(SimError):
    """The photo folder cannot be made into a world (missing photos, no focal length)."""


def read_sequence(folder: str | Path) -> tuple[list[NDArray[np.uint8]], list[float]]:
    """The photos of ``folder`` in name order (RGB) and their focal lengths in pixels.

    The focal lengths come from ``pano.txt`` (lines ``<path> <focal px>``, the format of the
    pano_grail / pano_parrington sequences), matched by file name; photos it does not name get
    the median of the others."""
    folder = Path(folder)
    if not folder.is_dir():
        raise PhotoWorldError(f'{folder}: not a folder')
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in PHOTO_SUFFIXES)
    if len(files) < 3:
        raise PhotoWorldError(f'{folder}: {len(files)} photos, a turn needs at least 3')
    focal: dict[str, float] = {}
    listing = folder / 'pano.txt'
    if listing.exists():
        for line in listing.read_text(encoding='utf-8', errors='replace').splitlines():
            parts = line.strip().rsplit(maxsplit=1)
            if len(parts) == 2:
                try:
                    focal[re.split(r'[\\/]', parts[0])[-1].lower()] = float(parts[1])
                except ValueError:
                    continue
    if not focal:
        raise PhotoWorldError(f'{folder}: no focal lengths (pano.txt with "<photo> <focal px>" lines)')
    default = float(np.median(list(focal.values())))
    photos, focals = [], []
    for path in files:
        bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if bgr is None:
            raise PhotoWorldError(f'{path}: not a readable image')
        photos.append(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
        focals.append(focal.get(path.name.lower(), default))
    return photos, focals


class _Layer:
    """One photo's footprint on the map band: where it lands (u, v maps) and its weight."""

    def __init__(self, photo: NDArray[np.uint8], focal: float) -> None:
        self.photo = photo.astype(np.float32) / np.float32(255.0)
        self.focal = focal
        h, w = photo.shape[:2]
        self.cx, self.cy = (w - 1) / 2, (h - 1) / 2
        self.K = np.array([[focal, 0.0, self.cx], [0.0, focal, self.cy], [0.0, 0.0, 1.0]])

    def project(self, dirs_cam: Array) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float32]]:
        """(map of photo x, map of photo y, weight) for camera-frame directions (H, W, 3)."""
        z = dirs_cam[..., 2]
        with np.errstate(divide='ignore', invalid='ignore'):
            x = self.focal * dirs_cam[..., 0] / z + self.cx
            y = self.focal * dirs_cam[..., 1] / z + self.cy
        h, w = self.photo.shape[:2]
        inside = (z > 0.1) & (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
        # Weight: 1 at the centre, 0 at the nearest edge (a feathered blend between photos).
        wx = 1.0 - np.abs(x - self.cx) / (self.cx + 1.0)
        wy = 1.0 - np.abs(y - self.cy) / (self.cy + 1.0)
        weight = np.where(inside, np.clip(wx, 0, 1) * np.clip(wy, 0, 1) ** 0.25, 0.0)
        x = np.where(inside, x, -1.0)
        y = np.where(inside, y, -1.0)
        return x.astype(np.float32), y.astype(np.float32), weight.astype(np.float32)


def _pair_rotation(a: _Layer, b: _Layer) -> Array | None:
    """Rotation of photo b's camera frame into photo a's (vectors), or None: SIFT matches between
    them, the inliers of a RANSAC homography (H = K_a R K_b^-1 for a camera turned about its
    centre), and the rotation of their rays (not H's nearest rotation: H's other degrees of
    freedom soak up noise that then tilts it, 0.1 deg per pair against 0.02)."""
    sift = cv2.SIFT_create(nfeatures=2000)
    feats = []
    for layer in (a, b):
        grey = cv2.cvtColor((layer.photo * 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)
        feats.append(sift.detectAndCompute(grey, None))
    (ka, da), (kb, db) = feats
    if da is None or db is None or len(ka) < 8 or len(kb) < 8:
        return None
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(db, da, k=2)
    good = [m[0] for m in pairs if len(m) == 2 and m[0].distance < 0.75 * m[1].distance]
    if len(good) < 12:
        return None
    pb = np.float32([kb[m.queryIdx].pt for m in good])
    pa = np.float32([ka[m.trainIdx].pt for m in good])
    H, inliers = cv2.findHomography(pb, pa, cv2.RANSAC, 3.0)
    if H is None or int(inliers.sum()) < 12:
        return None
    keep = inliers.ravel().astype(bool)
    ra, rb = (_rays(layer, pts[keep]) for layer, pts in ((a, pa), (b, pb)))
    # The rotation of the inlier rays (orthogonal Procrustes / Kabsch), then once more without
    # the rays it leaves more than 3 sigma off.
    R = align_directions(rb, ra)
    res = np.linalg.norm(ra - rb @ R.T, axis=1)
    ok = res < 3.0 * max(float(np.sqrt(np.mean(res ** 2))), 1e-9)
    return align_directions(rb[ok], ra[ok]) if ok.sum() >= 12 else R


def _rays(layer: _Layer, pts: NDArray[np.float32]) -> Array:
    """Unit camera-frame rays of pixel positions (n, 2)."""
    xy1 = np.column_stack([(pts[:, 0] - layer.cx) / layer.focal, (pts[:, 1] - layer.cy) / layer.focal,
                           np.ones(len(pts))])
    return xy1 / np.linalg.norm(xy1, axis=1, keepdims=True)


def photo_rotations(photos: list[NDArray[np.uint8]], focals: list[float]) -> list[Array]:
    """camera_optical -> ENU of every photo of a turn (RGB, focal length in px): neighbours'
    rotations chained around the turn, the loop's residual shared over it, and the turn's axis
    made vertical (the photos were taken turning about the vertical); the first photo looks
    north. A pair that does not match takes the nominal step of one n-th of a turn."""
    return _camera_rotations([_Layer(p, f) for p, f in zip(photos, focals, strict=True)])


def _camera_rotations(layers: list[_Layer]) -> list[Array]:
    n = len(layers)
    steps = [_pair_rotation(layers[i], layers[(i + 1) % n]) for i in range(n)]
    found = [R for R in steps if R is not None]
    if not found:
        raise PhotoWorldError('no two neighbouring photos share enough features to be laid together')
    # The nominal step (one n-th of the turn about the camera's vertical, in the measured sense).
    turn = np.mean([Rotation.from_matrix(R).as_rotvec()[1] for R in found])
    nominal = Rotation.from_rotvec([0.0, math.copysign(2 * math.pi / n, turn), 0.0]).as_matrix()
    steps = [nominal if R is None else R for R in steps]
    chain = [np.eye(3)]
    for R in steps[:-1]:
        chain.append(chain[-1] @ R)
    loop = Rotation.from_matrix(chain[-1] @ steps[-1]).as_rotvec()  # identity for a closed loop
    chain = [Rotation.from_rotvec(-loop * i / n).as_matrix() @ C for i, C in enumerate(chain)]
    # The turn's axis: normal of the plane the optical axes sweep (first photo's frame).
    axes = np.array([C[:, 2] for C in chain])
    up = np.linalg.eigh(axes.T @ axes)[1][:, 0]
    if up @ np.array([0.0, -1.0, 0.0]) < 0:  # camera y points down: up is mostly -y
        up = -up
    # Level frame: the first photo's optical axis, made horizontal, is north.
    fwd = chain[0][:, 2] - (chain[0][:, 2] @ up) * up
    fwd /= np.linalg.norm(fwd)
    east = np.cross(fwd, up)
    level_from_first = np.stack([east, fwd, up])  # first-photo vectors -> ENU
    return [level_from_first @ C for C in chain]


def _fill_outside(encoded: NDArray[np.float32], covered: NDArray[np.bool_]) -> None:
    """Above and below the photos: each column fades from its (smoothed) edge colour into the
    band's mean over :data:`FADE_RAD` and stays there (in place)."""
    mean = encoded[covered].mean(axis=0)
    rows_per_rad = PANO_HEIGHT / math.pi
    fade_rows = max(1, int(FADE_RAD * rows_per_rad))
    # The first and last fully covered rows of each column, smoothed along the horizon.
    first = np.argmax(covered, axis=0)
    last = covered.shape[0] - 1 - np.argmax(covered[::-1], axis=0)
    cols = np.arange(covered.shape[1])
    for edge, direction in ((first, -1), (last, +1)):
        colour = encoded[np.clip(edge + 2 * -direction, 0, covered.shape[0] - 1), cols].reshape(1, -1, 3)
        pad = EDGE_SMOOTH_PX
        wrapped = np.concatenate([colour[:, -pad:], colour, colour[:, :pad]], axis=1)
        colour = cv2.GaussianBlur(wrapped, (EDGE_SMOOTH_PX, 1), 0)[0, pad:-pad]
        span = range(int(edge.max()), -1, -1) if direction < 0 else range(int(edge.min()), covered.shape[0])
        for r in span:
            beyond = (edge - r) * -direction  # rows past the column's edge (> 0 outside)
            out = beyond > 0
            if not out.any():
                continue
            a = np.clip(beyond[out] / fade_rows, 0.0, 1.0)[:, None].astype(np.float32)
            encoded[r, out] = (1 - a) * colour[out] + a * mean


def photo_panorama(folder: str | Path, first_azimuth_deg: float = 0.0) -> Panorama:
    """The equirectangular world of a full-turn photo sequence (see the module docstring), its
    first photo's centre at compass azimuth ``first_azimuth_deg`` (to the map's column, 0.09
    deg). Raises :class:`PhotoWorldError` for a folder that is no such sequence."""
    laid = _laid_out(str(folder))
    shift = int(round(first_azimuth_deg / 360.0 * PANO_WIDTH)) % PANO_WIDTH
    return replace(laid, encoded=np.roll(laid.encoded, shift, axis=1))


@functools.lru_cache(maxsize=2)
def _laid_out(folder: str) -> Panorama:
    """The photos laid into the map, the first one's centre at azimuth 0 (cached: ~7 s)."""
    photos, focals = read_sequence(folder)
    max_el = PANO_MAX_ABS_EL
    r0 = int(math.floor((math.pi / 2 - max_el) * PANO_HEIGHT / math.pi))
    rows = np.arange(r0, PANO_HEIGHT - r0)
    dirs = pano_directions(rows, np.arange(PANO_WIDTH))
    layers = [_Layer(p, f) for p, f in zip(photos, focals, strict=True)]
    rotations = _camera_rotations(layers)
    acc = np.zeros((len(rows), PANO_WIDTH, 3), np.float32)
    wsum = np.zeros((len(rows), PANO_WIDTH), np.float32)
    for layer, R in zip(layers, rotations, strict=True):
        x, y, w = layer.project(dirs @ R)
        img = cv2.remap(layer.photo, x, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        acc += img * w[..., None]
        wsum += w
    encoded = np.zeros((PANO_HEIGHT, PANO_WIDTH, 3), np.float32)
    covered = np.zeros((PANO_HEIGHT, PANO_WIDTH), bool)
    band = wsum > 1e-3
    encoded[rows] = np.where(band[..., None], acc / np.maximum(wsum, 1e-6)[..., None], 0.0)
    covered[rows] = band
    if not covered.any():
        raise PhotoWorldError(f'{folder}: the photos cover no part of the map')
    _fill_outside(encoded, covered)
    linear = encoded[rows] ** GAMMA
    return Panorama(encoded=encoded, depth_m=np.full((PANO_HEIGHT, PANO_WIDTH), np.inf, np.float32),
                    viewpoint_enu=np.zeros(3), sun_visible=False, mean_radiance=float(linear.mean()))
