"""PTAM on a camera phone as one object: map, mapping thread and tracker (Klein & Murray 2009).

:class:`SlamSystem` owns the :class:`SlamMap`, the back end's :class:`MapMaker` running in its
background thread (sec. 3: tracking in the foreground, bundle adjustment in the background, its
steps run while the tracker waits for a frame, :mod:`.frame_gate`) and the :class:`Tracker`; ``process(gray, stamp_ns)`` tracks one frame. Accessors give what a ROS node
publishes: keyframe poses, map points and the camera path. No rclpy here.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .camera import Camera, camera_in_world
from .mapper import MapMaker, MapperConfig
from .slam_map import SlamMap
from .tracker import Tracker, TrackerConfig, TrackResult

log = logging.getLogger(__name__)

Array = NDArray[np.float64]


@dataclass(frozen=True)
class SlamConfig:
    """All SLAM parameters: the tracker's, the mapper's and the camera's readout time.

    ``readout_s`` (rolling shutter, sec. 6), when not None, overrides the camera's.
    ``threaded``: run the mapper in its background thread (False: the caller drives it, tests).
    """

    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    mapper: MapperConfig = field(default_factory=MapperConfig)
    readout_s: float | None = None
    threaded: bool = True
    max_path: int = 100000


class SlamSystem:
    """Map + MapMaker thread + Tracker. Use as a context manager or call :meth:`close`."""

    def __init__(self, camera: Camera, config: SlamConfig | None = None) -> None:
        self.config = config or SlamConfig()
        if self.config.readout_s is not None:
            camera = replace(camera, readout_s=float(self.config.readout_s))
        self.camera = camera
        self.map = SlamMap()
        self.mapper = MapMaker(self.map, camera, self.config.mapper)
        if self.config.threaded:
            self.mapper.start()
        self.tracker = Tracker(camera, self.map, self.mapper, self.config.tracker)
        #: (stamp_ns, R_w_c, p_w_c) of every frame with a pose.
        self.path: list[tuple[int, Array, Array]] = []
        self._closed = False

    def process(self, gray: NDArray[np.uint8], stamp_ns: int) -> TrackResult:
        """Tracks one frame (never raises on bad input; see :class:`TrackResult`)."""
        res = self.tracker.track(gray, int(stamp_ns))
        if res.R_c_w is not None and res.t_c_w is not None and res.state in ('tracking', 'relocalised'):
            R_w_c, p_w_c = camera_in_world(res.R_c_w, res.t_c_w)
            self.path.append((int(stamp_ns), R_w_c, p_w_c))
            if len(self.path) > self.config.max_path:
                del self.path[: len(self.path) // 10]
        if not self.config.threaded and res.keyframe_added:
            self.mapper.process_queue()
        return res

    def wait_for_mapping(self, timeout_s: float = 30.0) -> bool:
        """Blocks until the mapper has processed every queued keyframe and finished its global
        bundle adjustment. Lockstep graph runs call it *after* a frame's outputs are published, so
        the map the next frame sees does not depend on thread timing (reproducible runs); live
        tracking never calls it. Returns False on timeout."""
        if not self.config.threaded:
            return True
        return bool(self.mapper.wait_idle(timeout_s, include_global_ba=True))

    def keyframe_poses(self) -> list[tuple[int, Array, Array]]:
        """(id, R_w_c, p_w_c) of every keyframe not erased."""
        with self.map.lock:
            out = []
            for kf in self.map.keyframes.values():
                if not kf.erased:
                    R_w_c, p = camera_in_world(kf.R_c_w, kf.t_c_w)
                    out.append((kf.id, R_w_c.copy(), p.copy()))
            return out

    def map_points(self) -> Array:
        """(N, 3) positions of the good map points in the map frame."""
        return self.map.point_arrays()[1]

    def stats(self) -> dict[str, Any]:
        """Tracker and mapper statistics (tracking time p50/p95 in ms)."""
        t = self.tracker.stats
        p50, p95 = self.tracker.timing_ms()
        out = {k: v for k, v in t.items() if k != 'times_ms'}
        out.update(track_ms_p50=p50, track_ms_p95=p95, n_points=len(self.map.points),
                   n_keyframes=len(self.map.keyframes))
        out['mapper'] = dict(self.mapper.stats)
        return out

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            self.mapper.stop()
        except Exception:  # pragma: no cover
            log.exception('mapper stop failed')

    def __enter__(self) -> 'SlamSystem':
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
