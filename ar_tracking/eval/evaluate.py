"""Everything ``ar-tracking evaluate`` measures on one output bag, as one nested dict.

The orientation metrics (metrics.py) apply to every bag with ``/ground_truth/orientation``;
each further area (panorama, vi, ...) has an evaluator that returns None when the bag has
nothing of its kind. Areas are listed by module path so that one missing or failing area
never hides the others.
"""
from __future__ import annotations

import importlib
import logging
from pathlib import Path
from typing import Any, Callable

from .metrics import EvaluationError, evaluate_orientations, load_orientations, score

logger = logging.getLogger(__name__)

#: area name -> "module:function" taking the bag path and returning a dict or None.
AREA_EVALUATORS: dict[str, str] = {
    'panorama': 'ar_tracking.eval.evaluate:evaluate_panorama_area',
    'vi': 'ar_tracking.eval.vi_metrics:evaluate_vi',
    'markers': 'ar_tracking.eval.vi_metrics:evaluate_markers',
    'annotations': 'ar_tracking.eval.annotation_metrics:evaluate_annotations',
    'slam': 'ar_tracking.eval.slam_metrics:evaluate_slam',
}


def source_bag_of(path: Path) -> Path | None:
    """The input bag an output bag was made from (recorded by the runner), if it still exists."""
    from ..io.bags import read_metadata

    meta = read_metadata(path, 'ar_tracking.run') or {}
    src = meta.get('source_bag')
    return Path(src) if src and Path(src).exists() else None


def evaluate_panorama_area(path: Path) -> dict[str, Any] | None:
    """Panorama tracking measures; the seam error too when the input bag (with the camera
    images the output bag does not copy) can be found."""
    from .panorama_metrics import evaluate_panorama

    source = source_bag_of(path)
    return evaluate_panorama(path, source_bag=source, seam=source is not None)


def _load(spec: str) -> Callable[[Path], dict[str, Any] | None]:
    module, _, func = spec.partition(':')
    return getattr(importlib.import_module(module), func)


def orientation_metrics(path: str | Path, data: Any, align: str = 'none', reference: bool = True) -> dict[str, Any]:
    """The orientation section of :func:`evaluate_all` from the orientations already read from
    the output bag ``path`` (``data``: :func:`.metrics.load_orientations`), with the row
    ``reference/vqf`` (VQF on the bag's own IMU samples) when ``reference``."""
    metrics = evaluate_orientations(data, align)
    if reference and metrics.get('orientation'):
        from .reference_ahrs import vqf_reference

        ref = vqf_reference(path, source_bag_of(path))
        if ref is not None:
            metrics['orientation']['reference/vqf'] = score(data.truth, ref, 0, align)
    return metrics


def evaluate_all(path: str | Path, align: str = 'none', reference: bool = True) -> dict[str, Any]:
    """Orientation metrics plus every area whose topics the bag has (DESIGN sec. 8 names).

    ``align``: none / heading / rotation (metrics.align_world, for truth that is not
    north-referenced). ``reference``: add the row ``reference/vqf`` (VQF on the bag's own IMU
    samples, eval/reference_ahrs.py) next to the estimates."""
    path = Path(path)
    metrics: dict[str, Any] = {}
    missing_truth: EvaluationError | None = None
    try:
        metrics = orientation_metrics(path, load_orientations(path), align, reference)
    except EvaluationError as exc:
        missing_truth = exc
    for area, spec in AREA_EVALUATORS.items():
        try:
            result = _load(spec)(path)
        except Exception as exc:  # one failing area must not hide the others: say why instead
            logger.warning('%s: not scored: %s: %s', area, type(exc).__name__, exc)
            result = {'error': f'evaluation failed: {type(exc).__name__}: {exc}'}
        if result is not None:
            metrics[area] = result
    if missing_truth is not None and not metrics:
        raise missing_truth
    if missing_truth is not None:
        # Other areas were scored: say which truth topic the orientation section looked for.
        logger.warning('no orientation section: %s', missing_truth)
    return metrics
