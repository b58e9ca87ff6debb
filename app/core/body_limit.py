"""A limit on the size of request bodies (:attr:`app.core.config.Settings.max_body_bytes`).

Every request body the API takes is a small JSON document; without a limit a client could make the
server hold hundreds of megabytes per request (the body, then its parsed JSON, then its echo in a 422).
"""

from __future__ import annotations

import json
from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any

from starlette.exceptions import HTTPException

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]


class BodyTooLarge(HTTPException):
    """Raised from ``receive`` once the body passes the limit.

    An ``HTTPException``: FastAPI re-raises those from its body reading (any other error there would
    become a 400), so the app's exception handling answers 413 wherever the body is read.
    """

    def __init__(self, limit: int) -> None:
        super().__init__(413, detail=too_large_message(limit))


def too_large_message(limit: int) -> str:
    return f"Request body too large: the limit is {limit} bytes (LEAP_MAX_BODY_BYTES)"


class BodyLimit:
    """Pure ASGI middleware: answer 413 to a request whose body exceeds ``limit`` bytes.

    A declared ``Content-Length`` above the limit is refused before a byte of the body is read; a body
    sent without one (chunked) is counted as it streams in and refused as soon as it passes the limit,
    so at most ``limit`` bytes (plus one network chunk) are ever held.
    """

    def __init__(self, app: Callable[..., Awaitable[None]], limit: int) -> None:
        self.app = app
        self.limit = limit

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = _content_length(scope)
        if declared is not None and declared > self.limit:
            await _reply_413(send, self.limit)
            return
        seen = 0
        started = False

        async def counted_receive() -> Message:
            nonlocal seen
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > self.limit:
                    raise BodyTooLarge(self.limit)
            return message

        async def watched_send(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, counted_receive, watched_send)
        except BodyTooLarge:
            # Read by code outside FastAPI's body handling: answer here, unless a response has begun.
            if started:
                raise
            await _reply_413(send, self.limit)


def _content_length(scope: Scope) -> int | None:
    for key, value in scope.get("headers", []):
        if key == b"content-length":
            try:
                return int(value)
            except ValueError:
                return None
    return None


async def _reply_413(send: Send, limit: int) -> None:
    body = json.dumps({"detail": too_large_message(limit)}).encode()
    await send(
        {
            "type": "http.response.start",
            "status": 413,
            "headers": [
                (b"content-type", b"application/json"),
                (b"content-length", str(len(body)).encode()),
                (b"connection", b"close"),
            ],
        }
    )
    await send({"type": "http.response.body", "body": body})
