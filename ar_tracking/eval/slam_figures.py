"""A figure of the SLAM trajectory against the ground truth, for the evaluation report.

Left: top view (world x-y) of the true camera path and of the estimate after the Sim(3)
alignment that the ``slam`` measures use (ar_tracking.eval.slam_metrics), so what the figure
shows is what ``ate_rmse_m`` scores. Right: the translation error of every associated pose over
time. Rendered with matplotlib's Agg backend (no display needed).
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Mapping

from .slam_metrics import _compute, slam_metrics_with_alignment

logger = logging.getLogger(__name__)

#: Keys of the array form of :func:`slam_figure`'s source (as slam_metrics_from_arrays' arguments).
ARRAY_KEYS = ('stamps_ns_est', 'p_est', 'quat_xyzw_est', 'stamps_ns_gt', 'p_gt', 'quat_xyzw_gt')


def slam_figure(source: str | Path | Mapping[str, Any], out_png: str | Path,
                title: str | None = None) -> Path | None:
    """Write the figure for a bag (path) or for arrays (a mapping with :data:`ARRAY_KEYS`, plus
    optional ``n_frames``); returns the PNG path, or None when nothing can be aligned."""
    if isinstance(source, Mapping):
        missing = [k for k in ARRAY_KEYS if k not in source]
        if missing:
            raise ValueError(f'slam_figure: missing arrays {", ".join(missing)}')
        metrics, detail = _compute(*(source[k] for k in ARRAY_KEYS), source.get('n_frames'))
        name = title or 'SLAM vs ground truth'
    else:
        metrics, detail = slam_metrics_with_alignment(source)
        name = title or Path(source).name
    if detail is None:
        logger.warning('slam figure: no aligned trajectory to draw (%s)', name)
        return None

    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    out = Path(out_png)
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(11, 4.5), gridspec_kw={'width_ratios': [1, 1.3]})
    ax0.plot(detail.p_truth[:, 0], detail.p_truth[:, 1], '-', color='0.3', lw=1.5, label='ground truth')
    ax0.plot(detail.p_est_aligned[:, 0], detail.p_est_aligned[:, 1], '-', color='tab:orange', lw=1.0,
             label=f'SLAM (Sim(3) aligned, scale {detail.scale:.3g})')
    ax0.plot(detail.p_truth[0, 0], detail.p_truth[0, 1], 'o', color='0.3', ms=4)
    ax0.set_aspect('equal', adjustable='datalim')
    ax0.set_xlabel('x (m)')
    ax0.set_ylabel('y (m)')
    ax0.set_title('top view')
    ax0.legend(fontsize=8, loc='best')
    ax0.grid(alpha=0.3)
    ax1.plot(detail.t_s, detail.errors_m * 100, '-', color='tab:red', lw=1.0)
    ax1.set_xlabel('time (s)')
    ax1.set_ylabel('translation error (cm)')
    ratio = metrics.get('tracked_ratio')
    ax1.set_title(f"ATE RMSE {metrics['ate_rmse_m'] * 100:.2f} cm"
                  + (f", RPE RMSE {metrics['rpe_rmse'] * 100:.2f} cm / {metrics['rpe_delta_frames']} frames"
                     if metrics.get('rpe_rmse') is not None else '')
                  + (f', tracked {ratio:.0%}' if ratio is not None else ''), fontsize=9)
    ax1.grid(alpha=0.3)
    fig.suptitle(name, fontsize=10)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return out
