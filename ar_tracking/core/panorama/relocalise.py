"""Re-localisation against the finished tiles of the map (Langlotz 2011 sec. 3.1: tracking
"recovers when lost"; Wagner et al. re-localise against the map).

The frame is warped onto the cylinder under a hint orientation (the last tracked one) at half
resolution. A rotation about the cylinder axis is a pure horizontal shift of that warp, and a
small tilt nearly a vertical one, so each finished tile (downsampled) is searched in the warp
with normalised cross-correlation; every good match votes for a shift (du, dv) between where
the hint puts the frame and where it is. The shifts agreed on by several tiles become
orientation hypotheses, best first, for the tracker to verify with a wider active search.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from .cylinder import project_to_image, rotation_about_axis_y
from .map import PanoramaMap

Array = NDArray[np.float64]


@dataclass(frozen=True)
class RelocaliserConfig:
    scale: float = 0.5
    #: Smallest NCC of a tile match that may vote.
    min_ncc: float = 0.8
    #: Votes a shift needs to become a hypothesis.
    min_votes: int = 3
    #: At most this many tiles are tried (evenly spaced over the finished ones).
    max_tiles: int = 96
    max_hypotheses: int = 3


def _rotation_about(axis: Array, angle: float) -> Array:
    R, _ = cv2.Rodrigues((np.asarray(axis, float) / np.linalg.norm(axis) * angle).reshape(3, 1))
    return R


class Relocaliser:
    """See the module docstring."""

    def __init__(self, config: RelocaliserConfig | None = None) -> None:
        self.config = config or RelocaliserConfig()
        self._small: NDArray[np.uint8] | None = None
        self._small_version = -1

    def _small_map(self, pano: PanoramaMap) -> NDArray[np.uint8]:
        if self._small is None or self._small_version != pano.version:
            g = np.clip(pano.gray + 0.5, 0, 255).astype(np.uint8)
            s = self.config.scale
            self._small = cv2.resize(g, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
            self._small_version = pano.version
        return self._small

    def hypotheses(self, frame: NDArray[np.uint8], K: Array, R_hint: Array, pano: PanoramaMap
                   ) -> list[Array]:
        """Orientation hypotheses (R_pano_cam), best first; empty when nothing agrees."""
        cfg = self.config
        tiles = pano.finished_tiles()
        if tiles.size == 0:
            return []
        s = cfg.scale
        geo = pano.geometry
        h, w = frame.shape
        u0, u1, v0, v1 = pano.footprint(K, R_hint, (h, w))
        if v1 - v0 < 8:
            return []
        # The frame on the cylinder (half resolution) under the hint.
        us = np.arange(u0, u1, 1.0 / s)
        vs = np.arange(v0, v1, 1.0 / s)
        uu, vv = np.meshgrid(us, vs)
        d = geo.unproject(uu, vv)
        x, y, front = project_to_image(K, d @ R_hint)
        x = np.where(front, x, -10).astype(np.float32)
        y = np.where(front, y, -10).astype(np.float32)
        warp = cv2.remap(frame, x, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        valid = (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
        small = self._small_map(pano)
        ts = int(round(pano.config.tile_size * s))
        tw = pano.tiles_shape[1]
        if warp.shape[0] <= ts or warp.shape[1] <= ts:
            return []
        if tiles.size > cfg.max_tiles:
            tiles = tiles[np.linspace(0, tiles.size - 1, cfg.max_tiles).astype(int)]
        # Pixels outside the frame must not attract matches: fill them with noise-free mean.
        fill = float(warp[valid].mean()) if valid.any() else 0.0
        warp = np.where(valid, warp, np.uint8(fill)).astype(np.uint8)
        votes: dict[tuple[int, int], list[float]] = {}
        ws = small.shape[1]
        for t in tiles.tolist():
            r0, c0 = (t // tw) * ts, (t % tw) * ts
            tpl = small[r0:r0 + ts, c0:c0 + ts]
            if tpl.shape != (ts, ts) or float(tpl.std()) < 4.0:
                continue
            res = cv2.matchTemplate(warp, tpl, cv2.TM_CCOEFF_NORMED)
            _, peak, _, loc = cv2.minMaxLoc(res)
            if peak < cfg.min_ncc:
                continue
            # Tile content at small (c0, r0) appears where the hint puts small (u0*s + x, v0*s + y).
            du = (c0 - (u0 * s + loc[0]))
            du = (du + ws / 2) % ws - ws / 2
            dv = r0 - (v0 * s + loc[1])
            key = (int(round(du / 2)), int(round(dv / 2)))
            votes.setdefault(key, []).append(peak)
        # Merge neighbouring bins.
        scored = []
        for key in votes:
            near = [v for k2, vs_ in votes.items() if abs(k2[0] - key[0]) <= 1 and abs(k2[1] - key[1]) <= 1 for v in vs_]
            scored.append((len(near), sum(near), key))
        scored.sort(key=lambda e: (-e[0], -e[1], e[2]))
        out: list[Array] = []
        used: list[tuple[int, int]] = []
        for n_votes, _, key in scored:
            if n_votes < cfg.min_votes or len(out) >= cfg.max_hypotheses:
                break
            if any(abs(key[0] - k[0]) <= 1 and abs(key[1] - k[1]) <= 1 for k in used):
                continue
            used.append(key)
            du_map, dv_map = 2 * key[0] / s, 2 * key[1] / s
            yaw = du_map / geo.f
            # A vertical shift is a tilt about the horizontal axis across the view direction.
            view = R_hint[:, 2]
            axis = np.array([view[2], 0.0, -view[0]])
            R = rotation_about_axis_y(yaw) @ R_hint
            if np.linalg.norm(axis) > 1e-6:
                R = _rotation_about(rotation_about_axis_y(yaw) @ axis, -np.arctan(dv_map / geo.f)) @ R
            out.append(R)
        return out
