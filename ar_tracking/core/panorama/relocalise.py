"""Re-localisation against the finished tiles of the map (Langlotz 2011 sec. 3.1: tracking
"recovers when lost"; Wagner et al. re-localise against the map).

The frame is warped onto the cylinder under a hint orientation (the last tracked one) at half
resolution. A rotation about the cylinder axis is a pure horizontal shift of that warp, and a
small tilt or roll nearly a local shift, so each finished tile (downsampled) is searched in the
warp with normalised cross-correlation. Every good match is a correspondence: the tile's centre
direction in the map, and the camera ray that saw it (where it sits in the warp, taken back
through the hint). The rotations that most matches agree on (exhaustive two-point Kabsch
hypotheses, consensus within ``consensus_px``, then a Kabsch fit on the consensus) are the
orientation hypotheses, best first, for the tracker to verify with a wider active search. A
full rotation, not only a shift: after a fast pan the hand has also tilted and rolled the phone
by a few degrees, which moves a 320 px frame's edges by more than the tracker's wide search.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from ..rotations import align_directions
from .cylinder import project_to_image
from .map import PanoramaMap
from .tracker import pair_rotation_votes

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
    #: Matches within this many map pixels of a rotation's prediction agree with it.
    consensus_px: float = 6.0
    #: The best this many tile matches (by NCC) form the hypotheses (pairs grow as its square).
    max_matches: int = 24


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
        rays: list[Array] = []  # camera rays of the matches (through the hint)
        dirs: list[Array] = []  # map directions of the matched tiles' centres
        peaks: list[float] = []
        for t in tiles.tolist():
            r0, c0 = (t // tw) * ts, (t % tw) * ts
            tpl = small[r0:r0 + ts, c0:c0 + ts]
            if tpl.shape != (ts, ts) or float(tpl.std()) < 4.0:
                continue
            res = cv2.matchTemplate(warp, tpl, cv2.TM_CCOEFF_NORMED)
            _, peak, _, loc = cv2.minMaxLoc(res)
            if peak < cfg.min_ncc:
                continue
            half = ts / 2.0
            dirs.append(geo.unproject(np.array([(c0 + half) / s]), np.array([(r0 + half) / s]))[0])
            seen = geo.unproject(np.array([u0 + (loc[0] + half) / s]), np.array([v0 + (loc[1] + half) / s]))[0]
            rays.append(R_hint.T @ seen)
            peaks.append(float(peak))
        if len(rays) < cfg.min_votes:
            return []
        best = np.argsort(-np.array(peaks), kind='stable')[:cfg.max_matches]
        return _consensus_rotations(np.array(rays)[best], np.array(dirs)[best], cfg.consensus_px / geo.f,
                                    cfg.min_votes, cfg.max_hypotheses)


def _consensus_rotations(b: Array, d: Array, thr: float, min_votes: int, max_hypotheses: int) -> list[Array]:
    """Rotations R with d_i ~ R b_i agreed on by the most matches: every pair of matches gives
    a two-point Kabsch rotation (:func:`.tracker.pair_rotation_votes`), the one with the largest
    consensus (|R b - d| < thr) is refitted on it; its matches are removed and the next one sought."""
    keep = np.ones(b.shape[0], bool)
    out: list[Array] = []
    while len(out) < max_hypotheses:
        idx = np.flatnonzero(keep)
        if idx.size < max(min_votes, 2):
            break
        votes = pair_rotation_votes(b[idx], d[idx], np.column_stack(np.triu_indices(idx.size, 1)), None, thr)
        counts = votes.sum(axis=1)
        best = int(np.argmax(counts))
        if counts[best] < min_votes:
            break
        inl = idx[votes[best]]
        out.append(align_directions(b[inl], d[inl]))
        keep[inl] = False
    return out
