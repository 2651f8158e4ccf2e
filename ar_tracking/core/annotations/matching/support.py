"""Whether an alignment may be shown (Langlotz 2011 sec. 4.3; issue 17: no label the matcher is
not sure of): enough matches, agreement with the sensor prior within its uncertainty, and per
placement local support by nearby matched landmarks. A mixin of
:class:`.redetector.ReDetector`, which holds the state named below."""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from ...panorama.cylinder import CylinderGeometry
from ...rotations import trace_angle
from .config import MatchConfig
from .placement import Alignment, Placement, offset_from_prediction_px

Array = NDArray[np.float64]


class SupportTest:
    """:meth:`_support` of an alignment and the sensor prior it is judged against."""

    config: MatchConfig
    geometry: CylinderGeometry
    landmark: NDArray[np.bool_]
    R_enu_source: Sequence[Array | None]
    R_enu_target: Array | None
    source_sigma: Array
    target_sigma: float
    source_dirs: Array

    def _support(self, al: Alignment, ids: list[int]) -> None:
        """Whether the alignment supports showing its placements (:attr:`MatchConfig.min_support_matches`)."""
        cfg = self.config
        al.support = sum(p.status == 'matched' for p in al.placements + al.landmarks)
        al.supported = False
        if al.R_target_source is None:
            al.support_reason = 'no alignment'
            return
        if al.support < cfg.min_support_matches:
            al.support_reason = f'{al.support} matches (fewer than {cfg.min_support_matches})'
            return
        R_prior = self._prior_rotation(ids)
        if R_prior is not None:
            al.prior_correction_rad = float(trace_angle(R_prior.T @ al.R_target_source))
            sigma = math.hypot(float(self.source_sigma[ids[0]]), self.target_sigma)
            limit = cfg.support_prior_sigmas * sigma + cfg.inlier_px / self.geometry.f
            if math.isfinite(sigma) and al.prior_correction_rad > limit and al.support < cfg.strong_support_matches:
                al.support_reason = (f'{math.degrees(al.prior_correction_rad):.1f} deg from the sensor prior '
                                     f'(> {math.degrees(limit):.1f}) with {al.support} matches')
                return
        al.supported = True
        al.support_reason = ''
        matched = [p for p in al.placements + al.landmarks if p.status == 'matched']
        mu = np.array([p.u for p in matched])
        local = bool(self.landmark[ids].any())  # the local tests need landmarks' density
        W = self.geometry.width
        for p in al.placements:
            near = int(np.sum(self.geometry.column_distance(mu, p.u) <= cfg.local_support_px)) if len(mu) else 0
            if not local:
                p.supported = True
            elif p.status == 'matched':
                p.supported = ((not cfg.local_support_matched or near - 1 >= cfg.local_support_matches)
                               and self._agrees(p))
            else:
                p.supported = near >= cfg.local_support_matches
                if not p.supported and cfg.bracket_support_px > 0 and len(mu):
                    du = (mu - p.u + W / 2) % W - W / 2  # signed column offsets of the matches
                    p.supported = bool(((du < 0) & (du >= -cfg.bracket_support_px)).any()
                                       and ((du > 0) & (du <= cfg.bracket_support_px)).any())
                if p.supported and not self._depth_ratio_pins(al, p):
                    p.supported = False

    def _agrees(self, p: Placement) -> bool:
        """Whether the matched placement ``p`` lies within :attr:`MatchConfig.matched_agreement_px`
        of where the alignment puts it (always without a limit or a prediction)."""
        limit = self.config.matched_agreement_px
        return bool(limit <= 0 or p.predicted is None or offset_from_prediction_px(p, self.geometry) <= limit)

    def _depth_ratio_pins(self, al: Alignment, p: Placement) -> bool:
        """Whether the inferred placement ``p`` is pinned to within
        :attr:`MatchConfig.depth_ratio_support_rad` (1 sigma): the parallax model's term at it
        (heading and, with ``parallax_elevation``, elevation) times the depth ratio's standard
        deviation (the fitted ratio's, none without ``parallax_scale_sigma``, and
        ``depth_ratio_scatter``), with the model's own uncertainty there (``prediction_support``)."""
        limit = self.config.depth_ratio_support_rad
        if limit <= 0 or al.parallax is None or al.R_target_source is None:
            return True
        m = al.parallax
        at = self.source_dirs[p.index] @ al.R_target_source.T
        th = m.azimuth(at)  # once for both terms
        term = math.hypot(float(m.shift(at, th)[0]) - m.c, float(m.elevation_shift(at, th)[0]))
        fitted = al.depth_ratio_sigma if math.isfinite(al.depth_ratio_sigma) else 0.0
        ratio = abs(term) * math.hypot(fitted, self.config.depth_ratio_scatter)
        return math.hypot(ratio, al.prediction_sigma.get(p.index, 0.0)) <= limit

    def _prior_rotation(self, ids: list[int]) -> Array | None:
        """R_target_source from the absolute orientations of both panoramas (sec. 4.2), None
        without the sensor prior or either orientation."""
        R_src = self.R_enu_source[ids[0]] if ids else None
        if not self.config.sensor_prior or self.R_enu_target is None or R_src is None:
            return None
        return self.R_enu_target.T @ np.asarray(R_src, float)
