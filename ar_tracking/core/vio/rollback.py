"""Event-based fusion with roll-back for late camera measurements (Caarls et al. 2009, sec. 2.5,
Fig. 6 and Fig. 8).

"Received measurements are ordered in time, both filters and states are rolled back to the time
of measurement t, and all measurements since then are reprocessed" (Fig. 8). This module keeps a
time-ordered buffer of events - IMU samples and camera poses - each with the complete state
(real states and both covariances) *after* it. A camera pose captured at t (it arrives up to
80 ms later, after ~8 IMU samples) is inserted at t, the state before t is restored, the filters
are advanced to exactly t (the IMU value at t is interpolated between its neighbours), the pose
is applied, and every later event is processed again, camera poses included.

With ``rollback=False`` the same filters apply a pose when it arrives, as if it were taken at the
newest IMU time ("incorporates measurements only when they arrive", the alternative sec. 2.5
argues against); it exists to measure what the roll-back gains.

Between two events the IMU is integrated with the mean of the values at both ends (trapezoid),
and with the orientation at mid-interval for the rotation of the specific force.

Bad input (DESIGN sec. 7) gives a :class:`Verdict` instead of an exception: non-finite values,
stamps going back, a pose older than the buffer, a pose whose innovation fails the gate
(outlier: a pose that jumps). Gaps in the IMU stream are bridged with the newer sample (longer
than ``max_imu_gap_s``, reported) or end the track (longer than ``reset_gap_s``: the filter waits
for the next camera pose). Nothing here ever produces NaN: a state that would become non-finite
is dropped and the filter re-initialises from the next pose.
"""
from __future__ import annotations

import bisect
import enum
import logging
import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from .eskf import (
    CHI2_3DOF_999,
    GRAVITY_M_S2,
    Array,
    FilterNoise,
    InitialUncertainty,
    OrientationState,
    PositionState,
    matrix_to_quat,
    quat_exp,
    quat_mul,
    quat_to_matrix,
    update_orientation,
    update_position,
    predict_orientation,
    predict_position,
    sampling_error_cov,
)
from .joint import joint_covariance, pose_jacobian, predict_joint, update_joint
from .sampling import interval_model

logger = logging.getLogger(__name__)


class Verdict(enum.Enum):
    """What happened to one input."""

    OK = 'ok'
    APPLIED = 'applied'
    INITIALISED = 'initialised the filter'
    REINITIALISED = 're-initialised after consecutive rejections'
    PENDING = 'newer than the newest IMU sample; kept until the IMU catches up'
    INVALID = 'not finite or not a rotation'
    STAMP_BACK = 'stamp not newer than the previous IMU sample'
    TOO_OLD = 'older than the roll-back buffer'
    OUTLIER = 'innovation outside the gate (outlier)'
    GAP = 'IMU gap bridged with the newer sample'
    RESET_GAP = 'IMU gap too long: track lost until the next camera pose'


@dataclass(frozen=True)
class PoseMeasurement:
    """A camera pose in the world (marker-map) frame at its capture time ``t_ns``.

    ``cov`` is the 6x6 covariance in ROS order (x, y, z, rotation about world x, y, z) or None
    when unknown (then the configured sigmas are used).
    """

    t_ns: int
    R_world_cam: Array
    p_world_cam: Array
    cov: Array | None = None


@dataclass(frozen=True)
class FusionConfig:
    """Parameters of :class:`RollbackFusion` (the node declares one parameter per field)."""

    noise: FilterNoise = field(default_factory=FilterNoise)
    initial: InitialUncertainty = field(default_factory=InitialUncertainty)
    #: R_imu_cam: rotates camera_optical vectors into the IMU frame (the /tf_static imu -> camera).
    R_imu_cam: Array = field(default_factory=lambda: np.eye(3))
    #: Camera origin in the IMU frame, m.
    t_imu_cam: Array = field(default_factory=lambda: np.zeros(3))
    #: Used when a pose carries no covariance, and as a floor for the ones it carries.
    position_sigma_m: float = 0.002
    orientation_sigma_rad: float = 0.005
    #: Squared Mahalanobis distance above which a pose is an outlier (0 disables the gate).
    gate_chi2: float = CHI2_3DOF_999
    max_consecutive_rejections: int = 8
    buffer_s: float = 1.0
    max_imu_gap_s: float = 0.05
    reset_gap_s: float = 0.5
    rollback: bool = True
    gravity_m_s2: float = GRAVITY_M_S2
    #: Scale of the sampling error of the IMU input (:func:`.eskf.sampling_error_cov`; 0: off).
    sampling_error_scale: float = 1.0
    #: Integrate each IMU interval with the kink of the angular rate located from the gyro
    #: samples around it (:mod:`.sampling`): a step of the angular acceleration and the step
    #: of the specific force it causes at the lever arm are placed where they happened.
    sampling_model: bool = True
    #: One joint 15-state error filter (:mod:`.joint`: orientation-position couplings in the
    #: time update, the pose's full 6x6 covariance in the update) instead of Fig. 7's two.
    joint: bool = True


@dataclass
class FusionState:
    """Everything at one instant: the real states, both covariances, the IMU values there."""

    t_ns: int
    ori: OrientationState
    pos: PositionState
    gyro: Array
    accel: Array
    omega: Array     # bias-corrected angular rate, IMU frame
    a_world: Array   # acceleration in the world frame (gravity removed)
    #: covariance between the orientation (dtheta, db_g) and position (dp, dv, db_a) errors,
    #: 6x9; kept zero by the separate filters, propagated by the joint one
    cross: Array = field(default_factory=lambda: np.zeros((6, 9)))

    def copy(self) -> 'FusionState':
        return FusionState(self.t_ns, self.ori.copy(), self.pos.copy(), self.gyro, self.accel,
                           self.omega, self.a_world, self.cross.copy())

    def is_finite(self) -> bool:
        return bool(np.all(np.isfinite(self.ori.quat_wxyz)) and np.all(np.isfinite(self.ori.P))
                    and np.all(np.isfinite(self.pos.p)) and np.all(np.isfinite(self.pos.v))
                    and np.all(np.isfinite(self.pos.P)))


class _Event:
    __slots__ = ('t_ns', 'gyro', 'accel', 'meas', 'state', 'verdict', 'force_init')

    def __init__(self, t_ns: int, gyro: Array, accel: Array, meas: PoseMeasurement | None = None) -> None:
        self.t_ns = t_ns
        self.gyro = gyro
        self.accel = accel
        self.meas = meas
        self.state: FusionState | None = None
        self.verdict = Verdict.OK
        self.force_init = False


class RollbackFusion:
    """The two error-state filters of :mod:`.eskf` with the roll-back of Fig. 8."""

    def __init__(self, config: FusionConfig | None = None) -> None:
        self.config = config or FusionConfig()
        self._events: list[_Event] = []
        self._times: list[int] = []
        self._pending: list[PoseMeasurement] = []
        self._rejections = 0
        # the IMU samples alone (the events hold camera poses too, with interpolated values)
        self._imu_t: list[int] = []
        self._imu_g: list[Array] = []
        self._imu_a: list[Array] = []
        #: the interval models built so far (see :meth:`_interval`), trimmed with the samples
        self._models: dict[tuple[int, int, bool, bool, float], Any] = {}
        #: counters for diagnostics and the bench
        self.imu_updates = 0        # IMU propagations, replays included
        self.rollbacks = 0
        self.last_gap = Verdict.OK

    # -- public ---------------------------------------------------------------------------

    def reset(self) -> None:
        self._events.clear()
        self._times.clear()
        self._pending.clear()
        self._rejections = 0
        self._imu_t.clear()
        self._imu_g.clear()
        self._imu_a.clear()
        self._models.clear()

    @property
    def state(self) -> FusionState | None:
        """The newest state (None before the first camera pose or after a lost track)."""
        return self._events[-1].state if self._events else None

    @property
    def latest_imu_ns(self) -> int | None:
        return self._times[-1] if self._times else None

    def add_imu(self, t_ns: int, gyro: Array, accel: Array) -> Verdict:
        """Advance by one IMU sample (rad/s, m/s^2, IMU frame)."""
        gyro = np.asarray(gyro, dtype=float)
        accel = np.asarray(accel, dtype=float)
        if gyro.shape != (3,) or accel.shape != (3,) or not (np.all(np.isfinite(gyro)) and np.all(np.isfinite(accel))):
            return Verdict.INVALID
        if self._times and t_ns <= self._times[-1]:
            return Verdict.STAMP_BACK
        ev = _Event(int(t_ns), gyro, accel)
        self._events.append(ev)
        self._times.append(ev.t_ns)
        self._imu_t.append(ev.t_ns)
        self._imu_g.append(gyro)
        self._imu_a.append(accel)
        if self._lookahead_kinks():
            # the new sample is the look-ahead the interval before the previous sample needed,
            # and it puts a kink there: integrate that interval again, from the sample before
            # the previous one up to the previous sample (its gap, if any, was reported when
            # the previous sample came: not again)
            j = bisect.bisect_left(self._times, self._imu_t[-3])
            self._replay(j + 1, len(self._events) - 1)
        self.last_gap = Verdict.OK
        before = self._events[-2] if len(self._events) > 1 else None
        ev.state = self._advance(before.state if before is not None else None, before, ev)
        verdict = self.last_gap
        if self._pending:
            ready = [m for m in self._pending if m.t_ns <= t_ns]
            self._pending = [m for m in self._pending if m.t_ns > t_ns]
            for m in ready:
                self.add_pose(m)
        self._trim()
        return verdict

    def add_pose(self, meas: PoseMeasurement) -> Verdict:
        """Apply a camera pose taken at ``meas.t_ns`` (rolled back to that time, Fig. 8)."""
        if not _valid_pose(meas):
            return Verdict.INVALID
        if not self._events:
            self._pending.append(meas)
            return Verdict.PENDING
        if not self.config.rollback:
            meas = replace(meas, t_ns=self._times[-1])
        if meas.t_ns > self._times[-1]:
            self._pending.append(meas)
            return Verdict.PENDING
        if meas.t_ns < self._times[0]:
            return Verdict.TOO_OLD
        idx = bisect.bisect_right(self._times, meas.t_ns)
        before = self._events[idx - 1]
        if idx < len(self._events):
            after = self._events[idx]
            span = after.t_ns - before.t_ns
            f = (meas.t_ns - before.t_ns) / span if span > 0 else 0.0
            gyro = before.gyro + f * (after.gyro - before.gyro)
            accel = before.accel + f * (after.accel - before.accel)
            self.rollbacks += 1
        else:
            gyro, accel = before.gyro, before.accel
        ev = _Event(meas.t_ns, gyro, accel, meas)
        self._events.insert(idx, ev)
        self._times.insert(idx, ev.t_ns)
        self._replay(idx)
        if ev.verdict is Verdict.OUTLIER:
            self._rejections += 1
            if self._rejections >= self.config.max_consecutive_rejections:
                logger.warning('%d consecutive camera poses rejected: re-initialising from the camera',
                               self._rejections)
                ev.force_init = True
                self._replay(idx)
                ev.verdict = Verdict.REINITIALISED
                self._rejections = 0
        elif ev.verdict in (Verdict.APPLIED, Verdict.INITIALISED):
            self._rejections = 0
        return ev.verdict

    # -- outputs --------------------------------------------------------------------------

    def camera_pose(self, state: FusionState) -> tuple[Array, Array]:
        """(R_world_cam, p_world_cam) of a state."""
        R_w_imu = state.ori.R
        return R_w_imu @ self.config.R_imu_cam, state.pos.p + R_w_imu @ self.config.t_imu_cam

    def camera_covariance(self, state: FusionState) -> Array:
        """6x6 covariance of the camera pose, ROS order (x, y, z, rot x, y, z in the world): with
        the joint filter H P H^T (H of :func:`.joint.pose_observation`: the lever arm turns
        orientation uncertainty into camera position uncertainty, and the two correlate)."""
        R = state.ori.R
        if self.config.joint:
            H = pose_jacobian(R, self.config.t_imu_cam)
            P = joint_covariance(state.ori, state.pos, state.cross)
            cov_j = H @ P @ H.T
            return 0.5 * (cov_j + cov_j.T)
        cov = np.zeros((6, 6))
        cov[:3, :3] = state.pos.P[:3, :3]
        cov[3:, 3:] = R @ state.ori.P[:3, :3] @ R.T
        return cov

    def camera_velocity(self, state: FusionState) -> tuple[Array, Array]:
        """(linear velocity in the world, angular velocity in the camera frame)."""
        R_w_imu = state.ori.R
        v_cam = state.pos.v + R_w_imu @ np.cross(state.omega, self.config.t_imu_cam)
        return v_cam, self.config.R_imu_cam.T @ state.omega

    def extrapolate(self, state: FusionState, dt_s: float) -> tuple[Array, Array]:
        """Camera pose predicted ``dt_s`` ahead (Fig. 6: the pose at display time) with constant
        angular rate and acceleration."""
        q = quat_mul(state.ori.quat_wxyz, quat_exp(state.omega * dt_s))
        R_w_imu = quat_to_matrix(q / np.linalg.norm(q))
        p = state.pos.p + state.pos.v * dt_s + 0.5 * state.a_world * dt_s * dt_s
        return R_w_imu @ self.config.R_imu_cam, p + R_w_imu @ self.config.t_imu_cam

    # -- internals ------------------------------------------------------------------------

    def _trim(self) -> None:
        horizon = self._times[-1] - int(self.config.buffer_s * 1e9)
        k = bisect.bisect_left(self._times, horizon)
        if k > 64:  # trim in chunks: list deletion at the front is O(n)
            del self._events[:k - 1]
            del self._times[:k - 1]
            m = max(bisect.bisect_left(self._imu_t, self._times[0]) - 3, 0)
            del self._imu_t[:m]
            del self._imu_g[:m]
            del self._imu_a[:m]
            first = self._imu_t[0]
            self._models = {key: model for key, model in self._models.items() if key[0] >= first}

    def _lookahead_kinks(self) -> bool:
        """Whether the newest IMU sample changes the interval before the previous one.

        Every interval is first integrated when its end sample arrives, without the sample after
        it, and :func:`.sampling.interval_model` then gives the trapezoid (no kink). The sample
        after it (the newest) changes that model only when the model now finds a kink; without
        one it is the same trapezoid, and the states already integrated over the interval are
        exactly (bit for bit) what a second integration would give. So the interval is
        integrated again only when it kinks: each IMU interval is integrated once, those with a
        kink twice (none on robot_arcs' kind profile, one in ten on the hard profile's pans).
        """
        if not self.config.sampling_model or len(self._imu_t) < 3:
            return False
        model = self._interval(self._imu_t[-3], self._imu_t[-2])
        return model is not None and model[0].tau is not None

    def _replay(self, idx: int, stop: int | None = None) -> None:
        """Process the events ``idx`` .. ``stop - 1`` (to the newest without ``stop``) again from
        the state before ``idx``."""
        prev_state = self._events[idx - 1].state if idx > 0 else None
        prev_ev = self._events[idx - 1] if idx > 0 else None
        for j in range(idx, len(self._events) if stop is None else stop):
            ev = self._events[j]
            ev.state = self._advance(prev_state, prev_ev, ev)
            prev_state, prev_ev = ev.state, ev

    def _init_state(self, ev: _Event) -> FusionState:
        cfg = self.config
        m = ev.meas
        assert m is not None
        R_w_imu = m.R_world_cam @ cfg.R_imu_cam.T
        p_imu = m.p_world_cam - R_w_imu @ cfg.t_imu_cam
        Rm_pos, Rm_body = self._meas_cov(m, R_w_imu)
        init = cfg.initial
        Pq = np.zeros((6, 6))
        Pq[:3, :3] = Rm_body
        Pq[3:, 3:] = np.eye(3) * init.gyro_bias_rad_s ** 2
        Pp = np.zeros((9, 9))
        Pp[:3, :3] = Rm_pos
        Pp[3:6, 3:6] = np.eye(3) * init.velocity_m_s ** 2
        Pp[6:, 6:] = np.eye(3) * init.accel_bias_m_s2 ** 2
        ori = OrientationState(matrix_to_quat(R_w_imu), np.zeros(3), Pq)
        pos = PositionState(p_imu.copy(), np.zeros(3), np.zeros(3), Pp)
        return FusionState(ev.t_ns, ori, pos, ev.gyro, ev.accel, ev.gyro.copy(), np.zeros(3))

    def _meas_cov(self, m: PoseMeasurement, R_w_imu: Array) -> tuple[Array, Array]:
        """Position covariance (world) and orientation covariance (IMU frame) of a pose."""
        cfg = self.config
        sp2, so2 = cfg.position_sigma_m ** 2, cfg.orientation_sigma_rad ** 2
        if m.cov is None:
            return np.eye(3) * sp2, np.eye(3) * so2
        Rp = m.cov[:3, :3] + np.eye(3) * sp2
        Ro = R_w_imu.T @ m.cov[3:, 3:] @ R_w_imu + np.eye(3) * so2
        return Rp, Ro

    def _interval(self, t_a: int, t_b: int) -> tuple[Any, int] | None:
        """The :func:`.sampling.interval_model` of the IMU interval holding [t_a, t_b], and its
        start time; None when [t_a, t_b] is not inside one interval of known samples.

        Each model is built once and kept: the look-ahead test of a new sample builds the model
        of the interval before the previous one, and the re-integration of a kinked interval,
        every event a camera pose splits an interval into and every roll-back replay ask for
        the same model again (the 20 s sample of eval.bench_markers_vi.bench_imu_updates: 6,538
        builds of 3,984 models before, 3,984 now).
        The key fixes the model's inputs: the interval's end times, whether the samples
        before and after it take part (the samples are only ever appended, and trimmed at the
        front, so the neighbour of a sample is always the same one) and the gyro noise.
        """
        ts = self._imu_t
        i1 = bisect.bisect_left(ts, t_b)
        i0 = i1 - 1
        if i0 < 0 or i1 >= len(ts) or ts[i0] > t_a:
            return None
        span = ts[i1] - ts[i0]
        if span <= 0:
            return None

        def near(i: int) -> bool:  # an outer sample counts only at the same spacing
            return 0 <= i < len(ts) and 0 <= i + 1 < len(ts) and abs((ts[i + 1] - ts[i]) - span) <= span // 5

        before, after = near(i0 - 1), near(i1)
        noise = self.config.noise.gyro_noise_rad_s
        key = (ts[i0], ts[i1], before, after, noise)
        model = self._models.get(key)
        if model is None:
            wm2 = self._imu_g[i0 - 1] if before else None
            am2 = self._imu_a[i0 - 1] if before else None
            wp1 = self._imu_g[i1 + 1] if after else None
            ap1 = self._imu_a[i1 + 1] if after else None
            model = interval_model(span * 1e-9, (wm2, self._imu_g[i0], self._imu_g[i1], wp1),
                                   (am2, self._imu_a[i0], self._imu_a[i1], ap1), noise)
            self._models[key] = model
        return model, ts[i0]

    def _meas_cov_world(self, m: PoseMeasurement) -> Array:
        """The pose's full 6x6 covariance (position, rotation about the world axes) with the
        configured floors added to its diagonal (the configured sigmas alone without one)."""
        cfg = self.config
        floor = np.diag([cfg.position_sigma_m ** 2] * 3 + [cfg.orientation_sigma_rad ** 2] * 3)
        if m.cov is None:
            return floor
        c = np.asarray(m.cov, dtype=float)
        return 0.5 * (c + c.T) + floor

    def _advance(self, prev: FusionState | None, prev_ev: _Event | None, ev: _Event) -> FusionState | None:
        """The state after ``ev`` from the state after the previous event."""
        cfg = self.config
        if ev.meas is not None:
            ev.verdict = Verdict.OK
        if prev is None or prev_ev is None or ev.force_init:
            if ev.meas is not None:
                ev.verdict = Verdict.INITIALISED
                return self._init_state(ev)
            return None
        dt = (ev.t_ns - prev.t_ns) * 1e-9
        gyro, accel = 0.5 * (prev_ev.gyro + ev.gyro), 0.5 * (prev_ev.accel + ev.accel)
        if dt > cfg.reset_gap_s:
            self.last_gap = Verdict.RESET_GAP
            if ev.meas is not None:
                ev.verdict = Verdict.INITIALISED
                return self._init_state(ev)
            return None
        kinked = False
        if dt > cfg.max_imu_gap_s:
            self.last_gap = Verdict.GAP
            gyro, accel = ev.gyro, ev.accel
        elif cfg.sampling_model and dt > 0:
            model = self._interval(prev.t_ns, ev.t_ns)
            if model is not None:
                m, t0 = model
                gyro, accel = m.means((prev.t_ns - t0) * 1e-9, (ev.t_ns - t0) * 1e-9)
                kinked = m.tau is not None
        s = prev.copy()
        s.t_ns = ev.t_ns
        s.gyro, s.accel = ev.gyro, ev.accel
        if dt > 0:
            q_prev = s.ori.quat_wxyz
            step_cov = None
            if cfg.sampling_error_scale > 0 and not kinked:
                step_cov = cfg.sampling_error_scale * sampling_error_cov(
                    quat_to_matrix(q_prev) @ (ev.accel - prev_ev.accel))
            if cfg.joint:
                s.cross, w, s.a_world = predict_joint(s.ori, s.pos, s.cross, gyro, accel, dt, cfg.noise,
                                                      cfg.gravity_m_s2, step_cov)
            else:
                w = predict_orientation(s.ori, gyro, dt, cfg.noise)
                R_mid = quat_to_matrix(quat_mul(q_prev, quat_exp(0.5 * dt * w)))
                s.a_world = predict_position(s.pos, R_mid, accel, dt, cfg.noise, cfg.gravity_m_s2, step_cov)
            s.omega = w
            self.imu_updates += 1
        if ev.meas is not None:
            ev.verdict = self._apply(s, ev.meas)
        if not s.is_finite():
            logger.warning('filter state became non-finite at %d: dropped until the next pose', ev.t_ns)
            return None
        return s

    def _apply(self, s: FusionState, m: PoseMeasurement) -> Verdict:
        cfg = self.config
        gate = cfg.gate_chi2 if cfg.gate_chi2 > 0 else None
        if cfg.joint:
            R6 = self._meas_cov_world(m)
            ok, _ = update_joint(s.ori, s.pos, s.cross, cfg.R_imu_cam, cfg.t_imu_cam, m.R_world_cam,
                                 m.p_world_cam, R6, gate, apply=False)
            if not ok.accepted:
                return Verdict.OUTLIER
            _, s.cross = update_joint(s.ori, s.pos, s.cross, cfg.R_imu_cam, cfg.t_imu_cam, m.R_world_cam,
                                      m.p_world_cam, R6, None)
            return Verdict.APPLIED
        R_w_imu_m = m.R_world_cam @ cfg.R_imu_cam.T
        p_imu_m = m.p_world_cam - R_w_imu_m @ cfg.t_imu_cam
        Rp, Ro = self._meas_cov(m, R_w_imu_m)
        q_m = matrix_to_quat(R_w_imu_m)
        # Both parts must pass the gate before either is applied: a pose is one measurement.
        ok_o = update_orientation(s.ori, q_m, Ro, gate, apply=False)
        ok_p = update_position(s.pos, p_imu_m, Rp, gate, apply=False)
        if not (ok_o.accepted and ok_p.accepted):
            return Verdict.OUTLIER
        update_orientation(s.ori, q_m, Ro, None)
        update_position(s.pos, p_imu_m, Rp, None)
        return Verdict.APPLIED


def _valid_pose(m: PoseMeasurement) -> bool:
    R = np.asarray(m.R_world_cam, dtype=float)
    p = np.asarray(m.p_world_cam, dtype=float)
    if R.shape != (3, 3) or p.shape != (3,) or not (np.all(np.isfinite(R)) and np.all(np.isfinite(p))):
        return False
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-3 or np.linalg.det(R) < 0:
        return False
    if m.cov is not None:
        c = np.asarray(m.cov)
        if c.shape != (6, 6) or not np.all(np.isfinite(c)) or np.any(np.diag(c) < 0):
            return False
    return m.t_ns > 0 and math.isfinite(m.t_ns)
