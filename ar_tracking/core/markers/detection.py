"""Marker candidates and IDs from OpenCV's ArUco detector (AprilTag / ArUco dictionaries), then
corner refinement: the seed's edge model (:mod:`.edge_refinement`, Caarls 2009 sec. 2.4),
OpenCV's CORNER_REFINE_SUBPIX, or none - selectable, so that they can be compared.

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
from .edge_refinement import refine_quad
from .lens_model import LensModel

Array = NDArray[np.float64]
REFINEMENTS = ('caarls', 'subpix', 'none')


@dataclass(frozen=True)
class MarkerObservation:
    """One accepted marker: ID and its 4 corners (ArUco order: top-left, top-right,
    bottom-right, bottom-left of the marker seen from the front)."""

    id: int
    corners_px: Array       # (4, 2) refined, in the (distorted) image
    corners_norm: Array     # (4, 2) normalised undistorted coordinates
    detector_px: Array      # (4, 2) as the ArUco detector gave them


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
                 edge_sigma_px: float = 1.0) -> None:
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

    def detect(self, gray: NDArray[np.uint8], lens: LensModel,
               known_ids: set[int] | None = None) -> tuple[list[MarkerObservation], list[MarkerRejection]]:
        """Accepted markers and rejected ones (with reasons) in an 8-bit grey image."""
        corners, ids, _ = self.detector.detectMarkers(gray)
        accepted: list[MarkerObservation] = []
        rejected: list[MarkerRejection] = []
        if ids is None:
            return accepted, rejected
        for quad, mid in zip(corners, ids.ravel()):
            q = quad.reshape(4, 2).astype(np.float64)
            mid = int(mid)
            if known_ids is not None and mid not in known_ids:
                rejected.append(MarkerRejection(mid, q, 'ID not in the marker map'))
                continue
            problem = quad_shape_problem(q, self.min_corner_angle_deg, self.min_side_px)
            if problem is not None:
                rejected.append(MarkerRejection(mid, q, problem))
                continue
            if self.refinement == 'caarls':
                refined = refine_quad(gray, q, lens, sigma=self.edge_sigma_px)
                if refined is None:
                    rejected.append(MarkerRejection(mid, q, 'edges not found on all four sides'))
                    continue
                accepted.append(MarkerObservation(mid, refined.corners_px, refined.corners_norm, q))
            else:
                accepted.append(MarkerObservation(mid, q, lens.undistort(q), q))
        accepted.sort(key=lambda o: o.id)
        return accepted, rejected
