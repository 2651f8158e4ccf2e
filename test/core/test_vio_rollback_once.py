"""Each IMU interval of :class:`RollbackFusion` is integrated once: the look-ahead sample the
interval model (:mod:`ar_tracking.core.vio.sampling`) needs re-integrates an interval only when
it finds a kink there, and an IMU gap is reported once, with the sample that closes it."""
from __future__ import annotations

import numpy as np

from ar_tracking.core.vio.rollback import FusionConfig, FusionState, PoseMeasurement, RollbackFusion, Verdict
from ar_tracking.sim import robot_arcs as ra
from ar_tracking.sim import robot_arcs_real as rr

T0 = 1_700_000_000_000_000_000
DT_NS = 10_000_000


class _AlwaysReintegrate(RollbackFusion):
    """The reference: every new sample integrates the interval before the previous one again
    (what the filter did before it knew which look-ahead samples change nothing)."""

    def _lookahead_kinks(self) -> bool:
        return self.config.sampling_model and len(self._imu_t) >= 3


def _started_filter(gyro: np.ndarray | None = None, accel: np.ndarray | None = None) -> RollbackFusion:
    """A filter initialised by one pose at T0 on its first IMU sample (at rest by default)."""
    f = RollbackFusion(FusionConfig())
    gyro = np.zeros(3) if gyro is None else gyro
    accel = np.array([0.0, 0.0, ra.GRAVITY_M_S2]) if accel is None else accel
    assert f.add_imu(T0, gyro, accel) is Verdict.OK
    assert f.add_pose(PoseMeasurement(T0, np.eye(3), np.zeros(3))) is Verdict.INITIALISED
    return f


def test_n_imu_samples_without_camera_are_n_propagations():
    """Constant rates (no kink anywhere): N samples after the first pose, N propagations (every
    sample used to re-integrate the interval before it as well: ~2N)."""
    gyro, accel = np.array([0.01, -0.02, 0.3]), np.array([0.1, 0.0, ra.GRAVITY_M_S2])
    f = _started_filter(gyro, accel)
    n0 = f.imu_updates
    n = 200
    for k in range(1, n + 1):
        assert f.add_imu(T0 + k * DT_NS, gyro, accel) is Verdict.OK
    assert f.imu_updates - n0 == n
    assert f.state is not None and f.state.t_ns == T0 + n * DT_NS


def test_kinks_alone_are_integrated_again():
    """The noise-free IMU of a hard-profile pan: the intervals where the model finds a kink
    (the pan's start and stop, and its quickly curving rate) are integrated twice, every other
    once."""
    sched = ra.ArcSchedule.make(4.0)
    t_s = np.arange(1.00, 2.601, 0.01)
    tr = rr.truth_at(sched, t_s)
    R_imu_enu = np.swapaxes(tr.R_enu_imu, 1, 2)
    gyro = np.einsum('nij,nj->ni', R_imu_enu, tr.omega_world)
    accel = np.einsum('nij,nj->ni', R_imu_enu, tr.imu_accel + np.array([0, 0, ra.GRAVITY_M_S2]))
    t_ns = T0 + np.round(t_s * 1e9).astype(np.int64)
    f = RollbackFusion(FusionConfig(R_imu_cam=rr.R_IMU_CAM, t_imu_cam=rr.T_IMU_CAM, gate_chi2=0.0))
    f.add_imu(int(t_ns[0]), gyro[0], accel[0])
    f.add_pose(PoseMeasurement(int(t_ns[0]), tr.cam.R_enu_cam[0], tr.cam.position[0], np.eye(6) * 1e-12))
    n0, kinks = f.imu_updates, 0
    for k in range(1, len(t_s)):
        f.add_imu(int(t_ns[k]), gyro[k], accel[k])
        kinks += f._lookahead_kinks()
    n = len(t_s) - 1
    assert 0 < kinks < n // 2
    assert f.imu_updates - n0 == n + kinks


def _state_arrays(s: FusionState | None) -> list[np.ndarray]:
    if s is None:
        return []
    return [np.asarray(s.t_ns), s.ori.quat_wxyz, s.ori.P, s.pos.p, s.pos.v, s.pos.P, s.omega, s.a_world, s.cross]


def _same(a: FusionState | None, b: FusionState | None) -> bool:
    x, y = _state_arrays(a), _state_arrays(b)
    return len(x) == len(y) and all(np.array_equal(u, v) for u, v in zip(x, y, strict=True))


def test_states_bit_identical_to_integrating_every_interval_again():
    """Noisy hard-profile IMU with pans (kinks), 80 ms late camera poses between samples and on
    them, a bridged gap and a reset gap: every output state and every state at a camera pose is
    bit for bit the one of the filter that integrates every interval a second time."""
    dur = 6.0
    sched = ra.ArcSchedule.make(dur)
    t_ns = np.arange(1, int(dur * 1e9), DT_NS, dtype=np.int64)
    tr = rr.truth_at(sched, t_ns * 1e-9)
    gyro, accel = rr.simulate_imu(tr, ra.make_imu_errors(3), 3)
    keep = np.ones(len(t_ns), bool)
    keep[150:157] = False     # 80 ms: bridged
    keep[300:360] = False     # 0.61 s: track lost until the next pose
    cams = {int(i + 8): int(i) for i in range(0, len(t_ns), 7)}
    cfg = FusionConfig(R_imu_cam=rr.R_IMU_CAM, t_imu_cam=rr.T_IMU_CAM)
    new, ref = RollbackFusion(cfg), _AlwaysReintegrate(cfg)
    compared = poses = 0
    for i in range(len(t_ns)):
        j = cams.get(i)
        if j is not None:
            off = 0 if j % 2 else -4_000_000
            m = PoseMeasurement(int(t_ns[j]) + off, tr.cam.R_enu_cam[j], tr.cam.position[j])
            verdict = new.add_pose(m)
            assert ref.add_pose(m) is verdict
            if verdict in (Verdict.PENDING, Verdict.TOO_OLD, Verdict.INVALID):  # not in the buffer
                continue
            ev_new = next(e for e in reversed(new._events) if e.meas is m)
            ev_ref = next(e for e in reversed(ref._events) if e.meas is m)
            assert _same(ev_new.state, ev_ref.state)
            poses += 1
        if keep[i]:
            new.add_imu(int(t_ns[i]), gyro[i], accel[i])
            ref.add_imu(int(t_ns[i]), gyro[i], accel[i])
            assert _same(new.state, ref.state)
            compared += new.state is not None
    assert compared > 400 and poses > 60, (compared, poses)
    assert all(_same(a.state, b.state) for a, b in zip(new._events, ref._events, strict=True))
    assert new.imu_updates < 0.8 * ref.imu_updates  # the roll-backs of the late poses stay


def test_one_gap_one_gap_verdict():
    """An 80 ms gap in the IMU stream is reported by the sample that closes it, and by no other."""
    f = _started_filter()
    g = np.array([0.0, 0.0, ra.GRAVITY_M_S2])
    stamps = [T0 + k * DT_NS for k in range(1, 30)] + [T0 + k * DT_NS for k in range(38, 60)]
    verdicts = [f.add_imu(t, np.zeros(3), g) for t in stamps]
    assert verdicts.count(Verdict.GAP) == 1
    assert verdicts[29 - 1 + 1] is Verdict.GAP
    assert set(verdicts) == {Verdict.OK, Verdict.GAP}


def test_one_reset_gap_one_verdict():
    """A gap longer than reset_gap_s ends the track once; the next samples are plain OK."""
    f = _started_filter()
    g = np.array([0.0, 0.0, ra.GRAVITY_M_S2])
    stamps = [T0 + k * DT_NS for k in range(1, 30)] + [T0 + k * DT_NS for k in range(100, 120)]
    verdicts = [f.add_imu(t, np.zeros(3), g) for t in stamps]
    assert verdicts.count(Verdict.RESET_GAP) == 1 and verdicts[29] is Verdict.RESET_GAP
    assert set(verdicts) == {Verdict.OK, Verdict.RESET_GAP}
    assert f.state is None
