"""STATUSTEXT chunks (ARCHITECTURE.md §8): a text longer than one message's 50 characters, split the MAVLink 2 way.

A chunked text's messages share a nonzero ``id`` and count ``chunk_seq`` from 0; a receiver that reassembles
(QGroundControl, MAVSDK) joins them and knows the text ended at the first chunk holding a NUL, so a text whose
length is a whole number of chunks gets one more, empty, chunk. A receiver that does not shows each chunk as
its own line, the first one first: callers put what matters at the start. No I/O of its own: the sender
writes through the link's send function.
"""
from __future__ import annotations

import threading
from typing import Any, Callable, List, Tuple

__all__ = ["CHUNK_CHARS", "MAX_CHUNKS", "StatusSender", "chunk_status", "next_status_id"]
CHUNK_CHARS = 50            # STATUSTEXT.text
MAX_CHUNKS = 4              # 200 characters: a status line, not a log (each chunk is another ~66 bytes on a radio)
_CUT = "..."


def chunk_status(text: str, max_chunks: int = MAX_CHUNKS) -> List[Tuple[int, bytes]]:
    """(chunk_seq, text bytes) of each message for ``text``, ASCII (others as '?'); a text that fits is one chunk.

    A text that ``max_chunks`` chunks cannot hold with its end mark (a NUL: at most max_chunks·50 - 1 characters)
    is cut there and ends with "...".
    """
    data = text.encode("ascii", "replace")
    if len(data) <= CHUNK_CHARS:
        return [(0, data)]
    room = CHUNK_CHARS * max_chunks - 1
    if len(data) > room:
        data = data[:room - len(_CUT)] + _CUT.encode()
    parts = [data[i:i + CHUNK_CHARS] for i in range(0, len(data), CHUNK_CHARS)]
    if len(parts[-1]) == CHUNK_CHARS:
        parts.append(b"")                 # the end mark: a chunk that is all NUL
    return list(enumerate(parts))


def next_status_id(last_id: int) -> int:
    """The ``id`` of the next chunked text: 1..65535, wrapping (0 means "a single message")."""
    return last_id % 0xFFFF + 1


class StatusSender:
    """STATUSTEXT through ``send`` (the link's: True when the message left), one text at a time: the fusion thread,
    the main loop and the link thread all send them, and a ground station joins one chunked text per sender and
    gives it up when a message with another id comes between. ``mavlink``: pymavlink's dialect module."""

    def __init__(self, send: Callable[[Any], bool], mavlink: Any):
        self._send, self._make = send, mavlink.MAVLink_statustext_message
        self._lock = threading.Lock()                        # not the link's: its send function takes that one
        self._last_id = 0                                    # the last chunked text's id

    def send(self, text: str, severity: int) -> bool:
        """True when every chunk was sent; stops at the first that was not."""
        chunks = chunk_status(text)
        with self._lock:
            text_id = 0
            if len(chunks) > 1:
                self._last_id = text_id = next_status_id(self._last_id)
            for seq, part in chunks:
                if not self._send(self._make(severity, part, text_id, seq)):
                    return False
        return True
