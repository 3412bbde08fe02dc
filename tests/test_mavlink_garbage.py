"""Garbage bytes between real MAVLink 2 packets (a noisy serial line, a wrong-baud device, a misbehaving router):
the link still takes the real packets, and nothing that merely looks like a packet becomes telemetry."""
from __future__ import annotations

import random
import socket
import time

import pytest

from edge_landing.runtime.io.mavlink_conn import ResyncParser
from edge_landing.runtime.io.mavlink_link import LinkConfig, MavlinkLink, load_mavutil
from edge_landing.runtime.io.telemetry import TelemetryBuffer
from tests.run_helpers import free_tcp_port, free_udp_port, wait_for

mavutil = load_mavutil()
m = mavutil.mavlink
LOOKALIKE_ROLL = 0.7   # only the look-alike frames carry it


class _Bytes:
    def __init__(self) -> None:
        self.data = b""

    def write(self, buf: bytes) -> None:
        self.data += bytes(buf)


def _frame(mav, msg) -> bytes:
    mav.file = _Bytes()
    mav.send(msg)
    return mav.file.data


def _garbage(rng: random.Random, real: bytes, lookalike: bytes) -> bytes:
    """Noise with start markers in it, a cut-off real packet, or a well-formed frame that is not a packet."""
    kind = rng.randrange(4)
    if kind == 0:
        g = bytearray(rng.getrandbits(8) for _ in range(rng.randint(1, 40)))
        for _ in range(rng.randint(1, 3)):
            g[rng.randrange(len(g))] = rng.choice((0xFD, 0xFE))
        return bytes(g)
    if kind == 1:
        return real[:rng.randint(1, len(real) - 1)]
    if kind == 2:
        return lookalike
    return bytes(rng.getrandbits(8) for _ in range(rng.randint(0, 8)))


def _lookalikes(mav) -> list:
    """An ATTITUDE from the autopilot with its CRC broken, and a frame whose message id no dialect has."""
    bad_crc = bytearray(_frame(mav, m.MAVLink_attitude_message(5, LOOKALIKE_ROLL, 0.0, 0.0, 0, 0, 0)))
    bad_crc[-1] ^= 0x5A
    unknown = bytearray(_frame(mav, m.MAVLink_attitude_message(5, LOOKALIKE_ROLL, 0.0, 0.0, 0, 0, 0)))
    unknown[7:10] = bytes((0x21, 0x43, 0x65))
    return [bytes(bad_crc), bytes(unknown)]


def _stream(ticks: int, seed: int = 3, mav=None):
    """[(bytes to send, key of the real packet in them)]: four real packets a tick, each after some garbage."""
    rng = random.Random(seed)
    mav = mav or m.MAVLink(None, srcSystem=1, srcComponent=1)
    fakes = _lookalikes(m.MAVLink(None, srcSystem=1, srcComponent=1))
    out = []
    for tick in range(ticks):
        ms = 1000 + 33 * tick
        for msg, key in ((m.MAVLink_heartbeat_message(2, 3, 0, tick, 4, 3), ("HEARTBEAT", tick)),
                         (m.MAVLink_attitude_message(ms, 0.01, 0.02, 0.03, 0, 0, 0), ("ATTITUDE", ms)),
                         (m.MAVLink_local_position_ned_message(ms, 5.0, -3.0, -10.0, 0, 0, 0),
                          ("LOCAL_POSITION_NED", ms)),
                         (m.MAVLink_global_position_int_message(ms, 0, 0, 0, 10000, 0, 0, 0, 0),
                          ("GLOBAL_POSITION_INT", ms))):
            real = _frame(mav, msg)
            out.append((_garbage(rng, real, rng.choice(fakes)) + real, key))
    return out


def _key(msg):
    kind = msg.get_type()
    return (kind, msg.custom_mode if kind == "HEARTBEAT" else getattr(msg, "time_boot_ms", None))


def test_parser_finds_every_real_packet_in_garbage_whatever_the_chunks():
    stream = _stream(60)
    data = b"".join(chunk for chunk, _ in stream) + b"\xfd\x05"   # ends in a false start: held, never raised
    parser = ResyncParser(m.MAVLink(None)).install()
    rng, got, i = random.Random(5), [], 0
    while i < len(data):
        n = rng.choice((1, 2, 7, 64, 300))
        got += parser.mav.parse_buffer(data[i:i + n]) or []
        i += n
    assert [_key(msg) for msg in got] == [key for _, key in stream]
    assert parser.false_starts > 0 and parser.skipped_bytes > 0
    # Bounded: a flood of bytes that never form a packet is not kept.
    parser.mav.parse_buffer(random.Random(6).randbytes(3 * ResyncParser.MAX_BUFFERED))
    assert len(parser._buf) <= ResyncParser.MAX_BUFFERED


def _feed_link(transport: str, stream, key_path=None):
    """A MavlinkLink fed ``stream`` over loopback; returns it (stopped) and the messages its receive path took."""
    taken: list = []
    if transport == "udp":
        port = free_udp_port()
        peer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        peer.bind(("127.0.0.1", port))
        url = f"udpout:127.0.0.1:{port}"
    else:
        port = free_tcp_port()
        server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        server.bind(("127.0.0.1", port))
        server.listen(1)
        url = f"tcp:127.0.0.1:{port}"
    link = MavlinkLink(LinkConfig(url, key_path=key_path), TelemetryBuffer())
    handle = link._handle
    link._handle = lambda msg: (taken.append(msg), handle(msg))  # type: ignore[method-assign]
    link.start()
    try:
        if transport == "udp":
            peer.settimeout(5.0)
            _, addr = peer.recvfrom(65535)   # the link's heartbeat says where it listens

            def send(b: bytes) -> None:
                peer.sendto(b, addr)
        else:
            server.settimeout(5.0)
            peer, _ = server.accept()
            server.close()
            send = peer.sendall
        for i, (chunk, _) in enumerate(stream):
            send(chunk)
            if i % 8 == 7:
                time.sleep(0.004)   # a paced stream, not one burst into the socket buffer
        wait_for(lambda: len(taken) >= sum(key is not None for _, key in stream), 2.0)
    finally:
        link.stop()
        peer.close()
    return link, taken


@pytest.mark.parametrize("transport", ["udp", "tcp"])
def test_the_link_takes_real_packets_between_garbage_and_no_lookalike(transport):
    stream = _stream(60)
    link, taken = _feed_link(transport, stream)
    sent = {key for _, key in stream}
    real = {_key(msg) for msg in taken} & sent
    assert len(real) >= 0.9 * len(sent), f"{len(real)} of {len(sent)} real packets taken"
    assert all(_key(msg) in sent for msg in taken), {msg.get_type() for msg in taken}
    assert not [msg for msg in taken if getattr(msg, "roll", None) == pytest.approx(LOOKALIKE_ROLL)]
    assert link.peer == (1, 1) and link.telemetry.samples <= 3 * 60
    assert link.counters()["noise_bytes"] > 0                    # said and counted: a wrong baud rate shows


def test_signing_still_refuses_and_counts_bad_signatures_between_garbage(tmp_path):
    key = bytes(range(32))
    (tmp_path / "k.key").write_bytes(key)
    signed = m.MAVLink(None, srcSystem=1, srcComponent=1)
    signed.signing.secret_key, signed.signing.sign_outgoing = key, True
    signed.signing.timestamp = int((time.time() - 1420070400) * 100000)
    stream = _stream(30, mav=signed)
    wrong = m.MAVLink(None, srcSystem=1, srcComponent=1)
    wrong.signing.secret_key, wrong.signing.sign_outgoing = bytes(32 * [7]), True
    wrong.signing.timestamp, wrong.signing.link_id = signed.signing.timestamp, 1
    # (another link id: pymavlink stores a stream's time stamp before it checks the signature, so a wrong-key
    # sender on the same stream would make the real packets look replayed)
    bad = [(_frame(wrong, m.MAVLink_attitude_message(7, LOOKALIKE_ROLL, 0, 0, 0, 0, 0)), None) for _ in range(20)]
    mixed = [item for pair in zip(stream, bad + [(b"", None)] * len(stream)) for item in pair]
    link, taken = _feed_link("tcp", mixed, key_path=str(tmp_path / "k.key"))
    real = {_key(msg) for msg in taken} & {key for _, key in stream}
    assert len(real) >= 0.9 * len(stream)
    assert all(msg._signed for msg in taken)
    # each wrong-key packet, and a cut-off signed packet whose signature block the next packet filled
    assert link.counts["bad_signature"] >= len(bad)
