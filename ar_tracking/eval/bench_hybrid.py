"""Benchmark of the hybrid orientation filter (issue #4): core speed, accuracy against peers.

``bench_hybrid(workdir)`` returns one JSON-able dict (DESIGN sec. 8, area ``orientation``)::

    {'filter_updates_per_s': ..,
     'peers': {'hybrid': {'heading_rmse_deg': ..}, 'imu_magnetometer': {...},
               'vqf': {...}, 'madgwick': {...}},          # 60 s rotation_sweep with disturbances
     'sim': {'seed': .., 'bag': .., 'orientation/global': {...}, 'imu/data': {...}},
     'real': {'broad/<trial>': {'imu_magnetometer': {..}, 'vqf': {..}, 'madgwick': {..}}}}

The peers run on the same calibrated IMU/magnetometer samples (the sidecar calibration that
imu_magnetometer gets), their body orientation is turned into the camera's with the bag's
R_imu_cam and scored with the same heading/tilt split (:func:`heading_tilt_error_deg`) against
the truth slerped at the IMU stamps. VQF is PyPI ``vqf`` (Laidig & Seel 2023, with magnetic
disturbance rejection), Madgwick is ``imufusion`` (x-io's revision of Madgwick's filter, with its
acceleration and magnetic rejection). Peers are benchmark-only dependencies, imported here.

On BROAD (../shared/data/broad, optical ground truth, ENU but not north-referenced) the heading
error is taken after removing each estimator's mean heading offset over the movement phase (the
BROAD convention); only the sensor-only estimators run there (no visual tracker in BROAD).
"""
from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml
from numpy.typing import NDArray

from ..core.rotations import heading_tilt_error_deg, interpolate_rotations, quat_wxyz_to_xyzw, quat_xyzw_to_matrix
from . import SHARED_DATA
from .bench_bag import reusable_sweep_bag
from .bench_core_rates import bench_core_rates

if TYPE_CHECKING:
    from .metrics import BagOrientations

logger = logging.getLogger(__name__)

Array = NDArray[np.float64]

R_IMU_CAM_PHONE = np.diag([1.0, -1.0, -1.0])
BROAD_DIR = SHARED_DATA / 'broad'


# ----------------------------------------------------------------------------------------------
# Core speed


# ----------------------------------------------------------------------------------------------
# Peers


def _world_to_enu(quat_wxyz: Array) -> Array:
    """R_enu_world of a peer's output frame, found from a level device with the field north.

    A level device facing north has R_enu_body = I; whatever the peer returns for it is
    R_world_enu, so its frame convention is checked, not assumed.
    """
    R_world_body = quat_xyzw_to_matrix(quat_wxyz_to_xyzw(np.asarray(quat_wxyz, dtype=float)))
    # Snap to the nearest rotation about up by a multiple of 90 deg (ENU / NWU / ...).
    yaw = math.atan2(R_world_body[1, 0], R_world_body[0, 0])
    yaw = round(yaw / (math.pi / 2)) * (math.pi / 2)
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])  # Rz(-yaw)


def run_vqf(gyro: Array, accel: Array, mag_ut: Array, rate_hz: float) -> Array:
    """R_enu_body (N, 3, 3) from VQF (9D)."""
    from vqf import VQF

    def batch(g: Array, a: Array, m: Array) -> Array:
        out = VQF(1.0 / rate_hz).updateBatch(np.ascontiguousarray(g, dtype=float),
                                             np.ascontiguousarray(a, dtype=float),
                                             np.ascontiguousarray(m, dtype=float))
        return out['quat9D']

    n = 20 * int(rate_hz)
    probe = batch(np.zeros((n, 3)), np.tile([0.0, 0.0, 9.81], (n, 1)), np.tile([0.0, 20.0, -40.0], (n, 1)))
    R_enu_world = _world_to_enu(probe[-1])
    return R_enu_world @ quat_xyzw_to_matrix(quat_wxyz_to_xyzw(batch(gyro, accel, mag_ut)))


def run_madgwick(gyro: Array, accel: Array, mag_ut: Array, rate_hz: float) -> Array:
    """R_enu_body (N, 3, 3) from imufusion's AHRS (Madgwick-type, with rejection)."""
    import imufusion

    def run(g: Array, a: Array, m: Array) -> Array:
        ahrs = imufusion.Ahrs()
        ahrs.set_settings(imufusion.AhrsSettings(
            sample_rate=float(rate_hz), convention=imufusion.CONVENTION_ENU, gain=0.5,
            gyroscope_range=2000.0, acceleration_rejection=10.0, magnetic_rejection=10.0,
            rejection_timeout=int(5 * rate_hz)))
        ahrs.set_sample_period(1.0 / rate_hz)
        gd, ag = np.degrees(g), a / 9.80665
        q = np.empty((len(g), 4))
        for k in range(len(g)):
            ahrs.update(gd[k], ag[k], m[k])
            q[k] = ahrs.get_quaternion()
        return q

    n = 10 * int(rate_hz)
    probe = run(np.zeros((n, 3)), np.tile([0.0, 0.0, 9.81], (n, 1)), np.tile([0.0, 20.0, -40.0], (n, 1)))
    R_enu_world = _world_to_enu(probe[-1])
    return R_enu_world @ quat_xyzw_to_matrix(quat_wxyz_to_xyzw(run(gyro, accel, mag_ut)))


def run_imu_magnetometer(accel: Array, mag: Array, field_t: float = 0.0, dip_rad: float = 0.0) -> Array:
    """R_enu_body (N, 3, 3) from the imu_magnetometer core (eq. 3-4); NaN where undefined."""
    from ..core.imu_orientation import FieldModel, GravityFieldOrientation

    core = GravityFieldOrientation(model=FieldModel(field_t=field_t, dip_rad=dip_rad))
    out = np.full((len(accel), 3, 3), np.nan)
    for k in range(len(accel)):
        est = core.estimate(accel[k], mag[k])
        if est is not None:
            out[k] = est.R_enu_body
    return out


def heading_stats(R_est: Array, R_true: Array, remove_offset: bool = False) -> dict[str, Any]:
    """Heading / tilt RMSE in degrees over the samples where both are finite."""
    ok = np.all(np.isfinite(R_est), axis=(1, 2)) & np.all(np.isfinite(R_true), axis=(1, 2))
    if not ok.any():
        return {'heading_rmse_deg': None, 'tilt_rmse_deg': None, 'n': 0}
    _, heading, tilt = heading_tilt_error_deg(R_est[ok], R_true[ok])
    heading = np.atleast_1d(heading)
    offset = 0.0
    if remove_offset:
        offset = math.degrees(math.atan2(np.mean(np.sin(np.radians(heading))), np.mean(np.cos(np.radians(heading)))))
        heading = (heading - offset + 180.0) % 360.0 - 180.0
    out = {'heading_rmse_deg': round(float(np.sqrt(np.mean(heading**2))), 4),
           'tilt_rmse_deg': round(float(np.sqrt(np.mean(np.square(tilt)))), 4), 'n': int(ok.sum())}
    if remove_offset:
        out['heading_offset_deg'] = round(offset, 3)
    return out


# ----------------------------------------------------------------------------------------------
# Simulated bag


def _bag_imu(bag_path: Path, params: dict[str, Any]) -> dict[str, Array]:
    """Calibrated IMU/mag samples, their stamps and the truth at those stamps, from a sim bag."""
    from ..io.bags import BagReader, stamp_to_ns

    with BagReader(bag_path) as bag:
        imu = [m for _, m in bag.read_all('/imu/data_raw')]
        mag = {stamp_to_ns(m.header.stamp): m for _, m in bag.read_all('/imu/mag')}
        truth = [m for _, m in bag.read_all('/ground_truth/orientation')]
    t = np.array([stamp_to_ns(m.header.stamp) for m in imu], dtype=np.int64)
    keep = np.array([int(s) in mag for s in t])
    imu = [m for m, k in zip(imu, keep) if k]
    t = t[keep]
    gyro = np.array([[m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z] for m in imu])
    accel = np.array([[m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z] for m in imu])
    field = np.array([[mag[int(s)].magnetic_field.x, mag[int(s)].magnetic_field.y, mag[int(s)].magnetic_field.z] for s in t])
    gyro = gyro - np.asarray(params.get('gyro_bias', [0.0] * 3))
    accel = accel - np.asarray(params.get('accel_bias', [0.0] * 3))
    soft = np.asarray(params.get('soft_iron_matrix', np.eye(3).ravel())).reshape(3, 3)
    field = (field - np.asarray(params.get('hard_iron_offset', [0.0] * 3))) @ soft.T
    tt = np.array([stamp_to_ns(m.header.stamp) for m in truth], dtype=np.int64)
    RT = np.array([quat_xyzw_to_matrix(np.array([m.transform.rotation.x, m.transform.rotation.y,
                                                 m.transform.rotation.z, m.transform.rotation.w])) for m in truth])
    R_true, inside = interpolate_rotations((tt - tt[0]).astype(float), RT, (t - tt[0]).astype(float))
    R_full = np.full((len(t), 3, 3), np.nan)
    R_full[inside] = R_true
    return {'t': t, 'gyro': gyro, 'accel': accel, 'mag_t': field, 'R_enu_cam': R_full}


def bench_sim(workdir: Path, seed: int = 1, duration_s: float = 60.0, vision: str = 'panorama') -> dict[str, Any]:
    """Run imu_magnetometer + hybrid_orientation_filter on a rotation_sweep bag, evaluate, and
    score VQF and Madgwick on the same IMU data.

    ``vision='panorama'``: the relative orientation comes from the real panorama_mapper on the
    bag's images (the whole Langlotz chain); ``'synthetic'``: from the ground truth with drift,
    noise and lost stretches (sim/visual_orientation.py), to test the filter alone.
    """
    import yaml

    from ..eval.metrics import evaluate_bag
    from ..nodes.hybrid_orientation_filter import HybridOrientationFilterNode
    from ..nodes.imu_magnetometer import ImuMagnetometerNode
    from ..ros.runner import GraphRunner

    graph: dict[str, Any] = {'imu_magnetometer': ImuMagnetometerNode}
    if vision == 'panorama':
        from ..nodes.panorama_mapper import PanoramaMapperNode
        from .bench_bag import benchmark_bag

        bag = benchmark_bag(workdir, duration_s, seed=seed)
        graph['panorama_mapper'] = PanoramaMapperNode
    elif vision == 'synthetic':
        from ..sim.visual_orientation import visual_bag

        bag = visual_bag(workdir, seed=seed, duration_s=duration_s)
    else:
        raise ValueError(f'vision must be panorama or synthetic, not {vision!r}')
    graph['hybrid_orientation_filter'] = HybridOrientationFilterNode
    sidecar = bag.with_name(bag.name[: -len(bag.suffix)] + '.params.yaml')
    params_files = [sidecar] if sidecar.exists() else []
    out = workdir / f'hybrid_{vision}_seed{seed}.out.mcap'
    run = GraphRunner(bag, out, params_files=params_files, graph=graph).run()
    metrics = evaluate_bag(out)['orientation']
    calib: dict[str, Any] = {}
    if sidecar.exists():
        calib = (yaml.safe_load(sidecar.read_text()) or {}).get('imu_magnetometer', {}).get('ros__parameters', {})
    data = _bag_imu(bag, calib)
    rate = 1e9 / float(np.median(np.diff(data['t'])))
    R_true = data['R_enu_cam']
    peers = {
        'hybrid': {k: metrics.get('orientation/global', {}).get(k) for k in ('heading_rmse_deg', 'tilt_rmse_deg', 'n')},
        'imu_magnetometer': {k: metrics.get('imu/data', {}).get(k) for k in ('heading_rmse_deg', 'tilt_rmse_deg', 'n')},
        'vqf': heading_stats(run_vqf(data['gyro'], data['accel'], data['mag_t'] * 1e6, rate) @ R_IMU_CAM_PHONE, R_true),
        'madgwick': heading_stats(run_madgwick(data['gyro'], data['accel'], data['mag_t'] * 1e6, rate) @ R_IMU_CAM_PHONE, R_true),
    }
    return {'seed': seed, 'vision': vision, 'bag': str(bag), 'wall_s': round(run.wall_s, 3), 'peers': peers,
            'orientation/global': metrics.get('orientation/global'), 'imu/data': metrics.get('imu/data')}


# ----------------------------------------------------------------------------------------------
# Real data: BROAD and the RepoIMU excerpt


REPOIMU_CSV = SHARED_DATA / 'repoimu_ahrs_excerpt' / 'repoIMU.csv'

#: The estimators of the real-data table, in column order.
REAL_ESTIMATORS = ('ahrs', 'compass_eq34', 'vqf', 'imufusion', 'madgwick')


def run_ahrs(gyro: Array, accel: Array, mag: Array, rate_hz: float) -> Array:
    """R_enu_body (N, 3, 3) from our AHRS core (imu_magnetometer's default method), per sample
    with stamps as a driver would give them."""
    from ..core.ahrs import Ahrs, AhrsConfig

    core = Ahrs(AhrsConfig(sample_period_s=1.0 / rate_hz))
    dt_ns = 1e9 / rate_hz
    out = np.full((len(gyro), 3, 3), np.nan)
    for k in range(len(gyro)):
        t = int(round(k * dt_ns))
        est = core.update(t, gyro[k], accel[k], mag[k], t)
        if est is not None and not isinstance(est, str):
            out[k] = est.R_enu_body
    return out


def run_madgwick_ahrs(gyro: Array, accel: Array, mag: Array, rate_hz: float) -> Array:
    """R_enu_body (N, 3, 3) from Madgwick's MARG filter as the PyPI ``ahrs`` package has it
    (its default gain 0.041); frame convention checked like the other peers'."""
    from ahrs.filters import Madgwick

    def run(g: Array, a: Array, m: Array) -> Array:
        return Madgwick(gyr=g, acc=a, mag=m, frequency=float(rate_hz)).Q

    n = 20 * int(rate_hz)
    probe = run(np.zeros((n, 3)), np.tile([0.0, 0.0, 9.81], (n, 1)), np.tile([0.0, 20.0, -40.0], (n, 1)))
    R_enu_world = _world_to_enu(probe[-1])
    return R_enu_world @ quat_xyzw_to_matrix(quat_wxyz_to_xyzw(run(gyro, accel, mag)))


def _aligned_stats(R_est: Array, R_true: Array, align: str) -> dict[str, Any]:
    """Heading / tilt / total RMSE (deg) over the samples where both are finite, after removing
    a constant heading offset (BROAD: ENU truth, not north-referenced) or a constant rotation
    (RepoIMU: the truth is relative to the first sensor orientation)."""
    from ..core.rotations import angle_of
    from .metrics import constant_world_rotation

    ok = np.all(np.isfinite(R_est), axis=(1, 2)) & np.all(np.isfinite(R_true), axis=(1, 2))
    if not ok.any():
        return {'heading_rmse_deg': None, 'tilt_rmse_deg': None, 'total_rmse_deg': None, 'n': 0}
    Re, Rt = R_est[ok], R_true[ok]
    A = constant_world_rotation(Rt, Re, align)
    Re = A @ Re
    _, heading, tilt = heading_tilt_error_deg(Re, Rt)
    total = np.degrees(angle_of(np.einsum('nji,njk->nik', Rt, Re)))
    rms = lambda x: round(float(np.sqrt(np.mean(np.square(x)))), 4)  # noqa: E731
    return {'heading_rmse_deg': rms(heading), 'tilt_rmse_deg': rms(tilt), 'total_rmse_deg': rms(total),
            'n': int(ok.sum()), 'aligned_by_deg': round(float(np.degrees(angle_of(A))), 3)}


def _score_all(gyro: Array, accel: Array, mag: Array, rate: float, R_true: Array, keep: Array,
               align: str, mag_scale_t: float) -> dict[str, Any]:
    runs = {
        'ahrs': lambda: run_ahrs(gyro, accel, mag, rate),
        'compass_eq34': lambda: run_imu_magnetometer(accel, mag * mag_scale_t),
        'vqf': lambda: run_vqf(gyro, accel, mag, rate),
        'imufusion': lambda: run_madgwick(gyro, accel, mag, rate),
        'madgwick': lambda: run_madgwick_ahrs(gyro, accel, mag, rate),
    }
    out: dict[str, Any] = {}
    for name, fn in runs.items():
        try:
            R = fn()
        except ImportError as exc:  # a peer package not installed: say so, score the others
            out[name] = {'error': f'not installed ({exc.name})'}
            continue
        out[name] = _aligned_stats(R[keep], R_true[keep], align)
    return out


def bench_broad(folder: Path = BROAD_DIR, max_trials: int | None = None) -> dict[str, Any]:
    """Every estimator on the BROAD trials present, over the movement phase, heading after
    removing each estimator's constant heading offset (the BROAD convention: optical ENU
    frame, not north-referenced)."""
    from scipy.io import loadmat

    results: dict[str, Any] = {}
    files = sorted(folder.glob('*.mat')) if folder.is_dir() else []
    for path in files[:max_trials]:
        d = loadmat(path)
        rate = float(np.ravel(d['sampling_rate'])[0])
        gyro, accel, mag_ut = d['imu_gyr'], d['imu_acc'], d['imu_mag']
        q = d['opt_quat']
        move = np.ravel(d['movement']).astype(bool) & np.all(np.isfinite(q), axis=1)
        R_true = np.full((len(q), 3, 3), np.nan)
        R_true[move] = quat_xyzw_to_matrix(quat_wxyz_to_xyzw(q[move]))
        results[f'broad/{path.stem}'] = _score_all(gyro, accel, mag_ut, rate, R_true, move, 'heading', 1e-6)
    return results


def bench_repoimu(path: Path = REPOIMU_CSV) -> dict[str, Any]:
    """Every estimator on the RepoIMU excerpt (100 Hz; Vicon truth relative to the first
    sensor orientation, so a constant rotation is removed before scoring)."""
    if not path.is_file():
        return {}
    data = np.genfromtxt(path, delimiter=';', skip_header=2)
    data = data[np.all(np.isfinite(data[:, :14]), axis=1)]
    q = data[:, 1:5]
    accel, gyro, mag = data[:, 5:8], data[:, 8:11], data[:, 11:14]
    rate = 1.0 / float(np.median(np.diff(data[:, 0])))
    R_true = quat_xyzw_to_matrix(quat_wxyz_to_xyzw(q / np.linalg.norm(q, axis=1, keepdims=True)))
    keep = np.ones(len(q), dtype=bool)
    # Field in arbitrary units (|m| ~ 1): scaled to ~48 uT for the eq. 3-4 core's noise model.
    return {'repoimu/excerpt': _score_all(gyro, accel, mag, rate, R_true, keep, 'rotation', 48e-6)}


def bench_real() -> dict[str, Any]:
    """The real-data table (``orientation.real``) with per-estimator means over the recordings
    (``orientation.real_mean``) and our AHRS's worst ratio to VQF (``orientation.real_vs_vqf``)."""
    real = {**(bench_broad() if BROAD_DIR.is_dir() else {}), **bench_repoimu()}
    means: dict[str, Any] = {}
    for name in REAL_ESTIMATORS:
        rows = [r[name] for r in real.values() if name in r and r[name].get('heading_rmse_deg') is not None]
        if rows:
            means[name] = {k: round(float(np.mean([r[k] for r in rows])), 4)
                           for k in ('heading_rmse_deg', 'tilt_rmse_deg', 'total_rmse_deg')}
    ratio: dict[str, Any] = {}
    pairs = [(r['ahrs'], r['vqf']) for r in real.values() if 'heading_rmse_deg' in r.get('ahrs', {}) and 'heading_rmse_deg' in r.get('vqf', {})]
    if pairs:
        for k in ('heading_rmse_deg', 'tilt_rmse_deg'):
            ratio[f'{k}_max_ratio'] = round(max(a[k] / max(v[k], 1e-9) for a, v in pairs), 4)
    return {'real': real, 'real_mean': means, 'real_vs_vqf': ratio}


def bench_hybrid(workdir: Path, duration_s: float = 60.0, seed: int = 1, real: bool = True) -> dict[str, Any]:
    """The orientation benchmark: core speeds, one simulated bag through the graph with VQF and
    Madgwick on the same samples, and the real-data table (see the module docstring)."""
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    sim = bench_sim(workdir, seed=seed, duration_s=duration_s)
    result: dict[str, Any] = dict(bench_core_rates())
    result['peers'] = sim['peers']
    result['sim'] = {k: v for k, v in sim.items() if k != 'peers'}
    if real:
        from .bench_time_offset import bench_time_offset

        result.update(bench_real())
        result['time_offset_euroc'] = bench_time_offset()
    return result


# ----------------------------------------------------------------------------------------------
# Fresh simulated seeds: hybrid, sensor-only and VQF on the same bags


def _nees(path: Path, topic: str = '/orientation/global') -> float | None:
    """Mean normalised estimation error squared of an orientation topic against the truth
    (3 for an honest 3-dof covariance): error rotation vector in world axes, published
    covariance."""
    from ..io.bags import BagReader, stamp_to_ns

    with BagReader(path) as bag:
        est = [m for _, m in bag.read_all(topic)]
        truth = [m for _, m in bag.read_all('/ground_truth/orientation')]
    if not est or not truth:
        return None
    from ..core.rotations import so3_log

    tt = np.array([stamp_to_ns(m.header.stamp) for m in truth], dtype=np.int64)
    RT = np.array([quat_xyzw_to_matrix(np.array([m.transform.rotation.x, m.transform.rotation.y,
                                                 m.transform.rotation.z, m.transform.rotation.w])) for m in truth])
    te = np.array([stamp_to_ns(m.header.stamp) for m in est], dtype=np.int64)
    R_true, inside = interpolate_rotations((tt - tt[0]).astype(float), RT, (te - tt[0]).astype(float))
    values = []
    for m, Rt in zip((m for m, k in zip(est, inside) if k), R_true):
        P = np.asarray(m.orientation_covariance, dtype=float).reshape(3, 3)
        if P[0, 0] < 0 or not np.all(np.isfinite(P)):
            continue
        q = m.orientation
        e = so3_log(quat_xyzw_to_matrix(np.array([q.x, q.y, q.z, q.w])) @ Rt.T)
        values.append(float(e @ np.linalg.solve(P, e)))
    return round(float(np.mean(values)), 3) if values else None


def heading_split(data: BagOrientations, split_s: float = 2.0,
                  topics: tuple[str, ...] = ('/orientation/global', '/imu/data')) -> dict[str, Any]:
    """Heading RMSE (deg) of each topic before and after ``split_s`` seconds from the truth's first
    stamp: the first seconds are when the phone has barely turned, so the residual hard iron (an
    offset fixed in the phone) cannot yet be told apart from the field's own direction; past
    them the figure shows what the estimator does once the session holds some rotation.

    ``data``: the orientations already read from an output bag (:func:`.metrics.load_orientations`;
    the bench has them from scoring the bag)."""
    from .metrics import orientation_errors

    out: dict[str, Any] = {}
    for topic in topics:
        est = data.estimates.get(topic)
        if est is None:
            continue
        err = orientation_errors(data.truth, est.series)
        t = (err.stamps_ns - data.truth.stamps_ns[0]) * 1e-9
        for name, sel in ((f'first_{split_s:g}s', t < split_s), (f'after_{split_s:g}s', t >= split_s)):
            out[f'{topic.lstrip("/")}_heading_rmse_deg_{name}'] = (
                round(float(np.sqrt(np.mean(err.heading_deg[sel] ** 2))), 4) if sel.any() else None)
    return out


def compass_floor_deg(seed: int, duration_s: float, first_s: float = 1.0, session: str = 'authoring') -> float:
    """Heading error (deg) of an ideal compass over the first ``first_s`` of a rotation_sweep
    seed: the simulator's own magnetometer samples, calibrated with the bag's (rough)
    calibration, turned into the world with the TRUE orientation (no tilt error, no filter lag)
    and averaged, against the Earth's field. What is left is the residual hard and soft iron and
    any disturbance present at the start: while the phone has barely turned, no estimator can
    tell them from the field's own direction, so this error stays in the first seconds of every
    estimate. Reads the simulator's internals: for benches only."""
    from ..core.imu_orientation import ImuCalibration
    from ..sim import rotation_sweep as rs

    scn = rs.make_scenario(seed, session, duration_s)
    cal_params = rs.calibration_params(scn)
    cal = ImuCalibration(hard_iron_offset=np.asarray(cal_params['hard_iron_offset']),
                         soft_iron_matrix=np.asarray(cal_params['soft_iron_matrix']).reshape(3, 3))
    t = np.arange(0.0, first_s, 1.0 / rs.IMU_RATE_HZ)
    imu = rs.simulate_imu(scn, t)
    R_enu_imu = imu.R_enu_cam @ rs.R_IMU_CAM.T
    field_enu = np.einsum('nij,nj->i', R_enu_imu, np.array([cal.mag(m) for m in imu.mag_t])) / len(t)
    true_enu = scn.earth.vector_enu
    err = math.atan2(field_enu[0], field_enu[1]) - math.atan2(true_enu[0], true_enu[1])
    return round(abs(math.degrees((err + math.pi) % (2.0 * math.pi) - math.pi)), 4)


def _first_seconds_over_floor(rows: dict[str, Any]) -> float | None:
    """Median over seeds of the hybrid's heading RMSE in the first 2 s divided by the floor
    there: the hand's sway (:func:`.heading_floor.hand_motion_floor`) and the ideal compass's
    residual iron (:func:`compass_floor_deg`) in quadrature. 1 means at the floor."""
    ratios = []
    for r in rows.values():
        first = r['heading_split'].get('orientation/global_heading_rmse_deg_first_2s')
        if first is None or 'hand_motion_floor' not in r:
            continue
        floor = math.hypot(r['hand_motion_floor']['heading_rmse_deg_first_2s'], r['compass_floor_first_1s_deg'])
        if floor > 0:
            ratios.append(first / floor)
    return round(float(np.median(ratios)), 3) if ratios else None


def bench_seeds(workdir: Path, seeds: list[int] | range = range(301, 311), duration_s: float = 40.0,
                profile: str | None = None, imu_time_offset_ms: float | None = None,
                readout_ms: float | None = None, declare_readout: bool = True,
                world_photos: str | Path | None = None, parallax: bool | None = None) -> dict[str, Any]:
    """The hybrid filter on fresh rotation_sweep seeds (the simulator's default, harder profile
    unless ``profile`` says otherwise): per seed the heading / tilt RMSE of orientation/global
    (hybrid), imu/data (sensor only) and reference/vqf (VQF on the same IMU samples), the
    hybrid's mean NEES, and a summary (median and worst hybrid heading, worst tilt, worst
    hybrid / VQF heading ratio). ``imu_time_offset_ms`` replaces the profile's camera-IMU time
    offset in every bag (make-bag ``--imu-time-offset-ms``), ``readout_ms`` replaces the
    profile's rolling-shutter readout (``--readout-ms``; 0 a global shutter), which the mapper
    is then told (the bag's sidecar) unless ``declare_readout`` is false; the hard profile's
    own readout (8-30 ms) it always has to estimate. ``world_photos``, ``parallax``: make-bag's
    ``--world-photos``, ``--parallax`` (None: the profile's). Per seed: make-bag, run (imu_magnetometer, panorama_mapper,
    hybrid_orientation_filter), evaluate."""
    from ..ros.runner import GraphRunner
    from ..sim.bagmaker import make_bag
    from .evaluate import orientation_metrics
    from .panorama_metrics import evaluate_panorama
    from .heading_floor import hand_motion_floor
    from .metrics import load_orientations

    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    rows: dict[str, Any] = {}
    for seed in seeds:
        tag = f'seed{seed}_{duration_s:g}s' + (f'_{profile}' if profile else '') \
            + ('' if imu_time_offset_ms is None else f'_imu{imu_time_offset_ms:+g}ms') \
            + ('' if readout_ms is None else f'_rs{readout_ms:g}ms') + ('' if world_photos is None else
               f'_photos-{Path(world_photos).name}') + {None: '', True: '_parallax', False: '_noparallax'}[parallax]
        bag = workdir / f'rotation_sweep_{tag}.mcap'
        if not reusable_sweep_bag(bag):
            kwargs: dict[str, Any] = {'profile': profile} if profile else {}
            if imu_time_offset_ms is not None:
                kwargs['imu_time_offset_s'] = imu_time_offset_ms * 1e-3
            if readout_ms is not None:
                kwargs['readout_s'] = readout_ms * 1e-3
            kwargs.update(world_photos=world_photos, parallax=parallax)
            make_bag('rotation_sweep', bag, seed=seed, duration_s=duration_s, overwrite=True, **kwargs)
        sidecar = bag.with_name(bag.stem + '.params.yaml')
        if readout_ms and not declare_readout and sidecar.exists():
            params = yaml.safe_load(sidecar.read_text(encoding='utf-8'))
            params.pop('panorama_mapper', None)
            tag += '_undeclared'
            sidecar = workdir / f'rotation_sweep_{tag}.params.yaml'
            sidecar.write_text(yaml.safe_dump(params), encoding='utf-8')
        out = workdir / f'rotation_sweep_{tag}.out.mcap'
        GraphRunner(bag, out, params_files=[sidecar] if sidecar.exists() else [],
                    nodes=['imu_magnetometer', 'panorama_mapper', 'hybrid_orientation_filter']).run()
        # the orientation part of evaluate_all (the estimates and the VQF reference row), from
        # one read of the output bag that heading_split below reuses
        data = load_orientations(out)
        m = orientation_metrics(out, data)['orientation']
        keys = ('heading_rmse_deg', 'tilt_rmse_deg', 'max_deg', 'n')
        row: dict[str, Any] = {name: {k: m.get(topic, {}).get(k) for k in keys}
               for name, topic in (('hybrid', 'orientation/global'), ('sensor_only', 'imu/data'), ('vqf', 'reference/vqf'))}
        row['hybrid_nees_mean'] = _nees(out)
        h, v = row['hybrid']['heading_rmse_deg'], row['vqf']['heading_rmse_deg']
        row['hybrid_over_vqf_heading'] = round(h / v, 4) if h is not None and v else None
        row['heading_split'] = heading_split(data)
        pano = evaluate_panorama(out, seam=False) or {}
        row['panorama'] = {k: pano.get(k) for k in ('lost_frames', 'tracking_rmse_deg')}
        if profile in (None, 'hard'):
            row['compass_floor_first_1s_deg'] = compass_floor_deg(seed, duration_s)
            row['hand_motion_floor'] = hand_motion_floor(seed, duration_s)
        rows[str(seed)] = row
        logger.info('seed %d: %s', seed, row)
    heading = [r['hybrid']['heading_rmse_deg'] for r in rows.values() if r['hybrid']['heading_rmse_deg'] is not None]
    tilt = [r['hybrid']['tilt_rmse_deg'] for r in rows.values() if r['hybrid']['tilt_rmse_deg'] is not None]
    ratio = [r['hybrid_over_vqf_heading'] for r in rows.values() if r['hybrid_over_vqf_heading'] is not None]
    after = [r['heading_split'].get('orientation/global_heading_rmse_deg_after_2s') for r in rows.values()]
    after = [a for a in after if a is not None]
    summary = {
        'seeds': len(rows),
        'hybrid_heading_rmse_deg_after_2s_median': round(float(np.median(after)), 4) if after else None,
        'hybrid_heading_rmse_deg_after_2s_max': round(float(np.max(after)), 4) if after else None,
        'hybrid_heading_rmse_deg_median': round(float(np.median(heading)), 4) if heading else None,
        'hybrid_heading_rmse_deg_max': round(float(np.max(heading)), 4) if heading else None,
        'hybrid_tilt_rmse_deg_max': round(float(np.max(tilt)), 4) if tilt else None,
        'hybrid_over_vqf_heading_max': round(float(np.max(ratio)), 4) if ratio else None,
        # the heading RMSE the hand's sway alone leaves (everything else perfect): a lower bound
        'hand_motion_floor_heading_rmse_deg_median': round(float(np.median(
            [r['hand_motion_floor']['heading_rmse_deg'] for r in rows.values()])), 4)
        if rows and all('hand_motion_floor' in r for r in rows.values()) else None,
        # the first 2 s against what no estimator removes there (the sway and an ideal compass)
        'hybrid_first_2s_over_floor_median': _first_seconds_over_floor(rows),
        'vqf_heading_rmse_deg_median': round(float(np.median([r['vqf']['heading_rmse_deg'] for r in rows.values()
                                                              if r['vqf']['heading_rmse_deg'] is not None])), 4) if rows else None,
    }
    return {'duration_s': duration_s, 'profile': profile or 'default', 'imu_time_offset_ms': imu_time_offset_ms,
            'readout_ms': readout_ms, 'readout_declared': declare_readout,
            'per_seed': rows, 'summary': summary}
