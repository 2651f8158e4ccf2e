"""What ``ar-tracking evaluate`` prints: one compact table per area, targets beside the figures.

The metrics dict of :func:`ar_tracking.eval.evaluate.evaluate_all` is nested by area (DESIGN
sec. 8). :func:`area_rows` turns each area into rows of (measure, figure, target, verdict) so
that the console (:func:`format_console`) and the HTML report (report.py) show the same
figures against the same targets. The targets are the project's own, from the issues that set
them (named in each row) and docs/*.md; a figure without a target is shown without one.

:func:`unscored_areas` says which areas a bag could not be scored in and why (the topic that
is missing, and what would produce it). :func:`strict_json` makes the dict strict JSON: NaN and
infinities become null, numpy scalars plain numbers.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

#: Areas in the order they are shown; the names are DESIGN sec. 8's.
AREAS = ('orientation', 'panorama', 'annotations', 'slam', 'markers', 'vi')

#: What a reader calls each orientation estimate (the JSON keys stay the topic names).
ESTIMATE_NAMES: dict[str, str] = {
    'imu/data': 'sensor-only (imu/data)',
    'orientation/global': 'hybrid (orientation/global)',
    'reference/vqf': "VQF reference (on the bag's IMU samples)",
    'panorama/orientation': 'panorama tracking (panorama/orientation)',
    'vi/odometry': 'marker + IMU fusion (vi/odometry)',
    'vi/predicted_pose': 'marker + IMU, predicted (vi/predicted_pose)',
    'markers/pose': 'markers only (markers/pose)',
    'slam/pose': 'keyframe SLAM (slam/pose)',
}


def display_name(topic: str) -> str:
    """The legend/table name of an estimate topic (``imu/data`` -> ``sensor-only (imu/data)``)."""
    key = topic.lstrip('/')
    return ESTIMATE_NAMES.get(key, key)


@dataclass(frozen=True)
class Row:
    """One line of an area table: the figure, the target it is held to (or ''), the verdict
    ('met', 'NOT met', '' without a target, 'n/a' when the figure is missing)."""

    measure: str
    figure: str
    target: str = ''
    verdict: str = ''


def strict_json(value: Any) -> Any:
    """A copy of ``value`` that ``json.dumps(..., allow_nan=False)`` accepts: non-finite floats
    become None, numpy scalars and arrays plain Python numbers and lists, tuples lists."""
    if isinstance(value, dict):
        return {str(k): strict_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [strict_json(v) for v in value]
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return value
    if hasattr(value, 'tolist') and not isinstance(value, (int, float)):  # numpy scalar or array
        return strict_json(value.tolist())
    if isinstance(value, int):
        return int(value)
    if isinstance(value, float):
        return float(value) if math.isfinite(value) else None
    return value


def _get(d: Any, path: str) -> Any:
    for part in path.split('.'):
        if not isinstance(d, dict) or part not in d:
            return None
        d = d[part]
    return d


def _num(v: Any) -> float | None:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    return float(v) if math.isfinite(v) else None


def _fmt(v: Any, unit: str = '', digits: int = 2) -> str:
    x = _num(v)
    if x is None:
        return '-'
    text = str(int(x)) if digits == 0 else f'{x:.{digits}f}'
    return f'{text} {unit}'.rstrip()


def _verdict(value: Any, op: str, bound: float | None) -> str:
    x = _num(value)
    if bound is None or x is None:
        return 'n/a'
    ok = x <= bound if op == '<=' else x >= bound if op == '>=' else x < bound if op == '<' else x == bound
    return 'met' if ok else 'NOT met'


def _row(measure: str, value: Any, unit: str = '', digits: int = 2, op: str = '', bound: float | None = None,
         source: str = '', bound_text: str | None = None) -> Row:
    if not op:
        return Row(measure, _fmt(value, unit, digits))
    shown = bound_text if bound_text is not None else _fmt(bound, unit, digits if bound is None or bound != int(bound) else 0)
    target = f'{op} {shown}' + (f' ({source})' if source else '')
    return Row(measure, _fmt(value, unit, digits), target, _verdict(value, op, bound))


def _scaled(v: Any, k: float) -> float | None:
    x = _num(v)
    return None if x is None else x * k


# --- one table per area ---------------------------------------------------------------------

def orientation_rows(area: dict[str, Any]) -> list[Row]:
    """Per estimate: RMSE (heading, tilt), max, n; targets of issues #4/#16 for the hybrid and
    the sensor-only AHRS (relative to the VQF reference on the same samples)."""
    rows: list[Row] = []
    vqf = area.get('reference/vqf') or {}
    vqf_h, vqf_t = _num(vqf.get('heading_rmse_deg')), _num(vqf.get('tilt_rmse_deg'))
    order = sorted(area, key=lambda k: (k == 'reference/vqf', k not in ESTIMATE_NAMES, k))
    for key in order:
        m = area[key]
        name = display_name(key)
        if not isinstance(m, dict):
            continue
        if 'error' in m:
            rows.append(Row(name, f'not scored: {m["error"]}'))
            continue
        figure = (f'rmse {_fmt(m.get("rmse_deg"))}  heading {_fmt(m.get("heading_rmse_deg"))}  '
                  f'tilt {_fmt(m.get("tilt_rmse_deg"))}  max {_fmt(m.get("max_deg"))} deg  n {m.get("n", 0)}')
        if not m.get('n'):
            rows.append(Row(name, 'no estimate inside the ground truth time span'))
            continue
        rows.append(Row(name, figure))
        h, t = m.get('heading_rmse_deg'), m.get('tilt_rmse_deg')
        if key == 'orientation/global':
            rows.append(_row('  hybrid heading RMSE', h, 'deg', op='<=', bound=1.0, source='#16'))
            rows.append(_row('  hybrid tilt RMSE', t, 'deg', op='<=', bound=0.5, source='#16'))
            if vqf_h is not None:
                rows.append(_row('  hybrid heading RMSE vs VQF', h, 'deg', op='<=', bound=vqf_h / 3.0,
                                 source='#16', bound_text=f'VQF / 3 = {vqf_h / 3.0:.2f} deg'))
        elif key == 'imu/data' and vqf_h is not None and vqf_t is not None:
            rows.append(_row('  sensor-only heading RMSE vs VQF', h, 'deg', op='<=', bound=1.1 * vqf_h,
                             source='#16', bound_text=f'1.1 x VQF = {1.1 * vqf_h:.2f} deg'))
            rows.append(_row('  sensor-only tilt RMSE vs VQF', t, 'deg', op='<=', bound=1.1 * vqf_t,
                             source='#16', bound_text=f'1.1 x VQF = {1.1 * vqf_t:.2f} deg'))
    return rows


def panorama_rows(area: dict[str, Any]) -> list[Row]:
    """Tracking relative to the first frame, lost frames, the EDR seam error (issue #3)."""
    rows = [
        _row('tracking RMSE (vs first frame)', area.get('tracking_rmse_deg'), 'deg', 3, '<=', 0.25, '#3'),
        _row('tracking max', area.get('tracking_max_deg'), 'deg', 3),
    ]
    if 'frames' in area:
        rows.append(Row('lost frames', f'{area.get("lost_frames", 0)} of {area["frames"]}'))
    if 'lost_frames_below_90dps' in area:
        rows.append(_row('lost frames below 90 deg/s', area['lost_frames_below_90dps'], '', 0, '<=', 0, '#3',
                         bound_text='0'))
    seam = area.get('seam_error')
    if isinstance(seam, dict) and _num(seam.get('edr')) is not None:
        rows.append(Row('seam error EDR / 8-bit', f'{_fmt(seam.get("edr"))} / {_fmt(seam.get("8bit"))} (8-bit units)'))
        rows.append(_row('seam error ratio EDR / 8-bit', seam.get('ratio'), '', 2, '<=', 0.5, '#3'))
    return rows


def annotation_rows(area: dict[str, Any]) -> list[Row]:
    """Re-detection of the stored annotations (issues #5/#17)."""
    rows = [
        Row('annotations placed', f'{area.get("placed", 0)} of {area.get("n", 0)} '
                                  f'({area.get("matched", 0)} matched, {area.get("inferred", 0)} inferred)'),
        _row('redetection rate', area.get('redetection_rate'), '', 3, '>=', 0.95, '#17', bound_text='0.95'),
        _row('wrong rate', area.get('wrong_rate'), '', 3, '<=', 0.02, '#17', bound_text='0.02'),
    ]
    if 'wrong_label_time_share' in area:
        rows.append(_row('wrong label time share', area['wrong_label_time_share'], '', 3, '<=', 0.01, '#17',
                         bound_text='0.01'))
    rows.append(_row('time to first correct label', area.get('time_to_first_s'), 's', 1, '<=', 3.0, '#17, median',
                     bound_text='3 s'))
    rows.append(_row('median placement error', area.get('median_error_deg'), 'deg', 2))
    return rows


def slam_rows(area: dict[str, Any]) -> list[Row]:
    """Keyframe SLAM after a Sim(3) alignment (issue #6)."""
    rows = [
        _row('tracked frames', area.get('tracked_ratio'), '', 3, '>=', 0.95, '#6', bound_text='0.95'),
        _row('ATE RMSE', _scaled(area.get('ate_rmse_m'), 100.0), 'cm', 2),
        _row('ATE / path length', _scaled(area.get('ate_ratio'), 100.0), '%', 3, '<=', 1.0, '#6', bound_text='1 %'),
        _row('path length (truth)', area.get('path_length_m'), 'm', 2),
        _row('RPE RMSE', _scaled(area.get('rpe_rmse'), 100.0), 'cm', 2),
        Row('keyframes / map points', f'{_fmt(area.get("keyframes"), digits=0)} / {_fmt(area.get("points"), digits=0)}'),
    ]
    return rows


def vi_rows(area: dict[str, Any]) -> list[Row]:
    """Marker + IMU fusion against the camera alone (issues #7/#23)."""
    pos, ori = area.get('position_rmse_cm'), area.get('orientation_rmse_deg')
    rows = [
        _row('fused position RMSE', pos, 'cm', 3, '<=', 0.2, '#23'),
        _row('fused orientation RMSE', ori, 'deg', 3, '<=', 0.05, '#23'),
    ]
    cam = _num(_get(area, 'camera_only.position_rmse_cm'))
    if cam is not None:
        rows.append(_row('camera only, hold (position)', cam, 'cm', 3))
        rows.append(_row('fused vs camera-only hold', pos, 'cm', 3, '<=', cam / 3.0, '#7',
                         bound_text=f'camera-only / 3 = {cam / 3.0:.3f} cm'))
    ext = _num(_get(area, 'camera_only_extrapolated.position_rmse_cm'))
    if ext is not None:
        rows.append(_row('camera only, extrapolated (position)', ext, 'cm', 3))
    rb, nrb = _num(_get(area, 'offline_rollback.position_rmse_cm')), _num(_get(area, 'no_rollback.position_rmse_cm'))
    if rb is not None and nrb is not None:
        rows.append(_row('roll-back vs applied on arrival', rb, 'cm', 3, '<', nrb, '#7',
                         bound_text=f'{nrb:.3f} cm (on arrival)'))
    slow = _get(area, 'by_speed_cm_s.32.filter.orientation_rmse_deg')
    if slow is not None:
        rows.append(_row('orientation RMSE at 32 cm/s', slow, 'deg', 3, '<', 0.5, '#7'))
    return rows


def marker_rows(area: dict[str, Any]) -> list[Row]:
    """Marker poses from the camera alone and corner accuracy (issue #23)."""
    rows = [
        _row('camera-only position RMSE', _get(area, 'pose.position_rmse_cm'), 'cm', 3, '<=', 0.35, '#23'),
        _row('camera-only orientation RMSE', _get(area, 'pose.orientation_rmse_deg'), 'deg', 3),
        _row('coverage (poses / frames)', _get(area, 'pose.coverage'), '', 2),
        _row('position NEES median (3 = honest)', _get(area, 'pose.nees_position_median'), '', 2),
        _row('quick pans: position max', _get(area, 'pose.fast_rotation.position_max_cm'), 'cm', 2),
    ]
    bias = _num(area.get('corner_bias_px'))
    if bias is not None:
        rows.append(Row('corner bias (outward +)', _fmt(bias, 'px', 3), '|bias| <= 0.05 px (#23)',
                        _verdict(abs(bias), '<=', 0.05)))
        rows.append(_row('corner RMSE', area.get('corner_rmse_px'), 'px', 3))
    return rows


AREA_ROWS: dict[str, Callable[[dict[str, Any]], list[Row]]] = {
    'orientation': orientation_rows, 'panorama': panorama_rows, 'annotations': annotation_rows,
    'slam': slam_rows, 'markers': marker_rows, 'vi': vi_rows,
}

AREA_TITLES = {
    'orientation': 'orientation (camera in the world, against ground_truth/orientation)',
    'panorama': 'panorama (panorama_mapper, against ground_truth/orientation)',
    'annotations': 'annotations (annotation_matcher, against ground_truth/annotations)',
    'slam': 'slam (keyframe_slam_mapper, Sim(3)-aligned to ground_truth/pose)',
    'markers': 'markers (marker_tracker, camera only, against ground_truth/pose)',
    'vi': 'vi (visual_inertial_filter, against ground_truth/pose)',
}


def area_rows(metrics: dict[str, Any]) -> dict[str, list[Row]]:
    """Rows of every area the metrics hold (in :data:`AREAS` order); an area whose figures
    are all missing gets no rows (see :func:`unscored_areas`)."""
    out: dict[str, list[Row]] = {}
    for area in AREAS:
        values = metrics.get(area)
        if not isinstance(values, dict) or not values or not has_figures(values):
            continue
        # a row without any figure (a measure the bag could not give) is left out: the
        # "not scored" lines say why
        rows = [r for r in AREA_ROWS[area](values) if r.figure.replace('-', '').replace('/', '').strip()]
        if rows:
            out[area] = rows
    return out


def has_figures(values: Any) -> bool:
    """True when a (nested) area dict holds at least one number (not only None/empty)."""
    if isinstance(values, dict):
        return any(has_figures(v) for v in values.values())
    if isinstance(values, (list, tuple)):
        return any(has_figures(v) for v in values)
    if isinstance(values, str):
        return True
    return _num(values) is not None


# --- what could not be scored -----------------------------------------------------------------

#: area -> (topic whose absence means the node did not run, what would produce it)
_PRODUCERS = {
    'orientation': ('/imu/data', 'imu_magnetometer / hybrid_orientation_filter'),
    'panorama': ('/panorama/orientation', 'panorama_mapper (needs camera images)'),
    'annotations': ('/annotations/markers',
                    'annotation_matcher (needs a store: --params-file with annotation_matcher store_path)'),
    'slam': ('/slam/pose', 'keyframe_slam_mapper (ar-tracking run --graph slam)'),
    'markers': ('/markers/pose', 'marker_tracker (ar-tracking run --graph markers)'),
    'vi': ('/vi/odometry', 'visual_inertial_filter (ar-tracking run --graph markers)'),
}
_TRUTH = {
    'orientation': ('/ground_truth/orientation',),
    'panorama': ('/ground_truth/orientation',),
    'annotations': ('/ground_truth/annotations', '/ground_truth/orientation'),
    'slam': ('/ground_truth/pose',),
    'markers': ('/ground_truth/pose',),
    'vi': ('/ground_truth/pose',),
}


def _bag_topics(bag: str | Path) -> set[str]:
    from ..io.bags import BagError, BagReader

    try:
        with BagReader(bag) as reader:
            return set(reader.topics)
    except BagError:
        return set()


def unscored_areas(metrics: dict[str, Any], bag: str | Path | None = None,
                   topics: Iterable[str] | None = None) -> list[tuple[str, str]]:
    """(area, why) for every area of :data:`AREAS` without figures in ``metrics``; the reason
    names the missing topic (read from ``bag`` unless ``topics`` is given)."""
    have = set(topics) if topics is not None else (_bag_topics(bag) if bag is not None else set())
    shown = area_rows(metrics)
    out: list[tuple[str, str]] = []
    for area in AREAS:
        values = metrics.get(area)
        if area not in shown:
            out.append((area, _why(area, have, values)))
            continue
        assert isinstance(values, dict)  # shown: a dict with figures
        key = _KEY_FIGURE.get(area)
        if area == 'orientation':
            if not any(isinstance(v, dict) and v.get('n') for v in values.values()):
                out.append((area, 'no estimate could be scored (see the rows above)'))
        elif key is not None and _num(_get(values, key)) is None:
            out.append((area, f'{key} not scored: ' + _why(area, have, values)))
    return out


#: The figure without which an area counts as not scored although it has a table.
_KEY_FIGURE = {'panorama': 'tracking_rmse_deg', 'slam': 'ate_rmse_m', 'annotations': 'redetection_rate',
               'vi': 'position_rmse_cm', 'markers': 'pose.position_rmse_cm'}


def _why(area: str, have: set[str], values: Any) -> str:
    if isinstance(values, dict) and isinstance(values.get('error'), str):
        return values['error']
    produced, producer = _PRODUCERS[area]
    if area == 'orientation':
        if '/ground_truth/orientation' not in have:
            return 'no /ground_truth/orientation in the bag (the truth to score against)'
        return 'no orientation estimate in the bag (imu/data, orientation/global...)'
    if area == 'slam' and not any(t.startswith('/slam/') for t in have):
        return f'no /slam/ topics in the bag: {producer} did not run'
    if area != 'slam' and produced not in have:
        return f'no {produced} in the bag: {producer} did not run'
    missing = [t for t in _TRUTH[area] if t not in have]
    if missing:
        return f'no {" or ".join(missing)} in the bag (the truth to score against)'
    if area == 'slam':
        return 'SLAM ran but never tracked a pose that matches the truth (no initialisation?)'
    if isinstance(values, dict) and values:
        return 'the estimate and the truth do not overlap in time'
    return 'nothing to score'


# --- the console ----------------------------------------------------------------------------

def format_console(metrics: dict[str, Any], bag: str | Path | None = None,
                   topics: Iterable[str] | None = None) -> str:
    """The compact console report: a table per area, then the areas not scored and why."""
    lines: list[str] = []
    info = metrics.get('bag') if isinstance(metrics.get('bag'), dict) else None
    if info and info.get('world_alignment') not in (None, 'none'):
        lines.append(f'(world frames aligned by one constant {info["world_alignment"]} per estimate)')
    for area, rows in area_rows(metrics).items():
        lines.append(AREA_TITLES[area])
        w_measure = max(len(r.measure) for r in rows)
        w_figure = max((len(r.figure) for r in rows if r.target), default=0)
        for r in rows:
            if r.target:
                lines.append(f'  {r.measure:<{w_measure}}  {r.figure:<{w_figure}}  target {r.target}: {r.verdict}')
            else:
                lines.append(f'  {r.measure:<{w_measure}}  {r.figure}'.rstrip())
    missing = unscored_areas(metrics, bag, topics)
    if missing:
        lines.append('not scored:')
        width = max(len(a) for a, _ in missing)
        lines.extend(f'  {a:<{width}}  {why}' for a, why in missing)
    return '\n'.join(lines)
