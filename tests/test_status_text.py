"""STATUSTEXT longer than 50 characters: MAVLink 2 chunks (io.status_text), decoded by a pymavlink peer."""
from __future__ import annotations

import threading

import pytest

from edge_landing.runtime.io.mavlink_link import LinkConfig, MavlinkLink
from edge_landing.runtime.io.status_text import CHUNK_CHARS, MAX_CHUNKS, chunk_status, next_status_id
from edge_landing.runtime.io.telemetry import TelemetryBuffer
from tests.fake_autopilot import FakeAutopilot
from tests.run_helpers import free_udp_port, wait_for, wait_until_sendable


def test_a_text_that_fits_is_one_message():
    assert chunk_status("12.3m clear: edge target found") == [(0, b"12.3m clear: edge target found")]
    assert chunk_status("x" * CHUNK_CHARS) == [(0, b"x" * CHUNK_CHARS)]


def test_a_long_text_is_cut_into_chunks_in_order():
    text = "edge target lost: " + "unconfirmed: geometry has not measured the spot yet" * 2
    chunks = chunk_status(text)
    assert [seq for seq, _ in chunks] == list(range(len(chunks))) and len(chunks) == 3
    assert all(len(part) == CHUNK_CHARS for _, part in chunks[:-1]) and 0 < len(chunks[-1][1]) < CHUNK_CHARS
    assert b"".join(part for _, part in chunks).decode() == text


def test_a_whole_number_of_chunks_ends_with_an_empty_one():
    chunks = chunk_status("y" * (2 * CHUNK_CHARS))
    assert [part for _, part in chunks] == [b"y" * CHUNK_CHARS, b"y" * CHUNK_CHARS, b""]


def test_too_long_is_cut_with_a_mark_and_non_ascii_is_replaced():
    chunks = chunk_status("é" + "z" * 1000)
    joined = b"".join(part for _, part in chunks)
    assert len(chunks) == MAX_CHUNKS and len(joined) == MAX_CHUNKS * CHUNK_CHARS - 1
    assert joined.startswith(b"?z") and joined.endswith(b"...")


def test_ids_are_never_zero_and_wrap():
    assert next_status_id(0) == 1 and next_status_id(41) == 42
    assert next_status_id(0xFFFF) == 1


def test_a_pymavlink_peer_decodes_the_chunks_and_joins_them():
    port = free_udp_port()
    long_text = "edge target lost: unconfirmed: geometry sees an obstacle >= 1.0 m at the network's spot"
    with FakeAutopilot(port, lambda f, t: f.healthy()) as fake:
        link = MavlinkLink(LinkConfig(f"udpout:127.0.0.1:{port}"), TelemetryBuffer()).start()
        try:
            assert wait_until_sendable(link)
            assert link.send_status("short one", severity=6)
            assert link.send_status(long_text, severity=5)
            assert link.send_status(long_text, severity=5)
            assert wait_for(lambda: len(fake.of_type("STATUSTEXT")) >= 5, 3.0)
        finally:
            link.stop()
    msgs = [m for _, m in fake.of_type("STATUSTEXT")]
    assert msgs[0].text == "short one" and msgs[0].id == 0 and msgs[0].chunk_seq == 0
    first, second = msgs[1:3], msgs[3:5]
    for chunks in (first, second):
        assert {m.id for m in chunks} == {chunks[0].id} and chunks[0].id != 0
        assert [m.chunk_seq for m in chunks] == [0, 1] and {m.severity for m in chunks} == {5}
        assert "".join(m.text for m in chunks) == long_text
    assert first[0].id != second[0].id
    assert link.counts["statustext"] == 3


@pytest.mark.parametrize("n", [1, 49, 50, 51, 99, 100, 101, 199, 200, 201])
def test_every_length_round_trips_up_to_the_limit(n):
    text = "".join(chr(ord("a") + i % 26) for i in range(n))
    chunks = chunk_status(text)
    joined = b"".join(part for _, part in chunks).decode()
    assert len(chunks) <= MAX_CHUNKS and (n <= CHUNK_CHARS or len(chunks[-1][1]) < CHUNK_CHARS)
    assert joined == text if n < MAX_CHUNKS * CHUNK_CHARS else (joined.endswith("...") and len(joined) < n)


def test_texts_sent_from_two_threads_at_once_never_interleave_their_chunks():
    port = free_udp_port()
    texts = {k: f"thread {k}: " + chr(ord("a") + k) * 120 for k in range(2)}
    with FakeAutopilot(port, lambda f, t: f.healthy()) as fake:
        link = MavlinkLink(LinkConfig(f"udpout:127.0.0.1:{port}"), TelemetryBuffer()).start()
        try:
            assert wait_until_sendable(link)
            workers = [threading.Thread(target=lambda k=k: [link.send_status(texts[k]) for _ in range(10)])
                       for k in texts]
            for w in workers:
                w.start()
            for w in workers:
                w.join()
            assert wait_for(lambda: len(fake.of_type("STATUSTEXT")) >= 60, 5.0)
        finally:
            link.stop()
    msgs = [m for _, m in fake.of_type("STATUSTEXT")]
    assert len(msgs) == 60 and len({m.id for m in msgs}) == 20
    for start in range(0, 60, 3):                            # each text's three chunks back to back, in order
        group = msgs[start:start + 3]
        assert {m.id for m in group} == {group[0].id} and [m.chunk_seq for m in group] == [0, 1, 2]
        assert "".join(m.text for m in group) in texts.values()
