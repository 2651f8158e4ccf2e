"""The evaluation report: a section per area with its figures against the targets, and plots.

Orientation: one figure of the orientations over time (below). Panorama, annotations, SLAM and
VI: the same table of figures and targets that ``evaluate`` prints (console.py) and their plots
(figures.py: tracking error and map, labels placed, trajectory and error, error over time). An
area the bag has nothing of is listed under "Not in this bag" with the reason, never shown as
an empty table.

The figure has four panels sharing the time axis: the camera's heading, pitch and roll (what a
person calls them, see ``camera_heading_pitch_roll_deg``) for the ground truth (black) and each
estimate, and the heading error of each estimate, with the simulated magnetic disturbance
(compass deflection) shaded behind it when the bag has one, because a heading error that
follows the disturbance tells a magnetometer problem from a filter problem at a glance.

The HTML page embeds the PNG as base64 so that it is one self-contained file to attach to an
issue or open offline.
"""
from __future__ import annotations

import base64
import html
import io
import logging
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ar_tracking.core.rotations import camera_heading_pitch_roll_deg
from ar_tracking.eval.console import (
    AREA_TITLES,
    AREAS,
    area_rows,
    display_name,
    unscored_areas,
)
from ar_tracking.eval.metrics import (
    BagOrientations,
    EvaluationError,
    OrientationSeries,
    evaluate_orientations,
    load_orientations,
    orientation_errors,
    topic_key,
)

logger = logging.getLogger(__name__)

Array = NDArray[np.float64]

FIGSIZE_IN = (12.0, 10.0)
DPI = 100
#: Lines are thinned to at most this many points: enough for a 1200-pixel-wide figure.
MAX_PLOT_POINTS = 4000
#: Smallest y range of a panel, so that flat lines stay flat.
MIN_Y_SPAN_DEG = 2.0
TRUTH_COLOUR = 'black'
DISTURBANCE_COLOUR = 'tab:gray'


def write_report(bag: str | Path, out: str | Path, metrics: dict | None = None) -> Path:
    """Write the evaluation report of ``bag`` to ``out`` and return the path written.

    ``out`` ending in ``.png`` gives the figures alone, one under the other (orientation first,
    then every other area's); ending in ``.html`` (or ``.htm``) a page with a section per area
    (:func:`render_html`). ``metrics`` (the dict of
    :func:`~ar_tracking.eval.metrics.evaluate_bag`) is computed when not given.
    """
    out = Path(out)
    kind = out.suffix.lower()
    if kind not in ('.png', '.html', '.htm'):
        raise EvaluationError(f'{out}: a report ends in .png or .html')
    from .figures import area_figures

    try:
        data = load_orientations(bag)
    except EvaluationError:
        data = None  # no orientation ground truth (a SLAM or marker bag): the other areas only
    figures: dict[str, list[tuple[str, bytes]]] = {}
    if data is not None:
        if metrics is None:
            metrics = evaluate_orientations(data)
        png: bytes | None = render_figure_png(data, metrics) if _scored_estimates(data) else None
    else:
        if metrics is None:
            from .evaluate import evaluate_all

            metrics = evaluate_all(bag)
        png = None
    figures = area_figures(bag)
    out.parent.mkdir(parents=True, exist_ok=True)
    if kind == '.png':
        # every area's plots under the orientation figure, in one image
        pngs = ([png] if png is not None else []) + [fig for figs in figures.values() for _, fig in figs]
        if not pngs:
            raise EvaluationError(f'{bag}: nothing to draw (no orientation ground truth and no other figure)')
        out.write_bytes(stack_pngs(pngs))
    else:
        out.write_text(render_html(Path(bag), metrics, png, figures), encoding='utf-8')
    logger.debug('report written to %s', out)
    return out


def stack_pngs(pngs: list[bytes], width: int = int(FIGSIZE_IN[0] * DPI)) -> bytes:
    """PNG images one under the other, each scaled to ``width`` pixels (OpenCV)."""
    import cv2

    if len(pngs) == 1:
        return pngs[0]
    rows = []
    for data in pngs:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        if img is None:
            continue
        h, w = img.shape[:2]
        height = max(1, round(h * width / w))
        rows.append(cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA if w > width else cv2.INTER_LINEAR))
    ok, buf = cv2.imencode('.png', cv2.vconcat(rows))
    if not ok:
        raise EvaluationError('the report figures could not be encoded as one PNG')
    return buf.tobytes()


def _scored_estimates(data: BagOrientations) -> bool:
    return any(est.error is None and len(est.series) > 0 for est in data.estimates.values())


# --------------------------------------------------------------------------------------------
# Figure.


def render_figure_png(data: BagOrientations, metrics: dict) -> bytes:
    """The four-panel figure as PNG bytes (Agg backend: no display needed)."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(4, 1, figsize=FIGSIZE_IN, dpi=DPI, sharex=True)
    try:
        t0 = int(data.truth.stamps_ns[0])
        _plot_attitudes(axes[:3], data, t0)
        _plot_heading_errors(axes[3], data, t0)
        _label_axes(axes)
        fig.suptitle(_title(data.path, metrics), fontsize=11)
        fig.tight_layout()
        buf = io.BytesIO()
        fig.savefig(buf, format='png', dpi=DPI)
        return buf.getvalue()
    finally:
        plt.close(fig)


def _seconds(stamps_ns: NDArray[np.int64], t0: int) -> Array:
    """Seconds since t0, computed in integers first so that epoch stamps keep precision."""
    return (np.asarray(stamps_ns, dtype=np.int64) - t0) * 1e-9


def _thin(*arrays: np.ndarray) -> tuple[np.ndarray, ...]:
    """Every k-th element so that a line has at most MAX_PLOT_POINTS points."""
    step = max(1, int(np.ceil(len(arrays[0]) / MAX_PLOT_POINTS)))
    return tuple(a[::step] for a in arrays)


def _wrap180(deg: Array) -> Array:
    return (np.asarray(deg) + 180.0) % 360.0 - 180.0


def _unwrapped_heading(heading_deg: Array) -> Array:
    """Heading without 360-degree jumps, so that 359 -> 1 is drawn as a 2-degree step."""
    return np.degrees(np.unwrap(np.radians(heading_deg)))


def _heading_near(truth_t: Array, truth_heading: Array, t: Array, heading_deg: Array) -> Array:
    """An estimate's heading placed on the same unwrapped branch as the truth at its times."""
    reference = np.interp(t, truth_t, truth_heading)
    return reference + _wrap180(heading_deg - reference)


def _estimates_to_plot(data: BagOrientations) -> list[tuple[str, OrientationSeries]]:
    return [
        (topic, est.series)
        for topic, est in data.estimates.items()
        if est.error is None and len(est.series) > 0
    ]


def _colour(i: int) -> str:
    return f'C{i % 10}'


def _plot_attitudes(axes: Any, data: BagOrientations, t0: int) -> None:
    truth_t = _seconds(data.truth.stamps_ns, t0)
    heading, pitch, roll = camera_heading_pitch_roll_deg(data.truth.R_enu_cam)
    truth_heading = _unwrapped_heading(heading)
    for ax, values in zip(axes, (truth_heading, pitch, roll)):
        t, v = _thin(truth_t, values)
        ax.plot(t, v, color=TRUTH_COLOUR, linewidth=1.5, label='ground truth')
    for i, (topic, series) in enumerate(_estimates_to_plot(data)):
        t = _seconds(series.stamps_ns, t0)
        h, p, r = camera_heading_pitch_roll_deg(series.R_enu_cam)
        h = _heading_near(truth_t, truth_heading, t, h)
        for ax, values in zip(axes, (h, p, r)):
            tt, v = _thin(t, values)
            ax.plot(tt, v, color=_colour(i), linewidth=1.0, label=display_name(topic_key(topic)))


def _plot_heading_errors(ax: Any, data: BagOrientations, t0: int) -> None:
    if data.disturbance is not None:
        stamps, deflection_rad = data.disturbance
        # The simulator records the deflection clockwise-positive (as a compass reads); the
        # panel's heading error is counter-clockwise-positive, so a compass that follows the
        # disturbance lies on the shaded area.
        t, d = _thin(_seconds(stamps, t0), -np.degrees(deflection_rad))
        ax.fill_between(t, 0.0, d, color=DISTURBANCE_COLOUR, alpha=0.3, linewidth=0,
                        label='heading error a compass-only estimate would show (simulated disturbance)')
    for i, (topic, series) in enumerate(_estimates_to_plot(data)):
        errors = orientation_errors(data.truth, series)
        if len(errors.heading_deg) == 0:
            continue
        t, e = _thin(_seconds(errors.stamps_ns, t0), errors.heading_deg)
        ax.plot(t, e, color=_colour(i), linewidth=1.0, label=display_name(topic_key(topic)))
    ax.axhline(0.0, color=TRUTH_COLOUR, linewidth=0.5)


def _ensure_span(ax: Any, span: float) -> None:
    """Widen the y range to at least ``span`` so that a constant line (e.g. roll 0 with
    1e-14 of rounding noise) is not blown up into apparent noise."""
    low, high = ax.get_ylim()
    if high - low < span:
        middle = 0.5 * (low + high)
        ax.set_ylim(middle - 0.5 * span, middle + 0.5 * span)


def _label_axes(axes: Any) -> None:
    labels = (
        'heading [deg]\n(compass, unwrapped)',
        'pitch [deg]',
        'roll [deg]',
        'heading error [deg]\n(about up, CCW +)',
    )
    for ax, label in zip(axes, labels):
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
        _ensure_span(ax, MIN_Y_SPAN_DEG)
    axes[0].legend(loc='upper right', fontsize=8)
    if axes[3].get_legend_handles_labels()[0]:
        axes[3].legend(loc='lower left', fontsize=8)
    axes[3].set_xlabel('time since the first ground-truth stamp [s]')


def _fmt(value: Any, digits: int = 2) -> str:
    return '-' if value is None else f'{value:.{digits}f}'


def _title(bag: Path, metrics: dict) -> str:
    """Bag name and one line per topic with its RMSE split (at most a few topics)."""
    lines = [bag.name]
    entries = list(metrics.get('orientation', {}).items())
    for key, m in entries[:6]:
        if 'error' in m:
            lines.append(f'{display_name(key)}: {m["error"]}')
        else:
            lines.append(
                f'{display_name(key)}: RMSE {_fmt(m.get("rmse_deg"))} deg (heading '
                f'{_fmt(m.get("heading_rmse_deg"))}, tilt {_fmt(m.get("tilt_rmse_deg"))}), '
                f'max {_fmt(m.get("max_deg"))} deg, n={m.get("n", 0)}'
            )
    if len(entries) > 6:
        lines.append(f'... and {len(entries) - 6} more topics')
    return '\n'.join(lines)


# --------------------------------------------------------------------------------------------
# HTML.

_STYLE = """
body { font-family: sans-serif; margin: 2em; color: #222; }
table { border-collapse: collapse; margin: 1em 0; }
th, td { border: 1px solid #bbb; padding: 0.3em 0.8em; text-align: right; }
th:first-child, td:first-child { text-align: left; }
img { max-width: 100%; }
td.met { color: #1a7f37; } td.notmet { color: #c62828; font-weight: bold; }
details { margin: 1em 0; }
"""

_COLUMNS = (
    ('rmse_deg', 'RMSE [deg]'),
    ('heading_rmse_deg', 'heading RMSE [deg]'),
    ('tilt_rmse_deg', 'tilt RMSE [deg]'),
    ('max_deg', 'max [deg]'),
    ('n', 'n'),
)


def _table_rows(metrics: dict) -> list[str]:
    rows = []
    for key, m in metrics.get('orientation', {}).items():
        cells = [f'<td>{html.escape(display_name(key))}</td>']
        if 'error' in m:
            cells.append(f'<td colspan="{len(_COLUMNS)}">{html.escape(m["error"])}</td>')
        else:
            for name, _ in _COLUMNS:
                value = m.get(name)
                text = str(value) if name == 'n' else _fmt(value, 3)
                cells.append(f'<td>{text}</td>')
        rows.append('<tr>' + ''.join(cells) + '</tr>')
    return rows


def _bag_info(bag: Path, metrics: dict) -> tuple[str, str, str]:
    """(path, duration text, topic count text) from the metrics, or read from the bag."""
    bag_entry = metrics.get('bag')
    info: dict[str, Any] = bag_entry if isinstance(bag_entry, dict) else {}
    duration, topics = info.get('duration_s'), info.get('topics')
    if duration is None or topics is None:
        from ..io.bags import BagError, BagReader

        try:
            with BagReader(bag) as reader:
                duration = reader.duration_s if duration is None else duration
                topics = len(reader.topics) if topics is None else topics
        except BagError:
            pass
    duration_text = f'{duration:.1f} s' if isinstance(duration, (int, float)) else 'duration unknown'
    topics_text = f'{topics} topics' if isinstance(topics, int) else 'topics unknown'
    return str(info.get('path', bag)), duration_text, topics_text


def render_html(bag: Path, metrics: dict, png: bytes | None,
                figures: dict[str, list[tuple[str, bytes]]] | list[tuple[str, bytes]] | None = None) -> str:
    """A self-contained page: title, bag summary, then a section per area (its figures against
    the targets, and its plots), the areas the bag has nothing of, and every measure by name."""
    name = html.escape(bag.name)
    if isinstance(figures, list):  # (caption, PNG) without areas: shown after the areas
        figures = {'other': figures}
    figures = figures or {}
    path, duration, topics = _bag_info(bag, metrics)
    rows = area_rows(metrics)
    parts: list[str] = []
    for area in AREAS:
        if area == 'orientation':
            if png is not None or area in rows:
                parts += _orientation_section(name, metrics, png)
            continue
        if area not in rows and not figures.get(area):
            continue
        parts.append(f'<h2>{html.escape(AREA_TITLES[area])}</h2>')
        parts += _rows_table(rows.get(area, []))
        parts += _figure_tags(figures.get(area, []))
    parts += _figure_tags(figures.get('other', []))
    missing = unscored_areas(metrics, bag)
    if missing:
        parts.append('<h2>Not in this bag, or not scored</h2><ul>')
        parts += [f'<li><b>{html.escape(a)}</b>: {html.escape(why)}</li>' for a, why in missing]
        parts.append('</ul>')
    parts += _all_measures(metrics)
    return '\n'.join([
        '<!DOCTYPE html>',
        '<html lang="en"><head><meta charset="utf-8">',
        f'<title>ar_tracking evaluation: {name}</title>',
        f'<style>{_STYLE}</style></head><body>',
        f'<h1>Evaluation: {name}</h1>',
        f'<p>Bag {html.escape(path)}, {duration}, {topics}.</p>',
        *parts,
        '</body></html>',
        '',
    ])


def _orientation_section(name: str, metrics: dict, png: bytes | None) -> list[str]:
    header = ''.join(f'<th>{html.escape(label)}</th>' for _, label in _COLUMNS)
    rows = _table_rows(metrics) or [f'<tr><td colspan="{len(_COLUMNS) + 1}">no orientation estimates</td></tr>']
    parts = [
        f'<h2>{html.escape(AREA_TITLES["orientation"])}</h2>',
        '<p>Errors are of the camera orientation against the ground truth, interpolated at each '
        'estimate\'s header stamp; heading is about the world\'s up axis, tilt the rest.</p>',
        '<table>', f'<tr><th>estimate</th>{header}</tr>', *rows, '</table>',
    ]
    parts += _rows_table([r for r in area_rows(metrics).get('orientation', []) if r.target])
    if png is not None:
        image = base64.b64encode(png).decode('ascii')
        parts.append(f'<img alt="orientation over time for {name}" src="data:image/png;base64,{image}">')
    return parts


def _rows_table(rows: list[Any]) -> list[str]:
    """The console rows of an area (measure, figure, target, verdict) as an HTML table."""
    if not rows:
        return []
    out = ['<table>', '<tr><th>measure</th><th>figure</th><th>target (issue)</th><th></th></tr>']
    for r in rows:
        css = {'met': 'met', 'NOT met': 'notmet'}.get(r.verdict, '')
        out.append(f'<tr><td>{html.escape(r.measure.strip())}</td><td>{html.escape(r.figure)}</td>'
                   f'<td>{html.escape(r.target)}</td><td class="{css}">{html.escape(r.verdict)}</td></tr>')
    out.append('</table>')
    return out


def _figure_tags(figures: list[tuple[str, bytes]]) -> list[str]:
    parts: list[str] = []
    for caption, png in figures:
        data = base64.b64encode(png).decode('ascii')
        parts.append(f'<h3>{html.escape(caption)}</h3>')
        parts.append(f'<img alt="{html.escape(caption)}" src="data:image/png;base64,{data}">')
    return parts


def _flatten(prefix: str, value: Any, out: list[tuple[str, Any]]) -> None:
    if isinstance(value, dict):
        for k in sorted(value):
            _flatten(f'{prefix}.{k}' if prefix else str(k), value[k], out)
    else:
        out.append((prefix, value))


def _all_measures(metrics: dict) -> list[str]:
    """Every measure by its JSON name (what ``evaluate --json`` prints), folded away."""
    flat: list[tuple[str, Any]] = []
    for area in sorted(metrics):
        if area != 'bag':
            _flatten(area, metrics[area], flat)
    if not flat:
        return []
    rows = ''.join(f'<tr><td>{html.escape(k)}</td><td>{html.escape("null" if v is None else str(v))}</td></tr>'
                   for k, v in flat)
    return [f'<details><summary>Every measure by its JSON name ({len(flat)})</summary>',
            f'<table><tr><th>name</th><th>value</th></tr>{rows}</table></details>']
