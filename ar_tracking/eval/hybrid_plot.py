"""Fig. 8-like plot of the hybrid orientation filter (Langlotz 2011 sec. 6.2).

Heading, pitch and roll over time of the sensor-only orientation (``imu/data``), the hybrid
output (``orientation/global``) and the truth, and the heading error of each estimate, from an
output bag of the graph runner. The lead hooks :func:`plot_hybrid` into the report.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..core.rotations import camera_heading_pitch_roll_deg
from .console import display_name
from .metrics import load_orientations, orientation_errors

TOPICS = (('/imu/data', display_name('imu/data'), 'tab:orange'),
          ('/orientation/global', display_name('orientation/global'), 'tab:blue'))


def plot_hybrid(bag: str | Path, out_png: str | Path) -> Path:
    """Write the figure to ``out_png`` and return its path.

    Raises :class:`ar_tracking.eval.metrics.EvaluationError` for a bag without ground truth.
    """
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    data = load_orientations(bag)
    t0 = int(data.truth.stamps_ns[0])
    fig, axes = plt.subplots(4, 1, figsize=(10, 10), sharex=True)
    names = ('heading (deg)', 'pitch (deg)', 'roll (deg)')
    truth_hpr = list(camera_heading_pitch_roll_deg(data.truth.R_enu_cam))
    truth_hpr[0] = np.degrees(np.unwrap(np.radians(truth_hpr[0])))  # no 360 -> 0 jumps
    t_truth = (data.truth.stamps_ns - t0) * 1e-9
    for ax, values, name in zip(axes[:3], truth_hpr, names):
        ax.plot(t_truth, values, color='k', lw=1.0, label='ground truth')
        ax.set_ylabel(name)
    for topic, label, color in TOPICS:
        est = data.estimates.get(topic)
        if est is None or est.error is not None or len(est.series) == 0:
            continue
        t = (est.series.stamps_ns - t0) * 1e-9
        for ax, values in zip(axes[:3], camera_heading_pitch_roll_deg(est.series.R_enu_cam)):
            if ax is axes[0]:  # unwrap the compass heading around the truth for readability
                ref = np.interp(t, t_truth, truth_hpr[0])
                values = ref + (values - ref + 180.0) % 360.0 - 180.0
            ax.plot(t, values, color=color, lw=0.8, label=label)
        err = orientation_errors(data.truth, est.series)
        rms = float(np.sqrt(np.mean(err.heading_deg**2))) if len(err.heading_deg) else float('nan')
        axes[3].plot((err.stamps_ns - t0) * 1e-9, err.heading_deg, color=color, lw=0.8,
                     label=f'{label}: RMSE {rms:.2f} deg')
    if data.disturbance is not None:
        ts, defl = data.disturbance
        # The deflection is clockwise-positive (a compass reading); the error is about up.
        axes[3].plot((ts - t0) * 1e-9, -np.degrees(defl), color='tab:red', lw=0.8, ls='--',
                     label='heading error of a compass-only estimate (simulated disturbance)')
    axes[3].set_ylabel('heading error (deg)')
    axes[3].set_xlabel('time (s)')
    axes[3].axhline(0.0, color='k', lw=0.5)
    for ax in axes:
        ax.grid(True, alpha=0.3)
        ax.legend(loc='upper right', fontsize=7)
    axes[0].set_title(f'Hybrid orientation vs sensor only: {Path(bag).name}')
    fig.tight_layout()
    out_png = Path(out_png)
    fig.savefig(out_png, dpi=100)
    plt.close(fig)
    return out_png
