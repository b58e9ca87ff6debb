"""A time limit and a size limit for every request head (request line and headers) the server reads.

uvicorn closes an idle keep-alive connection only after a response, and stops that timer at the first byte
of the next request: a client that opens connections and sends part of a request head, a byte now and
then, holds each one open forever (slowloris), and its headers may grow without end. The server's HTTP
protocol here gives each connection ``head_timeout`` seconds, from its start or from the end of its
previous response, to complete the next head: past that it is answered 408 and closed (closed without an
answer when it sent nothing). A head larger than :data:`MAX_HEAD_BYTES` is answered 431 and closed. A
request whose head is complete is never cut: its body and its response (a long progress stream
included) are the app's business.
"""

from __future__ import annotations

import asyncio
from typing import Any, ClassVar

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

MAX_HEAD_BYTES = 64 * 1024
"""Largest request head accepted, in bytes (the app's own requests send well under 4 KiB)."""

KEEP_ALIVE_S = 5
"""Seconds an idle keep-alive connection stays open after a response (uvicorn's own limit)."""


def _closing_answer(status: int, reason: str, text: str) -> bytes:
    body = text.encode()
    head = (
        f"HTTP/1.1 {status} {reason}\r\ncontent-type: text/plain; charset=utf-8\r\n"
        f"content-length: {len(body)}\r\nconnection: close\r\n\r\n"
    )
    return head.encode("ascii") + body


class HeadLimitProtocol(HttpToolsProtocol):
    """uvicorn's httptools protocol with the head limits of this module; use :func:`head_limit_protocol`."""

    head_timeout: ClassVar[float] = 10.0
    """Seconds a connection has to complete a request head."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._deadline: asyncio.TimerHandle | None = None
        self._head_bytes: int | None = 0
        """Bytes of the head being read; None while no head is expected (a request is being served)."""

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._expect_head()

    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        if self._head_bytes is None or self.transport.is_closing():
            return
        # Bytes fed while the head is still incomplete all belong to it.
        self._head_bytes += len(data)
        if self._head_bytes > MAX_HEAD_BYTES:
            self._refuse(431, "Request Header Fields Too Large", f"request head over {MAX_HEAD_BYTES} bytes")

    def on_headers_complete(self) -> None:
        self._stop_clock()
        self._head_bytes = None
        super().on_headers_complete()

    def on_response_complete(self) -> None:
        waiting = not self.pipeline  # else the next request's head is complete already
        super().on_response_complete()
        if waiting and not self.transport.is_closing():
            self._expect_head()

    def connection_lost(self, exc: Exception | None) -> None:
        self._stop_clock()
        super().connection_lost(exc)

    def _expect_head(self) -> None:
        self._stop_clock()
        self._head_bytes = 0
        self._deadline = self.loop.call_later(self.head_timeout, self._head_overdue)

    def _stop_clock(self) -> None:
        if self._deadline is not None:
            self._deadline.cancel()
            self._deadline = None

    def _head_overdue(self) -> None:
        self._deadline = None
        if self._head_bytes is None or self.transport.is_closing():
            return
        if self._head_bytes == 0:
            # Nothing sent: closed without an answer, which a client sending its next request just now
            # could take for that request's.
            self.transport.close()
            return
        self._refuse(408, "Request Timeout", f"no complete request head within {self.head_timeout:g} s")

    def _refuse(self, status: int, reason: str, text: str) -> None:
        self._stop_clock()
        self._head_bytes = None
        self.transport.write(_closing_answer(status, reason, text))
        self.transport.close()


def head_limit_protocol(head_timeout: float) -> type[HeadLimitProtocol]:
    """The protocol class to give ``uvicorn.Config(http=...)``: :class:`HeadLimitProtocol` with
    ``head_timeout`` seconds per request head."""
    return type("HeadLimitProtocol", (HeadLimitProtocol,), {"head_timeout": float(head_timeout)})
