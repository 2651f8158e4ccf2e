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
    return gx, gy


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


def edge_points_along_side(gx: Array, gy: Array, mag: Array, a: Array, b: Array,
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


def _scan_rows(mag: Array, a: Array, b: Array, length: float, margin_px: float, search_px: int,
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
                margin_px: float = 3.0, search_px: int = 2, max_shift_px: float = 3.0) -> RefinedQuad | None:
    """Refine the 4 corners of a detected quad (Fig. 5 pipeline); None when a side gives too
    few edge points (occluded, out of the image, too small) or the lines do not intersect.
    ``gray`` should be linear in light (:func:`.photometry.linearize`): eq. 1 is a model of
    light, not of gamma-encoded values."""
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
    for i in range(4):
        a, b = local[i], local[(i + 1) % 4]
        found = edge_points_along_side(gx, gy, mag, a, b, margin_px, search_px)
        if len(found) < 4:
            return None
        pts = found[:, :2]
        side = b - a
        length = float(np.hypot(*side))
        # Width along the scan -> across the edge; minus the derivative filter's own scale.
        cos_scan = max(abs(side[1]), abs(side[0])) / max(length, 1e-9)
        w = found[:, 2] * cos_scan
        w = w[np.isfinite(w)]
        blur[i] = math.sqrt(max(float(np.median(w)) ** 2 - sigma * sigma, 0.0)) if len(w) else float('inf')
        coverage[i] = min(1.0, len(pts) / max(max(abs(side[0]), abs(side[1])) - 2 * margin_px, 1.0))
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
