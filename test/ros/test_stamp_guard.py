"""Stamp checks: zero, duplicate and older stamps dropped; a large jump back resets."""
from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from ar_tracking.ros.stamp_guard import StampGuard, StampVerdict

SEC = 1_000_000_000
MS = 1_000_000
T0 = 1_700_000_000 * SEC


def test_first_stamp_and_increasing_stamps_are_ok():
    guard = StampGuard()
    assert guard.last_ns is None
    for k in range(5):
        assert guard.check(T0 + k * 10 * MS) is StampVerdict.OK
        assert guard.last_ns == T0 + k * 10 * MS


def test_one_nanosecond_steps_at_epoch_time():
    """Integer nanoseconds: steps a float-seconds stamp could not resolve are still ordered."""
    guard = StampGuard()
    assert guard.check(T0 + 1) is StampVerdict.OK
    assert guard.check(T0 + 2) is StampVerdict.OK
    assert guard.check(T0 + 1) is StampVerdict.OLDER
    assert guard.check(T0 + 2) is StampVerdict.DUPLICATE


def test_zero_and_negative_stamps_are_dropped_without_state_change():
    guard = StampGuard()
    assert guard.check(0) is StampVerdict.ZERO
    assert guard.last_ns is None
    assert guard.check(T0) is StampVerdict.OK
    assert guard.check(0) is StampVerdict.ZERO
    assert guard.check(-5) is StampVerdict.ZERO
    assert guard.last_ns == T0
    assert guard.check(T0 + MS) is StampVerdict.OK


def test_duplicates():
    guard = StampGuard()
    guard.check(T0)
    assert guard.check(T0) is StampVerdict.DUPLICATE
    assert guard.last_ns == T0
    lenient = StampGuard(allow_duplicates=True)
    lenient.check(T0)
    assert lenient.check(T0) is StampVerdict.OK
    assert lenient.check(T0 - MS) is StampVerdict.OLDER  # duplicates allowed, older still not


def test_slightly_older_stamp_is_dropped_and_does_not_move_the_stream_back():
    guard = StampGuard(reset_after_s=1.0)
    guard.check(T0 + SEC)
    assert guard.check(T0 + SEC - 5 * MS) is StampVerdict.OLDER
    assert guard.last_ns == T0 + SEC
    # a stamp between the dropped one and the last accepted one is still older
    assert guard.check(T0 + SEC - 1 * MS) is StampVerdict.OLDER
    assert guard.check(T0 + SEC + 1 * MS) is StampVerdict.OK


def test_large_jump_back_resets_and_continues():
    guard = StampGuard(reset_after_s=1.0)
    for k in range(100):  # a 10 s bag
        assert guard.check(T0 + k * 100 * MS) is StampVerdict.OK
    # the bag loops: back to its start
    assert guard.check(T0) is StampVerdict.RESET
    assert guard.last_ns == T0
    assert guard.check(T0 + 100 * MS) is StampVerdict.OK
    assert guard.check(T0 + 50 * MS) is StampVerdict.OLDER


def test_reset_threshold_is_strict():
    guard = StampGuard(reset_after_s=0.5)
    guard.check(T0 + SEC)
    assert guard.check(T0 + SEC // 2) is StampVerdict.OLDER  # exactly 0.5 s back
    assert guard.check(T0 + SEC // 2 - 1) is StampVerdict.RESET  # one nanosecond more


def test_reset_forgets_the_last_stamp():
    guard = StampGuard()
    guard.check(T0 + 5 * SEC)
    guard.reset()
    assert guard.last_ns is None
    assert guard.check(T0 + 4 * SEC + 900 * MS) is StampVerdict.OK  # would be OLDER otherwise


def test_verdicts_have_readable_reasons():
    for verdict in StampVerdict:
        assert isinstance(verdict.value, str) and verdict.value
    assert StampVerdict.OK.value == 'ok'


@settings(max_examples=200, deadline=None, derandomize=True)
@given(
    stamps=st.lists(st.integers(-SEC, 20 * SEC), min_size=1, max_size=60),
    reset_after_s=st.sampled_from([0.0, 0.1, 1.0, 5.0]),
    allow_duplicates=st.booleans(),
)
def test_accepted_stamps_only_go_forward_between_resets(stamps, reset_after_s, allow_duplicates):
    """Between resets the accepted stream is monotonic; every verdict matches its definition."""
    guard = StampGuard(reset_after_s, allow_duplicates)
    last = None
    for stamp in stamps:
        verdict = guard.check(stamp)
        if stamp <= 0:
            assert verdict is StampVerdict.ZERO
        elif last is None or stamp > last or (stamp == last and allow_duplicates):
            assert verdict is StampVerdict.OK
        elif stamp == last:
            assert verdict is StampVerdict.DUPLICATE
        elif last - stamp > int(reset_after_s * 1e9):
            assert verdict is StampVerdict.RESET
        else:
            assert verdict is StampVerdict.OLDER
        if verdict in (StampVerdict.OK, StampVerdict.RESET):
            last = stamp
        assert guard.last_ns == last
