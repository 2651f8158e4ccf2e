"""Image patches of a panorama map (the support area of an annotation or a landmark, sec. 3.2)."""
from __future__ import annotations

import numpy as np

from ..panorama.cylinder import CylinderGeometry


def cut_patch(gray: np.ndarray, mapped: np.ndarray, u: float, v: float, side: int,
              geometry: CylinderGeometry) -> tuple[np.ndarray | None, np.ndarray | None, str]:
    """(uint8 patch, unit direction of its exact centre, reason) of the map around (u, v).

    The patch is stretched linearly onto 0..255 (NCC is invariant to it); it must be fully
    mapped (columns wrap) and textured. On failure the patch and direction are None and the
    reason says why (one line)."""
    H, W = gray.shape
    x0 = int(round(u - (side - 1) / 2.0))
    y0 = int(round(v - (side - 1) / 2.0))
    if y0 < 0 or y0 + side > H:
        return None, None, f'anchor at v={v:.0f} is too close to the top or bottom of the map'
    cols = np.arange(x0, x0 + side) % W
    if not mapped[y0:y0 + side][:, cols].all():
        return None, None, f'anchor at ({u:.0f}, {v:.0f}) is not (fully) mapped in the panorama'
    vals = gray[y0:y0 + side][:, cols].astype(np.float64)
    lo, hi = float(vals.min()), float(vals.max())
    if hi - lo < 4.0:
        return None, None, f'anchor at ({u:.0f}, {v:.0f}) has no texture'
    patch = np.round((vals - lo) * (255.0 / (hi - lo))).astype(np.uint8)
    d = geometry.unproject(np.array((x0 + (side - 1) / 2.0) % W), np.array(y0 + (side - 1) / 2.0))
    return patch, np.asarray(d, float).reshape(3), ''
