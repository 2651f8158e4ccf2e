"""3-DoF orientation tracking against the panoramic map (Langlotz 2011 sec. 3.1; Wagner et al.).

One frame: the map keypoints (directions on the cylinder, from finished tiles) are projected
into the frame with the predicted orientation (active search). For each selected keypoint the
map around it is warped into the camera's view at that orientation (so the template has the
camera's perspective, scale and roll), then searched in the frame within a small radius by
normalised cross-correlation; the peak is refined to sub-pixel by a parabola through its
neighbours. Matched frame pixels give bearing vectors b_i, the keypoints give directions d_i
in the panorama frame, and the rotation R_pano_cam with d_i ~ R b_i is estimated robustly:
RANSAC over two-point Kabsch hypotheses (closed form, they only vote), then a Kabsch (SVD) fit
on the inliers.

The same matches give the EDR exposure correction of sec. 4.1: the mean intensity difference
between the map's patches (baseline units) and the frame's matched patches (``intensity_offset``,
with its standard error) and the same mean of log intensities (``log_gain``, with its standard error; patches touching
0 or 255 or darker than ``min_photometric_level`` do not vote), see exposure.py.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import NDArray

from ..box_sums import window_box_sums
from ..rotations import align_directions
from .cylinder import camera_rays, image_rows, project_to_image, row_rotations
from .map import PanoramaMap
from .readout import RowFit

Array = NDArray[np.float64]


@dataclass(frozen=True)
class TrackerConfig:
    """Active search and robust estimation parameters."""

    #: Side of the square patches, pixels (odd).
    patch_size: int = 9
    #: Search radius around the predicted position, pixels (constant-motion prediction).
    search_radius_px: int = 4
    #: Keypoints searched per frame (spread over a grid of the frame).
    max_features: int = 60
    grid_cols: int = 8
    grid_rows: int = 6
    #: Smallest accepted NCC peak.
    min_ncc: float = 0.75
    #: RANSAC inlier threshold, pixels (angle * focal length).
    inlier_px: float = 1.5
    ransac_iterations: int = 32
    #: Patches darker than this (8-bit units) do not vote for the exposure gain (log noise).
    min_photometric_level: float = 12.0
    #: Quality gate (end of :meth:`ActiveSearchTracker.track`, with ``_weak_agreements``): the
    #: frame is tracked only with this many inliers, ...
    min_inliers: int = 10
    #: ... this fraction of the searched keypoints agreeing with the rotation (inliers, or weak
    #: agreements: see ``weak_ncc``), ...
    min_inlier_ratio: float = 0.7
    #: ... and this fraction of the matched keypoints (NCC peak >= min_ncc) being inliers.
    min_matched_inlier_ratio: float = 0.7
    #: A keypoint whose correlation peak stayed below ``min_ncc`` still agrees with the rotation
    #: when its peak is at least this and within ``weak_px`` of where the rotation puts it: fine
    #: detail that blur, aliasing or the map's resampling weakened (branches, grass, blinds) is
    #: still there; a keypoint that parallax or an occluder moved has no such peak.
    weak_ncc: float = 0.5
    weak_px: float = 2.0
    seed: int = 0
    #: Estimate the exposure's log gain of the frame (``TrackResult.log_gain``: what the
    #: mapper's 'gain' EDR correction filters). False: not computed (0, its standard error inf,
    #: 0 pairs); the mapper turns it off in its other correction modes, which never read it.
    log_gain: bool = True

    def __post_init__(self) -> None:
        if self.patch_size % 2 == 0 or self.patch_size < 5:
            raise ValueError('patch_size must be odd and >= 5')


@dataclass
class TrackResult:
    """Outcome of one tracking attempt."""

    ok: bool
    R_pano_cam: Array
    searched: int = 0
    matched: int = 0
    inliers: int = 0
    rms_px: float = float('nan')
    #: Mean (map - frame) intensity of the inlier pairs, 8-bit units (sec. 4.1, additive).
    intensity_offset: float = 0.0
    reason: str = ''
    #: Mean (log map - log frame) intensity of the usable inlier pairs (sec. 4.1 in the log
    #: domain: the exposure is a gain, so exp(log_gain) is the frame's multiplicative correction).
    log_gain: float = 0.0
    #: Standard error of ``log_gain`` (spread of the pairs / sqrt(n)); inf without usable pairs.
    log_gain_se: float = float('inf')
    #: Pairs used for ``log_gain`` (inliers neither dark nor touching the 8-bit limits).
    photometric_pairs: int = 0
    #: Standard error of ``intensity_offset`` (spread of the kept pairs / sqrt(n)), 8-bit units.
    intensity_offset_se: float = float('inf')
    #: The inliers of the fit, for the readout's estimate (:mod:`.readout`); None on failure.
    row_fit: RowFit | None = None
    #: The rotation fitted to the inliers, also when the ratios rejected it (where a lost
    #: camera's view was found; the prediction when fewer than 3 agreed); None when the attempt
    #: ended before the fit.
    R_fit: Array | None = None


def kabsch(b: Array, d: Array, w: Array | None = None) -> Array:
    """Rotation R minimising sum w |d_i - R b_i|^2 (see core.rotations.align_directions)."""
    return align_directions(b, d, w)


def _pair_frames(v: Array, F: Array) -> None:
    """Orthonormal frames (M, 3, 3), as columns (s, t, s x t), of M pairs of unit directions
    v (M, 2, 3), with s along v0 + v1 and t along v0 - v1 (orthogonal, as |v0| = |v1|), written
    into ``F`` (M, 3, 3); a degenerate pair (v0 = +-v1) gives a non-finite frame (the caller
    silences numpy's invalid and divide warnings)."""
    s = v[:, 0] + v[:, 1]
    t = v[:, 0] - v[:, 1]
    s /= np.sqrt((s * s).sum(axis=1))[:, None]
    t /= np.sqrt((t * t).sum(axis=1))[:, None]
    F[:, :, 0] = s
    F[:, :, 1] = t
    F[:, 0, 2] = s[:, 1] * t[:, 2] - s[:, 2] * t[:, 1]
    F[:, 1, 2] = s[:, 2] * t[:, 0] - s[:, 0] * t[:, 2]
    F[:, 2, 2] = s[:, 0] * t[:, 1] - s[:, 1] * t[:, 0]


def pair_rotation_votes(b: Array, d: Array, pairs: NDArray[np.int64], R_pred: Array | None, thr: float
                        ) -> NDArray[np.bool_]:
    """(M + 1, n) inlier masks |R_m b_i - d_i| < thr of the two-point Kabsch rotations R_m of
    the index ``pairs`` (M, 2) and of ``R_pred`` (the last row; (M, n) without one): the RANSAC
    hypotheses, which only vote (the estimate is the Kabsch fit on the winner's inliers). The
    tracker's RANSAC and the relocaliser's consensus over tile matches both use it.

    The two-point Kabsch rotation in closed form: with s = b0 + b1 and t = b0 - b1 the
    correlation matrix is H = d0 b0^T + d1 b1^T = (s_d s_b^T + t_d t_b^T) / 2, whose singular
    vectors are the unit s and t directions, so R = F_d F_b^T maps the frame F_b = (s, t, s x t)
    of the bearings onto F_d of the directions. Then |R b - d| = |F_b^T b - F_d^T d|: every
    hypothesis's residuals come from two matrix products, (n, 3) x (3, 3 M), with no batched
    SVD (4 times the cost) and no rotation formed. A degenerate pair votes for nothing.
    (One warning context for all of it: entering numpy's costs about as much as the arithmetic.)"""
    M = pairs.shape[0]
    m = M + (R_pred is not None)
    Fb = np.empty((m, 3, 3))
    Fd = np.empty((m, 3, 3))
    n = b.shape[0]
    with np.errstate(invalid='ignore', divide='ignore'):
        _pair_frames(b[pairs], Fb[:M])
        _pair_frames(d[pairs], Fd[:M])
        if R_pred is not None:
            Fb[M] = _EYE  # R_pred: |b - R_pred^T d|
            Fd[M] = R_pred
        diff = (b @ Fb.transpose(1, 0, 2).reshape(3, 3 * m) - d @ Fd.transpose(1, 0, 2).reshape(3, 3 * m))
        diff = diff.reshape(n, m, 3)
        return (np.einsum('nmi,nmi->mn', diff, diff) < thr * thr)


_EYE = np.eye(3)
_EYE.flags.writeable = False


def _row_norms(e: Array) -> Array:
    """``np.linalg.norm(e, axis=1)`` of an (n, 3) array: its very sum of squares per row and
    root, without the generic function's argument handling (a few us a call, three a frame)."""
    return np.sqrt(np.add.reduce(e * e, axis=1))


def _project_rows(K: Array, cam: Array, row_motion: tuple[Array, float] | None, h: int
                  ) -> tuple[Array, Array, NDArray[np.bool_]]:
    """Pixel coordinates and in-front flags of camera-frame directions (n, 3) at the stamp; with
    a rolling shutter, where the row that sees each one saw it (one iteration: the stamp's row,
    then that row's camera)."""
    if row_motion is None:
        return project_to_image(K, cam)
    y = image_rows(K, cam[:, 1], cam[:, 2])
    return project_to_image(K, np.einsum('nji,nj->ni', row_rotations(row_motion, y, h), cam))


def _trimmed_mean_se(x: Array, trim: float = 0.2) -> tuple[float, float]:
    """Mean of the central 1 - 2 * trim of the values (robust to a few bad pairs) and its
    standard error (spread of the kept values / sqrt(kept)).

    The mean and ``std(ddof=1)`` as numpy's ndarray methods compute them (the same sums,
    divisions and squares, so the same values) without their generic reduction wrappers."""
    x = np.sort(x)
    k = int(trim * x.size)
    c = x[k:x.size - k] if x.size > 2 * k else x
    if c.size < 2:
        return (float(c.mean()) if c.size else 0.0), float('inf')
    n = c.size
    mean = np.add.reduce(c, axis=None) / n
    dev = np.subtract(c, mean)
    np.square(dev, out=dev)
    std = np.sqrt(np.add.reduce(dev, axis=None) / (n - 1))
    return float(mean), float(std / np.sqrt(n))


def _patch_rows(windows: NDArray[np.float32], side: int, P: int) -> NDArray[np.float32]:
    """(n, side * side, P * P) contiguous: row (sy, sx) of window i holds its P x P patch at
    offset (sy, sx), row-major - ``sliding_window_view(windows, (P, P), axis=(1, 2))`` reshaped.

    The same copy with each patch row (P float32) moved as one opaque item: numpy's strided copy
    of the 5-D view moves P floats per inner loop, and at the tracker's 60 windows the items
    take about two thirds of its time."""
    n = windows.shape[0]
    windows = np.ascontiguousarray(windows)
    s0, s1, s2 = windows.strides
    row = np.dtype((np.void, P * windows.itemsize))
    src = np.ndarray((n, side, side, P), row, windows, 0, (s0, s1, s2, s1))
    out = np.empty((n, side, side, P), row)
    out[...] = src
    return out.view(np.float32).reshape(n, side * side, P * P)


#: From this search radius on, the NCC is computed per keypoint by OpenCV instead of as one
#: batched product (see :meth:`ActiveSearchTracker.track`, step 3).
_PER_WINDOW_RADIUS_PX = 7


class ActiveSearchTracker:
    """Tracks one frame at a time against a :class:`PanoramaMap` (see module docstring)."""

    def __init__(self, config: TrackerConfig | None = None) -> None:
        self.config = cfg = config or TrackerConfig()
        self._rng = np.random.default_rng(cfg.seed)
        #: the camera's tables: ((K bytes, h, w), every pixel's ray (h w, 3), the widest angle of
        #: the frame's corner rays from the optical axis) - see :meth:`_camera`
        self._camera_tables: tuple[tuple[bytes, int, int], Array, float] | None = None

    def reset(self) -> None:
        self._rng = np.random.default_rng(self.config.seed)

    def track(self, frame: NDArray[np.uint8], K: Array, R_pred: Array, pano: PanoramaMap,
              radius_px: int | None = None, row_motion: tuple[Array, float] | None = None) -> TrackResult:
        """Estimate R_pano_cam of ``frame`` (grey uint8) starting from ``R_pred``.

        ``row_motion`` = (omega, readout_s): a rolling shutter - row y was read ``readout_s (y +
        0.5) / h`` after the stamp while the camera turned at ``omega`` (rad/s, camera axes); the
        keypoints are searched where each row saw them and the matched bearings are turned back
        to the stamp's orientation, which is what is estimated."""
        cfg = self.config
        r = cfg.search_radius_px if radius_px is None else int(radius_px)
        P = cfg.patch_size
        half = P // 2
        h, w = frame.shape
        dirs, _, score = pano.keypoints()
        fail = TrackResult(False, R_pred)
        if dirs.shape[0] < cfg.min_inliers:
            fail.reason = 'too few map keypoints'
            return fail
        # 1. Active search: project the keypoints with the prediction, keep the visible ones.
        cam = dirs @ R_pred
        # Only the keypoints within the frame's cone (widened by the rows' turn) can be in view:
        # the others are not projected (most of the map's; each keypoint's values are its own).
        cand = np.flatnonzero(cam[:, 2] >= self._cone_cos(K, h, w, row_motion))
        x, y, front = _project_rows(K, cam[cand], row_motion, h)
        m = half + r + 1
        vis = front & (x >= m) & (x < w - 1 - m) & (y >= m) & (y < h - 1 - m)
        pos = np.flatnonzero(vis)  # positions in cand
        if pos.size < cfg.min_inliers:
            fail.reason = f'{pos.size} map keypoints in view'
            return fail
        pos = self._spread(pos, x[pos], y[pos], score[cand[pos]], w, h)
        idx = cand[pos]
        n = idx.size
        px, py = x[pos], y[pos]
        xr, yr = np.rint(px).astype(np.int64), np.rint(py).astype(np.int64)
        # 2. Templates: the map warped into the predicted view around each keypoint.
        # Rays (xn, yn, 1) (n, P, P, 3) of the P x P pixel grids centred on (xr, yr), x (n, 1, P)
        # and y (n, P, 1) broadcast; then one (n P P, 3) x (3, 3) product (a stack of n P small
        # ones costs more; same values).
        rays = self._template_rays(K, h, w, xr, yr)
        if row_motion is None:
            u, v = pano.geometry.project((rays.reshape(-1, 3) @ R_pred.T).reshape(rays.shape))
        else:  # each template turned by its row's rotation
            R_rows = R_pred @ row_rotations(row_motion, py, h)
            # (n, P P, 3) x (n, 3, 3)^T as one batched product: a tenth of an einsum's time
            u, v = pano.geometry.project(np.matmul(rays.reshape(n, P * P, 3), R_rows.transpose(0, 2, 1)
                                                   ).reshape(rays.shape))
        # Each sample depends only on its own map coordinates, so the layout of the maps is
        # free: one row (cv2.remap's per-row cost, ~30 % of the call with n P rows of P) unless
        # it would pass remap's 32767 limit on a side.
        layout = (1, n * P * P) if n * P * P <= 32767 else (n * P, P)
        T = cv2.remap(pano.gray, u.reshape(layout).astype(np.float32),
                      v.reshape(layout).astype(np.float32), cv2.INTER_LINEAR,
                      borderMode=cv2.BORDER_WRAP).reshape(n, P, P).astype(np.float64)
        t_mean = T.mean(axis=(1, 2))
        Tz = T - t_mean[:, None, None]
        t_norm = np.sqrt(np.einsum('nij,nij->n', Tz, Tz))
        # 3. Search windows in the frame and NCC at every offset within the radius.
        S = P + 2 * r
        # (n, S, S) uint8 windows gathered by flat index (a window view's fancy indexing costs more)
        grid = np.arange(S)
        Wu = np.take(np.ascontiguousarray(frame).reshape(-1),
                     ((yr - half - r) * w + (xr - half - r))[:, None, None] + (grid[:, None] * w + grid))
        Wn = Wu.astype(np.float32)
        side = 2 * r + 1
        # Window sums of the values and their squares from integral images: integers, exact in
        # float64 (the same values as summing each window, at a fifth of the time).
        box, box2 = window_box_sums(Wu, P)
        var = np.maximum(box2 - box * box / (P * P), 0.0)
        denom = np.sqrt(var) * t_norm[:, None, None]
        if r < _PER_WINDOW_RADIUS_PX:
            # Cross-correlation of each template with every window position as one batched
            # matrix product (float32: exact enough for 8-bit pixels, and about twice as fast).
            views = _patch_rows(Wn, side, P)
            num = np.matmul(views, Tz.astype(np.float32).reshape(n, P * P, 1)).reshape(n, side, side)
            ncc = np.where(denom > 1e-6 * P * P, num.astype(np.float64) / np.maximum(denom, 1e-12), -1.0)
        else:
            # A wide search: the batched product's copy of every window position grows with the
            # radius squared (12 MB at 10 px); OpenCV's plain correlation per keypoint is ~4x
            # faster there. The zero-mean template makes it the same numerator, normalised by
            # the same box sums (OpenCV's normalised mode would compute them again).
            Tz32 = Tz.astype(np.float32)
            num = np.empty((n, side, side), np.float32)
            for i in range(n):
                num[i] = cv2.matchTemplate(Wn[i], Tz32[i], cv2.TM_CCORR)
            ncc = np.where(denom > 1e-6 * P * P, num.astype(np.float64) / np.maximum(denom, 1e-12), -1.0)
        flat = ncc.reshape(n, -1)
        best = np.argmax(flat, axis=1)
        peak = flat[np.arange(n), best]
        by, bx = np.divmod(best, 2 * r + 1)
        good = (peak >= cfg.min_ncc) & (by > 0) & (by < 2 * r) & (bx > 0) & (bx < 2 * r) \
            & (t_norm > 2.0 * P)
        if np.count_nonzero(good) < cfg.min_inliers:
            fail.searched, fail.matched = n, int(np.count_nonzero(good))
            fail.reason = f'{fail.matched} of {n} keypoints matched'
            return fail
        k = np.flatnonzero(good)
        bxk, byk = bx[k], by[k]
        c0 = ncc[k, byk, bxk]
        # 4. Sub-pixel: parabola through the peak and its neighbours, separately in x and y.
        lft, rr = ncc[k, byk, bxk - 1], ncc[k, byk, bxk + 1]
        t_, b_ = ncc[k, byk - 1, bxk], ncc[k, byk + 1, bxk]
        dx = 0.5 * (lft - rr) / np.minimum(lft - 2 * c0 + rr, -1e-9)
        dy = 0.5 * (t_ - b_) / np.minimum(t_ - 2 * c0 + b_, -1e-9)
        mx = px[k] + (bxk - r) + np.clip(dx, -0.5, 0.5)
        my = py[k] + (byk - r) + np.clip(dy, -0.5, 0.5)
        b = camera_rays(K, mx, my)
        if row_motion is not None:  # each bearing turned back to the stamp's camera
            b = np.einsum('nij,nj->ni', row_rotations(row_motion, my, h), b)
        d = dirs[idx[k]]
        # 5. Robust rotation: RANSAC over 2-point Kabsch, then Kabsch on the inliers.
        f = float(K[0, 0])
        # The threshold in frame pixels, but never finer than a map pixel: a frame sharper than
        # the map (more pixels per degree) cannot be matched more precisely than the map's grid.
        thr = cfg.inlier_px / min(f, pano.geometry.f)
        nk = k.size
        pairs = self._rng.integers(0, nk, size=(cfg.ransac_iterations, 2))
        pairs = pairs[pairs[:, 0] != pairs[:, 1]]
        inside = pair_rotation_votes(b, d, pairs, R_pred, thr)
        inl = inside[int(np.argmax(inside.sum(axis=1)))]
        R = R_pred
        resid = None  # the residuals of R (once there is a fit)
        for _ in range(2):
            if np.count_nonzero(inl) < 3:
                break
            R = kabsch(b[inl], d[inl])
            resid = _row_norms(b @ R.T - d)
            refit = resid < thr
            unchanged = np.array_equal(refit, inl)
            inl = refit
            if unchanged:  # a refit on the same inliers is the same rotation
                break
        n_in = int(np.count_nonzero(inl))
        if resid is None:
            resid = _row_norms(b @ R.T - d)
        rms = float(np.sqrt(np.mean(resid[inl] ** 2)) * f) if n_in else float('nan')
        # 6. EDR offset: map patch mean minus the frame patch mean at the match (sec. 4.1).
        # The frame patch mean at the sub-pixel match: bilinear in the patch-mean surface.
        sx, sy = np.clip(dx, -0.5, 0.5), np.clip(dy, -0.5, 0.5)
        ox = np.where(sx >= 0, 1, -1)
        oy = np.where(sy >= 0, 1, -1)
        ax, ay = np.abs(sx), np.abs(sy)
        f_mean = ((1 - ax) * (1 - ay) * box[k, byk, bxk] + ax * (1 - ay) * box[k, byk, bxk + ox]
                  + (1 - ax) * ay * box[k, byk + oy, bxk] + ax * ay * box[k, byk + oy, bxk + ox]) / (P * P)
        if n_in:
            offset, offset_se = _trimmed_mean_se((t_mean[k] - f_mean)[inl])
        else:
            offset, offset_se = 0.0, float('inf')
        # The exposure is a gain on the encoded values: its estimate is the same mean, of log
        # intensities. Pairs whose frame patch touches 0 or 255 (clipped: the gain is not seen
        # there) or that are dark (log noise) do not vote.
        log_gain, log_se, pairs_used = 0.0, float('inf'), 0
        if cfg.log_gain:
            peak_patch = sliding_window_view(Wn, (P, P), axis=(1, 2))[k, byk, bxk].reshape(k.size, P * P)
            unclipped = (peak_patch.max(axis=1) < 254.5) & (peak_patch.min(axis=1) > 0.5)
            use = inl & unclipped & (f_mean > cfg.min_photometric_level) & (t_mean[k] > cfg.min_photometric_level)
            pairs_used = int(np.count_nonzero(use))
            if pairs_used >= 3:
                log_gain, log_se = _trimmed_mean_se(np.log(t_mean[k][use]) - np.log(f_mean[use]))
        weak = 0
        ok = n_in >= cfg.min_inliers and n_in >= cfg.min_matched_inlier_ratio * nk
        if ok and n_in < cfg.min_inlier_ratio * n:
            weakly = np.flatnonzero(~good & (peak >= cfg.weak_ncc) & (t_norm > 2.0 * P))  # textured, unmatched
            weak = self._weak_agreements(weakly, dirs[idx], R, K, xr + bx - r, yr + by - r, row_motion, h)
            ok = n_in + weak >= cfg.min_inlier_ratio * n
        reason = '' if ok else (f'{n_in} inliers of {nk} matched keypoints and {n_in + weak} of {n} searched '
                                'agreeing')
        fit = None
        if ok:
            rays = b[inl] @ R.T
            fit = RowFit(rays, d[inl] - rays, (my[inl] + 0.5) / h, idx[k][inl])
        return TrackResult(ok, R if ok else R_pred, n, nk, n_in, rms, offset, reason,
                           log_gain, log_se, pairs_used, offset_se, fit, R)

    def _camera(self, K: Array, h: int, w: int) -> tuple[Array, float]:
        """(every pixel's ray (h w, 3) as :func:`.cylinder.camera_rays` gives it, the widest angle
        of the rays through the frame's corners from the optical axis), kept while the camera
        (K and the frame size) stays the same."""
        key = (K.tobytes(), h, w)
        if self._camera_tables is None or self._camera_tables[0] != key:
            rays = camera_rays(K, np.arange(w, dtype=float)[None, :], np.arange(h, dtype=float)[:, None], unit=False)
            corners = camera_rays(K, np.array([-1.0, w, -1.0, w]), np.array([-1.0, -1.0, h, h]))
            self._camera_tables = (key, rays.reshape(h * w, 3),
                                   float(np.arccos(np.clip(corners[:, 2], -1.0, 1.0)).max()))
        return self._camera_tables[1], self._camera_tables[2]

    def _template_rays(self, K: Array, h: int, w: int, xr: NDArray[np.int64], yr: NDArray[np.int64]) -> Array:
        """Rays (xn, yn, 1) (n, P, P, 3) of the P x P pixel grids centred on the integer pixels
        (xr, yr) (inside the frame), gathered from a table of every pixel's ray kept for the
        camera: :func:`.cylinder.camera_rays` of each pixel (the same values), without computing
        them again for every frame."""
        P = self.config.patch_size
        half = P // 2
        grid = np.arange(P)
        corner = (yr - half) * w + (xr - half)
        return np.take(self._camera(K, h, w)[0], corner[:, None, None] + (grid[:, None] * w + grid), axis=0)

    def _cone_cos(self, K: Array, h: int, w: int, row_motion: tuple[Array, float] | None) -> float:
        """A lower bound of the optical-axis component of every unit direction (camera axes at
        the stamp) that the frame can see: the cosine of the widest angle between the optical
        axis and a ray through the image's corners, plus the rows' largest turn (a row's camera is
        the stamp's turned by at most ``|omega| readout (h + 0.5) / h``, :func:`.cylinder.row_rotations`)
        and a margin; -inf (everything) when that cone reaches 90 degrees. The frame's view is
        bounded by its corners (the rays through a convex image region fill a cone whose widest
        ray is a corner's), so a keypoint below the bound is out of view whatever its row."""
        angle = self._camera(K, h, w)[1] + 1e-3
        if row_motion is not None:
            omega, readout = row_motion
            angle += float(np.linalg.norm(omega)) * abs(float(readout)) * (h + 0.5) / h
        return math.cos(angle) if angle < 0.5 * math.pi - 1e-3 else -math.inf

    def _weak_agreements(self, o: NDArray[np.int64], dirs: Array, R: Array, K: Array, peak_x: Array,
                         peak_y: Array, row_motion: tuple[Array, float] | None, h: int) -> int:
        """How many of the keypoints ``o`` (indices into the searched ones, whose NCC peak stayed
        under min_ncc but reached weak_ncc) have that peak within weak_px of where the fitted
        rotation ``R`` puts them.

        The searched keypoints that do not agree with the rotation are what tells a view that
        has moved (parallax of a translating camera, an occluder) from one that has not; but in a
        real scene many keypoints fail min_ncc only because the frame is a weakened copy of the
        map there (motion blur over fine branches or grass, blinds, the map's resampling): their
        correlation still peaks where the rotation says. Counting those keeps a real outdoor
        scene tracked (pano_parrington as the simulator's world lost 2,058 of 12,000 frames with
        only the inliers counted, none with these) while a translating camera is still lost."""
        if o.size == 0:
            return 0
        x, y, front = _project_rows(K, dirs[o] @ R, row_motion, h)
        dx, dy = peak_x[o] - x, peak_y[o] - y
        limit = self.config.weak_px
        return int(np.count_nonzero(front & (dx * dx + dy * dy <= limit * limit)))

    def _spread(self, idx: NDArray[np.int64], x: Array, y: Array, score: Array, w: int, h: int
                ) -> NDArray[np.int64]:
        """At most ``max_features`` keypoints, the strongest of each grid cell first, so that
        they cover the whole frame (a rotation is better conditioned by spread bearings)."""
        cfg = self.config
        if idx.size <= cfg.max_features:
            return idx
        cx = np.minimum((x * cfg.grid_cols / w).astype(np.int64), cfg.grid_cols - 1)
        cy = np.minimum((y * cfg.grid_rows / h).astype(np.int64), cfg.grid_rows - 1)
        cell = cy * cfg.grid_cols + cx
        neg = -score
        order = np.lexsort((neg, cell))
        cs = cell[order]
        # Rank of each keypoint in its cell (0: the cell's strongest): its position in the
        # sorted order minus the position where its cell starts.
        start = np.zeros(cs.size, np.int64)
        new_cell = np.flatnonzero(cs[1:] != cs[:-1]) + 1
        start[new_cell] = new_cell
        rank = np.arange(cs.size) - np.maximum.accumulate(start)
        pick = order[np.lexsort((neg[order], rank))][:cfg.max_features]
        pick.sort()
        return idx[pick]
