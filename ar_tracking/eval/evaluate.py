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

from .metrics import EvaluationError, evaluate_bag

logger = logging.getLogger(__name__)

#: area name -> "module:function" taking the bag path and returning a dict or None.
AREA_EVALUATORS: dict[str, str] = {}


def _load(spec: str) -> Callable[[Path], dict[str, Any] | None]:
    module, _, func = spec.partition(':')
    return getattr(importlib.import_module(module), func)


def evaluate_all(path: str | Path) -> dict[str, Any]:
    """Orientation metrics plus every area whose topics the bag has (DESIGN sec. 8 names)."""
    path = Path(path)
    metrics: dict[str, Any] = {}
    try:
        metrics = evaluate_bag(path)
    except EvaluationError:
        if not AREA_EVALUATORS:
            raise
        logger.info('%s: no orientation ground truth; other areas only', path)
    for area, spec in AREA_EVALUATORS.items():
        result = _load(spec)(path)
        if result is not None:
            metrics[area] = result
    if not any(k for k in metrics if k != 'bag'):
        raise EvaluationError(f'{path}: nothing to evaluate (no ground truth topics this package knows)')
    return metrics
