"""The benchmark bag that several ``ar-tracking bench`` areas run the graph on.

Its own module so that :mod:`~ar_tracking.eval.bench` (which calls the areas) and the areas
that need the bag (:mod:`~ar_tracking.eval.bench_hybrid`, :mod:`~ar_tracking.eval.bench_foxglove`)
do not import each other.
"""
from __future__ import annotations

import logging
from pathlib import Path

# bench's logger: the message belongs to the benchmark run
logger = logging.getLogger('ar_tracking.eval.bench')


def benchmark_bag(workdir: Path, duration_s: float, seed: int = 1) -> Path:
    """The rotation_sweep bag the graph benchmark runs on (made once, then reused)."""
    from ..sim.bagmaker import make_bag

    path = workdir / f'rotation_sweep_seed{seed}_{duration_s:g}s.mcap'
    if not path.exists():
        logger.info('making the benchmark bag %s', path)
        make_bag('rotation_sweep', path, seed=seed, duration_s=duration_s, overwrite=True)
    return path
