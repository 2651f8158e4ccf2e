"""TrackingNode limits the OpenBLAS thread pools and OpenCV's of its process
(ar_tracking/blas.limit_blas_threads)."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

PROBE = r'''
import ctypes, sys
import rclpy
from rclpy.context import Context
from ar_tracking.ros.node_base import TrackingNode

def threads():
    out = {}
    for line in open('/proc/self/maps'):
        path = line.split()[-1]
        if 'openblas' in path.rsplit('/', 1)[-1].lower() and path.startswith('/') and path not in out:
            lib = ctypes.CDLL(path)
            for name in ('scipy_openblas_get_num_threads64_', 'scipy_openblas_get_num_threads',
                         'openblas_get_num_threads64_', 'openblas_get_num_threads'):
                if hasattr(lib, name):
                    out[path] = getattr(lib, name)()
                    break
    return out

import cv2, numpy, scipy.linalg  # every bundled OpenBLAS loaded before the node
before, cv_before = threads(), cv2.getNumThreads()
ctx = Context()
rclpy.init(context=ctx, domain_id=int(sys.argv[1]))
node = TrackingNode('blas_probe', context=ctx)
after, cv_after = threads(), cv2.getNumThreads()
node.destroy_node()
rclpy.shutdown(context=ctx)
print(len(before), max(before.values()), sorted(set(after.values())), cv_before, cv_after)
'''


def _probe(env: dict[str, str]) -> list[str]:
    out = subprocess.run([sys.executable, '-c', PROBE, '57'], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    return out.stdout.split()


@pytest.mark.skipif(not sys.platform.startswith('linux'), reason='finds the libraries in /proc/self/maps')
def test_a_node_limits_every_openblas_to_one_thread() -> None:
    env = {k: v for k, v in os.environ.items()
           if k not in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'OPENCV_FOR_THREADS_NUM')}
    n_libs, most_before, after, cv_before, cv_after = _probe(env)
    assert int(n_libs) >= 2  # numpy's and scipy's (and OpenCV's) builds
    if (os.cpu_count() or 1) > 1:
        assert int(most_before) > 1 and int(cv_before) > 1  # the defaults: a thread per core
    assert after == '[1]' and cv_after == '1'


@pytest.mark.skipif(not sys.platform.startswith('linux'), reason='finds the libraries in /proc/self/maps')
def test_openblas_num_threads_set_by_the_user_wins() -> None:
    env = {**os.environ, 'OPENBLAS_NUM_THREADS': '2'}
    if (os.cpu_count() or 1) < 2:
        pytest.skip('one core: OpenBLAS runs one thread whatever the setting')
    _, most_before, after, _, cv_after = _probe(env)
    assert int(most_before) == 2 and after == '[2]' and cv_after == '1'  # OpenCV's pool still limited
    _, _, after, _, cv_after = _probe({**env, 'OPENCV_FOR_THREADS_NUM': '2'})
    assert after == '[2]' and cv_after == '2'
