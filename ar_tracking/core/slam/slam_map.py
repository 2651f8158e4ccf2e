"""The map shared by the tracking and the mapping thread (Klein & Murray 2009 sec. 3).

Keyframes own their image pyramid and their measurements; map points know which keyframes
measure them. Partially initialised points (sec. 5.2) live beside the map points until a second
keyframe measures them. Every mutation goes through :class:`SlamMap` methods under ``lock`` so
that the two threads keep the keyframe and point sides consistent; the tracker only copies what
it needs under the lock (:meth:`SlamMap.point_arrays`) and never waits on bundle adjustment, which
works on copies and writes its result back in one short locked step (:meth:`SlamMap.apply_update`).
"""
from __future__ import annotations

import threading
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]
Image = NDArray[np.uint8]


@dataclass
class Measurement:
    """One observation of a map point in a keyframe, in level-0 pixels.

    ``uv`` is what the search found; ``uv_corrected`` is ``uv`` after the rolling-shutter
    correction of sec. 6 (equal to ``uv`` until the mapper corrects it) and is what bundle
    adjustment uses. ``level`` is the pyramid level the match was made on; the measurement's
    standard deviation is ``2**level`` level-0 pixels.
    """

    kf_id: int
    point_id: int
    uv: Array
    level: int
    uv_corrected: Array | None = None

    def __post_init__(self) -> None:
        self.uv = np.asarray(self.uv, dtype=float).reshape(2)
        if self.uv_corrected is None:
            self.uv_corrected = self.uv.copy()

    @property
    def sigma_px(self) -> float:
        return float(2 ** self.level)


@dataclass
class Keyframe:
    """A keyframe: pose ``R_c_w, t_c_w`` (world -> camera), its pyramid and its measurements.

    ``sbi`` is the small blurry image (coarsest level, blurred, zero mean) used by the
    keyframe-based relocaliser. ``erased`` keyframes were culled (sec. 3.3): they stay in memory
    for their pixels, to stop new keyframes at the same place, and for relocalisation, but take no
    part in bundle adjustment. ``fixed`` keyframes (the first) anchor the gauge in bundle adjustment.
    """

    id: int
    stamp_ns: int
    R_c_w: Array
    t_c_w: Array
    pyramid: list[Image]
    sbi: NDArray[np.float32] | None = None
    measurements: dict[int, Measurement] = field(default_factory=dict)
    #: Image velocities (level-0 px/s) of measured points, point id -> (du/dt, dv/dt), from the
    #: frames before and after the keyframe (sec. 6); filled by the tracker when known.
    image_velocities: dict[int, Array] = field(default_factory=dict)
    fixed: bool = False
    erased: bool = False

    @property
    def position_w(self) -> Array:
        return -self.R_c_w.T @ self.t_c_w


@dataclass
class MapPoint:
    """A 3-D point in the map frame, created from a corner of ``source_kf`` at ``source_level``.

    ``source_uv`` (level-0 pixels in the source keyframe) and ``source_level`` say where the
    template patch comes from (sec. 4: the search level is fixed, the source level varies).
    ``n_found`` / ``n_tried`` count the tracker's searches, for outlier removal.
    """

    id: int
    xyz: Array
    source_kf: int
    source_level: int
    source_uv: Array
    observers: set[int] = field(default_factory=set)
    n_found: int = 0
    n_tried: int = 0
    bad: bool = False


@dataclass
class PartialPoint:
    """A partially initialised point (sec. 5.2): a ray from ``source_kf`` with inverse depth q.

    The point is ``ray / q`` in the source keyframe's camera frame, ``ray = (x, y, 1)``;
    ``q ~ N(q_hat, 1 / info)`` with ``info = 0`` meaning infinite uncertainty.
    """

    id: int
    source_kf: int
    source_level: int
    source_uv: Array
    ray: Array
    q_hat: float
    info: float = 0.0
    n_updates: int = 0


class SlamMap:
    """Keyframes, map points and partial points with a lock shared by both threads."""

    def __init__(self) -> None:
        self.lock = threading.RLock()
        self.keyframes: dict[int, Keyframe] = {}
        self.points: dict[int, MapPoint] = {}
        self.partial_points: dict[int, PartialPoint] = {}
        #: Bumped whenever bundle adjustment or culling changes poses or points.
        self.version = 0
        self._next_kf = 0
        self._next_point = 0

    # ---- ids -------------------------------------------------------------------------------
    def new_keyframe_id(self) -> int:
        with self.lock:
            self._next_kf += 1
            return self._next_kf - 1

    def new_point_id(self) -> int:
        with self.lock:
            self._next_point += 1
            return self._next_point - 1

    # ---- mutation ----------------------------------------------------------------------------
    def add_keyframe(self, kf: Keyframe) -> None:
        with self.lock:
            self.keyframes[kf.id] = kf
            for m in kf.measurements.values():
                if m.point_id in self.points:
                    self.points[m.point_id].observers.add(kf.id)

    def add_point(self, point: MapPoint) -> None:
        with self.lock:
            self.points[point.id] = point

    def add_measurement(self, m: Measurement) -> None:
        with self.lock:
            kf = self.keyframes[m.kf_id]
            kf.measurements[m.point_id] = m
            self.points[m.point_id].observers.add(m.kf_id)

    def remove_measurement(self, kf_id: int, point_id: int) -> None:
        with self.lock:
            kf = self.keyframes.get(kf_id)
            if kf is not None:
                kf.measurements.pop(point_id, None)
            p = self.points.get(point_id)
            if p is not None:
                p.observers.discard(kf_id)

    def remove_point(self, point_id: int) -> None:
        with self.lock:
            p = self.points.pop(point_id, None)
            if p is None:
                return
            for kf_id in p.observers:
                kf = self.keyframes.get(kf_id)
                if kf is not None:
                    kf.measurements.pop(point_id, None)

    def erase_keyframe(self, kf_id: int) -> None:
        """Culls a keyframe (sec. 3.3): its measurements leave the map; the keyframe stays."""
        with self.lock:
            kf = self.keyframes[kf_id]
            for pid in list(kf.measurements):
                p = self.points.get(pid)
                if p is not None:
                    p.observers.discard(kf_id)
            kf.measurements.clear()
            kf.erased = True
            self.version += 1

    def apply_update(self, poses: dict[int, tuple[Array, Array]], points: dict[int, Array]) -> None:
        """Writes bundle-adjusted keyframe poses and point positions back in one locked step."""
        with self.lock:
            for kf_id, (R, t) in poses.items():
                kf = self.keyframes.get(kf_id)
                if kf is not None:
                    kf.R_c_w, kf.t_c_w = np.asarray(R, float), np.asarray(t, float)
            for pid, xyz in points.items():
                p = self.points.get(pid)
                if p is not None:
                    p.xyz = np.asarray(xyz, float)
            self.version += 1

    # ---- reading -------------------------------------------------------------------------------
    def active_keyframes(self) -> list[Keyframe]:
        with self.lock:
            return [kf for kf in self.keyframes.values() if not kf.erased]

    def point_arrays(self) -> tuple[NDArray[np.int64], Array]:
        """(ids, xyz (N, 3)) of the good map points: a copy the tracker can use without the lock."""
        with self.lock:
            good = [p for p in self.points.values() if not p.bad]
            ids = np.array([p.id for p in good], dtype=np.int64)
            xyz = np.array([p.xyz for p in good], dtype=float).reshape(-1, 3)
            return ids, xyz

    def __len__(self) -> int:
        return len(self.points)
