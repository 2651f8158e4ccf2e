"""Guided re-detection after the alignment (Langlotz 2011 sec. 4.3): each annotation searched
by NCC around where the alignment puts it, the parallax model fitted on the matches (a browsing
spot 0.4-1.5 m from the authoring one), and the look-alike test of a match. A mixin of
:class:`.redetector.ReDetector`, which holds the state named below."""
from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass, replace

import cv2
import numpy as np
from numpy.typing import NDArray

from ...panorama.cylinder import CylinderGeometry
from ..parallax import (ParallaxModel, depth_scale_sigma, fit_depth_scale, fit_parallax, leave_one_out_predictions,
                        prediction_sigma)
from .config import MatchConfig
from .placement import Alignment, CandidateDirections, Placement, offset_from_prediction_px, place_annotations
from .tiles import Candidate

Array = NDArray[np.float64]
#: NCC of a patch around a position: (ncc, column offsets, row offsets, inside mask, distance of
#: each position from the predicted one)
NccWindow = tuple[NDArray[np.float32], Array, Array, NDArray[np.bool_], Array]
#: An NCC surface kept across :meth:`GuidedSearch._finish` calls: [the bytes of the map pixels
#: and of the mapped mask it was computed on, the surface (read-only), the last finish that used it]
_Surface = list

#: A kept NCC surface not used in this many consecutive finishes is dropped.
_SURFACE_KEEP_FINISHES = 3


#: Parallax fits kept for the next ``result`` calls (the latest ones).
_PARALLAX_FITS_KEPT = 4


@dataclass(frozen=True)
class _ParallaxFit:
    """:meth:`GuidedSearch._parallax_fit`'s outcome: the model, the corrected predictions
    (read-only; the group's order), the depth ratio's sigma (NaN: none fitted), the model's
    heading sigma per annotation (None: not asked for) and the placement gate (NaN: none)."""

    model: ParallaxModel
    corrected: Array
    depth_ratio_sigma: float
    prediction_sigma: dict[int, float] | None
    gate_px: float


def _pixel_bytes(region: NDArray | None) -> bytes | None:
    """A map region's values as bytes with its dtype (equal bytes: bit for bit the same pixels)."""
    return None if region is None else region.dtype.str.encode() + region.tobytes()


class GuidedSearch:
    """The re-detector's steps after an alignment: :meth:`_finish` (guided search, parallax
    model, look-alike test)."""

    config: MatchConfig
    geometry: CylinderGeometry
    source_dirs: Array
    landmark: NDArray[np.bool_]
    R_enu_target: Array | None
    _patches: dict[int, NDArray[np.float32]]
    _map: tuple[NDArray[np.float32], NDArray[np.bool_] | None] | None
    #: :meth:`_window_ncc` results of the current :meth:`_finish` (the look-alike test asks for
    #: the window the guided search of the same placement has just computed)
    _ncc_windows: dict[tuple[int, float, float, float, float | None], NccWindow | None]
    #: NCC surfaces by (index, x0, y0, r, rv) across finishes (:meth:`_ncc_surface`): each
    #: ``result`` searches ~100 windows again after a new match, most of them on map pixels
    #: that have not changed since the last one
    _ncc_surfaces: dict[tuple[int, int, int, int, int], _Surface]
    #: :meth:`_finish` calls so far (the age of a kept surface)
    _finishes: int
    #: the candidates' directions, kept from one ``result`` to the next
    _directions: CandidateDirections
    #: :meth:`_parallax_fit` by its inputs, the latest last
    _parallax_fits: OrderedDict[tuple[object, ...], _ParallaxFit]

    def _guided(self, todo: list[tuple[Placement, float, float]], v_tol: float | None = None,
                config: MatchConfig | None = None) -> None:
        """Guided re-detection of placements around where the alignment puts them ((placement,
        u, v) each; an inferred one: the placement itself): NCC in a +-``placement_px`` window
        (+-``v_tol`` vertically after a gravity-constrained alignment), minus ``guided_penalty``
        x distance / ``placement_px``; the best position with an NCC of at least
        ``guided_min_ncc`` becomes the placement when its penalised score beats that of the
        current match (an inferred placement has none). The windows are scored as one stack
        (each placement's own values: the same as one at a time)."""
        cfg, geo = config or self.config, self.geometry
        wins = self._window_ncc([(p.index, cu, cv_) for p, cu, cv_ in todo], cfg.placement_px, v_tol)
        found = [(t, w) for t, w in zip(todo, wins) if w is not None]
        if not found:
            return
        res = np.stack([w[0] for _, w in found])
        dist = np.stack([w[4] for _, w in found])
        inside = np.stack([w[3] for _, w in found])
        score = np.where(inside, res - cfg.guided_penalty * dist / cfg.placement_px, -np.inf)
        best = score.reshape(len(found), -1).argmax(axis=1)
        for j, ((p, cu, cv_), (_, xs, ys, _, _)) in enumerate(found):
            y, x = divmod(int(best[j]), score.shape[2])
            if res[j, y, x] < cfg.guided_min_ncc:
                continue
            if p.status == 'matched':
                d_now = float(geo.map_distance(np.array(p.u), np.array(p.v), cu, cv_))
                if score[j, y, x] <= p.score - cfg.guided_penalty * d_now / cfg.placement_px + 1e-6:
                    continue
            p.u = float((cu + xs[x]) % geo.width)
            p.v = float(cv_ + ys[y])
            p.direction = geo.unproject(np.array(p.u), np.array(p.v))
            p.status = 'matched'
            p.score = float(res[j, y, x])

    def _window_ncc(self, at: list[tuple[int, float, float]], radius_px: float, v_tol: float | None
                    ) -> list[NccWindow | None]:
        """:meth:`_ncc_window` of each (index, u, v), once per arguments within one
        :meth:`_finish` (the map does not change there; the callers do not modify the arrays)."""
        keys = [(index, cu, cv_, radius_px, v_tol) for index, cu, cv_ in at]
        new = [k for k, key in enumerate(keys) if key not in self._ncc_windows]
        for k, win in zip(new, self._ncc_window([at[k] for k in new], radius_px, v_tol)):
            self._ncc_windows[keys[k]] = win
        return [self._ncc_windows[key] for key in keys]

    def _ncc_window(self, at: list[tuple[int, float, float]], radius_px: float, v_tol: float | None
                    ) -> list[NccWindow | None]:
        """NCC (TM_CCOEFF_NORMED) of patch ``index`` at every position within ``radius_px`` of
        (u, v) (and ``v_tol`` above or below), for each (index, u, v) of ``at``: (ncc, column
        offsets, row offsets from (u, v), inside mask, distance from (u, v)); positions not fully
        mapped get -1. None without a map, outside the rows or for an unknown index. The
        offsets of all windows are computed as one array (each element as for one window)."""
        out: list[NccWindow | None] = [None] * len(at)
        if self._map is None:
            return out
        height = self._map[0].shape[0]
        r = int(math.ceil(radius_px))
        rv = r if v_tol is None else int(math.ceil(min(v_tol, radius_px)))
        rows, surfaces, corners, at_ok = [], [], [], []
        for k, (index, cu, cv_) in enumerate(at):
            patch = self._patches.get(index)
            if patch is None:
                continue
            P = patch.shape[0]
            x0 = int(round(cu - (P - 1) / 2)) - r
            y0 = int(round(cv_ - (P - 1) / 2)) - rv
            if y0 < 0 or y0 + P + 2 * rv > height:
                continue
            rows.append(k)
            surfaces.append(self._ncc_surface(index, patch, x0, y0, r, rv))
            c = (P - 1) / 2.0
            corners.append((x0 + c, y0 + c))  # the window's first position's centre
            at_ok.append((cu, cv_))
        if not rows:
            return out
        # Offsets from the predicted positions (sub-pixel: x0, y0 were rounded).
        first = np.array(corners, float)
        centre = np.array(at_ok, float)
        xs: Array = first[:, :1] + np.arange(2 * r + 1, dtype=float)[None] - centre[:, :1]
        ys: Array = first[:, 1:] + np.arange(2 * rv + 1, dtype=float)[None] - centre[:, 1:]
        dist: Array = np.hypot(xs[:, None, :], ys[:, :, None])
        inside: NDArray[np.bool_] = (dist <= radius_px) & (
            np.abs(ys)[:, :, None] <= (v_tol if v_tol is not None else np.inf))
        for j, k in enumerate(rows):
            out[k] = (surfaces[j], xs[j], ys[j], inside[j], dist[j])
        return out

    def _ncc_surface(self, index: int, patch: NDArray[np.float32], x0: int, y0: int, r: int, rv: int
                     ) -> NDArray[np.float32]:
        """The NCC surface of patch ``index`` over the (2 rv + 1, 2 r + 1) positions whose
        top-left pixel is at (x0, y0) or after it (columns wrap at the map's seam; rows inside the
        map), -1 where not fully mapped; read-only. Kept across finishes and reused while the map
        pixels and mapped mask under it are bit for bit those it was computed on (the surface
        depends on nothing else), so a reused one equals a fresh one exactly."""
        assert self._map is not None
        gray, mapped = self._map
        P = patch.shape[0]
        # The window's columns (wrapping at the map's seam: gathered, else a slice - same pixels).
        cols: slice | Array = slice(x0, x0 + P + 2 * r)
        if x0 < 0 or x0 + P + 2 * r > self.geometry.width:
            cols = np.arange(x0, x0 + P + 2 * r) % self.geometry.width
        reg = gray[y0:y0 + P + 2 * rv][:, cols]
        m = None if mapped is None else mapped[y0:y0 + P + 2 * rv][:, cols]
        key = (index, x0, y0, r, rv)
        pixels, mask = _pixel_bytes(reg), _pixel_bytes(m)
        kept = self._ncc_surfaces.get(key)
        if kept is not None and kept[0] == pixels and kept[1] == mask:
            kept[3] = self._finishes
            return kept[2]
        if m is not None:
            full = cv2.boxFilter(m.astype(np.float32), -1, (P, P), anchor=(0, 0), normalize=True,
                                 borderType=cv2.BORDER_CONSTANT)[:2 * rv + 1, :2 * r + 1]
        else:
            full = np.ones((2 * rv + 1, 2 * r + 1), np.float32)
        res: NDArray[np.float32] = np.asarray(
            cv2.matchTemplate(reg.astype(np.float32), patch, cv2.TM_CCOEFF_NORMED), np.float32)
        res[(full < 0.999) | ~np.isfinite(res)] = -1.0
        res.flags.writeable = False
        self._ncc_surfaces[key] = [pixels, mask, res, self._finishes]
        return res

    def _lookalike(self, p: Placement, predicted: Array, v_tol: float | None, gate_px: float) -> None:
        """The look-alike test of a matched placement (:attr:`MatchConfig.lookalike_margin`):
        another local NCC maximum (3 x 3) inside the gate around its prediction, at least
        ``lookalike_sep_px`` from the match, with an NCC within the margin of the match's makes
        the placement the prediction itself (inferred) - unless the match lies within
        :attr:`MatchConfig.matched_agreement_px` of the prediction."""
        cfg, geo = self.config, self.geometry
        if offset_from_prediction_px(p, geo) <= cfg.matched_agreement_px:  # p.predicted is `predicted`
            return  # the match agrees with the other matches: a rival would change nothing shown
        cu, cv_ = (float(x) for x in geo.project(predicted))
        win = self._window_ncc([(p.index, cu, cv_)], gate_px, v_tol)[0]
        if win is None:
            return
        res, xs, ys, inside, _ = win
        peak = (res >= cv2.dilate(res, np.ones((3, 3), np.uint8))) & inside & (res > -1.0)
        far = geo.map_distance(cu + xs[None, :], cv_ + ys[:, None], p.u, p.v) >= cfg.lookalike_sep_px
        rivals = res[peak & far]
        # The match's own NCC on the current map (the candidate's may be from an earlier map).
        own = res[inside & ~far]
        score = float(own.max()) if own.size else p.score
        if rivals.size == 0 or float(rivals.max()) < score - cfg.lookalike_margin:
            return
        p.u, p.v = cu, cv_
        p.direction = np.asarray(predicted, float).copy()
        p.status = 'inferred'
        p.score = float('nan')

    def _finish(self, al: Alignment, ids: list[int], cands: list[list[Candidate]]) -> None:
        """Make the placements' indices global and re-detect them guided; with a gravity-
        constrained alignment and enough matches, the parallax model: fitted on the matches,
        then every annotation placed and guided again around its corrected position."""
        self._ncc_windows = {}
        self._finishes += 1
        try:
            self._finish_on_map(al, ids, cands)
        finally:
            self._ncc_windows = {}
            old = self._finishes - _SURFACE_KEEP_FINISHES
            for key in [k for k, v in self._ncc_surfaces.items() if v[3] <= old]:
                del self._ncc_surfaces[key]

    def _finish_on_map(self, al: Alignment, ids: list[int], cands: list[list[Candidate]]) -> None:
        """:meth:`_finish` on the current map (its NCC windows memoised)."""
        cfg, geo = self.config, self.geometry
        R = al.R_target_source
        src = self.source_dirs[ids]
        predicted = None if R is None else src @ R.T
        self._guide_all(al.placements, ids, predicted, al.v_tol)
        matched = [ids.index(p.index) for p in al.placements if p.status == 'matched']
        up = self._up()
        if (R is None or al.v_tol is None or up is None or not cfg.parallax_model
                or len(matched) < cfg.parallax_min_matches):
            return
        assert predicted is not None  # R is set
        found = {p.index: p.direction for p in al.placements}
        observed = np.array([found[ids[k]] for k in matched])
        fitted = self._parallax_fit(ids, predicted, matched, observed, up)
        model, corrected = fitted.model, fitted.corrected.copy()
        al.depth_ratio_sigma = fitted.depth_ratio_sigma
        if fitted.prediction_sigma is not None:
            al.prediction_sigma = dict(fitted.prediction_sigma)
        post = cfg
        if cfg.parallax_gate_sigmas > 0:
            al.parallax_gate_px = fitted.gate_px
            post = replace(cfg, placement_px=al.parallax_gate_px)
        al.placements = place_annotations(R, src, cands, post, geo, al.v_tol, predicted=corrected,
                                          directions=self._directions)
        al.parallax = model
        self._guide_all(al.placements, ids, corrected, al.v_tol, post)
        if cfg.lookalike_margin > 0:
            local = {i: k for k, i in enumerate(ids)}
            for p in al.placements:
                if p.status == 'matched' and not self.landmark[p.index]:
                    self._lookalike(p, corrected[local[p.index]], al.v_tol, post.placement_px)

    def _parallax_fit(self, ids: list[int], predicted: Array, matched: list[int], observed: Array,
                      up: Array) -> _ParallaxFit:
        """The parallax model fitted on the matches (``predicted`` where the rotation puts the
        group's annotations, ``observed`` where the ``matched`` ones were found) and the corrected
        predictions: every annotation's with the model (the annotations' scaled by their depth
        ratio), a matched one's from the others only. Kept for the next ``result`` calls: while
        the rotation, the up direction and the matches stay bit for bit the same (a tile that
        added only candidates nothing was placed at), so does all of this."""
        key = (tuple(ids), predicted.tobytes(), tuple(matched), observed.tobytes(), up.tobytes())
        kept = self._parallax_fits.get(key)
        if kept is not None:
            self._parallax_fits.move_to_end(key)
            return kept
        cfg = self.config

        def fit(rows: Array | slice) -> ParallaxModel:
            return fit_parallax(predicted[matched][rows], observed[rows], up, cfg.parallax_sigma_match,
                                cfg.parallax_sigma, cfg.parallax_trim_sigmas, cfg.parallax_elevation)

        # The annotations' parallax as a factor of the model's (their facades are farther than
        # the landmarks it is mostly fitted on), from the matched annotations - without the one
        # being predicted; landmarks keep the common depth.
        shown = ~self.landmark[ids]
        ann = shown[matched]

        def scaled(m: ParallaxModel, rows: NDArray[np.bool_]) -> ParallaxModel:
            if cfg.parallax_scale_sigma <= 0:
                return m
            return m.scaled(fit_depth_scale(m, predicted[matched][rows & ann], observed[rows & ann],
                                            cfg.parallax_sigma_match, cfg.parallax_scale_sigma))

        every = np.ones(len(matched), bool)
        model = fit(slice(None))
        corrected = model.apply(predicted)
        depth_ratio_sigma = float('nan')
        if cfg.parallax_scale_sigma > 0:
            corrected[shown] = scaled(model, every).apply(predicted[shown])
            depth_ratio_sigma = depth_scale_sigma(model, predicted[matched][ann], cfg.parallax_sigma_match,
                                                  cfg.parallax_scale_sigma)
        sigmas = None
        if cfg.prediction_support and cfg.depth_ratio_support_rad > 0:  # read by the support rule only
            rows = np.flatnonzero(shown)  # the support rule judges annotations only
            sig = prediction_sigma(model, predicted[matched], observed, predicted[rows], cfg.parallax_sigma_match,
                                   cfg.parallax_sigma)
            sigmas = {ids[k]: float(x) for k, x in zip(rows, sig)}
        # A matched annotation's own position comes from the others only (leave-one-out).
        corrected[matched] = leave_one_out_predictions(
            predicted[matched], observed, up, cfg.parallax_sigma_match, cfg.parallax_sigma, cfg.parallax_trim_sigmas,
            cfg.parallax_elevation, ann if cfg.parallax_scale_sigma > 0 else None, cfg.parallax_scale_sigma)
        gate = self._parallax_gate(corrected[matched], observed) if cfg.parallax_gate_sigmas > 0 else float('nan')
        corrected.flags.writeable = False
        fitted = _ParallaxFit(model, corrected, depth_ratio_sigma, sigmas, gate)
        self._parallax_fits[key] = fitted
        while len(self._parallax_fits) > _PARALLAX_FITS_KEPT:
            self._parallax_fits.popitem(last=False)
        return fitted

    def _parallax_gate(self, predicted: Array, observed: Array) -> float:
        """Placement gate after the parallax model (``parallax_gate_sigmas``): that many robust
        standard deviations (1.4826 x median absolute) of the horizontal distances between the
        matches and their leave-one-out predictions, clipped to [inlier_px, placement_px]."""
        cfg, geo = self.config, self.geometry
        du = geo.column_distance(geo.project(predicted)[0], geo.project(observed)[0])
        scale = 1.4826 * float(np.median(du))
        return float(np.clip(cfg.parallax_gate_sigmas * scale, cfg.inlier_px, cfg.placement_px))

    def _guide_all(self, placements: list[Placement], ids: list[int], predicted: Array | None,
                   v_tol: float | None, config: MatchConfig | None = None) -> None:
        """Placement indices from the group's (local) to the annotations' (``ids``), then the
        guided re-detection (``guided_search``) of inferred placements and, with ``guided_all``,
        of matched ones around their ``predicted`` direction (local order); ``config`` (default
        the detector's) sets the window."""
        cfg = config or self.config
        todo: list[tuple[Placement, float, float]] = []
        for p in placements:
            local = p.index
            p.index = ids[local]
            if not cfg.guided_search:
                continue
            if p.status == 'inferred':
                todo.append((p, p.u, p.v))
            elif cfg.guided_all and predicted is not None:
                u, v = self.geometry.project(predicted[local])
                todo.append((p, float(u), float(v)))
        if todo:
            self._guided(todo, v_tol, cfg)

    def _up(self) -> Array | None:
        """The up direction (ENU z) in the browsing panorama's frame, None without its orientation."""
        return None if self.R_enu_target is None else self.R_enu_target[2].copy()
