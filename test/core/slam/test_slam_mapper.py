"""The mapping thread (Klein & Murray 2009 sec. 3, 5.2): initial map, partial-point promotion,
culling, and the locking discipline (bundle adjustment never under SlamMap.lock)."""
from __future__ import annotations

import threading
import time

import cv2
import numpy as np

from ar_tracking.core.slam.bundle_adjustment import project_world
from ar_tracking.core.slam.camera import Camera
from ar_tracking.core.slam.mapper import MapMaker, MapperConfig
from ar_tracking.core.slam.slam_map import Keyframe, MapPoint, Measurement, PartialPoint, SlamMap
from ar_tracking.sim.ba_problem import make_synthetic_ba_problem

CAM = Camera(fx=300.0, fy=300.0, cx=159.5, cy=119.5, width=320, height=240)


class TimingRLock:
    """An RLock that records, per thread name, the longest outermost hold."""

    def __init__(self) -> None:
        self._lock = threading.RLock()
        self._local = threading.local()
        self.max_hold: dict[str, float] = {}

    def acquire(self, blocking: bool = True, timeout: float = -1) -> bool:
        ok = self._lock.acquire(blocking, timeout)
        if ok:
            depth = getattr(self._local, 'depth', 0)
            if depth == 0:
                self._local.t0 = time.perf_counter()
            self._local.depth = depth + 1
        return ok

    def release(self) -> None:
        self._local.depth -= 1
        if self._local.depth == 0:
            dt = time.perf_counter() - self._local.t0
            name = threading.current_thread().name
            self.max_hold[name] = max(self.max_hold.get(name, 0.0), dt)
        self._lock.release()

    def __enter__(self) -> bool:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()


def _pyramid(seed: int) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.integers(0, 256, (CAM.height, CAM.width)).astype(np.uint8), (0, 0), 2.0)
    img = cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX)
    pyr = [img]
    for _ in range(4):
        pyr.append(cv2.pyrDown(pyr[-1]))
    return pyr


def _kf(slam: SlamMap, R, t, seed: int) -> Keyframe:
    return Keyframe(id=slam.new_keyframe_id(), stamp_ns=seed, R_c_w=np.asarray(R, float),
                    t_c_w=np.asarray(t, float), pyramid=_pyramid(seed))


def test_initial_map_then_thread_promotes_a_partial_point():
    rng = np.random.default_rng(0)
    slam = SlamMap()
    mapper = MapMaker(slam, CAM)
    uv0 = rng.uniform([30, 30], [290, 210], (40, 2))
    depth = rng.uniform(1.8, 2.6, 40)
    X = CAM.unproject(uv0) * depth[:, None]          # world = keyframe 0's camera frame
    kf0 = _kf(slam, np.eye(3), np.zeros(3), 0)
    R1, _ = cv2.Rodrigues(np.array([0.0, -0.05, 0.0]))
    t1 = np.array([-0.25, 0.0, 0.0])
    kf1 = _kf(slam, R1, t1 + rng.normal(0, 0.01, 3), 1)
    uv1 = CAM.project(X @ R1.T + t1)[0] + rng.normal(0, 0.3, (40, 2))
    X_init = X * 1.0 + rng.normal(0, 0.03, X.shape)
    mapper.initialise_map(kf0, kf1, X_init, uv0, uv1, np.zeros(40, int))

    assert kf0.fixed and not kf1.fixed
    assert len(slam.points) == 40 and all(p.observers == {0, 1} for p in slam.points.values())
    assert mapper.stats['ba_runs'] == 1
    assert mapper.stats['last_ba_objective_after'] < mapper.stats['last_ba_objective_before']
    err = np.median([np.linalg.norm(slam.points[p].xyz - X[i]) for i, p in enumerate(sorted(slam.points))])
    assert err < np.median(np.linalg.norm(X_init - X, axis=1))
    assert len(slam.partial_points) > 0           # corners seeded in the initial keyframes

    # A partial point of keyframe 1, its depth still badly known.
    Xp = np.array([0.3, -0.2, 2.2])
    uv_src = CAM.project((R1 @ Xp + t1)[None])[0][0]
    ppid = slam.new_point_id()
    slam.partial_points[ppid] = PartialPoint(ppid, 1, 0, uv_src, CAM.unproject(uv_src)[0], 1.0)

    R2, _ = cv2.Rodrigues(np.array([0.0, -0.1, 0.0]))
    t2 = np.array([-0.5, 0.05, 0.0])
    kf2 = _kf(slam, R2, t2, 2)
    uv2 = CAM.project(X @ R2.T + t2)[0]
    for i, pid in enumerate(sorted(p for p in slam.points)):
        kf2.measurements[pid] = Measurement(kf2.id, pid, uv2[i] + rng.normal(0, 0.3, 2), 0)
    uvp = CAM.project((R2 @ Xp + t2)[None])[0][0]
    bad_pid = min(slam.points)
    slam.points[bad_pid].bad = True            # the tracker gave up on this one
    mapper.start()
    try:
        t0 = time.perf_counter()
        mapper.add_keyframe(kf2, {ppid: Measurement(kf2.id, ppid, uvp, 0)})
        assert time.perf_counter() - t0 < 0.01      # non-blocking
        assert mapper.wait_idle(20.0)
    finally:
        mapper.stop()
    assert not mapper.running and not mapper.busy

    assert bad_pid not in slam.points and bad_pid not in kf2.measurements
    assert ppid in slam.points and ppid not in slam.partial_points
    p = slam.points[ppid]
    assert p.observers == {1, 2} and p.source_kf == 1
    assert np.linalg.norm(p.xyz - Xp) < 0.1
    assert ppid in kf2.measurements and ppid in slam.keyframes[1].measurements
    assert mapper.stats['points_promoted'] == 1 and mapper.stats['keyframes_added'] == 3
    assert mapper.stats['local_ba_runs'] >= 1
    assert mapper.stats['errors'] == 0


def _big_map(config: MapperConfig) -> tuple[SlamMap, MapMaker, TimingRLock, object]:
    prob = make_synthetic_ba_problem(35, 300, seed=3)
    slam = SlamMap()
    lock = TimingRLock()
    slam.lock = lock  # type: ignore[assignment]
    for i in range(300):
        assert slam.new_point_id() == i
    for pid, xyz in prob.points.items():
        src = min(kf.id for kf in prob.keyframes if pid in kf.measurements)
        slam.add_point(MapPoint(pid, xyz.copy(), src, 0, prob.keyframes[src].measurements[pid].uv))
    for kf in prob.keyframes:
        assert slam.new_keyframe_id() == kf.id
        slam.add_keyframe(kf)
    return slam, MapMaker(slam, prob.camera, config), lock, prob


def test_mapper_never_holds_the_lock_during_bundle_adjustment_and_culls():
    cfg = MapperConfig(keyframe_utility_threshold=1e9, global_ba_iterations=10)
    slam, mapper, lock, prob = _big_map(cfg)
    # A 36th keyframe beside keyframe 17 measuring everything it sees: points get a 9th
    # measurement (measurement culling) and there are now 36 active keyframes (keyframe culling).
    R, t = prob.true_poses[17]
    kf = Keyframe(id=slam.new_keyframe_id(), stamp_ns=0, R_c_w=R.copy(), t_c_w=t + 0.01, pyramid=[])
    for pid, X in prob.true_points.items():
        uv, z = project_world(prob.camera, R, t + 0.01, X)
        if z[0] > 0 and prob.camera.in_image(uv)[0]:
            kf.measurements[pid] = Measurement(kf.id, pid, uv[0], 0)
    mapper.start()
    try:
        t0 = time.perf_counter()
        mapper.add_keyframe(kf, {})
        assert time.perf_counter() - t0 < 0.01
        assert mapper.wait_idle(20.0, include_global_ba=True)
    finally:
        mapper.stop()
    s = mapper.stats
    assert s['local_ba_runs'] == 1 and s['global_ba_runs'] >= 1 and s['errors'] == 0
    hold = lock.max_hold.get('slam-mapper', 0.0) * 1e3
    assert 0.0 < hold < 15.0, hold
    assert s['last_ba_ms'] > hold          # BA took longer than any lock hold
    assert s['measurements_culled'] > 0
    assert all(len(p.observers) <= 8 for p in slam.points.values())
    assert s['keyframes_culled'] == 1
    erased = [k.id for k in slam.keyframes.values() if k.erased]
    assert len(erased) == 1 and erased[0] not in (0, kf.id)
    assert len(slam.active_keyframes()) == 35
    # Global BA pulled the noisy keyframes towards the truth.
    errs = [np.linalg.norm(k.position_w + prob.true_poses[k.id][0].T @ prob.true_poses[k.id][1])
            for k in slam.active_keyframes() if k.id in prob.true_poses]
    assert np.median(errs) < 0.02


def test_stop_aborts_a_running_global_bundle_adjustment():
    cfg = MapperConfig(global_ba_iterations=1000, idle_poll_s=0.005)
    slam, mapper, _, _ = _big_map(cfg)
    mapper._global_dirty = True       # the map has changed: the idle thread starts global BA
    mapper.start()
    deadline = time.monotonic() + 5.0
    while not mapper.busy and time.monotonic() < deadline:
        time.sleep(0.002)
    assert mapper.busy
    t0 = time.perf_counter()
    mapper.stop()
    assert not mapper.running
    assert time.perf_counter() - t0 < 1.0
