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


def reusable_sweep_bag(path: Path) -> bool:
    """Whether a rotation_sweep bag a bench made before can be used again: it exists and was
    made by this simulator revision (a hard bag records it; a kind bag, frozen byte for byte,
    records nothing), and was finished (a bench killed while making it leaves an empty or
    unfinished file). A stale or unfinished one is said so, and made again by the caller."""
    from ..io.bags import read_metadata
    from ..io.mcap_recovery import is_unfinished_mcap
    from ..sim.rotation_sweep_bag import SIM_METADATA, SIM_REVISION

    if not path.exists():
        return False
    if path.stat().st_size == 0 or is_unfinished_mcap(path):
        logger.info('%s was not finished (a run stopped while making it): making it again', path)
        return False
    meta = read_metadata(path, SIM_METADATA)
    if meta is None or meta.get('revision') == SIM_REVISION:
        return True
    logger.info('%s was made by an earlier simulator (revision %s, now %s): making it again',
                path, meta.get('revision', 'before 18'), SIM_REVISION)
    return False


def benchmark_bag(workdir: Path, duration_s: float, seed: int = 1) -> Path:
    """The rotation_sweep bag the graph benchmark runs on (made once, then reused while the
    simulator's revision is the same)."""
    from ..sim.bagmaker import make_bag

    path = workdir / f'rotation_sweep_seed{seed}_{duration_s:g}s.mcap'
    if not reusable_sweep_bag(path):
        logger.info('making the benchmark bag %s', path)
        make_bag('rotation_sweep', path, seed=seed, duration_s=duration_s, overwrite=True)
    return path
