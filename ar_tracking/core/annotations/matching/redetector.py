"""The re-detection scheduler (Langlotz 2011 sec. 3.2, 6.1): the queue of finished tiles and
the per-frame budget, and the choice between several source panoramas near one GPS fix. What
follows an alignment is in :mod:`.guided` (guided search, parallax model, look-alike test) and
:mod:`.support` (whether it may be shown)."""
from __future__ import annotations

import math
from collections import OrderedDict, deque
from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from ...panorama.cylinder import CylinderGeometry
from .config import MatchConfig
from .placement import Alignment, CandidateDirections, best_candidate_placements
from .alignment import ransac_alignment
from .guided import GuidedSearch
from .support import SupportTest
from .tiles import CandidateList, TileMatcher

Array = NDArray[np.float64]


def expected_positions(source_dirs: Array, R_enu_source: Sequence[Array | None],
                       R_enu_target: Array, geometry: CylinderGeometry) -> Array:
    """(n, 2) expected map positions of the annotations in the target panorama from the
    absolute orientations of both panoramas (sec. 4.2); NaN where the source's is unknown."""
    out = np.full((len(source_dirs), 2), np.nan)
    known = [i for i, R in enumerate(R_enu_source) if R is not None]
    if known:
        Rs = np.stack([np.asarray(R_enu_source[i], float) for i in known])
        # batched matrix-vector products: the same sums, bit for bit, as one R_t.T @ (R @ d) each
        d = (R_enu_target.T @ (Rs @ np.asarray(source_dirs, float)[known][:, :, None]))[..., 0]
        u, v = geometry.project(d)
        out[known, 0] = u
        out[known, 1] = v
    return out


class ReDetector(GuidedSearch, SupportTest):
    """Matching state of one browsing panorama against a set of annotations.

    The annotations may come from several source panoramas (``groups``: one id per
    annotation); matching runs on all of them, the alignment per group, and :meth:`result`
    gives the group whose annotations score best (sec. 6.1). Newly finished tiles go into a
    FIFO (:meth:`add_finished_tiles`), :meth:`step` does at most ``max_ops`` tile x annotation
    comparisons (the per-frame budget of sec. 3.2).

    ``landmark`` flags the patches that are landmarks of their source panorama
    (:mod:`.landmarks`): matched and aligned like annotations, but not placed for the user and
    not counted in the group's score; their placements are in ``Alignment.landmarks``."""

    def __init__(self, patches: Sequence[NDArray[np.uint8]], source_dirs: Array,
                 groups: Sequence[str], config: MatchConfig | None = None,
                 geometry: CylinderGeometry | None = None,
                 R_enu_source: Sequence[Array | None] | None = None,
                 landmark: Sequence[bool] | None = None,
                 source_heading_sigma_rad: Sequence[float] | None = None) -> None:
        self.config = cfg = config or MatchConfig()
        self.geometry = geo = geometry or CylinderGeometry()
        self.source_dirs = np.asarray(source_dirs, float).reshape(-1, 3)
        n = len(self.source_dirs)
        self.groups = list(groups)
        self.landmark = np.zeros(n, bool) if landmark is None else np.asarray(landmark, bool).reshape(n)
        self.R_enu_source = list(R_enu_source) if R_enu_source is not None else [None] * n
        self.source_sigma = (np.full(n, np.nan) if source_heading_sigma_rad is None
                             else np.asarray(source_heading_sigma_rad, float).reshape(n))
        self.target_sigma = float('nan')
        # One TileMatcher per patch size.
        self.matchers: list[tuple[TileMatcher, list[int]]] = []
        for side in sorted({p.shape[0] for p in patches}):
            ids = [i for i, p in enumerate(patches) if p.shape[0] == side]
            self.matchers.append((TileMatcher([patches[i] for i in ids], cfg, geo), ids))
        #: annotation index -> its patch (float32, as matched), for the guided re-detection
        self._patches: dict[int, NDArray[np.float32]] = {
            i: matcher.patches[k] for matcher, ids in self.matchers for k, i in enumerate(ids)}
        self.candidates = [CandidateList(cfg.candidates, cfg.min_separation_px, geo.width) for _ in range(n)]
        self.queue: deque[int] = deque()
        self.seen: set[int] = set()
        self.expected_uv: Array | None = None
        self.R_enu_target: Array | None = None
        self.dirty = False
        self.tiles_done = 0
        self._cache: tuple[str | None, Alignment] | None = None
        self._map: tuple[NDArray[np.float32], NDArray[np.bool_] | None] | None = None
        self._ncc_surfaces = {}
        self._finishes = 0
        self._directions = CandidateDirections(geo)
        self._parallax_fits = OrderedDict()

    def _clear_kept(self) -> None:
        """Forget what is kept from one :meth:`result` to the next (the NCC surfaces of the
        guided search, the candidates' directions, the parallax fits): the next result is computed from scratch,
        and is the same."""
        self._ncc_surfaces.clear()
        self._directions = CandidateDirections(self.geometry)
        self._parallax_fits.clear()

    @property
    def n(self) -> int:
        return len(self.source_dirs)

    def add_finished_tiles(self, tiles: NDArray) -> int:
        """Queue the finished tiles (mono8 tile image, >0 finished) not seen before."""
        new = [int(t) for t in np.flatnonzero(np.asarray(tiles).reshape(-1) > 0) if int(t) not in self.seen]
        self.seen.update(new)
        self.queue.extend(new)
        return len(new)

    def set_orientation(self, R_enu_target: Array | None, heading_sigma_rad: float = float('nan')) -> None:
        """The browsing panorama's absolute orientation (R_enu_panorama) for the prior, with the
        1-sigma of its heading when known (for the support test)."""
        self.R_enu_target = None if R_enu_target is None else np.asarray(R_enu_target, float)
        if math.isfinite(heading_sigma_rad) != math.isfinite(self.target_sigma) or (
                math.isfinite(heading_sigma_rad) and abs(heading_sigma_rad - self.target_sigma) > 1e-9):
            self._cache = None
        self.target_sigma = float(heading_sigma_rad)
        if R_enu_target is None or not self.config.sensor_prior:
            self.expected_uv = None
        else:
            self.expected_uv = expected_positions(self.source_dirs, self.R_enu_source,
                                                  np.asarray(R_enu_target, float), self.geometry)

    def step(self, gray: NDArray[np.float32], mapped: NDArray[np.bool_] | None, max_ops: int | None = None) -> int:
        """Match queued tiles until ``max_ops`` tile x annotation comparisons are done (at
        least one tile); returns the number of tiles processed."""
        self._map = (gray, mapped)
        done = ops = 0
        while self.queue and (max_ops is None or ops < max_ops or done == 0):
            tile = self.queue.popleft()
            for matcher, ids in self.matchers:
                exp = self.expected_uv[ids] if self.expected_uv is not None else None
                found = matcher.match_tile(gray, mapped, tile, None, exp)
                ops += len(ids)
                for k, cands in found.items():
                    for c in cands:
                        if self.candidates[ids[k]].add(c):
                            self.dirty = True
            done += 1
        self.tiles_done += done
        if done:
            self._cache = None if self.dirty else self._cache
        return done

    def result(self) -> tuple[str | None, Alignment]:
        """(source panorama id, alignment/placements) of the best-scoring group."""
        if self._cache is not None and not self.dirty:
            return self._cache
        self.dirty = False
        self._directions.next_round()
        best: tuple[float, str | None, Alignment] = (-1.0, None, Alignment(None))
        for g in dict.fromkeys(self.groups):
            ids = [i for i, gi in enumerate(self.groups) if gi == g]
            cands = [self.candidates[i].items for i in ids]
            shown = [c for i, c in zip(ids, cands) if not self.landmark[i]]
            if not shown:
                continue
            score = float(np.mean([c[0].ncc if c else 0.0 for c in shown]))
            if score <= best[0]:
                continue
            if self.config.ransac:
                al = ransac_alignment(self.source_dirs[ids], cands, self.config, self.geometry,
                                      R_prior=self._prior_rotation(ids), up=self._up(), directions=self._directions)
                if al.R_target_source is None:
                    al.placements = best_candidate_placements(cands, self.geometry)
            else:
                al = Alignment(None, best_candidate_placements(cands, self.geometry))
            self._finish(al, ids, cands)
            al.landmarks = [p for p in al.placements if self.landmark[p.index]]
            al.placements = [p for p in al.placements if not self.landmark[p.index]]
            self._support(al, ids)
            best = (score, g, al)
        self._cache = (best[1], best[2])
        return self._cache
