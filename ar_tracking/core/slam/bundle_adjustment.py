"""Bundle adjustment of keyframe poses and map points with gtsam (Klein & Murray 2009 sec. 3, 7).

The mapping thread refines the map by minimising the robustified sum of squared reprojection
errors of every measurement ``uv_corrected`` (the rolling-shutter corrected position, sec. 6) of
every map point in every keyframe taking part. A measurement made on pyramid level L has standard
deviation ``2**L`` level-0 pixels.

Robust cost: **Tukey** biweight by default. The paper uses the Tukey M-estimator (sec. 3.2: the
measurement weights ``w_j`` fed to the culling metric are "the weight returned by the Tukey
M-Estimator"), and Tukey is what lets bundle adjustment *flag* outliers: its weight reaches exactly
zero beyond ``c`` so a bad patch match neither drags the map nor survives (the mapper removes
zero-weight measurements). Huber never reaches zero weight and so only down-weights gross
mismatches; it is available (``robust='huber'``) because it is convex and safer from a very poor
initialisation. Tukey's non-convexity is tamed as in PTAM by scaling ``c`` with a robust estimate
of the residual spread (median of the whitened residual norms), re-estimated between stages, so a
noisy initialisation is first treated almost like least squares and the kernel tightens as the
map converges.

Gauge: keyframes in ``fixed_kf_ids`` keep their poses (very tight gtsam priors; their returned
poses are the input poses). *Local* bundle adjustment frees the newest keyframe and its
neighbours and holds every other keyframe that measures the same points fixed; *global* bundle
adjustment frees all keyframes but the first (``Keyframe.fixed``); see :mod:`.mapper`.

Cost: in gtsam's Python wrapper the C++ optimiser holds the GIL, so :func:`bundle_adjust` runs
one Levenberg-Marquardt iteration per Python call; before each iteration the ``checkpoint``
callback lets the mapping thread wait for the tracker to be between frames (:mod:`.frame_gate`)
and the ``abort`` callback is polled (PTAM aborts global BA for a new keyframe).
The paper's phone needed ~750 ms per iteration for 35 keyframes / 300 points (sec. 7);
``ar_tracking.eval.bench_slam.benchmark_one_iteration`` measures ours (with :func:`prepare_lm`)
on the synthetic problem of ``ar_tracking.sim.ba_problem`` (test fixtures with their ground
truth live in sim, not here).
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Mapping, Sequence

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X
from numpy.typing import NDArray

from .camera import Camera
from .slam_map import Keyframe, MapPoint, Measurement

logger = logging.getLogger(__name__)

Array = NDArray[np.float64]

#: Tukey biweight constant (95 % efficiency on Gaussian noise), in units of the residual scale.
TUKEY_C = 4.6851
#: Huber constant (95 % efficiency), in units of the residual scale.
HUBER_K = 1.345
#: Median of the norm of a 2-D unit Gaussian (Rayleigh median sqrt(2 ln 2)).
_RAYLEIGH_MEDIAN = float(np.sqrt(2.0 * np.log(2.0)))
#: Standard deviation of the priors that hold fixed keyframes (rad / map units).
_FIXED_SIGMA = 1e-6


# ---------------------------------------------------------------------------------------------
# Geometry shared by bundle adjustment, culling (sec. 3.2) and the rolling-shutter correction
# (sec. 6). Pose convention: x_c = R_c_w @ x_w + t_c_w.
# ---------------------------------------------------------------------------------------------
def projection_jacobian_camera(camera: Camera, X_c: Array) -> Array:
    """d(u, v)/d(X_c) (N, 2, 3) of the pinhole projection at camera-frame points ``X_c`` (N, 3)."""
    X_c = np.atleast_2d(np.asarray(X_c, float))
    z = np.where(np.abs(X_c[:, 2]) > 1e-9, X_c[:, 2], 1e-9)
    iz = 1.0 / z
    J = np.zeros((len(X_c), 2, 3))
    J[:, 0, 0] = camera.fx * iz
    J[:, 0, 2] = -camera.fx * X_c[:, 0] * iz * iz
    J[:, 1, 1] = camera.fy * iz
    J[:, 1, 2] = -camera.fy * X_c[:, 1] * iz * iz
    return J


def point_jacobians(camera: Camera, R_c_w: Array, t_c_w: Array, X_w: Array) -> Array:
    """B (N, 2, 3): the projection Jacobians w.r.t. world point positions (sec. 3.2, H&Z A6.6)."""
    X_c = np.atleast_2d(X_w) @ np.asarray(R_c_w).T + np.asarray(t_c_w)
    return projection_jacobian_camera(camera, X_c) @ np.asarray(R_c_w)


def pose_jacobians(camera: Camera, R_c_w: Array, t_c_w: Array, X_w: Array) -> Array:
    """J (N, 2, 6): projection Jacobians w.r.t. a camera motion ``xi = (v, omega)`` (sec. 6).

    The motion acts on the left of the world->camera transform, ``T_c_w <- exp(xi) T_c_w``,
    i.e. ``x_c <- x_c + v + omega x x_c`` to first order, so ``dx_c/dxi = [I | -[x_c]_x]``;
    ``xi`` is expressed in the camera frame (translation first) as in PTAM.
    """
    X_c = np.atleast_2d(X_w) @ np.asarray(R_c_w).T + np.asarray(t_c_w)
    Jp = projection_jacobian_camera(camera, X_c)
    D = np.zeros((len(X_c), 3, 6))
    D[:, 0, 0] = D[:, 1, 1] = D[:, 2, 2] = 1.0
    x, y, z = X_c[:, 0], X_c[:, 1], X_c[:, 2]
    # -[x_c]_x
    D[:, 0, 4], D[:, 0, 5] = z, -y
    D[:, 1, 3], D[:, 1, 5] = -z, x
    D[:, 2, 3], D[:, 2, 4] = y, -x
    return Jp @ D


def project_world(camera: Camera, R_c_w: Array, t_c_w: Array, X_w: Array) -> tuple[Array, Array]:
    """Level-0 pixels (N, 2) and depths (N,) of world points in a camera ``R_c_w, t_c_w``."""
    X_c = np.atleast_2d(X_w) @ np.asarray(R_c_w).T + np.asarray(t_c_w)
    uv, _ = camera.project(X_c)
    return uv, X_c[:, 2]


def pose_to_gtsam(R_c_w: Array, t_c_w: Array) -> gtsam.Pose3:
    """Our world->camera pose as gtsam's camera-in-world Pose3 (R_w_c, p_w_c)."""
    R_w_c = np.asarray(R_c_w, float).T
    return gtsam.Pose3(gtsam.Rot3(R_w_c), -R_w_c @ np.asarray(t_c_w, float))


def pose_from_gtsam(pose: gtsam.Pose3) -> tuple[Array, Array]:
    """gtsam's camera-in-world Pose3 as our (R_c_w, t_c_w)."""
    R_c_w = np.asarray(pose.rotation().matrix()).T
    return R_c_w, -R_c_w @ np.asarray(pose.translation())


# ---------------------------------------------------------------------------------------------
# Robust kernels (evaluated in numpy so that objectives and weights are independent of gtsam's
# internal scaling conventions; they match gtsam's mEstimator loss/weight definitions).
# ---------------------------------------------------------------------------------------------
def robust_weights(d: Array, robust: str, c: float) -> Array:
    """M-estimator weights of whitened residual norms ``d`` (Tukey: 0 beyond c; Huber: k/d)."""
    d = np.abs(np.asarray(d, float))
    if robust == 'tukey':
        return np.where(d <= c, (1.0 - (d / c) ** 2) ** 2, 0.0)
    if robust == 'huber':
        return np.where(d <= c, 1.0, c / np.maximum(d, 1e-12))
    return np.ones_like(d)


def robust_loss(d: Array, robust: str, c: float) -> Array:
    """rho(d) of whitened residual norms; ~ d**2 / 2 near zero as in gtsam."""
    d = np.abs(np.asarray(d, float))
    if robust == 'tukey':
        return np.where(d <= c, c * c / 6.0 * (1.0 - (1.0 - (d / c) ** 2) ** 3), c * c / 6.0)
    if robust == 'huber':
        return np.where(d <= c, 0.5 * d * d, c * d - 0.5 * c * c)
    return 0.5 * d * d


# ---------------------------------------------------------------------------------------------
@dataclass
class BAResult:
    """Result of :func:`bundle_adjust`.

    ``poses``: kf id -> (R_c_w, t_c_w) of every keyframe in the problem (fixed ones unchanged);
    ``points``: point id -> xyz of every optimised point; ``weights``: (kf id, point id) -> the
    M-estimator weight of that measurement at the solution (0 = Tukey outlier);
    ``residuals_px``: (kf id, point id) -> reprojection error norm in level-0 pixels;
    objectives are the robustified sums of whitened squared errors, both evaluated with the
    final kernel scale ``robust_c`` so that they are comparable.
    """

    poses: dict[int, tuple[Array, Array]]
    points: dict[int, Array]
    weights: dict[tuple[int, int], float]
    objective_before: float
    objective_after: float
    iterations: int
    residuals_px: dict[tuple[int, int], float] = field(default_factory=dict)
    robust_c: float = TUKEY_C
    converged: bool = False
    aborted: bool = False
    time_ms: float = 0.0
    n_measurements: int = 0


@dataclass
class _Problem:
    kf_ids: list[int]
    point_ids: list[int]
    kf_index: NDArray[np.int64]     # per measurement
    pt_index: NDArray[np.int64]     # per measurement
    uv: Array                       # (M, 2) corrected measurements
    sigma: Array                    # (M,)
    fixed: set[int]


def _points_mapping(points: Mapping[int, Array] | Iterable[MapPoint]) -> dict[int, Array]:
    if isinstance(points, Mapping):
        return {int(k): np.asarray(v, float).reshape(3) for k, v in points.items()}
    return {p.id: np.asarray(p.xyz, float).reshape(3) for p in points}


def _build_problem(keyframes: Sequence[Keyframe], pts: dict[int, Array], fixed: set[int],
                   fixed_point_ids: set[int]) -> _Problem:
    kf_ids = [kf.id for kf in keyframes]
    kpos = {k: i for i, k in enumerate(kf_ids)}
    obs: dict[int, list[tuple[int, Measurement]]] = {}
    for kf in keyframes:
        for pid, m in kf.measurements.items():
            if pid in pts:
                obs.setdefault(pid, []).append((kf.id, m))
    # A point needs two measurements to be constrained; single-measurement points are left out.
    point_ids = sorted(pid for pid, lst in obs.items() if len(lst) >= 2 or pid in fixed_point_ids)
    ppos = {p: i for i, p in enumerate(point_ids)}
    ki, pi, uv, sg = [], [], [], []
    for pid in point_ids:
        for kf_id, m in obs[pid]:
            ki.append(kpos[kf_id])
            pi.append(ppos[pid])
            uv.append(m.uv_corrected if m.uv_corrected is not None else m.uv)
            sg.append(m.sigma_px)
    return _Problem(kf_ids, point_ids, np.asarray(ki, np.int64), np.asarray(pi, np.int64),
                    np.asarray(uv, float).reshape(-1, 2), np.asarray(sg, float), fixed)


def _whitened_residuals(prob: _Problem, camera: Camera, R: Array, t: Array, P: Array) -> Array:
    """Norms of (uv_meas - project) / sigma for all measurements; behind-camera -> large."""
    Xc = np.einsum('mij,mj->mi', R[prob.kf_index], P[prob.pt_index]) + t[prob.kf_index]
    z = Xc[:, 2]
    front = z > 1e-6
    zs = np.where(front, z, 1.0)
    u = camera.fx * Xc[:, 0] / zs + camera.cx
    v = camera.fy * Xc[:, 1] / zs + camera.cy
    e = np.hypot(prob.uv[:, 0] - u, prob.uv[:, 1] - v) / prob.sigma
    return np.where(front, e, 1e6)


def _robust_scale(d: Array, robust: str, tukey_c: float, huber_k: float,
                  scale: float | None) -> float:
    base = tukey_c if robust == 'tukey' else huber_k
    if scale is not None:
        return base * float(scale)
    if len(d) == 0:
        return base
    sigma_hat = float(np.median(d)) / _RAYLEIGH_MEDIAN
    return base * max(1.0, sigma_hat)


def _values_to_arrays(values: gtsam.Values, prob: _Problem) -> tuple[Array, Array, Array]:
    n = len(prob.kf_ids)
    R = np.zeros((n, 3, 3))
    t = np.zeros((n, 3))
    for i, k in enumerate(prob.kf_ids):
        R[i], t[i] = pose_from_gtsam(values.atPose3(X(k)))
    P = np.array([values.atPoint3(L(p)) for p in prob.point_ids], float).reshape(-1, 3)
    return R, t, P


def _build_graph(prob: _Problem, camera: Camera, K: gtsam.Cal3_S2, robust: str, c: float,
                 values: gtsam.Values) -> gtsam.NonlinearFactorGraph:
    graph = gtsam.NonlinearFactorGraph()
    models: dict[float, gtsam.noiseModel.Base] = {}
    for s in np.unique(prob.sigma):
        base = gtsam.noiseModel.Isotropic.Sigma(2, float(s))
        if robust == 'tukey':
            models[float(s)] = gtsam.noiseModel.Robust.Create(
                gtsam.noiseModel.mEstimator.Tukey.Create(c), base)
        elif robust == 'huber':
            models[float(s)] = gtsam.noiseModel.Robust.Create(
                gtsam.noiseModel.mEstimator.Huber.Create(c), base)
        else:
            models[float(s)] = base
    kf_keys = [X(k) for k in prob.kf_ids]
    pt_keys = [L(p) for p in prob.point_ids]
    uv = prob.uv
    sig = prob.sigma
    for m in range(len(uv)):
        graph.add(gtsam.GenericProjectionFactorCal3_S2(
            uv[m], models[float(sig[m])], kf_keys[prob.kf_index[m]], pt_keys[prob.pt_index[m]], K))
    prior = gtsam.noiseModel.Isotropic.Sigma(6, _FIXED_SIGMA)
    for k in prob.kf_ids:
        if k in prob.fixed:
            graph.add(gtsam.PriorFactorPose3(X(k), values.atPose3(X(k)), prior))
    return graph


def _ordering(prob: _Problem) -> gtsam.Ordering:
    """Points first, then poses: eliminating points first is the Schur complement (H&Z A6.6)."""
    order = gtsam.Ordering()
    for p in prob.point_ids:
        order.push_back(L(p))
    for k in prob.kf_ids:
        order.push_back(X(k))
    return order


@dataclass
class _Start:
    """A bundle-adjustment problem and its initial poses and points (arrays in the problem's
    keyframe and point order): what :func:`bundle_adjust` and :func:`prepare_lm` both start from."""

    prob: _Problem
    R0: Array    # (K, 3, 3) R_c_w
    t0: Array    # (K, 3) t_c_w
    P0: Array    # (N, 3)


def _start(keyframes: Sequence[Keyframe], points: Mapping[int, Array] | Iterable[MapPoint],
           fixed_kf_ids: Iterable[int]) -> _Start:
    pts = _points_mapping(points)
    prob = _build_problem(keyframes, pts, set(int(k) for k in fixed_kf_ids), set())
    kf_by_id = {kf.id: kf for kf in keyframes}
    R0 = np.array([np.asarray(kf_by_id[k].R_c_w, float) for k in prob.kf_ids]).reshape(-1, 3, 3)
    t0 = np.array([np.asarray(kf_by_id[k].t_c_w, float) for k in prob.kf_ids]).reshape(-1, 3)
    P0 = np.array([pts[p] for p in prob.point_ids], float).reshape(-1, 3)
    return _Start(prob, R0, t0, P0)


def _initial_values(start: _Start) -> gtsam.Values:
    """The gtsam values of the start (poses as camera-in-world Pose3)."""
    values = gtsam.Values()
    for i, k in enumerate(start.prob.kf_ids):
        values.insert(X(k), pose_to_gtsam(start.R0[i], start.t0[i]))
    for i, p in enumerate(start.prob.point_ids):
        values.insert(L(p), start.P0[i])
    return values


def _calibration(camera: Camera) -> gtsam.Cal3_S2:
    return gtsam.Cal3_S2(camera.fx, camera.fy, 0.0, camera.cx, camera.cy)


def bundle_adjust(keyframes: Sequence[Keyframe], points: Mapping[int, Array] | Iterable[MapPoint],
                  camera: Camera, fixed_kf_ids: Iterable[int] = (), iterations: int = 10, *,
                  robust: str = 'tukey', tukey_c: float = TUKEY_C, huber_k: float = HUBER_K,
                  scale: float | None = None, max_stages: int = 3,
                  relative_tolerance: float = 1e-5,
                  abort: Callable[[], bool] | None = None,
                  checkpoint: Callable[[str], object] | None = None) -> BAResult:
    """Levenberg-Marquardt bundle adjustment of ``keyframes`` and ``points`` (sec. 3, 7).

    ``keyframes`` supply poses and measurements (``Measurement.uv_corrected``, sigma
    ``2**level``); only measurements of ids in ``points`` are used, and points with fewer than two
    measurements are left out (unconstrained). ``fixed_kf_ids`` hold their poses (gauge; the
    non-optimised neighbours of local BA). ``robust`` is ``'tukey'`` (default, see module doc),
    ``'huber'`` or ``'none'``; the kernel width is ``tukey_c`` (``huber_k``) times ``scale`` or,
    with ``scale=None``, times a robust estimate of the whitened residual spread (at least 1),
    re-estimated up to ``max_stages`` times. ``iterations`` bounds the total number of LM
    iterations; ``abort()`` is polled between iterations (returns the best state so far).
    ``checkpoint(step)`` is called before each step that holds the interpreter for a while
    (``'build'`` a stage's graph, ``'iterate'`` one LM iteration, ``'read'`` the values back,
    ``'result'``): the mapping thread waits there for the tracker (:mod:`.frame_gate`).
    """
    step = checkpoint if checkpoint is not None else (lambda _s: None)
    t_start = time.perf_counter()
    start = _start(keyframes, points, fixed_kf_ids)
    prob, R0, t0, P0 = start.prob, start.R0, start.t0, start.P0
    d0 = _whitened_residuals(prob, camera, R0, t0, P0)

    def result(R: Array, t: Array, P: Array, d: Array, c: float, its: int, conv: bool,
               aborted: bool) -> BAResult:
        w = robust_weights(d, robust, c)
        keys = [(prob.kf_ids[a], prob.point_ids[b]) for a, b in zip(prob.kf_index, prob.pt_index)]
        poses = {k: (R[i].copy(), t[i].copy()) for i, k in enumerate(prob.kf_ids)}
        for k in prob.fixed & set(prob.kf_ids):       # fixed poses are returned exactly as given
            poses[k] = (R0[prob.kf_ids.index(k)].copy(), t0[prob.kf_ids.index(k)].copy())
        return BAResult(
            poses=poses, points={p: P[i].copy() for i, p in enumerate(prob.point_ids)},
            weights={k: float(x) for k, x in zip(keys, w)},
            objective_before=float(robust_loss(d0, robust, c).sum()),
            objective_after=float(robust_loss(d, robust, c).sum()), iterations=its,
            residuals_px={k: float(x) for k, x in zip(keys, d * prob.sigma)}, robust_c=c,
            converged=conv, aborted=aborted, time_ms=(time.perf_counter() - t_start) * 1e3,
            n_measurements=len(d))

    c = _robust_scale(d0, robust, tukey_c, huber_k, scale)
    if len(prob.point_ids) == 0 or iterations <= 0:
        return result(R0, t0, P0, d0, c, 0, True, False)

    K = _calibration(camera)
    values = _initial_values(start)
    ordering = _ordering(prob)

    its = 0
    converged = aborted = False
    R, t, P, d = R0, t0, P0, d0
    for stage in range(max(1, max_stages)):
        step('build')
        graph = _build_graph(prob, camera, K, robust, c, values)
        params = gtsam.LevenbergMarquardtParams()
        params.setOrdering(ordering)
        params.setMaxIterations(iterations)
        params.setRelativeErrorTol(relative_tolerance)
        opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        stage_converged = False
        prev = opt.error()
        while its < iterations:
            step('iterate')  # may wait for the tracker: poll abort after it
            if abort is not None and abort():
                aborted = True
                break
            opt.iterate()
            its += 1
            err = opt.error()
            if prev - err <= relative_tolerance * max(prev, 1e-12) or err <= 1e-12:
                stage_converged = True
                break
            prev = err
        step('read')
        values = opt.values()
        R, t, P = _values_to_arrays(values, prob)
        d = _whitened_residuals(prob, camera, R, t, P)
        if aborted or its >= iterations:
            converged = stage_converged
            break
        new_c = _robust_scale(d, robust, tukey_c, huber_k, scale)
        if stage_converged and abs(new_c - c) <= 0.1 * c:
            converged = True
            break
        logger.debug('BA stage %d: kernel %.2f -> %.2f after %d iterations', stage, c, new_c, its)
        c = new_c
    else:
        converged = stage_converged
    step('result')
    res = result(R, t, P, d, c, its, converged, aborted)
    logger.debug('BA %d kf / %d pts / %d meas: %d it, %.1f -> %.1f in %.1f ms', len(prob.kf_ids),
                 len(prob.point_ids), len(d), its, res.objective_before, res.objective_after,
                 res.time_ms)
    return res


def bundle_adjust_one_iteration(keyframes: Sequence[Keyframe],
                                points: Mapping[int, Array] | Iterable[MapPoint], camera: Camera,
                                fixed_kf_ids: Iterable[int] = (), **kwargs: Any) -> BAResult:
    """Exactly one Levenberg-Marquardt iteration (the sec. 7 cost figure), Tukey kernel;
    ``kwargs`` go to :func:`bundle_adjust`."""
    kwargs.setdefault('max_stages', 1)
    return bundle_adjust(keyframes, points, camera, fixed_kf_ids, iterations=1, **kwargs)


@dataclass
class PreparedLM:
    """The gtsam graph, initial values and elimination ordering of one bundle-adjustment stage,
    built once, for timing the bare Levenberg-Marquardt iteration (the sec. 7 cost figure; the
    benchmark is ``ar_tracking.eval.bench_slam.benchmark_one_iteration``)."""

    graph: gtsam.NonlinearFactorGraph
    values: gtsam.Values
    ordering: gtsam.Ordering
    n_keyframes: int
    n_points: int
    n_measurements: int

    def optimizer(self) -> gtsam.LevenbergMarquardtOptimizer:
        """A fresh optimiser at the initial values (points eliminated first, as bundle_adjust)."""
        params = gtsam.LevenbergMarquardtParams()
        params.setOrdering(self.ordering)
        return gtsam.LevenbergMarquardtOptimizer(self.graph, self.values, params)


def prepare_lm(keyframes: Sequence[Keyframe], points: Mapping[int, Array] | Iterable[MapPoint],
               camera: Camera, fixed_kf_ids: Iterable[int] = (), *, robust: str = 'tukey',
               c: float = TUKEY_C * 10.0) -> PreparedLM:
    """The graph :func:`bundle_adjust` optimises in one stage, with the kernel width ``c``
    (built by the same steps: :func:`_start`, :func:`_initial_values`, :func:`_build_graph`)."""
    start = _start(keyframes, points, fixed_kf_ids)
    p = start.prob
    values = _initial_values(start)
    graph = _build_graph(p, camera, _calibration(camera), robust, c, values)
    return PreparedLM(graph, values, _ordering(p), len(p.kf_ids), len(p.point_ids), len(p.uv))


__all__ = ['BAResult', 'PreparedLM', 'bundle_adjust', 'bundle_adjust_one_iteration', 'prepare_lm', 'pose_jacobians',
           'point_jacobians', 'projection_jacobian_camera', 'project_world', 'pose_to_gtsam',
           'pose_from_gtsam', 'robust_weights', 'robust_loss', 'TUKEY_C', 'HUBER_K']
