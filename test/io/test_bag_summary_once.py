"""BagReader reads an MCAP file's summary once per open reader, not on every messages() call:
a bench that reads one topic after another would otherwise parse the footer and the whole
summary (channels, schemas, chunk indexes) each time."""
from __future__ import annotations

import pytest
from mcap.reader import SeekingReader

from ar_tracking.io.bags import BagReader, BagWriter, msg_class, serialize

SEC = 1_000_000_000
T0 = 1_700_000_000 * SEC
String = msg_class('std_msgs/msg/String')


def write_two_topic_bag(path, n: int = 40):
    with BagWriter(path, chunk_size=300) as w:
        for i in range(n):
            w.write(('/a', '/b')[i % 2], T0 + i * SEC // 10, serialize(String(data=f'm{i}')),
                    msgtype='std_msgs/msg/String')
    return path


@pytest.fixture
def summary_reads(monkeypatch):
    """How many times the mcap package's reader parsed a file's summary."""
    calls = []
    original = SeekingReader.get_summary

    def counted(self):
        calls.append(1)
        return original(self)

    monkeypatch.setattr(SeekingReader, 'get_summary', counted)
    return calls


def test_two_messages_calls_read_the_summary_once(tmp_path, summary_reads):
    path = write_two_topic_bag(tmp_path / 'b.mcap')
    with BagReader(path) as bag:
        a = [m.rawdata for m in bag.messages(['/a'])]
        b = [m.rawdata for m in bag.messages(['/b'])]
        every = list(bag.messages())
    assert len(summary_reads) == 1
    assert len(a) == len(b) == 20
    assert len(every) == 40
    # the same messages as rosbags' reader gives
    with BagReader(path) as bag:
        bag.fast_mcap = False
        assert [m.rawdata for m in bag.messages(['/a'])] == a
        assert list(bag.messages()) == every


def test_a_reopened_reader_reads_the_summary_again(tmp_path, summary_reads):
    """The cache belongs to one open reader: a file rewritten between two opens is read anew."""
    path = write_two_topic_bag(tmp_path / 'b.mcap', n=40)
    bag = BagReader(path)
    with bag:
        assert len(list(bag.messages())) == 40
    write_two_topic_bag(tmp_path / 'c.mcap', n=60).replace(path)
    with bag:
        assert len(list(bag.messages())) == 60
        assert len(list(bag.messages(['/a']))) == 30
    assert len(summary_reads) == 2
