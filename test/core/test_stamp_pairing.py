"""NearestStampPairer: the same pairs for any interleaving of the two streams."""
from __future__ import annotations

import random

from hypothesis import given, settings
from hypothesis import strategies as st

from ar_tracking.core.stamp_pairing import NearestStampPairer

MS = 1_000_000


def run(events, max_gap_ns=15 * MS):
    pairer = NearestStampPairer(max_gap_ns)
    out = []
    for kind, t in events:
        if kind == 'p':
            out += pairer.add_primary(t, t)
        else:
            out += pairer.add_secondary(t, t)
    out += pairer.add_primary(10**15, None)  # flush: far in the future
    return [(t, s) for t, p, s in out if p is not None]


def test_pairs_nearest_within_gap():
    events = [('p', 100 * MS), ('s', 95 * MS), ('s', 103 * MS), ('p', 200 * MS), ('s', 300 * MS)]
    assert run(events) == [(100 * MS, 103 * MS), (200 * MS, None)]


def test_waits_for_a_later_secondary():
    pairer = NearestStampPairer(50 * MS)
    assert pairer.add_primary(100 * MS, 'a') == []
    assert pairer.add_secondary(90 * MS, 'x') == []  # a later one may still be nearer
    assert pairer.add_secondary(101 * MS, 'y') == [(100 * MS, 'a', 'y')]


@settings(max_examples=60, deadline=None)
@given(st.lists(st.integers(0, 50), min_size=1, max_size=40), st.lists(st.integers(0, 50), min_size=1, max_size=40),
       st.integers(0, 10**6))
def test_result_is_independent_of_interleaving(p_steps, s_steps, seed):
    p_times = sorted({sum(p_steps[: i + 1]) * MS + 1 for i in range(len(p_steps))})
    s_times = sorted({sum(s_steps[: i + 1]) * MS + 2 for i in range(len(s_steps))})
    in_order = sorted([('p', t) for t in p_times] + [('s', t) for t in s_times], key=lambda e: (e[1], e[0]))
    rng = random.Random(seed)
    # Another arrival order that keeps each stream in order, and delays secondaries at most a bit.
    shuffled, ps, ss = [], [('p', t) for t in p_times], [('s', t) for t in s_times]
    while ps or ss:
        take_p = ps and (not ss or rng.random() < 0.5)
        shuffled.append(ps.pop(0) if take_p else ss.pop(0))
    expected = run(in_order, max_gap_ns=10**12)
    assert run(shuffled, max_gap_ns=10**12) == expected
    # With an unbounded gap every primary pairs with its nearest secondary.
    for t, s in expected:
        assert s == min(s_times, key=lambda x: (abs(x - t), x))
