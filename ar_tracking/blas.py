"""One BLAS (and OpenCV) thread per process, for the nodes and the benches that time what they run.

Plain process set-up (ctypes and /proc/self/maps): it imports nothing of ROS, so a benchmark can
limit its pools as the nodes do without rclpy.
"""
from __future__ import annotations

import os

#: set once the BLAS thread pools are limited (see :func:`limit_blas_threads`)
_blas_limited = False
#: setters of the OpenBLAS builds that numpy, scipy and OpenCV bundle (symbol prefixes differ)
_BLAS_SETTERS = ('scipy_openblas_set_num_threads64_', 'scipy_openblas_set_num_threads',
                 'openblas_set_num_threads64_', 'openblas_set_num_threads')


def limit_blas_threads(threads: int = 1) -> list[str]:
    """Limit every OpenBLAS loaded in this process (numpy's, scipy's, OpenCV's) and OpenCV's
    parallel_for pool to ``threads``; returns the BLAS libraries changed. Done once per process;
    OPENBLAS_NUM_THREADS or OPENCV_FOR_THREADS_NUM set in the environment wins.

    Why: the nodes multiply small matrices (the matcher's Walsh scores, 54 x 6 by 6 x 4,096,
    the trackers' batched Kabsch fits), where a BLAS thread pool costs more than it saves - and
    on a busy machine much more: with other processes on both cores, OpenBLAS's worker threads
    wait for a core on every product (that one product took 14 ms instead of 0.1 ms, and the
    annotation graph on the sample browsing bag spent 2.3 of its 3 s of tile matching there).
    Each node already has a thread or a process of its own. Results are the same (the products
    split rows among threads, never a sum).
    """
    global _blas_limited
    if _blas_limited:
        return []
    _blas_limited = True
    import cv2  # (OpenCV and scipy bring OpenBLAS builds of their own: load them now, so that
    import scipy.linalg  # noqa: F401  they are limited too)

    if 'OPENCV_FOR_THREADS_NUM' not in os.environ:
        # OpenCV's own pool too (matchTemplate, remap, cvtColor split rows among threads, the
        # same pixels either way): on the bench's 60 s bag the mapper's process took 4 % less
        # CPU with one thread, the output bag byte-identical.
        cv2.setNumThreads(threads)
    if 'OPENBLAS_NUM_THREADS' in os.environ:
        return []
    import ctypes

    try:
        with open('/proc/self/maps') as maps:
            paths = sorted({line.split()[-1] for line in maps
                            if 'openblas' in line.rsplit('/', 1)[-1].lower() and line.split()[-1].startswith('/')})
    except OSError:  # not Linux: leave the defaults
        return []
    changed = []
    for path in paths:
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for name in _BLAS_SETTERS:
            setter = getattr(lib, name, None)
            if setter is not None:
                setter(ctypes.c_int(threads))
                changed.append(path)
                break
    return changed
