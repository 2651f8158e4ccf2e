"""The camera's photometric response, undone before the edge model is fitted.

The seed's edge model (Caarls 2009 sec. 2.4, eq. 1) is a Gaussian-blurred step in *intensity*:
its gradient is a Gaussian around the edge, so the log-parabola vertex is the edge. That holds
for light, not for the 8-bit values of a real camera, which go through a response curve - a
display gamma, I = 255 (L / L_max)^(1 / gamma). Through the curve the blurred step becomes
asymmetric (the bright side stretched, the dark side squeezed for gamma > 1) and the gradient
peak moves towards the dark side: a black-bordered marker's corners come out inward by about
0.4 px for gamma 2.2 and 1-2 px of blur. Mapping the values back to light first (a lookup
table) makes the model true again.

The gamma is a parameter, or estimated from the marker's own edges: across each side the
values go from the black border to the white quiet zone, and in light they follow eq. 1,
L(d) = L_b + (L_w - L_b) Phi((d - delta) / s), point-symmetric about the mid level.
:func:`estimate_gamma` samples the values across the four (lens-curved) sides at whole pixels
and finds the gamma under which each side's mean light profile is symmetric again: the
asymmetry of the encoded profile is what identifies gamma (no assumption on the blur's shape). :class:`GammaEstimator` keeps the median of
these per-marker estimates (a camera's response does not change; the first markers settle it).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from .lens_model import LensModel

Array = NDArray[np.float64]

#: gamma values outside this range are not a display response (or the fit failed).
GAMMA_RANGE = (0.4, 4.0)


def linearize(gray: NDArray, gamma: float) -> NDArray[np.float32]:
    """8-bit values mapped back to light on the same 0-255 scale: 255 (I / 255)^gamma."""
    if abs(gamma - 1.0) < 1e-9:
        return np.asarray(gray, dtype=np.float32)
    lut = (255.0 * np.power(np.arange(256) / 255.0, gamma)).astype(np.float32)
    g = np.asarray(gray)
    if g.dtype == np.uint8:
        return lut[g]
    return (255.0 * np.power(np.clip(g.astype(np.float32), 0, 255) / 255.0, gamma)).astype(np.float32)


def side_samples(corners_norm: Array, lens: LensModel, step_px: float = 1.5,
                 margin: float = 0.15) -> list[tuple[Array, Array]]:
    """Points along each side (between the corners, away from them) in pixels and the unit
    outward normals there, following the side's curve through the lens distortion."""
    c = np.asarray(corners_norm, float).reshape(4, 2)
    centre = lens.distort(c.mean(0, keepdims=True))[0]
    out = []
    for i in range(4):
        a, b = c[i], c[(i + 1) % 4]
        pa, pb = lens.distort(np.stack([a, b]))
        n = max(int(np.linalg.norm(pb - pa) * (1 - 2 * margin) / step_px), 4)
        t = np.linspace(margin, 1 - margin, n)
        pts_n = a + t[:, None] * (b - a)
        eps = 1e-4 * (b - a)
        pts = lens.distort(pts_n)
        tangent = lens.distort(pts_n + eps) - lens.distort(pts_n - eps)
        tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
        normal = np.stack([-tangent[:, 1], tangent[:, 0]], -1)
        flip = np.sum((pts - centre) * normal, axis=1) < 0
        normal[flip] *= -1
        out.append((pts, normal))
    return out


def edge_profiles(gray: NDArray, corners_norm: Array, lens: LensModel,
                  half_width_px: int = 4) -> tuple[Array, Array, Array] | None:
    """Pixel values across the 4 sides, at whole pixels (no interpolation, which would mix
    values on the response curve): for each point along a side, the pixels of its row or
    column (whichever is closer to the normal) within ``half_width_px``, with their signed
    distance from the side (outward positive). Returns (distances (P, S), side index (P,),
    values (P, S))."""
    img = np.asarray(gray)
    h, w = img.shape[:2]
    k = np.arange(-half_width_px - 1, half_width_px + 2)
    dist, sides, vals = [], [], []
    for side, (pts, normal) in enumerate(side_samples(corners_norm, lens, step_px=1.0)):
        axis = (np.abs(normal[:, 1]) > np.abs(normal[:, 0])).astype(int)
        base = np.rint(pts).astype(int)
        step = np.zeros((len(pts), 2), int)
        step[np.arange(len(pts)), axis] = 1
        pix = base[:, None, :] + k[None, :, None] * step[:, None, :]
        ok = np.all((pix[..., 0] >= 0) & (pix[..., 0] < w) & (pix[..., 1] >= 0) & (pix[..., 1] < h), axis=1)
        pix, pts, normal = pix[ok], pts[ok], normal[ok]
        if len(pix) < 3:
            return None
        dist.append(np.sum((pix - pts[:, None, :]) * normal[:, None, :], axis=2))
        vals.append(img[pix[..., 1], pix[..., 0]].astype(np.float64))
        sides.append(np.full(len(pix), side))
    return np.concatenate(dist), np.concatenate(sides), np.concatenate(vals)


def _symmetry_cost(d: Array, side: Array, vals: Array, gamma: float, bin_px: float = 0.25,
                   reach_px: float = 2.5) -> float:
    """How far the mean light profile of each side is from point symmetry about its
    mid-level crossing, for one candidate gamma (relative to the contrast; summed over sides)."""
    light = np.power(vals / 255.0, gamma)
    total, n = 0.0, 0
    for k in np.unique(side):
        sel = side == k
        dk, lk = d[sel], light[sel]
        lb, lw = lk[dk < -3.0].mean(), lk[dk > 3.0].mean()
        if not lw - lb > 1e-3:
            continue
        edges = np.arange(-4.0, 4.0 + 1e-9, bin_px)
        idx = np.digitize(dk, edges) - 1
        ok = (idx >= 0) & (idx < len(edges) - 1)
        cnt = np.bincount(idx[ok], minlength=len(edges) - 1)
        sm = np.bincount(idx[ok], lk[ok], minlength=len(edges) - 1)
        have = cnt > 0
        centres = (edges[:-1] + bin_px / 2)[have]
        prof = (sm[have] / cnt[have] - lb) / (lw - lb)
        # mid-level crossing (the profile rises from the dark side; take the first crossing)
        above = np.nonzero(prof >= 0.5)[0]
        if len(above) == 0 or above[0] == 0:
            continue
        j = above[0]
        f = (0.5 - prof[j - 1]) / max(prof[j] - prof[j - 1], 1e-9)
        delta = centres[j - 1] + f * (centres[j] - centres[j - 1])
        u = np.arange(0.25, reach_px + 1e-9, 0.25)
        if delta + reach_px > centres[-1] or delta - reach_px < centres[0]:
            continue
        r = np.interp(delta + u, centres, prof) + np.interp(delta - u, centres, prof) - 1.0
        total += float(np.sum(r * r))
        n += len(u)
    return total / n if n else float('inf')


def marker_levels(gray: NDArray, corners_norm: Array, lens: LensModel) -> tuple[float, float] | None:
    """The marker's black (border) and white (quiet zone) values next to its sides: medians of
    the pixels 2.5-4 px inside and outside the edges, over the profiles that show a clean step."""
    prof = edge_profiles(gray, corners_norm, lens)
    if prof is None:
        return None
    d, _, vals = prof
    lo = np.where((d < -2.5) & (d >= -4.0), vals, np.nan)
    hi = np.where((d > 2.5) & (d <= 4.0), vals, np.nan)
    with np.errstate(all='ignore'):
        b, w = np.nanmedian(lo, 1), np.nanmedian(hi, 1)
    contrast = w - b
    med = np.nanmedian(contrast)
    good = np.isfinite(contrast) & (contrast > 0.6 * med)
    if good.sum() < 12 or not med > 20:
        return None
    return float(np.median(b[good])), float(np.median(w[good]))


def gamma_from_levels(black: float, white: float, print_contrast: float) -> float | None:
    """The gamma that maps the marker's white/black value ratio to its printed reflectance
    ratio: (white / black)^gamma = print_contrast (vignetting and exposure cancel in the ratio)."""
    if not (black > 0.5 and white > black * 1.05 and print_contrast > 1.0):
        return None
    g = math.log(print_contrast) / math.log(white / black)
    return g if GAMMA_RANGE[0] < g < GAMMA_RANGE[1] else None


def estimate_gamma(gray: NDArray, corners_norm: Array, lens: LensModel,
                   print_contrast: float = 0.0) -> float | None:
    """The display gamma from one marker, or None when it does not constrain it.

    With ``print_contrast`` (the white/black reflectance ratio of the printed marker, > 1):
    from the marker's own black and white levels (:func:`gamma_from_levels`). Without (0): from
    the shape of its edges, as follows.

    In light, a blurred step is point-symmetric about its mid level whatever the blur kernel
    (any symmetric point-spread function: defocus, pixel area, motion blur): L(delta + u) +
    L(delta - u) = L_b + L_w. The response curve breaks the symmetry; the gamma that restores it
    on the mean profile of every side is the estimate (a grid search, then a finer one). This
    needs no knowledge of the print but is noisier (about +-20 % per marker on the simulator's
    images, hence the median over many markers in :class:`GammaEstimator`)."""
    if print_contrast > 0:
        levels = marker_levels(gray, corners_norm, lens)
        return None if levels is None else gamma_from_levels(levels[0], levels[1], print_contrast)
    prof = edge_profiles(gray, corners_norm, lens)
    if prof is None:
        return None
    d, side, vals = prof
    # Profiles that are not one clean dark-to-bright step (occlusion, another edge) are left out.
    lo = np.where(d < -2.5, vals, np.nan)
    hi = np.where(d > 2.5, vals, np.nan)
    with np.errstate(all='ignore'):
        contrast = np.nanmean(hi, 1) - np.nanmean(lo, 1)
    med = np.nanmedian(contrast)
    good = np.isfinite(contrast) & (contrast > 0.6 * med)
    if good.sum() < 12 or not med > 20:
        return None
    d, vals = d[good], vals[good]
    side = np.broadcast_to(side[good][:, None], d.shape).ravel()
    d, vals = d.ravel(), np.maximum(vals.ravel(), 0.5)
    use = np.abs(d) <= 4.0
    d, vals, side = d[use], vals[use], side[use]
    coarse = np.exp(np.linspace(math.log(GAMMA_RANGE[0]), math.log(GAMMA_RANGE[1]), 47))
    costs = np.array([_symmetry_cost(d, side, vals, g) for g in coarse])
    if not np.isfinite(costs).any():
        return None
    k = int(np.argmin(costs))
    if k == 0 or k == len(coarse) - 1:
        return None
    fine = np.linspace(coarse[k - 1], coarse[k + 1], 21)
    costs = np.array([_symmetry_cost(d, side, vals, g) for g in fine])
    return float(fine[int(np.argmin(costs))])


@dataclass
class GammaEstimator:
    """Median of per-marker gamma estimates; settled after ``settle_after`` of them."""

    settle_after: int = 40
    values: list[float] = field(default_factory=list)

    @property
    def settled(self) -> bool:
        return len(self.values) >= self.settle_after

    @property
    def gamma(self) -> float | None:
        return float(np.median(self.values)) if self.values else None

    def add(self, value: float | None) -> None:
        if value is not None and np.isfinite(value) and not self.settled:
            self.values.append(float(value))
