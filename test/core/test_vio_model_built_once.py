"""RollbackFusion builds the sampling model (:func:`ar_tracking.core.vio.sampling.interval_model`)
of each IMU interval once: the look-ahead test of a new sample, the re-integration of a kinked
interval, the two parts of an interval a camera pose splits and the roll-back replays all use
the model already built, and the states are bit for bit those of building it every time."""
from __future__ import annotations

from collections import Counter

import numpy as np

import ar_tracking.core.vio.rollback as rollback
from ar_tracking.core.vio.rollback import FusionConfig, FusionState, PoseMeasurement, RollbackFusion, Verdict
from ar_tracking.sim import robot_arcs as ra
from ar_tracking.sim import robot_arcs_real as rr

DT_NS = 10_000_000


class _BuildEveryTime(RollbackFusion):
    """The reference: every request builds the interval's model anew."""

    def _interval(self, t_a: int, t_b: int):
        self._models.clear()
        return super()._interval(t_a, t_b)


def _states(s: FusionState | None) -> list[np.ndarray]:
    if s is None:
        return []
    return [np.asarray(s.t_ns), s.ori.quat_wxyz, s.ori.gyro_bias, s.ori.P, s.pos.p, s.pos.v, s.pos.P, s.omega,
            s.a_world, s.cross]


def _same(a: FusionState | None, b: FusionState | None) -> bool:
    x, y = _states(a), _states(b)
    return len(x) == len(y) and all(np.array_equal(u, v) for u, v in zip(x, y, strict=True))


def _run(fusions: list[RollbackFusion], dur: float = 4.0) -> tuple[int, int]:
    """Noisy hard-profile IMU (pans: kinks) at 100 Hz with camera poses arriving 80 ms late,
    between samples and on them, and an 80 ms gap; states compared after every input. Returns
    (IMU states compared, roll-backs)."""
    sched = ra.ArcSchedule.make(dur)
    t_ns = np.arange(1, int(dur * 1e9), DT_NS, dtype=np.int64)
    tr = rr.truth_at(sched, t_ns * 1e-9)
    gyro, accel = rr.simulate_imu(tr, ra.make_imu_errors(5), 5)
    keep = np.ones(len(t_ns), bool)
    keep[150:157] = False
    cams = {int(i + 8): int(i) for i in range(0, len(t_ns), 7)}
    compared = 0
    for i in range(len(t_ns)):
        j = cams.get(i)
        if j is not None:
            off = 0 if j % 2 else -4_000_000
            m = PoseMeasurement(int(t_ns[j]) + off, tr.cam.R_enu_cam[j], tr.cam.position[j])
            verdicts = {f.add_pose(m) for f in fusions}
            assert len(verdicts) == 1
        if keep[i]:
            verdicts = {f.add_imu(int(t_ns[i]), gyro[i], accel[i]) for f in fusions}
            assert len(verdicts) == 1
            assert all(_same(f.state, fusions[0].state) for f in fusions[1:])
            compared += fusions[0].state is not None
    return compared, fusions[0].rollbacks


def test_each_interval_model_is_built_once(monkeypatch):
    builds: Counter = Counter()
    kinked = 0
    original = rollback.interval_model

    def counted(dt, w, a, *args, **kwargs):
        nonlocal kinked
        key = (dt,) + tuple(None if x is None else x.tobytes() for x in (*w, *a))
        builds[key] += 1
        model = original(dt, w, a, *args, **kwargs)
        kinked += model.tau is not None
        return model

    monkeypatch.setattr(rollback, 'interval_model', counted)
    f = RollbackFusion(FusionConfig(R_imu_cam=rr.R_IMU_CAM, t_imu_cam=rr.T_IMU_CAM))
    compared, rollbacks = _run([f])
    assert compared > 300 and rollbacks > 40
    assert kinked > 5  # kinked intervals were re-integrated: their models were asked for again
    assert max(builds.values()) == 1, sum(n > 1 for n in builds.values())


def test_states_bit_identical_to_building_every_time():
    cfg = FusionConfig(R_imu_cam=rr.R_IMU_CAM, t_imu_cam=rr.T_IMU_CAM)
    new, ref = RollbackFusion(cfg), _BuildEveryTime(cfg)
    compared, _ = _run([new, ref])
    assert compared > 300
    assert all(_same(a.state, b.state) for a, b in zip(new._events, ref._events, strict=True))
    assert new.imu_updates == ref.imu_updates


def test_a_changed_gyro_noise_is_a_new_model():
    """The gyro noise decides what counts as a kink: a filter whose noise changes does not reuse
    the models built with the old one (the same states as a filter built with the new noise)."""
    cfg = FusionConfig(R_imu_cam=rr.R_IMU_CAM, t_imu_cam=rr.T_IMU_CAM)
    f = RollbackFusion(cfg)
    t0 = 1_000_000_000
    f.add_imu(t0, np.zeros(3), np.array([0.0, 0.0, ra.GRAVITY_M_S2]))
    assert f.add_pose(PoseMeasurement(t0, np.eye(3), np.zeros(3))) is Verdict.INITIALISED
    rng = np.random.default_rng(1)
    for k in range(1, 30):
        f.add_imu(t0 + k * DT_NS, rng.normal(size=3), rng.normal(size=3))
    n = len(f._models)
    assert f._interval(t0 + 10 * DT_NS, t0 + 11 * DT_NS)[0].tau is not None  # a kink at this noise
    assert len(f._models) == n  # (built before: kept)
    quiet = FusionConfig(R_imu_cam=rr.R_IMU_CAM, t_imu_cam=rr.T_IMU_CAM,
                         noise=type(cfg.noise)(**{**vars(cfg.noise), 'gyro_noise_rad_s': 1e3}))
    f.config = quiet
    assert f._interval(t0 + 10 * DT_NS, t0 + 11 * DT_NS) is not None
    assert len(f._models) == n + 1
    assert f._interval(t0 + 10 * DT_NS, t0 + 11 * DT_NS)[0].tau is None  # huge noise: no kink
