"""Mapping runs while the tracker waits for a frame (Klein & Murray 2009 sec. 3): the frame gate."""
from __future__ import annotations

import threading
import time

from ar_tracking.core.slam.frame_gate import FrameGate
from ar_tracking.core.slam.mapper import MapperConfig
from test_slam_mapper import _big_map


def _worker(gate: FrameGate, label: str, out: dict, ready: threading.Event) -> threading.Thread:
    def run() -> None:
        gate.bind()
        ready.set()
        out['held'] = gate.checkpoint(label)
        out['t'] = time.perf_counter()
    th = threading.Thread(target=run, daemon=True)
    th.start()
    return th


def test_mapper_step_waits_for_the_frame_to_end() -> None:
    gate = FrameGate()
    gate.frame_started()
    out: dict = {}
    ready = threading.Event()
    th = _worker(gate, 'step', out, ready)
    assert ready.wait(2.0)
    time.sleep(0.05)
    assert 't' not in out  # still held: a frame is being tracked
    t_end = time.perf_counter()
    gate.frame_finished()
    th.join(2.0)
    assert out['t'] >= t_end and out['held'] >= 0.04
    assert gate.stats['held'] == 1


def test_other_threads_and_an_open_gate_are_never_held() -> None:
    gate = FrameGate()
    gate.bind(threading.Thread(target=lambda: None))  # bound to some other thread
    gate.frame_started()
    t0 = time.perf_counter()
    assert gate.checkpoint('x') == 0.0  # the caller's own thread (process_queue, initialise_map)
    assert time.perf_counter() - t0 < 0.01
    gate2 = FrameGate()
    gate2.bind()
    gate2.frame_started()
    with gate2.opened():  # someone waits for the mapper (lockstep wait_for_mapping)
        t0 = time.perf_counter()
        gate2.checkpoint('x')
        assert time.perf_counter() - t0 < 0.01
    gate2.release()  # stopping: never held again
    t0 = time.perf_counter()
    gate2.checkpoint('x')
    assert time.perf_counter() - t0 < 0.01


def test_a_step_that_does_not_fit_before_the_next_frame_waits_for_it() -> None:
    gate = FrameGate()
    gate.bind()
    # Learn a 100 ms frame period and a 60 ms step.
    for _ in range(3):
        gate.frame_started()
        gate.frame_finished()
        time.sleep(0.1)
    gate.frame_started()
    gate.frame_finished()
    gate.checkpoint('big')
    time.sleep(0.06)
    gate.idle()
    # 60 ms of the 100 ms period are gone: another 60 ms step would overrun the next frame.
    out: dict = {}
    ready = threading.Event()
    th = _worker(gate, 'big', out, ready)
    assert ready.wait(2.0)
    time.sleep(0.03)  # the next frame is due ~100 ms after the last one started
    gate.frame_started()
    time.sleep(0.01)
    assert 't' not in out
    t_end = time.perf_counter()
    gate.frame_finished()
    th.join(2.0)
    assert out['t'] >= t_end


def test_mapper_bundle_adjustment_runs_between_frames() -> None:
    """With the mapping thread busy (global BA), no BA step starts while a frame is tracked."""
    cfg = MapperConfig(global_ba_iterations=1000, idle_poll_s=0.005)
    slam, mapper, _, _ = _big_map(cfg)
    starts: list[float] = []
    checkpoint = mapper.gate.checkpoint

    def recording_checkpoint(label: str) -> float:
        held = checkpoint(label)
        if threading.current_thread().name == 'slam-mapper':
            starts.append(time.perf_counter())
        return held

    mapper.gate.checkpoint = recording_checkpoint  # type: ignore[method-assign]
    mapper._global_dirty = True
    mapper.start()
    frames: list[tuple[float, float]] = []
    try:
        deadline = time.monotonic() + 5.0
        while not mapper.busy and time.monotonic() < deadline:
            time.sleep(0.002)
        for _ in range(12):  # 40 ms frames, 40 ms waiting for the next one
            mapper.gate.frame_started()
            t_a = time.perf_counter()
            time.sleep(0.04)
            t_b = time.perf_counter()
            mapper.gate.frame_finished()
            frames.append((t_a, t_b))
            time.sleep(0.04)
    finally:
        mapper.stop()
    assert mapper.stats['errors'] == 0
    between = sum(1 for s in starts if any(a - 0.05 < s < a for a, _ in frames))
    inside = [s for s in starts if any(a + 0.002 < s < b for a, b in frames)]
    assert between >= 6  # the mapper worked while the "tracker" waited for frames
    # A step starts inside a frame only if the OS woke the thread a whole idle gap late.
    assert len(inside) <= 1, (len(inside), len(starts))
