"""Keyframe-based relocalisation (Klein & Murray ECCV'08, used by PTAM on the phone, sec. 3.3).

When tracking is lost, the frame's small blurry image (coarsest pyramid level, blurred, zero mean,
:func:`.pyramid.small_blurry_image`) is compared with every keyframe's - erased keyframes too,
they are kept for this purpose (sec. 3.3 footnote) - by the zero-mean sum of squared differences.
The best keyframe's SBI is then aligned to the frame by the same 3-DoF ESM rotation estimate as
the full-frame rotation prior (sec. 4); the candidate pose is the keyframe's pose turned by that
rotation about the camera centre. The tracker then tries to track from the candidate.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from ..rotations import trace_angle
from .camera import Camera
from .rotation_prior import estimate_rotation
from .slam_map import Keyframe

log = logging.getLogger(__name__)

Array = NDArray[np.float64]


@dataclass
class RelocCandidate:
    """Candidate pose from the best-matching keyframe."""

    kf_id: int
    R_c_w: Array
    t_c_w: Array
    ssd: float  #: mean squared difference per pixel of the SBIs (grey levels^2)
    rotation_residual: float


def sbi_distance(a: NDArray[np.float32], b: NDArray[np.float32]) -> float:
    """Zero-mean SSD per pixel between two small blurry images of the same size."""
    if a.shape != b.shape:
        return float('inf')
    d = (a - a.mean()) - (b - b.mean())
    return float(np.mean(d * d))


def relocalise(sbi: NDArray[np.float32], keyframes: Sequence[Keyframe], camera: Camera,
               max_ssd: float | None = None, exclude: set[int] | None = None) -> RelocCandidate | None:
    """Best keyframe by SBI ZSSD and its rotation-corrected pose, or None.

    ``camera`` is the level-0 camera; the coarsest level is inferred from the SBI size. Keyframes in
    ``exclude`` (e.g. already tried) are skipped; ``max_ssd`` rejects poor matches.
    """
    best: tuple[float, Keyframe, NDArray[np.float32]] | None = None  # (distance, keyframe, its SBI)
    for kf in keyframes:
        if kf.sbi is None or (exclude and kf.id in exclude):
            continue
        d = sbi_distance(sbi, kf.sbi)
        if best is None or d < best[0]:
            best = (d, kf, kf.sbi)
    if best is None:
        return None
    d, kf, kf_sbi = best
    if max_ssd is not None and d > max_ssd:
        return None
    level = int(round(np.log2(camera.width / sbi.shape[1])))
    est = estimate_rotation(kf_sbi, sbi, camera.at_level(level), iterations=10)
    R = est.R_cur_prev
    if not np.isfinite(est.residual) or est.residual > est.residual0 or trace_angle(R) > 0.6:
        R = np.eye(3)
    return RelocCandidate(kf.id, R @ kf.R_c_w, R @ kf.t_c_w, d, est.residual)
