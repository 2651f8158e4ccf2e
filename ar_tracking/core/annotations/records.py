"""The records of the annotation store (Langlotz 2011 sec. 3.2, 4.3): :class:`Annotation`,
:class:`Landmark`, :class:`PanoramaInfo`, their validation (a bad record is skipped and reported,
never stored) and row conversion, the great-circle distance of the radius query and the
:class:`AddReport` of a write. The stores (:mod:`.store`, :mod:`ar_tracking.io.postgis_store`)
share them; :mod:`.store` re-exports every name."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

#: Patch sides (pixels) a record may have.
PATCH_SIDES = (8, 16, 24, 32)
EARTH_RADIUS_M = 6_371_008.8
#: Where a panorama's orientation in the world came from. ``annotate`` writes 'estimated' or
#: 'none'; nothing writes 'ground_truth' any more (stores authored with the simulator's truth by
#: earlier versions stay readable, and the matcher treats them like any stored orientation).
ORIENTATION_SOURCES = ('estimated', 'ground_truth', 'none')


@dataclass(frozen=True)
class Annotation:
    """One annotation record (see the module docstring).

    ``direction`` is a unit 3-vector in the source panorama frame (x right, y down, z forward of
    its first camera frame); ``panorama_in_world_quat_xyzw`` is R_enu_panorama of the source
    panorama when known (NaN otherwise)."""

    text: str
    patch: NDArray[np.uint8]
    direction: NDArray[np.float64]
    latitude_deg: float
    longitude_deg: float
    altitude_m: float
    panorama_id: str
    author: str = ''
    created_ns: int = 0
    panorama_in_world_quat_xyzw: NDArray[np.float64] = field(
        default_factory=lambda: np.full(4, np.nan))
    id: int | None = None

    @property
    def patch_side(self) -> int:
        return int(self.patch.shape[0])

    def has_world_orientation(self) -> bool:
        q = np.asarray(self.panorama_in_world_quat_xyzw, float)
        return bool(q.shape == (4,) and np.all(np.isfinite(q)) and abs(np.linalg.norm(q) - 1) < 1e-3)


@dataclass(frozen=True)
class Landmark:
    """A distinctive patch of a source panorama that is not an annotation (see the module docstring).

    The re-detector matches it like an annotation, to get more correspondences for the global
    rotation and the parallax fit, but it is never shown. ``patch`` is a textured square uint8
    image of a side in :data:`PATCH_SIDES`; ``direction`` is the unit 3-vector to its centre in
    the source panorama frame (as :attr:`Annotation.direction`)."""

    panorama_id: str
    patch: NDArray[np.uint8]
    direction: NDArray[np.float64]
    id: int | None = None

    @property
    def patch_side(self) -> int:
        return int(self.patch.shape[0])


@dataclass(frozen=True)
class PanoramaInfo:
    """What authoring knows of a source panorama as a whole: its orientation in the world
    (R_enu_panorama, x y z w; NaN when unknown), the covariance of that orientation's error about
    the ENU axes (x, y: tilt, z: heading; rad^2), the up direction in the panorama frame (unit,
    from gravity; NaN when unknown) and where they came from (:data:`ORIENTATION_SOURCES`:
    ``estimated`` by the graph's cores from the session's own sensors, ``none``, or
    ``ground_truth`` in stores of earlier versions only)."""

    panorama_id: str
    panorama_in_world_quat_xyzw: NDArray[np.float64] = field(default_factory=lambda: np.full(4, np.nan))
    covariance_enu: NDArray[np.float64] = field(default_factory=lambda: np.full((3, 3), np.nan))
    up: NDArray[np.float64] = field(default_factory=lambda: np.full(3, np.nan))
    orientation_source: str = 'none'
    created_ns: int = 0

    def has_world_orientation(self) -> bool:
        q = np.asarray(self.panorama_in_world_quat_xyzw, float)
        return bool(q.shape == (4,) and np.all(np.isfinite(q)) and abs(np.linalg.norm(q) - 1) < 1e-3)

    def heading_sigma_rad(self) -> float:
        """1-sigma of the heading (NaN when unknown)."""
        c = np.asarray(self.covariance_enu, float)
        return float(math.sqrt(c[2, 2])) if c.shape == (3, 3) and np.isfinite(c[2, 2]) and c[2, 2] >= 0 else float('nan')


def validate_panorama(info: PanoramaInfo) -> str | None:
    """None if the panorama record can be stored, else the reason (one line)."""
    if not isinstance(info, PanoramaInfo):
        return f'not a PanoramaInfo ({type(info).__name__})'
    if not info.panorama_id:
        return 'panorama_id is empty'
    if info.orientation_source not in ORIENTATION_SOURCES:
        return f'orientation_source must be one of {ORIENTATION_SOURCES}, got {info.orientation_source!r}'
    q = np.asarray(info.panorama_in_world_quat_xyzw, float)
    if q.shape != (4,) or (np.any(np.isfinite(q)) and not info.has_world_orientation()):
        return 'panorama_in_world_quat_xyzw must be a unit quaternion (or all NaN)'
    c = np.asarray(info.covariance_enu, float)
    if c.shape != (3, 3) or (np.all(np.isfinite(c)) and (np.any(np.diag(c) < 0) or not np.allclose(c, c.T))):
        return 'covariance_enu must be a symmetric 3x3 matrix with a non-negative diagonal (or NaN)'
    u = np.asarray(info.up, float)
    if u.shape != (3,) or (np.all(np.isfinite(u)) and abs(np.linalg.norm(u) - 1.0) > 1e-3):
        return 'up must be a unit 3-vector (or NaN)'
    return None


def _panorama_row(info: PanoramaInfo) -> tuple:
    """(panorama_id, qx, qy, qz, qw, cov blob, up x y z, source, created_ns); NULL for unknowns."""
    q = [float(v) for v in np.asarray(info.panorama_in_world_quat_xyzw, float)] \
        if info.has_world_orientation() else [None] * 4
    c = np.asarray(info.covariance_enu, float)
    cov = c.astype('<f8').tobytes() if np.all(np.isfinite(c)) else None
    u = np.asarray(info.up, float)
    up = [float(v) for v in u] if np.all(np.isfinite(u)) else [None] * 3
    return (info.panorama_id, *q, cov, *up, info.orientation_source, int(info.created_ns))


def panorama_from_row(row: tuple) -> tuple[PanoramaInfo | None, str]:
    """A :class:`PanoramaInfo` from a row in the order of :func:`_panorama_row` (or the reason)."""
    try:
        pid, qx, qy, qz, qw, cov, ux, uy, uz, source, created = row
        q = np.array([np.nan] * 4 if qw is None else [qx, qy, qz, qw], float)
        c = np.full((3, 3), np.nan) if cov is None else np.frombuffer(bytes(cov), '<f8').reshape(3, 3).copy()
        u = np.array([np.nan] * 3 if ux is None else [ux, uy, uz], float)
        info = PanoramaInfo(str(pid), q, c, u, str(source), int(created))
    except (TypeError, ValueError) as exc:
        return None, str(exc)
    reason = validate_panorama(info)
    return (None, reason) if reason else (info, '')


def _patch_and_direction_problem(patch: NDArray[np.uint8], direction: NDArray[np.float64]) -> str | None:
    """None if ``patch`` is a textured square uint8 image of a side in :data:`PATCH_SIDES` and
    ``direction`` a finite unit 3-vector, else the reason (one line). Shared by annotations and
    landmarks."""
    patch = np.asarray(patch)
    if patch.dtype != np.uint8 or patch.ndim != 2 or patch.shape[0] != patch.shape[1] \
            or patch.shape[0] not in PATCH_SIDES:
        return f'patch must be a square uint8 image of side {PATCH_SIDES}, got {patch.dtype} {patch.shape}'
    # OpenCV's standard deviation equals numpy's (population) at a sixth of the cost: every
    # record read back by a radius query passes here.
    if float(cv2.meanStdDev(np.ascontiguousarray(patch))[1][0, 0]) < 1.0:
        return 'patch has no texture'
    d = np.asarray(direction, float)
    if d.shape != (3,) or not np.all(np.isfinite(d)):
        return f'direction must be a finite 3-vector, got {d.tolist()}'
    if abs(np.linalg.norm(d) - 1.0) > 1e-3:
        return f'direction must be a unit vector (norm {np.linalg.norm(d):.3g})'
    return None


def validate_annotation(a: Annotation) -> str | None:
    """None if the record can be stored, else the reason (one line)."""
    reason = _patch_and_direction_problem(a.patch, a.direction)
    if reason is not None:
        return reason
    if not (math.isfinite(a.latitude_deg) and -90 <= a.latitude_deg <= 90
            and math.isfinite(a.longitude_deg) and -180 <= a.longitude_deg <= 180):
        return f'position ({a.latitude_deg}, {a.longitude_deg}) is not a valid latitude/longitude'
    if not math.isfinite(a.altitude_m):
        return f'altitude {a.altitude_m} is not finite'
    if not a.text.strip():
        return 'text is empty'
    if not a.panorama_id:
        return 'panorama_id is empty'
    return None


def validate_landmark(lm: Landmark) -> str | None:
    """None if the landmark can be stored, else the reason (one line)."""
    if not isinstance(lm, Landmark):
        return f'not a Landmark ({type(lm).__name__})'
    reason = _patch_and_direction_problem(lm.patch, lm.direction)
    if reason is not None:
        return reason
    if not lm.panorama_id:
        return 'panorama_id is empty'
    return None


def distance_m(lat1: float, lon1: float, lat2: NDArray | float, lon2: NDArray | float) -> NDArray:
    """Great-circle (haversine) distance in metres."""
    p1, p2 = math.radians(lat1), np.radians(lat2)
    dp, dl = p2 - p1, np.radians(lon2) - math.radians(lon1)
    h = np.sin(dp / 2) ** 2 + math.cos(p1) * np.cos(p2) * np.sin(dl / 2) ** 2
    return 2 * EARTH_RADIUS_M * np.arcsin(np.sqrt(np.clip(h, 0.0, 1.0)))


@dataclass
class AddReport:
    """Outcome of :meth:`AnnotationStore.add` and :meth:`AnnotationStore.add_landmarks`: ids of
    the stored records, reasons of the skipped."""

    ids: list[int] = field(default_factory=list)
    skipped: list[tuple[int, str]] = field(default_factory=list)  # (index in the input, reason)
