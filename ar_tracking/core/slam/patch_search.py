"""Warped-template patch search (Klein & Murray 2009, sec. 4), vectorised over all points.

Every map point is searched at a *fixed* search level (L1; L2 when the rotation prior predicts
fast rotation) by exhaustive evaluation of a radius-4 circle with the zero-mean SSD (ZSSD) of an
8x8 template; the template comes from the point's *source keyframe* at the source level whose
scale matches the search level (sec. 4, after Wuest et al.: fix the search level, vary the source
level - possible because every map point is a corner in L0, L1 and L2, sec. 3.1). The template is
warped by the affine map of a fronto-parallel patch (plane through the point, normal to the source
ray) under the relative pose, sampled bilinearly (``cv2.remap``, one call per source image).

A match is accepted when the best ZSSD per pixel is under a threshold, and then refined to
sub-pixel accuracy by 2-DoF ESM (Benhimane & Malis) on the search level: a few Gauss-Newton steps
whose Jacobian averages the template and image gradients, image and template zero-meaned. The
measurement is reported in level-0 pixels with its level (sigma = 2**level level-0 pixels).

Everything is vectorised over the points (no per-point Python or OpenCV calls): templates are one
``cv2.remap`` per (source keyframe, source level); the ZSSD of all windows is one batched matmul
over the rows of the windows (row im2col) plus one integral image of all windows stacked; ESM is
one ``cv2.remap`` per iteration. Cost (80 points, 640x480, one core): templates ~0.3 ms, search
~0.6 ms, ESM ~0.5 ms.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Mapping, Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from ..box_sums import window_box_sums
from .camera import Camera, level0_to_level, level_to_level0

log = logging.getLogger(__name__)

Array = NDArray[np.float64]
Image = NDArray[np.uint8]

PATCH = 8  #: template size (sec. 4: 8x8)
MARGIN = 1  #: extra template border for the ESM gradients


@dataclass(frozen=True)
class SearchConfig:
    """Patch-search parameters (sec. 4)."""

    radius: float = 4.0  #: search circle radius, search-level pixels
    max_zssd_per_px: float = 500.0  #: acceptance: best ZSSD / 64 (grey levels^2)
    max_zssd_per_px_coarse: float = 900.0  #: looser threshold for the L2 (fast rotation) search
    #: ... and at most this fraction of the template's own energy sum(T - mean T)^2 (a match must
    #: explain the template; also rejects flat image regions for low-contrast templates)
    max_zssd_fraction: float = 0.6
    max_zssd_fraction_coarse: float = 0.8
    min_template_var: float = 40.0  #: templates flatter than this (grey^2 per px) are not searched
    esm_iterations: int = 3
    max_esm_shift: float = 1.0  #: ESM may move the integer match at most this far


@dataclass
class SearchResult:
    """Per searched point: found flag, level-0 position, level, best ZSSD per pixel."""

    found: NDArray[np.bool_]
    uv0: Array
    level: int
    zssd: Array


def affine_from_poses(X_w: Array, camera: Camera, R_c_w: Array, t_c_w: Array,
                      R_s_w: Array, t_s_w: Array) -> Array:
    """``A`` (N, 2, 2) = d(source level-0 pixel) / d(current level-0 pixel) at each point.

    The patch is the plane through ``X_w`` normal to the source keyframe's viewing ray (sec. 4);
    ``R_s_w`` (N, 3, 3), ``t_s_w`` (N, 3) are each point's source keyframe pose. Computed by
    unit pixel steps in the current image, intersected with the patch plane and projected into the
    source keyframe.
    """
    X_w = np.asarray(X_w, float).reshape(-1, 3)
    n = len(X_w)
    if n == 0:
        return np.zeros((0, 2, 2))
    C_cur = -R_c_w.T @ t_c_w
    C_src = -np.einsum('nji,nj->ni', R_s_w, t_s_w)
    nrm = X_w - C_src
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    uv, _ = camera.project(X_w @ R_c_w.T + t_c_w)
    K = camera.K

    def src_px(Y: Array) -> Array:
        Yc = np.einsum('nij,nj->ni', R_s_w, Y) + t_s_w
        z = np.where(Yc[:, 2] > 1e-9, Yc[:, 2], 1e-9)
        return np.column_stack([K[0, 0] * Yc[:, 0] / z + K[0, 2], K[1, 1] * Yc[:, 1] / z + K[1, 2]])

    base = src_px(X_w)
    A = np.zeros((n, 2, 2))
    num = np.einsum('ni,ni->n', nrm, X_w - C_cur)
    for k in range(2):
        uvk = uv.copy()
        uvk[:, k] += 1.0
        d_c = camera.unproject(uvk)
        d_w = d_c @ R_c_w  # rows: R_c_w.T @ d
        den = np.einsum('ni,ni->n', nrm, d_w)
        den = np.where(np.abs(den) > 1e-12, den, 1e-12)
        Y = C_cur + (num / den)[:, None] * d_w
        A[:, :, k] = src_px(Y) - base
    return A


def choose_source_level(A: Array, search_level: int, n_levels: int) -> NDArray[np.int64]:
    """Source level whose pixel scale matches one search-level pixel: round(log2(2^L sqrt|det A|))."""
    det = np.abs(A[:, 0, 0] * A[:, 1, 1] - A[:, 0, 1] * A[:, 1, 0])
    scale = np.sqrt(np.maximum(det, 1e-12)) * (2 ** search_level)
    return np.clip(np.rint(np.log2(scale)), 0, n_levels - 1).astype(np.int64)


#: (dx, dy) offsets of the (PATCH+2)^2 template pixels from its centre (search-level pixels).
_TEMPLATE_OFFSETS = np.arange(PATCH + 2 * MARGIN, dtype=np.float64) - (PATCH + 2 * MARGIN - 1) / 2.0
_TEMPLATE_GRID = tuple(np.meshgrid(_TEMPLATE_OFFSETS, _TEMPLATE_OFFSETS))


def warp_templates(src_pyramids: Mapping[int, Sequence[Image]], src_kf: NDArray[np.int64], src_uv0: Array,
                   A: Array, search_level: int, max_source_level: int = 3
                   ) -> tuple[NDArray[np.float32], NDArray[np.int64], NDArray[np.bool_]]:
    """Warped (PATCH+2)^2 templates (with a 1-px margin), their source levels and a valid mask.

    Template pixel offsets ``d`` (search-level pixels from the point) map to the source level
    ``ls`` as ``uv_src_ls + A * 2^search_level / 2^ls * d``. Invalid: the sampled square leaves the
    source image.
    """
    n = len(src_uv0)
    S = PATCH + 2 * MARGIN
    out = np.zeros((n, S, S), np.float32)
    if n == 0:
        return out, np.zeros(0, np.int64), np.zeros(0, bool)
    ref = next((p for p in src_pyramids.values() if len(p)), None)
    if ref is None:
        return out, np.zeros(n, np.int64), np.zeros(n, bool)
    n_levels = min(len(ref), max_source_level + 1)
    ls = choose_source_level(A, search_level, n_levels)
    valid = np.ones(n, bool)
    dx, dy = _TEMPLATE_GRID
    M = A * ((2.0 ** search_level) / (2.0 ** ls))[:, None, None]
    centre = (src_uv0 + 0.5) / (2.0 ** ls)[:, None] - 0.5
    mx = (centre[:, 0, None, None] + M[:, 0, 0, None, None] * dx + M[:, 0, 1, None, None] * dy).astype(np.float32)
    my = (centre[:, 1, None, None] + M[:, 1, 0, None, None] * dx + M[:, 1, 1, None, None] * dy).astype(np.float32)
    # Every keyframe pyramid has the same level sizes: the inside test for all points at once.
    sizes = np.array([p.shape for p in ref[:n_levels]], float)
    hl, wl = sizes[ls, 0], sizes[ls, 1]
    valid &= ((mx.min((1, 2)) >= 0) & (my.min((1, 2)) >= 0)
              & (mx.max((1, 2)) <= wl - 1) & (my.max((1, 2)) <= hl - 1))
    # One remap per (source keyframe, source level): sort so that each group is a slice.
    keys = src_kf.astype(np.int64) * 16 + ls
    order = np.argsort(keys, kind='stable')
    ks = keys[order]
    mxs = mx[order].reshape(-1, S)
    mys = my[order].reshape(-1, S)
    outs = np.empty((n * S, S), np.float32)
    cuts = np.flatnonzero(np.diff(ks)) + 1
    for a, b in zip(np.concatenate([[0], cuts]), np.concatenate([cuts, [n]])):
        key = int(ks[a])
        kf, lev = key // 16, key % 16
        pyr = src_pyramids.get(kf)
        if pyr is None or lev >= len(pyr) or pyr[lev].shape != ref[lev].shape:
            valid[order[a:b]] = False
            outs[a * S:b * S] = 0.0
            continue
        outs[a * S:b * S] = cv2.remap(pyr[lev], mxs[a * S:b * S], mys[a * S:b * S], cv2.INTER_LINEAR,
                                      borderMode=cv2.BORDER_REPLICATE)
    out[order] = outs.reshape(n, S, S)
    return out, ls, valid


def _circle(radius: float) -> tuple[int, NDArray[np.bool_]]:
    c = _CIRCLES.get(radius)
    if c is None:
        r = int(np.floor(radius))
        yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
        c = _CIRCLES[radius] = (r, (xx * xx + yy * yy) <= radius * radius + 1e-9)
        if len(_CIRCLES) > 64:
            _CIRCLES.clear()
    return c


_CIRCLES: dict[float, tuple[int, NDArray[np.bool_]]] = {}


def search(image: Image, templates: NDArray[np.float32], uv_pred: Array, config: SearchConfig | None = None,
           coarse: bool = False, radius: float | None = None) -> tuple[NDArray[np.bool_], Array, Array]:
    """Exhaustive ZSSD search of (PATCH+2)^2 templates in a circle around ``uv_pred`` (level pixels).

    Returns ``found``, sub-pixel positions (search-level pixels) and the best ZSSD per pixel. The
    match position of an 8x8 template is its centre (a half-integer offset from its top-left).
    """
    cfg = config or SearchConfig()
    n = len(uv_pred)
    found = np.zeros(n, bool)
    pos = np.full((n, 2), np.nan)
    best = np.full(n, np.inf)
    if n == 0:
        return found, pos, best
    r, circle = _circle(cfg.radius if radius is None else radius)
    h, w = image.shape
    P = PATCH
    T = templates[:, MARGIN:MARGIN + P, MARGIN:MARGIN + P].reshape(n, P * P).astype(np.float32)
    Tz = T - T.mean(1, keepdims=True)
    tvar = (Tz * Tz).mean(1)
    # Top-left of the template at the predicted position, rounded.
    tl = np.rint(np.asarray(uv_pred, float) - (P - 1) / 2.0).astype(np.int64)
    W = P + 2 * r
    x0 = tl[:, 0] - r
    y0 = tl[:, 1] - r
    ok = (x0 >= 0) & (y0 >= 0) & (x0 + W <= w) & (y0 + W <= h) & (tvar >= cfg.min_template_var)
    ok &= np.all(np.isfinite(uv_pred), axis=1)
    idx = np.nonzero(ok)[0]
    if len(idx) == 0:
        return found, pos, best
    m = len(idx)
    k = 2 * r + 1
    # The (W, W) windows around the predictions (one gather from a strided view of the image).
    win = np.lib.stride_tricks.sliding_window_view(image, (W, W))[y0[idx], x0[idx]].astype(np.float32)
    # Cross-correlation with the zero-mean template for all points at once, separably: every
    # window row correlated with every template row (one batched matmul over the row im2col),
    # then the diagonal sums over the template rows.
    Tzi = Tz[idx]
    rows = np.lib.stride_tricks.sliding_window_view(win, P, axis=2).reshape(m, W * k, P)
    R = np.matmul(rows, Tzi.reshape(m, P, P).transpose(0, 2, 1)).reshape(m, W, k, P)
    cross = R[:, 0:k, :, 0].astype(np.float64)
    for i in range(1, P):
        cross += R[:, i:i + k, :, i]
    # Window sums and sums of squares: one integral image of all windows stacked vertically.
    s1, s2 = window_box_sums(win, P)
    zssd = s2 - s1 * s1 / (P * P) - 2.0 * cross + (Tzi.astype(np.float64) ** 2).sum(1)[:, None, None]
    zssd = np.where(circle[None], zssd, np.inf)
    flat = zssd.reshape(m, -1).argmin(1)
    by, bx = np.divmod(flat, k)
    bz = zssd.reshape(m, -1)[np.arange(m), flat] / (P * P)
    thr = cfg.max_zssd_per_px_coarse if coarse else cfg.max_zssd_per_px
    frac = cfg.max_zssd_fraction_coarse if coarse else cfg.max_zssd_fraction
    acc = (bz <= thr) & (bz <= frac * tvar[idx])
    best[idx] = bz
    ipos = np.column_stack([x0[idx] + bx + (P - 1) / 2.0, y0[idx] + by + (P - 1) / 2.0])
    pos[idx] = ipos
    found[idx] = acc
    sel = idx[acc]
    if len(sel) and cfg.esm_iterations > 0:
        pos[sel] = esm_refine(image, templates[sel], ipos[acc], cfg.esm_iterations, cfg.max_esm_shift)
    return found, pos, best


#: (row offsets, column offsets) of the (PATCH+2)^2 template pixels from its centre, float32.
_ESM_GRID = (np.mgrid[0:PATCH + 2 * MARGIN, 0:PATCH + 2 * MARGIN].astype(np.float32)
             - np.float32((PATCH + 2 * MARGIN - 1) / 2.0))


def esm_refine(image: Image, templates: NDArray[np.float32], uv: Array, iterations: int = 3,
               max_shift: float = 1.0) -> Array:
    """2-DoF ESM sub-pixel refinement of template positions (search-level pixels), vectorised.

    ``templates`` carry a 1-pixel margin for the gradients. Zero-mean template and image patch (a
    brightness offset is free); points that move more than ``max_shift`` keep their start value.
    """
    n = len(uv)
    S = PATCH + 2 * MARGIN
    gy_, gx_ = _ESM_GRID
    T = templates.astype(np.float32, copy=False)
    # Template gradients (central differences) and the zero-mean inner template, (n, P*P).
    Tgx = (0.5 * (T[:, 1:-1, 2:] - T[:, 1:-1, :-2])).reshape(n, -1)
    Tgy = (0.5 * (T[:, 2:, 1:-1] - T[:, :-2, 1:-1])).reshape(n, -1)
    Tin = T[:, 1:-1, 1:-1].reshape(n, -1)
    Tin = Tin - Tin.mean(1, keepdims=True)
    p = np.asarray(uv, float).copy()
    start = p.copy()
    img = image if image.dtype == np.float32 else image.astype(np.float32)
    G = np.empty((n, 2, Tin.shape[1]), np.float32)
    for _ in range(iterations):
        pf = p.astype(np.float32)
        mx = (pf[:, 0, None, None] + gx_).reshape(-1, S)
        my = (pf[:, 1, None, None] + gy_).reshape(-1, S)
        Iw = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).reshape(n, S, S)
        # ESM Jacobian: mean of image and template gradients, zero-meaned over the patch (the
        # brightness offset is free), so the residual's mean drops out of J^T r.
        G[:, 0] = 0.25 * (Iw[:, 1:-1, 2:] - Iw[:, 1:-1, :-2]).reshape(n, -1) + 0.5 * Tgx
        G[:, 1] = 0.25 * (Iw[:, 2:, 1:-1] - Iw[:, :-2, 1:-1]).reshape(n, -1) + 0.5 * Tgy
        G -= G.mean(2, keepdims=True)
        r = Iw[:, 1:-1, 1:-1].reshape(n, -1) - Tin
        H = np.matmul(G, G.transpose(0, 2, 1)).astype(np.float64)  # (n, 2, 2)
        e = np.matmul(G, r[:, :, None])[:, :, 0].astype(np.float64)  # (n, 2)
        a = H[:, 0, 0] + 1e-6
        b = H[:, 0, 1]
        c = H[:, 1, 1] + 1e-6
        det = a * c - b * b
        det = np.where(np.abs(det) > 1e-9, det, 1e-9)
        p[:, 0] -= (c * e[:, 0] - b * e[:, 1]) / det
        p[:, 1] -= (-b * e[:, 0] + a * e[:, 1]) / det
    bad = (np.abs(p - start) > max_shift).any(1) | ~np.isfinite(p).all(1)
    p[bad] = start[bad]
    return p


def search_points(cur_pyramid: Sequence[Image], camera: Camera, R_c_w: Array, t_c_w: Array,
                  X_w: Array, src_pyramids: Mapping[int, Sequence[Image]], src_kf: NDArray[np.int64],
                  src_uv0: Array, src_R: Array, src_t: Array, search_level: int = 1,
                  config: SearchConfig | None = None, coarse: bool = False,
                  radius: float | None = None, uv_pred0: Array | None = None,
                  A: Array | None = None) -> SearchResult:
    """Project, warp templates and search all points on ``search_level`` of the current pyramid.

    ``src_R`` (N, 3, 3), ``src_t`` (N, 3): source keyframe poses per point. ``uv_pred0`` (level 0)
    and ``A`` may be given instead of being derived from the pose (the initialiser does so with
    its homography). ``coarse`` selects the looser threshold (fast rotation, sec. 4).
    """
    cfg = config or SearchConfig()
    X_w = np.asarray(X_w, float).reshape(-1, 3)
    n = len(X_w) if uv_pred0 is None else len(uv_pred0)
    if uv_pred0 is None:
        uv_pred0, _ = camera.project(X_w @ R_c_w.T + t_c_w)
    if A is None:
        A = affine_from_poses(X_w, camera, R_c_w, t_c_w, src_R, src_t)
    tmpl, _, valid = warp_templates(src_pyramids, np.asarray(src_kf), np.asarray(src_uv0, float), A, search_level)
    uv_l = level0_to_level(uv_pred0, search_level)
    found = np.zeros(n, bool)
    uv = np.full((n, 2), np.nan)
    z = np.full(n, np.inf)
    vi = np.nonzero(valid)[0]
    if len(vi):
        f, p, b = search(cur_pyramid[search_level], tmpl[vi], uv_l[vi], cfg, coarse=coarse, radius=radius)
        found[vi] = f
        uv[vi] = level_to_level0(p, search_level)
        z[vi] = b
    return SearchResult(found, uv, search_level, z)
