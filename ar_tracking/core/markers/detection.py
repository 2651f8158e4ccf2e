"""Marker candidates and IDs from OpenCV's ArUco detector (AprilTag / ArUco dictionaries), then
corner refinement: the seed's edge model (:mod:`.edge_refinement`, Caarls 2009 sec. 2.4),
OpenCV's CORNER_REFINE_SUBPIX, or none - selectable, so that they can be compared.

Real images: the edge model is fitted on the image mapped back to light
(:mod:`.photometry`: a display gamma given as ``response_gamma``, or estimated from the
markers' own edges when it is 0). The refinement measures each side's blur; a blurred marker
(motion blur of a quick pan, defocus) keeps its corners, but every corner carries a 1-sigma
(:attr:`MarkerObservation.corner_sigma_px`) that grows with the blur of its two sides, with
their line-fit residuals and with missing edge points (a side partly occluded or cut by the
image border), so that the pose covariance says when the corners are poor.

The candidate search of the paper (Canny contours, Haralick-Shapiro corners) is replaced by a
maintained detector; what the paper contributes - the corner locations - is computed here.
Markers whose quad is too oblique ("seen edge-on": an interior angle outside
[min_corner_angle_deg, 180 - min_corner_angle_deg] or a side much shorter than the opposite
side) or too small are rejected with a reason, as are IDs missing from the marker map.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from . import MarkerError
from .edge_refinement import RefinedQuad, refine_quad
from .lens_model import LensModel
from .photometry import GammaEstimator, estimate_gamma, linearize

Array = NDArray[np.float64]
REFINEMENTS = ('caarls', 'subpix', 'none')
#: Markers with edges blurred less than this (px) feed the gamma estimate.
SHARP_BLUR_PX = 1.5


@dataclass(frozen=True)
class MarkerObservation:
    """One accepted marker: ID and its 4 corners (ArUco order: top-left, top-right,
    bottom-right, bottom-left of the marker seen from the front)."""

    id: int
    corners_px: Array       # (4, 2) refined, in the (distorted) image
    corners_norm: Array     # (4, 2) normalised undistorted coordinates
    detector_px: Array      # (4, 2) as the ArUco detector gave them
    #: (4,) 1-sigma of each corner, px (None: unknown, the pose uses its configured floor)
    corner_sigma_px: Array | None = None
    #: largest edge blur (eq. 1 sigma) of the four sides, px
    blur_px: float = 0.0


@dataclass(frozen=True)
class MarkerRejection:
    id: int
    corners_px: Array
    reason: str


def quad_shape_problem(quad: Array, min_corner_angle_deg: float, min_side_px: float) -> str | None:
    """Why a quad is unusable for pose (edge-on, too small), or None."""
    q = np.asarray(quad, float).reshape(4, 2)
    sides = np.roll(q, -1, axis=0) - q
    lengths = np.linalg.norm(sides, axis=1)
    if lengths.min() < min_side_px:
        return f'too small (side {lengths.min():.1f} px)'
    for i in range(4):
        a, b = -sides[i - 1], sides[i]
        cosang = float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))
        ang = math.degrees(math.acos(max(-1.0, min(1.0, cosang))))
        if ang < min_corner_angle_deg or ang > 180.0 - min_corner_angle_deg:
            return f'seen edge-on (corner angle {ang:.0f} deg)'
    ratio = min(lengths[0] / lengths[2], lengths[2] / lengths[0], lengths[1] / lengths[3], lengths[3] / lengths[1])
    if ratio < 0.3:
        return f'seen edge-on (opposite sides differ {1 / ratio:.1f}x)'
    # A square marker turned by more than ~78 deg away from the camera looks like a sliver.
    aspect = lengths.min() / lengths.max()
    if aspect < 0.2:
        return f'seen edge-on (aspect {aspect:.2f})'
    return None


class MarkerDetector:
    """ArUco/AprilTag candidates + the selected corner refinement."""

    def __init__(self, dictionary: str = 'DICT_APRILTAG_36h11', refinement: str = 'caarls',
                 min_corner_angle_deg: float = 25.0, min_side_px: float = 12.0,
                 edge_sigma_px: float = 1.0, response_gamma: float = 0.0,
                 corner_sigma_px: float = 0.06, blur_sigma_gain: float = 0.25,
                 print_contrast: float = 0.0) -> None:
        """``response_gamma``: the camera's display gamma (1: linear images; 0: estimated from
        the markers: from their black and white levels when ``print_contrast``, the printed
        white/black reflectance ratio, is given, else from the symmetry of their edges). ``corner_sigma_px``: corner 1-sigma of a sharp, fully seen marker;
        ``blur_sigma_gain``: corner sigma added per px of edge blur beyond 1 px."""
        if not hasattr(cv2.aruco, dictionary) or not dictionary.startswith('DICT_'):
            raise MarkerError(f'unknown marker dictionary {dictionary!r}')
        if refinement not in REFINEMENTS:
            raise MarkerError(f'unknown corner refinement {refinement!r} (use {", ".join(REFINEMENTS)})')
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX if refinement == 'subpix' else cv2.aruco.CORNER_REFINE_NONE
        self.detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)), params)
        self.refinement = refinement
        self.min_corner_angle_deg = min_corner_angle_deg
        self.min_side_px = min_side_px
        self.edge_sigma_px = edge_sigma_px
        if not (response_gamma == 0.0 or 0.2 <= response_gamma <= 5.0):
            raise MarkerError(f'response_gamma {response_gamma} is not a display gamma (0 = estimate, or 0.2-5)')
        self.response_gamma = float(response_gamma)
        self.print_contrast = float(print_contrast)
        self.gamma_estimator = GammaEstimator()
        self.corner_sigma_px = float(corner_sigma_px)
        self.blur_sigma_gain = float(blur_sigma_gain)

    @property
    def gamma(self) -> float:
        """The response gamma in use (the parameter, or the estimate so far; 1 before any)."""
        if self.response_gamma > 0:
            return self.response_gamma
        return self.gamma_estimator.gamma or 1.0

    def _refine(self, lin: NDArray, q: Array, lens: LensModel) -> RefinedQuad | None:
        """Edge-model corners on the linear image. (Refining blurred markers again with a
        derivative filter as wide as their edges was tried: the corners' RMS went down, but
        their errors became correlated along each side and the pose got worse - 2.9 vs 1.6 cm
        on the pan frames of a hard bag - so blur only raises the corner sigmas.)"""
        return refine_quad(lin, q, lens, sigma=self.edge_sigma_px)

    def corner_sigmas(self, refined: RefinedQuad) -> Array:
        """1-sigma of each corner, px: the floor, the blur and line residuals of its two sides,
        inflated when a side gave edge points along only part of its length."""
        b = np.asarray(refined.side_blur_px, float)
        b = np.where(np.isfinite(b), b, 10.0)
        rms = np.asarray(refined.side_rms_px, float)
        cover = np.clip(np.asarray(refined.side_coverage, float), 0.05, 1.0)
        # A blur up to ~1 px (focus, pixel area) costs nothing the floor does not cover.
        side_var = (self.blur_sigma_gain * np.maximum(b - 1.0, 0.0)) ** 2 + rms ** 2
        side_scale = np.where(cover < 0.8, 1.0 / cover, 1.0)
        prev = np.roll(np.arange(4), 1)  # corner i is where side i-1 meets side i
        var = self.corner_sigma_px ** 2 + 0.5 * (side_var + side_var[prev])
        return np.sqrt(var) * np.maximum(side_scale, side_scale[prev])

    def detect(self, gray: NDArray[np.uint8], lens: LensModel,
               known_ids: set[int] | None = None) -> tuple[list[MarkerObservation], list[MarkerRejection]]:
        """Accepted markers and rejected ones (with reasons) in an 8-bit grey image."""
        corners, ids, _ = self.detector.detectMarkers(gray)
        accepted: list[MarkerObservation] = []
        rejected: list[MarkerRejection] = []
        if ids is None:
            return accepted, rejected
        candidates = []
        for quad, raw_id in zip(corners, ids.ravel()):
            q = quad.reshape(4, 2).astype(np.float64)
            mid = int(raw_id)
            if known_ids is not None and mid not in known_ids:
                rejected.append(MarkerRejection(mid, q, 'ID not in the marker map'))
                continue
            problem = quad_shape_problem(q, self.min_corner_angle_deg, self.min_side_px)
            if problem is not None:
                rejected.append(MarkerRejection(mid, q, problem))
                continue
            candidates.append((mid, q))
        if self.refinement != 'caarls':
            for mid, q in candidates:
                accepted.append(MarkerObservation(mid, q, lens.undistort(q), q))
            accepted.sort(key=lambda o: o.id)
            return accepted, rejected
        gamma = self.gamma
        lin = linearize(gray, gamma)
        refined_all = [(mid, q, self._refine(lin, q, lens)) for mid, q in candidates]
        if self.response_gamma == 0.0 and not self.gamma_estimator.settled:
            for _mid, _q, refined in refined_all:
                if refined is not None and float(np.max(refined.side_blur_px)) < SHARP_BLUR_PX:
                    self.gamma_estimator.add(estimate_gamma(gray, refined.corners_norm, lens, self.print_contrast))
            if abs(self.gamma - gamma) > 0.01 * gamma:  # the estimate moved: refine this frame again
                lin = linearize(gray, self.gamma)
                refined_all = [(mid, q, self._refine(lin, q, lens)) for mid, q in candidates]
        for mid, q, refined in refined_all:
            if refined is None:
                rejected.append(MarkerRejection(mid, q, 'edges not found on all four sides'))
                continue
            accepted.append(MarkerObservation(mid, refined.corners_px, refined.corners_norm, q,
                                              self.corner_sigmas(refined), float(np.max(refined.side_blur_px))))
        accepted.sort(key=lambda o: o.id)
        return accepted, rejected
