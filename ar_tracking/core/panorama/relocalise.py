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

Each tile is first sought at half that resolution over the whole warp, then at the warp's own
resolution only around the coarse peak (``refine_px``): the same acceptance (the NCC at the
finer scale) for about a tenth of the correlation work, which matters because a lost camera
runs this on every frame (graph bench: 315 lost frames, ~75 % of the mapper's time).
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
    #: The fine search around the coarse peak: this many warp pixels each way (0: no coarse
    #: pass, every tile searched over the whole warp at ``scale``).
    refine_px: int = 3
    #: A tile whose coarse peak is below this never gets a fine search.
    coarse_min_ncc: float = 0.6


class Relocaliser:
    """See the module docstring."""

    def __init__(self, config: RelocaliserConfig | None = None) -> None:
        self.config = config or RelocaliserConfig()
        self._small: NDArray[np.uint8] | None = None
        self._coarse: NDArray[np.uint8] | None = None
        self._tile_std: Array | None = None
        self._small_version = -1

    def _small_map(self, pano: PanoramaMap) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
        """The map at ``scale`` and at half of it (remade when the map has changed)."""
        if self._small is None or self._coarse is None or self._small_version != pano.version:
            g = np.clip(pano.gray + 0.5, 0, 255).astype(np.uint8)
            s = self.config.scale
            self._small = cv2.resize(g, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
            self._coarse = _half(self._small)
            self._small_version = pano.version
            self._tile_std = None
        return self._small, self._coarse

    def _tile_stds(self, small: NDArray[np.uint8], ts: int) -> Array:
        """Grey-level standard deviation of every whole tile of the scaled map (one pass per
        map version instead of one numpy call per tile and frame)."""
        if self._tile_std is None:
            rows, cols = small.shape[0] // ts, small.shape[1] // ts
            blocks = small[:rows * ts, :cols * ts].reshape(rows, ts, cols, ts).astype(np.float32)
            self._tile_std = blocks.std(axis=(1, 3)).astype(float)
        return self._tile_std

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
        # a column's sine and cosine once (unproject broadcasts them over the rows: the same grid)
        d = geo.unproject(us[None, :], vs[:, None])
        x, y, front = project_to_image(K, d @ R_hint)
        x = np.where(front, x, -10).astype(np.float32)
        y = np.where(front, y, -10).astype(np.float32)
        warp = cv2.remap(frame, x, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        valid = (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
        small, coarse = self._small_map(pano)
        ts = int(round(pano.config.tile_size * s))
        tw = pano.tiles_shape[1]
        if warp.shape[0] <= ts or warp.shape[1] <= ts:
            return []
        if tiles.size > cfg.max_tiles:
            tiles = tiles[np.linspace(0, tiles.size - 1, cfg.max_tiles).astype(int)]
        # Pixels outside the frame must not attract matches: fill them with noise-free mean.
        fill = float(warp[valid].mean()) if valid.any() else 0.0
        filled: NDArray[np.uint8] = np.where(valid, warp, np.uint8(fill)).astype(np.uint8)
        search = _TileSearch(filled, cfg.refine_px, cfg.coarse_min_ncc) if cfg.refine_px > 0 else None
        stds = self._tile_stds(small, ts)
        found: list[tuple[int, int, int, int, float]] = []  # tile row, col (scaled map px), match x, y, NCC
        for t in tiles.tolist():
            row, col = divmod(t, tw)
            if row >= stds.shape[0] or col >= stds.shape[1] or stds[row, col] < _MIN_TILE_STD:
                continue  # not whole at this scale, or flat: nothing to match
            r0, c0 = row * ts, col * ts
            tpl = small[r0:r0 + ts, c0:c0 + ts]
            if search is not None:
                match = search.find(tpl, coarse[r0 // 2:r0 // 2 + ts // 2, c0 // 2:c0 // 2 + ts // 2])
            else:
                match = _best_match(filled, tpl)
            if match is not None and match[2] >= cfg.min_ncc:
                found.append((r0, c0, *match))
        if len(found) < cfg.min_votes:
            return []
        rows = np.array(found, dtype=float)
        best = np.argsort(-rows[:, 4], kind='stable')[:cfg.max_matches]
        rows = rows[best]
        half = ts / 2.0
        # map directions of the matched tiles' centres, and the camera rays that saw them (through the hint)
        dirs = geo.unproject((rows[:, 1] + half) / s, (rows[:, 0] + half) / s)
        rays = geo.unproject(u0 + (rows[:, 2] + half) / s, v0 + (rows[:, 3] + half) / s) @ R_hint
        return _consensus_rotations(rays, dirs, cfg.consensus_px / geo.f, cfg.min_votes, cfg.max_hypotheses)


#: Tiles flatter than this grey-level standard deviation are not searched (nothing to match).
_MIN_TILE_STD = 4.0


def _half(image: NDArray[np.uint8]) -> NDArray[np.uint8]:
    return np.asarray(cv2.resize(image, (image.shape[1] // 2, image.shape[0] // 2), interpolation=cv2.INTER_AREA),
                      dtype=np.uint8)


def _best_match(warp: NDArray[np.uint8], tpl: NDArray[np.uint8]) -> tuple[int, int, float]:
    """Where ``tpl`` correlates best in ``warp`` (x, y of its corner) and the NCC there."""
    res = cv2.matchTemplate(warp, tpl, cv2.TM_CCOEFF_NORMED)
    _, peak, _, loc = cv2.minMaxLoc(res)
    return int(loc[0]), int(loc[1]), float(peak)


class _TileSearch:
    """Coarse-to-fine template search in one warp: the tile at half resolution over the whole
    half-resolution warp, then at full resolution within ``refine_px`` of twice the coarse peak."""

    def __init__(self, warp: NDArray[np.uint8], refine_px: int, coarse_min_ncc: float) -> None:
        self.warp = warp
        self.coarse_warp = _half(warp)
        self.refine_px = refine_px
        self.coarse_min_ncc = coarse_min_ncc

    def find(self, tpl: NDArray[np.uint8], coarse_tpl: NDArray[np.uint8]) -> tuple[int, int, float] | None:
        ct = coarse_tpl.shape[0]
        if ct < 4 or self.coarse_warp.shape[0] <= ct or self.coarse_warp.shape[1] <= ct:
            return _best_match(self.warp, tpl)
        res = cv2.matchTemplate(self.coarse_warp, coarse_tpl, cv2.TM_CCOEFF_NORMED)
        _, peak, _, loc = cv2.minMaxLoc(res)
        if peak < self.coarse_min_ncc:
            return None
        ts, r = tpl.shape[0], self.refine_px
        h, w = self.warp.shape
        x0 = min(max(2 * loc[0] - r, 0), w - ts)
        y0 = min(max(2 * loc[1] - r, 0), h - ts)
        x1 = min(2 * loc[0] + r + ts, w)
        y1 = min(2 * loc[1] + r + ts, h)
        fine = cv2.matchTemplate(self.warp[y0:y1, x0:x1], tpl, cv2.TM_CCOEFF_NORMED)
        _, peak, _, loc = cv2.minMaxLoc(fine)
        return x0 + int(loc[0]), y0 + int(loc[1]), float(peak)


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
