"""Sub-pixel marker corners from the Gaussian-blurred step-edge model (Caarls et al. 2009,
sec. 2.4, eq. 1 and Fig. 5: "locate edges, correct distortions, fit a line through each
segment, intersect 4 lines for corners").

Eq. 1 models an edge as a blurred step, I(x) = b + a (1/2 + 1/2 erf((x - x_edge) / (sqrt(2)
sigma_edge))). Its gradient magnitude is a Gaussian around x_edge, so the *logarithm* of the
gradient magnitude is a parabola and the vertex of the parabola through three samples is the
edge location exactly ("where usually the gradient magnitudes are used to find the location as
the top of a parabola, we use the logarithm of the gradients ... an unbiased estimate").
Gradients come from a Gaussian derivative filter of scale 1.0 px (the paper's "Gaussian
derivative operators with a scale of 1.0 px"); the three pixels are taken along the row or the
column, whichever is more perpendicular to the edge ("to increase processing speed we evaluate
three pixels along the horizontal or vertical direction").

The edge points of each side are then corrected for lens distortion (:mod:`.lens_model`), a
line is fitted to each side by total least squares (with one pass of outlier removal), and the
corners are the intersections of adjacent lines, in undistorted normalised coordinates (what the
pose needs) and re-distorted to pixels (what is drawn and compared).
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from .lens_model import LensModel

Array = NDArray[np.float64]


@functools.lru_cache(maxsize=8)
def _gaussian_kernels(sigma: float) -> tuple[Array, Array]:
    r = max(2, int(math.ceil(3.5 * sigma)))
    x = np.arange(-r, r + 1, dtype=np.float64)
    g = np.exp(-0.5 * (x / sigma) ** 2)
    g /= g.sum()
    dg = -x / (sigma * sigma) * g
    dg -= dg.mean() * 0  # keep antisymmetric (sums to zero by construction)
    return g.astype(np.float32), dg.astype(np.float32)


def gaussian_gradient(gray: NDArray, sigma: float = 1.0) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """(gx, gy) of an image with Gaussian derivative filters of scale ``sigma`` px."""
    g, dg = _gaussian_kernels(float(sigma))
    img = np.asarray(gray, dtype=np.float32)
    gx = cv2.sepFilter2D(img, cv2.CV_32F, dg[::-1].copy(), g, borderType=cv2.BORDER_REPLICATE)
    gy = cv2.sepFilter2D(img, cv2.CV_32F, g, dg[::-1].copy(), borderType=cv2.BORDER_REPLICATE)
    return np.asarray(gx, dtype=np.float32), np.asarray(gy, dtype=np.float32)


def log_parabola_offset(m_minus: Array, m0: Array, m_plus: Array) -> Array:
    """Vertex offset (in samples, within [-0.5, 0.5] for a true peak) of the parabola through
    the logarithms of three gradient magnitudes at -1, 0, +1 (sec. 2.4)."""
    lm, l0, lp = np.log(m_minus), np.log(m0), np.log(m_plus)
    den = lm - 2.0 * l0 + lp
    with np.errstate(divide='ignore', invalid='ignore'):
        off = np.where(den < -1e-12, 0.5 * (lm - lp) / den, 0.0)
    return np.clip(off, -0.5, 0.5)


@dataclass(frozen=True)
class RefinedQuad:
    """Refined corners (same order as the input quad) and fit diagnostics."""

    corners_px: Array        # (4, 2) pixels (distorted image)
    corners_norm: Array      # (4, 2) normalised undistorted coordinates
    edge_points: int         # points used in the four line fits
    line_rms_px: float       # RMS distance of the edge points from their lines, px
    #: per side (side i runs from corner i to corner i+1): edge blur (the eq. 1 sigma, px,
    #: from the curvature of the log-gradient: the derivative filter's own scale removed),
    #: the share of the side that gave edge points (an occluded side gives few), and the RMS
    #: distance of its points from its line, px
    side_blur_px: Array = field(default_factory=lambda: np.zeros(4))
    side_coverage: Array = field(default_factory=lambda: np.ones(4))
    side_rms_px: Array = field(default_factory=lambda: np.zeros(4))


def edge_points_along_side(gx: NDArray[np.floating], gy: NDArray[np.floating], mag: NDArray[np.floating], a: Array, b: Array,
                           margin_px: float = 3.0, search_px: int = 2) -> Array:
    """Sub-pixel edge points (N, 3: x, y, profile width along the scan in px) along the side
    a->b of a quad (pixel coordinates in the arrays' frame): for every row (or column) the side
    crosses, the gradient maximum within ``search_px`` of the side, refined by the
    log-parabola."""
    d = b - a
    length = float(np.hypot(*d))
    if length < 2 * margin_px + 2:
        return np.zeros((0, 3))
    # The marker's black border is inside a white quiet zone and the quad runs clockwise in the
    # image: the gradient of a true edge point points outward, along (d_y, -d_x). Maxima whose
    # gradient points elsewhere (an occluder's edge, the border's inner edge) are not this side.
    n_out = np.array([d[1], -d[0]]) / length
    along = gx * np.float32(n_out[0]) + gy * np.float32(n_out[1])
    if abs(d[1]) >= abs(d[0]):  # the edge is closer to vertical: scan along x, row by row
        return _scan_rows(mag, a, b, length, margin_px, search_px, along)
    # Closer to horizontal: the same scan on the transposed image, column by column.
    r = _scan_rows(mag.T, a[::-1], b[::-1], length, margin_px, search_px, along.T)
    return np.concatenate([r[:, 1::-1], r[:, 2:]], axis=1)


#: cos of the largest angle between an edge point's gradient and the side's outward normal.
MIN_GRADIENT_ALIGNMENT = 0.8


def _scan_rows(mag: NDArray[np.floating], a: Array, b: Array, length: float, margin_px: float, search_px: int,
               along: Array | None = None) -> Array:
    """Edge points (x, y) of the side a->b, one per image row it crosses (see above)."""
    h, w = mag.shape
    d = b - a
    lo, hi = sorted((a[1], b[1]))
    cut = margin_px * (hi - lo) / length
    rows = np.arange(math.ceil(lo + cut), math.floor(hi - cut) + 1)
    if len(rows) == 0:
        return np.zeros((0, 3))
    centre = np.rint(a[0] + (rows - a[1]) * d[0] / d[1]).astype(int)
    xs = centre[:, None] + np.arange(-search_px, search_px + 1)[None, :]
    ok = (xs.min(1) >= 1) & (xs.max(1) <= w - 2) & (rows >= 0) & (rows < h)
    rows, xs = rows[ok], xs[ok]
    x0 = xs[np.arange(len(xs)), np.argmax(mag[rows[:, None], xs], axis=1)]
    m0 = mag[rows, x0]
    mm, mp = mag[rows, x0 - 1], mag[rows, x0 + 1]
    peak = (m0 >= mm) & (m0 >= mp) & (mm > 0) & (mp > 0)
    if along is not None:
        peak &= along[rows, x0] >= MIN_GRADIENT_ALIGNMENT * m0
    lm, l0, lp = np.log(np.maximum(mm, 1e-6)), np.log(np.maximum(m0, 1e-6)), np.log(np.maximum(mp, 1e-6))
    off = log_parabola_offset(np.maximum(mm, 1e-6), np.maximum(m0, 1e-6), np.maximum(mp, 1e-6))
    # The log of a Gaussian of scale w has second difference -1/w^2: the profile's width along the scan.
    curv = lm - 2 * l0 + lp
    with np.errstate(divide='ignore', invalid='ignore'):
        width = np.where(curv < -1e-9, np.sqrt(-1.0 / curv), np.inf)
    pts = np.stack([x0 + off, rows.astype(float), width], -1)[peak]
    m_used = m0[peak]
    if len(pts) == 0:
        return np.zeros((0, 3))
    # Weak maxima are noise or another edge: keep points with at least half the median strength.
    return pts[m_used >= 0.5 * np.median(m_used)]


#: Sides blurred beyond this (eq. 1 sigma, px) are located at their half level, not at the
#: gradient peak (:func:`relocate_blurred_side`).
MEDIAN_EDGE_BLUR_PX = 1.6


def plate_levels(lin: Array, a: Array, b: Array, cell_px: float, margin_px: float = 3.0) -> tuple[float, float] | None:
    """(white, black) light levels beside a *sharp* side a->b: the median of the image half a
    code cell outside the side (the white quiet zone) and half a cell inside it (the middle of
    the black border strip, which runs along the whole side). None when out of the image."""
    d = b - a
    length = float(np.hypot(*d))
    if length < 2 * margin_px + 2:
        return None
    n_out = np.array([d[1], -d[0]]) / length
    s = np.linspace(margin_px + 0.5 * cell_px, length - margin_px - 0.5 * cell_px, max(int(length / 2), 3)) / length
    base = a[None, :] + s[:, None] * d[None, :]
    h, w = lin.shape
    out = []
    for sign in (1.0, -1.0):
        pts = base + sign * 0.5 * cell_px * n_out[None, :]
        if np.any(pts < 0) or np.any(pts[:, 0] > w - 1) or np.any(pts[:, 1] > h - 1):
            return None
        v = cv2.remap(np.asarray(lin, np.float32), pts[:, 0].astype(np.float32).reshape(-1, 1),
                      pts[:, 1].astype(np.float32).reshape(-1, 1), cv2.INTER_LINEAR)
        out.append(float(np.median(v)))
    white, black = out
    return (white, black) if white > black else None


def relocate_blurred_side(lin: Array, a: Array, b: Array, points: Array, level: float,
                          reach_px: float) -> Array:
    """Edge points of a motion-blurred side where the image (in light) crosses ``level`` - the
    mean of the plate's white and black (:func:`plate_levels`, from the sides the motion left
    sharp) - instead of at the gradient peak.

    Why: during the exposure a moving edge sweeps its blur; the light at x is the share of the
    exposure the edge spent on either side of x, so the half level is crossed exactly where the
    edge was at mid-exposure - the image stamp and what the pose must give - whatever the speed
    profile. The gradient peak is where the edge *lingered*: at the slow end of a decelerating
    pan, up to about half the blur length off (0.5-1 px at the end of this repository's quick
    pans). The half level at that point is also the only one the neighbours leave alone: the
    quiet zone's outer edge and the border's inner edge (to the code bits) are a code cell away
    and, while the blur is shorter than two cells, never sweep over it; so the search runs
    from the outside inward over +-``reach_px`` (about a cell) and takes the first crossing.
    Points without a crossing keep their peak position.
    """
    if len(points) == 0:
        return points
    d = b - a
    rows_scan = abs(d[1]) >= abs(d[0])
    img = np.asarray(lin) if rows_scan else np.asarray(lin).T
    pts = points[:, :2] if rows_scan else points[:, 1::-1]
    n_out = np.array([d[1], -d[0]])
    outward = np.sign(n_out[0] if rows_scan else n_out[1]) or 1.0
    h, w = img.shape
    reach = int(max(2, math.floor(reach_px)))
    rows = np.rint(pts[:, 1]).astype(int)
    centre = np.rint(pts[:, 0]).astype(int)
    ok = (rows >= 0) & (rows < h) & (centre - reach >= 0) & (centre + reach < w)
    out = pts.copy()
    idx = np.flatnonzero(ok)
    if len(idx):
        # samples ordered from the outside (white) inward (black)
        offs = outward * np.arange(reach, -reach - 1, -1)
        cols = centre[idx, None] + offs[None, :].astype(int)
        v = img[rows[idx, None], cols].astype(np.float64)
        below = v < level
        k = np.argmax(below, axis=1)                       # first sample below the half level
        found = below[np.arange(len(k)), k] & (k > 0)
        kk = np.maximum(k, 1)
        v0, v1 = v[np.arange(len(k)), kk - 1], v[np.arange(len(k)), kk]
        with np.errstate(divide='ignore', invalid='ignore'):
            f = np.clip((v0 - level) / (v0 - v1), 0.0, 1.0)
        pos = centre[idx] + outward * (reach - (kk - 1) - f)
        good = found & np.isfinite(pos)
        out[idx[good], 0] = pos[good]
    res = points.copy()
    res[:, :2] = out if rows_scan else out[:, ::-1]
    return res


def fit_line(points: Array) -> tuple[Array, Array, Array]:
    """Total-least-squares line through points: (centroid, unit direction, residuals)."""
    c = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - c, full_matrices=False)
    direction = vt[0]
    normal = np.array([-direction[1], direction[0]])
    return c, direction, (points - c) @ normal


def robust_line(points: Array) -> tuple[Array, Array, Array] | None:
    """:func:`fit_line` with one pass of outlier removal (residuals beyond 3.5 robust sigmas)."""
    if len(points) < 3:
        return None
    c, d, r = fit_line(points)
    mad = 1.4826 * np.median(np.abs(r - np.median(r)))
    keep = np.abs(r) <= max(3.5 * mad, 1e-9)
    if keep.sum() >= 3 and keep.sum() < len(points):
        c, d, r = fit_line(points[keep])
    return c, d, r


def intersect(c1: Array, d1: Array, c2: Array, d2: Array) -> Array | None:
    A = np.array([[d1[0], -d2[0]], [d1[1], -d2[1]]])
    det = np.linalg.det(A)
    if abs(det) < 1e-9:
        return None
    t = np.linalg.solve(A, c2 - c1)
    return c1 + t[0] * d1


def refine_quad(gray: NDArray, quad_px: Array, lens: LensModel, sigma: float = 1.0,
                margin_px: float = 3.0, search_px: int = 2, max_shift_px: float = 3.0,
                median_blur_px: float = MEDIAN_EDGE_BLUR_PX) -> RefinedQuad | None:
    """Refine the 4 corners of a detected quad (Fig. 5 pipeline); None when a side gives too
    few edge points (occluded, out of the image, too small) or the lines do not intersect.
    ``gray`` should be linear in light (:func:`.photometry.linearize`): eq. 1 is a model of
    light, not of gamma-encoded values. Sides blurred beyond ``median_blur_px`` (0: never)
    are located at their half-crossing (:func:`relocate_blurred_side`)."""
    quad_px = np.asarray(quad_px, dtype=np.float64).reshape(4, 2)
    h, w = gray.shape[:2]
    pad = int(math.ceil(3.5 * sigma)) + search_px + 3
    x0 = max(int(math.floor(quad_px[:, 0].min())) - pad, 0)
    y0 = max(int(math.floor(quad_px[:, 1].min())) - pad, 0)
    x1 = min(int(math.ceil(quad_px[:, 0].max())) + pad + 1, w)
    y1 = min(int(math.ceil(quad_px[:, 1].max())) + pad + 1, h)
    if x1 - x0 < 8 or y1 - y0 < 8:
        return None
    gx, gy = gaussian_gradient(gray[y0:y1, x0:x1], sigma)
    mag = np.sqrt(gx * gx + gy * gy)
    origin = np.array([x0, y0], dtype=np.float64)
    local = quad_px - origin
    lines = []
    used = 0
    residuals = []
    focal = lens.focal_px
    blur = np.zeros(4)
    coverage = np.ones(4)
    side_rms = np.zeros(4)
    sides = []
    for i in range(4):
        a, b = local[i], local[(i + 1) % 4]
        found = edge_points_along_side(gx, gy, mag, a, b, margin_px, search_px)
        if len(found) < 4:
            return None
        side = b - a
        length = float(np.hypot(*side))
        # Width along the scan -> across the edge; minus the derivative filter's own scale.
        cos_scan = max(abs(side[1]), abs(side[0])) / max(length, 1e-9)
        w = found[:, 2] * cos_scan
        w = w[np.isfinite(w)]
        blur[i] = math.sqrt(max(float(np.median(w)) ** 2 - sigma * sigma, 0.0)) if len(w) else float('inf')
        coverage[i] = min(1.0, len(found) / max(max(abs(side[0]), abs(side[1])) - 2 * margin_px, 1.0))
        sides.append(found)
    blurred = [i for i in range(4) if median_blur_px > 0 and blur[i] > median_blur_px]
    sharp = [i for i in range(4) if blur[i] <= median_blur_px]
    if blurred and sharp:
        # The plate's white and black from the sides the motion left sharp (a 36h11 tag is 8
        # code cells across), then each blurred side at the half level between them.
        cell = float(np.mean([np.hypot(*(local[(i + 1) % 4] - local[i])) for i in range(4)])) / 8.0
        levels = [plate_levels(gray[y0:y1, x0:x1], local[i], local[(i + 1) % 4], cell, margin_px) for i in sharp]
        levels = [lv for lv in levels if lv is not None]
        if levels:
            white, black = np.median(np.array(levels), axis=0)
            for i in blurred:
                sides[i] = relocate_blurred_side(gray[y0:y1, x0:x1], local[i], local[(i + 1) % 4], sides[i],
                                                 0.5 * (white + black), 0.9 * cell)
    for i in range(4):
        pts = sides[i][:, :2]
        norm = lens.undistort(pts + origin)
        fit = robust_line(norm)
        if fit is None:
            return None
        c, d, r = fit
        lines.append((c, d))
        used += len(pts)
        residuals.append(r * focal)
        side_rms[i] = float(np.sqrt(np.mean((r * focal) ** 2)))
    corners_norm = []
    for i in range(4):
        c1, d1 = lines[(i - 1) % 4]
        c2, d2 = lines[i]
        p = intersect(c1, d1, c2, d2)
        if p is None:
            return None
        corners_norm.append(p)
    corners_norm_arr = np.array(corners_norm)
    corners_px = lens.distort(corners_norm_arr)
    if not np.all(np.isfinite(corners_px)) or np.abs(corners_px - quad_px).max() > max_shift_px:
        return None
    rms = float(np.sqrt(np.mean(np.concatenate(residuals) ** 2)))
    return RefinedQuad(corners_px, corners_norm_arr, used, rms, blur, coverage, side_rms)
