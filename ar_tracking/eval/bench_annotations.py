"""``ar-tracking bench --areas annotations``: speed of re-detection and the Fig. 7 table
(Langlotz 2011 sec. 3.2, 4.3, 6.1).

* ``tile_match_ms``: one 64 x 64 tile against 12 annotations (Walsh pre-check + NCC), median
  (seed: 28 ms on an HTC HD2; target here <= 1 ms);
* ``ransac_ms``: one global alignment with 8 annotations and 3 candidates each (seed: 30 ms;
  target <= 2 ms); ``ransac_gravity_ms`` the same with the gravity-constrained alignment,
  ``ransac_landmarks_ms`` that with 24 landmarks and 4 support landmarks per annotation
  besides the 8 annotations (what a spot authored with the default landmarks aligns);
* ``fig7.<row>.<column>``: redetection rate over ``spots`` simulated spots (4-6 annotations
  each), rows baseline, +sensor, +RANSAC, +sensor+RANSAC, +EDR, all; columns ``same_lighting``
  (browsing walk under the authoring sun: ``make_bag(..., session='browsing',
  lighting='authoring')``) and ``changed_lighting`` (browsing session: midday sun, other
  shadows, flare, other exposure). Also ``fig7.<row>.<column>_wrong``.

The Fig. 7 pipeline runs the cores without ROS and without bags (frames rendered by the
simulator straight into :class:`PanoramaMapper`): authoring map -> patches at the anchors ->
browsing map -> :class:`ReDetector` on all finished tiles; the sensor prior is the browsing
panorama's orientation from gravity + field (eq. 3-4, the device calibration of the sidecar)
averaged over the tracked frames, i.e. with the simulated compass errors.

26 spots (about 120 annotations, ~17 min): on 13 spots the parameters of the extensions fitted
the first 13 seeds (changed lighting, all: 0.97 redetection) while seeds 14-26 gave 0.75, so the
table is taken over both halves.
"""
from __future__ import annotations

import logging
import math
import time
from typing import Any

import cv2
import numpy as np

from ..core.annotations.landmarks import select_landmarks
from ..core.annotations.matching import (Candidate, MatchConfig, ReDetector, TileMatcher,
                                         ransac_alignment)
from ..core.annotations.patches import cut_patch
from ..core.panorama import MapConfig, MapperConfig, PanoramaMapper
from ..core.panorama.cylinder import CylinderGeometry, rotation_about_axis_y
from ..core.rotations import so3_log

logger = logging.getLogger(__name__)

#: Rows of Fig. 7: which enhancements are on. The source panorama's landmarks (stored with its
#: annotations, :mod:`ar_tracking.core.annotations.landmarks`) are matched in every row; only
#: the alignment (RANSAC) uses them. ``all_without_landmarks``: the annotations alone.
ROWS = {
    'baseline': dict(edr=False, sensor_prior=False, ransac=False),
    'sensor': dict(edr=False, sensor_prior=True, ransac=False),
    'ransac': dict(edr=False, sensor_prior=False, ransac=True),
    'sensor_ransac': dict(edr=False, sensor_prior=True, ransac=True),
    'edr': dict(edr=True, sensor_prior=False, ransac=False),
    'all': dict(edr=True, sensor_prior=True, ransac=True),
    'all_without_landmarks': dict(edr=True, sensor_prior=True, ransac=True, landmarks=False),
}
COLUMNS = {'same_lighting': 'authoring', 'changed_lighting': 'browsing'}
CORRECT_DEG = 1.0


def _median_ms(fn, n: int) -> float:
    for _ in range(max(3, n // 10)):
        fn()
    times = []
    for _ in range(n):
        t = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t) * 1e3)
    return round(float(np.median(times)), 4)


def _texture(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = np.zeros((512, 2048), np.float32)
    for sigma, amp in ((1.0, 40.0), (3.0, 60.0), (8.0, 50.0)):
        n = cv2.GaussianBlur(rng.normal(0, 1, (512, 2048)).astype(np.float32), (0, 0), sigma)
        img += amp * n / n.std()
    return np.clip(img + 128.0, 0, 255)


def _as_the_nodes_run() -> None:
    """Limit this process's OpenBLAS pools to one thread, as every node does
    (:func:`ar_tracking.blas.limit_blas_threads`): the matcher's Walsh product is a small matrix
    product, and with other processes on both cores OpenBLAS's worker threads wait for a core on
    every one (one tile took 51-56 ms instead of 0.8 ms on the loaded 2-core machine, session
    11)."""
    from ..blas import limit_blas_threads

    limit_blas_threads()


def bench_tile_match(n: int = 300, seed: int = 0) -> float:
    """Median ms of one 64x64 tile against 12 annotations (no prior: all 12 are tested), with
    the BLAS pools as the nodes run them (:func:`_as_the_nodes_run`)."""
    _as_the_nodes_run()
    gray = _texture(seed)
    rng = np.random.default_rng(seed)
    patches = []
    for x, y in zip(rng.integers(0, 2000, 12), rng.integers(100, 400, 12)):
        p = gray[y:y + 16, x:x + 16]
        patches.append(np.round((p - p.min()) * 255 / (p.max() - p.min())).astype(np.uint8))
    matcher = TileMatcher(patches, MatchConfig(sensor_prior=False))
    tile = 3 * 32 + 10
    return _median_ms(lambda: matcher.match_tile(gray, None, tile), n)


def bench_ransac(n: int = 200, seed: int = 0, gravity: bool = False, points: int = 8) -> float:
    """Median ms of one alignment: ``points`` annotations (8) or annotations and landmarks, 3
    candidates each (a quarter with only wrong ones); the paper's rotation hypotheses, or with
    ``gravity`` the sensor prior (3 deg off) turned about the vertical
    (``MatchConfig.gravity_alignment``); BLAS pools as the nodes run them."""
    _as_the_nodes_run()
    geo = CylinderGeometry()
    rng = np.random.default_rng(seed)
    u = rng.uniform(0, 2048, points)
    v = rng.uniform(150, 350, points)
    dirs = geo.unproject(u, v)
    R = rotation_about_axis_y(0.7)
    tu, tv = geo.project(dirs @ R.T)
    cands = []
    for i in range(points):
        c = [Candidate(float((tu[i] + rng.uniform(100, 1900)) % 2048), float(tv[i] + rng.uniform(-40, 40)), 0.8, 0.8)
             for _ in range(2)]
        if i >= points // 4:
            c.insert(int(rng.integers(0, 3)), Candidate(float(tu[i]), float(tv[i]), 0.7, 0.7))
        cands.append(c)
    cfg = MatchConfig()
    if gravity:
        R_prior = rotation_about_axis_y(0.7 + math.radians(3.0))
        up = np.array([0.0, -1.0, 0.0])
        return _median_ms(lambda: ransac_alignment(dirs, cands, cfg, geo, R_prior=R_prior, up=up), n)
    return _median_ms(lambda: ransac_alignment(dirs, cands, cfg, geo), n)


# -- Fig. 7 ---------------------------------------------------------------------------------

def _session_maps(seed: int, trajectory: str, lighting: str, duration_s: float) -> dict[str, Any]:
    """Run the mapper (EDR and 8-bit) over one simulated session; per map the estimated
    orientation in the world (what authoring stores and the browsing graph's prior is: the
    hybrid filter's world alignment plus the AHRS on the session's own 100 Hz IMU and field
    samples, :class:`PanoramaWorldEstimator`, with the device calibration of the sidecar) and,
    for scoring only, the truth."""
    from ..core.annotations.world_orientation import PanoramaWorldEstimator
    from ..core.imu_orientation import ImuCalibration
    from ..sim import rotation_sweep as rs
    from ..sim.bagmaker import EXPOSURE_COMPENSATION, EXPOSURE_TARGET, session_view
    from ..sim.world import FrameRenderer, PinholeCamera, rng_stream

    scn = rs.make_scenario(seed, trajectory, duration_s)
    # The public view of make_bag(..., session=trajectory, lighting=lighting).
    world, light, pano = session_view(seed, trajectory, lighting)
    spot = rs.session_offset(seed, trajectory)
    cam = PinholeCamera()
    renderer = FrameRenderer(pano, light, cam, rng_stream(seed, 'pixel-noise', trajectory))
    n_cam = int(math.ceil(duration_s * rs.CAMERA_RATE_HZ))
    cam_ns = (np.arange(n_cam, dtype=np.int64) * 1_000_000_000) // rs.CAMERA_RATE_HZ
    factor, wb = rs.make_exposure(seed, trajectory, duration_s).at(cam_ns * 1e-9)
    gain = (EXPOSURE_TARGET / max(pano.mean_radiance, 1e-3)) ** EXPOSURE_COMPENSATION * factor
    truth = rs.simulate_imu(scn, cam_ns * 1e-9).R_enu_cam  # scoring only
    n_imu = int(math.ceil(duration_s * rs.IMU_RATE_HZ))
    imu_t = np.arange(n_imu) / rs.IMU_RATE_HZ
    imu = rs.simulate_imu(scn, imu_t)
    imu_ns = np.round(imu_t * 1e9).astype(np.int64) + scn.imu_time_offset_ns  # header stamps
    params = rs.calibration_params(scn)
    calibration = ImuCalibration(gyro_bias=params['gyro_bias'], accel_bias=params['accel_bias'],
                                 hard_iron_offset=params['hard_iron_offset'],
                                 soft_iron_matrix=params['soft_iron_matrix'])
    mappers = {edr: PanoramaMapper(MapperConfig(map=MapConfig(edr=edr))) for edr in (True, False)}
    init = {edr: None for edr in mappers}
    est = {edr: PanoramaWorldEstimator(calibration, rs.R_IMU_CAM) for edr in mappers}
    for k, t in enumerate(cam_ns):
        rgb = renderer.render(rs.frame_orientations(scn.trajectory, t * 1e-9, cam.fx, scn.readout_s, cam.height),
                              float(gain[k]), wb[k])
        gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
        for edr, m in mappers.items():
            res = m.process(gray, cam.K, int(t))
            m.background()
            if res.status == 'initialised':
                init[edr] = k
            if res.R_pano_cam is not None:
                est[edr].add_visual(int(t), res.R_pano_cam)
    out = {'spot': spot, 'anchors': world.anchors}
    for edr, m in mappers.items():
        for i in range(n_imu):
            est[edr].add_imu(int(imu_ns[i]), imu.gyro_rad_s[i], imu.accel_m_s2[i])
            est[edr].add_mag(int(imu_ns[i]), imu.mag_t[i])
        world_est = est[edr].estimate()
        out[edr] = {'gray': m.map.gray.copy(), 'mapped': m.map.mapped.copy(), 'tiles': m.map.tiles_image(),
                    'R_enu_pano_truth': truth[init[edr]] if init[edr] is not None else None,
                    'world': world_est}
    return out


def _authored(auth: dict[str, Any], edr: bool, geo: CylinderGeometry) -> dict[str, Any] | None:
    """What authoring stores from one source map: patches at the anchors whose support area
    it covers (the others could not have been annotated), their directions, the anchors, the
    map's landmarks and the estimated orientation; None without a map or an estimate. The
    anchors are placed where they appear in the map (the truth stands in for the user who
    clicks on them); everything stored is estimated (the landmarks' up too)."""
    src = auth[edr]
    if src['R_enu_pano_truth'] is None or src['world'] is None:
        return None
    patches, dirs, labels = [], [], []
    for a in auth['anchors']:
        u, v = geo.project(src['R_enu_pano_truth'].T @ a.direction)
        patch, d, _ = cut_patch(src['gray'], src['mapped'], float(u), float(v), 16, geo)
        if patch is not None:
            patches.append(patch)
            dirs.append(d)
            labels.append(a)
    landmarks = (select_landmarks(src['gray'], src['mapped'], geo, src['world'].up, avoid=np.array(dirs))
                 if patches else [])
    return {'patches': patches, 'dirs': dirs, 'labels': labels, 'landmarks': landmarks,
            'R_enu_pano': src['world'].R_enu_pano}


def fig7_spot(seed: int, duration_s: float = 30.0) -> dict[str, dict[str, list[float]]]:
    """Per row and column, the placement error (deg, inf when not placed) of every annotation of
    one spot that could be authored (:func:`_authored`)."""
    geo = CylinderGeometry()
    auth = _session_maps(seed, 'authoring', 'authoring', duration_s)
    browse = {col: _session_maps(seed, 'browsing', light, duration_s) for col, light in COLUMNS.items()}
    authored = {edr: _authored(auth, edr, geo) for edr in (True, False)}
    out: dict[str, dict[str, list[float]]] = {}
    # Errors of the estimated orientations (EDR maps; scoring only).
    out['orientation_error_deg'] = {
        name: ([float(np.degrees(np.linalg.norm(so3_log(s[True]['R_enu_pano_truth'].T @ s[True]['world'].R_enu_pano))))]
               if s[True]['world'] is not None and s[True]['R_enu_pano_truth'] is not None else [])
        for name, s in (('authoring', auth), *(((f'browsing_{c}'), browse[c]) for c in COLUMNS))}
    for row, opts in ROWS.items():
        edr = opts['edr']
        stored = authored[edr]
        if stored is None:
            continue
        patches, labels = stored['patches'], stored['labels']
        landmarks = stored['landmarks'] if opts.get('landmarks', True) else []
        all_patches = patches + [lm.patch for lm in landmarks]
        all_dirs = np.array(stored['dirs'] + [lm.direction for lm in landmarks]).reshape(-1, 3)
        flags = [False] * len(patches) + [True] * len(landmarks)
        R_enu_source = stored['R_enu_pano']  # estimated
        out[row] = {}
        for col in COLUMNS:
            tgt = browse[col][edr]
            errors = [math.inf] * len(labels)
            if patches and tgt['R_enu_pano_truth'] is not None and tgt['world'] is not None:
                cfg = MatchConfig(sensor_prior=opts['sensor_prior'], ransac=opts['ransac'])
                det = ReDetector(all_patches, all_dirs, ['p'] * len(all_patches), cfg, geo,
                                 [R_enu_source] * len(all_patches), landmark=flags)
                det.set_orientation(tgt['world'].R_enu_pano)  # estimated
                det.add_finished_tiles(tgt['tiles'])
                det.step(tgt['gray'], tgt['mapped'])
                _, al = det.result()
                spot = browse[col]['spot']
                for p in al.placements:
                    d = labels[p.index].position_enu - spot
                    truth = tgt['R_enu_pano_truth'].T @ (d / np.linalg.norm(d))
                    errors[p.index] = float(np.degrees(math.acos(np.clip(p.direction @ truth, -1, 1))))
            out[row][col] = errors
    return out


def bench_fig7(spots: int = 10, first_seed: int = 1, duration_s: float = 30.0) -> dict[str, Any]:
    """The Fig. 7 table over ``spots`` seeds (see the module docstring)."""
    errors: dict[str, dict[str, list[float]]] = {r: {c: [] for c in COLUMNS} for r in ROWS}
    for seed in range(first_seed, first_seed + spots):
        t = time.perf_counter()
        res = fig7_spot(seed, duration_s)
        for r, cols in res.items():
            for c, e in cols.items():
                errors.setdefault(r, {}).setdefault(c, []).extend(e)
        logger.info('fig7: spot %d done in %.1f s', seed, time.perf_counter() - t)
    table: dict[str, Any] = {'spots': spots, 'first_seed': first_seed,
                             'annotations': len(errors['all']['changed_lighting'])}
    table['orientation_error_deg'] = {
        k: {'median': round(float(np.median(v)), 3), 'max': round(float(np.max(v)), 3)}
        for k, v in errors.get('orientation_error_deg', {}).items() if v}
    for r in ROWS:
        table[r] = {}
        for c in COLUMNS:
            e = np.asarray(errors[r][c])
            if e.size == 0:
                continue
            table[r][c] = round(float(np.mean(e <= CORRECT_DEG)), 4)
            table[r][c + '_wrong'] = round(float(np.mean((e > CORRECT_DEG) & np.isfinite(e))), 4)
    return table


def bench_annotations(fig7_spots: int = 30, duration_s: float = 30.0, fig7_first_seed: int = 401) -> dict[str, Any]:
    """The ``annotations`` area of ``ar-tracking bench`` (fig7_spots=0 skips the table): the Fig. 7
    table on spots 401-430 by default, the fresh range of session 11 (docs/annotations.md;
    341-400 were used to develop the look-alike test and the bracket rule)."""
    out: dict[str, Any] = {'tile_match_ms': bench_tile_match(), 'ransac_ms': bench_ransac(),
                           'ransac_gravity_ms': bench_ransac(gravity=True),
                           'ransac_landmarks_ms': bench_ransac(gravity=True, points=8 + 24 + 4 * 8)}
    if fig7_spots > 0:
        out['fig7'] = bench_fig7(fig7_spots, first_seed=fig7_first_seed, duration_s=duration_s)
    return out


# -- the whole browsing graph on fresh simulated spots ---------------------------------------

def bench_graph_spots(spots: int = 6, first_seed: int = 341, duration_s: float = 30.0,
                      workdir: str | None = None, matcher_params: dict[str, Any] | None = None) -> dict[str, Any]:
    """What a user sees, end to end, on ``spots`` fresh simulated spots: per seed an authoring
    and a browsing bag made independently (``make_bag``; browsing 0.4-1.5 m away under the
    changed lighting, 'hard' sensor profile), ``annotate`` with the estimated orientation (the
    simulated user clicks on the anchors the authoring panorama shows:
    :func:`simulated_user_positions`), the annotations graph (imu_magnetometer, panorama_mapper,
    hybrid_orientation_filter, annotation_matcher) in lockstep on the browsing bag, and
    :func:`evaluate_annotations` on its output, scored on the annotations the user placed (those
    in the store). Counts: ``anchors`` in the scenes, ``offered`` (the user clicked: the
    authoring panorama saw them), ``annotations`` (placed: stored by ``annotate``). Pooled
    ``redetection_rate`` / ``wrong_rate`` (final placements, of the placed annotations; also
    ``..._of_anchors`` over every anchor, a missing annotation counting as not re-detected),
    ``wrong_label_time_share`` (pooled label-time), ``time_to_first_s`` median and max, and the
    per-spot rows. ``matcher_params``:
    annotation_matcher parameters besides the store (e.g. ``{'local_support_deg': 60.0}``).
    Needs rclpy."""
    import tempfile
    from pathlib import Path

    import yaml

    from ..annotate import annotate_bag
    from ..io.stores import open_store
    from ..ros.runner import GraphRunner
    from ..sim.bagmaker import make_bag
    from .annotation_metrics import evaluate_annotations, simulated_user_positions

    root = Path(workdir or tempfile.mkdtemp(prefix='ar_tracking_graph_spots_'))
    root.mkdir(parents=True, exist_ok=True)
    rows: dict[str, Any] = {}
    for seed in range(first_seed, first_seed + spots):
        t = time.perf_counter()
        auth = make_bag('rotation_sweep', root / f'{seed}_authoring.mcap', seed=seed, duration_s=duration_s,
                        session='authoring', image_format='compressed', overwrite=True)
        browse = make_bag('rotation_sweep', root / f'{seed}_browsing.mcap', seed=seed, duration_s=duration_s,
                          session='browsing', image_format='compressed', overwrite=True)
        store = root / f'{seed}.db'
        store.unlink(missing_ok=True)
        user = simulated_user_positions(auth)
        offered: list[Any] = []

        def clicks(first_ns: int, user: Any = user, offered: list[Any] = offered) -> list[Any]:
            offered.extend(user(first_ns))
            return offered

        rep = annotate_bag(auth, store, positions=clicks)
        with open_store(store, create=False) as st:
            placed = [a.text for a in st.annotations_of(rep.panorama_id)]
        params = root / f'{seed}_store.yaml'
        params.write_text(yaml.safe_dump({'annotation_matcher': {'ros__parameters': {
            'store_path': str(store), **(matcher_params or {})}}}))
        out = root / f'{seed}_out.mcap'
        GraphRunner(browse, out, params_files=[browse.with_name(browse.stem + '.params.yaml'), params],
                    nodes=['imu_magnetometer', 'panorama_mapper', 'hybrid_orientation_filter',
                           'annotation_matcher']).run()
        m = evaluate_annotations(out, labels=placed) or {}
        m['offered'] = len(offered)
        m['authored'] = len(rep.stored)
        m['not_placed'] = [f'{t}: {r}' for t, r in rep.skipped]
        m['authoring_heading_sigma_deg'] = round(rep.heading_sigma_deg, 3)
        rows[str(seed)] = m
        logger.info('graph spot %d: %s (%.0f s)', seed, {k: m.get(k) for k in (
            'redetection_rate', 'wrong_rate', 'wrong_label_time_share', 'time_to_first_s')}, time.perf_counter() - t)
    n = sum(r.get('n', 0) for r in rows.values())
    anchors = sum(r.get('anchors', 0) for r in rows.values())
    right = sum(round(r['redetection_rate'] * r['n']) for r in rows.values() if r.get('n'))
    wrong = sum(round(r['wrong_rate'] * r['n']) for r in rows.values() if r.get('n'))
    shown = sum(r.get('label_time_s', 0.0) for r in rows.values())
    wrong_s = sum((r.get('wrong_label_time_share') or 0.0) * r.get('label_time_s', 0.0) for r in rows.values())
    ttf = [r['time_to_first_s'] for r in rows.values() if r.get('time_to_first_s') is not None]
    return {
        'spots': spots, 'first_seed': first_seed, 'anchors': anchors,
        'offered': sum(r.get('offered', 0) for r in rows.values()), 'annotations': n,
        'redetection_rate': round(right / n, 4) if n else None,
        'wrong_rate': round(wrong / n, 4) if n else None,
        'redetection_rate_of_anchors': round(right / anchors, 4) if anchors else None,
        'wrong_rate_of_anchors': round(wrong / anchors, 4) if anchors else None,
        'wrong_label_time_share': round(wrong_s / shown, 4) if shown else None,
        'time_to_first_s_median': round(float(np.median(ttf)), 3) if ttf else None,
        'time_to_first_s_max': round(float(np.max(ttf)), 3) if ttf else None,
        'spots_without_a_correct_label': spots - len(ttf),
        'per_spot': rows,
    }
