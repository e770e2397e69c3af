"""The request-body limit, enforced while the body streams in (``RANGEFUSE_MAX_UPLOAD_MB``)."""

from __future__ import annotations

from fastapi.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

__all__ = ["BodyLimit", "BodyTooLargeError"]


class BodyTooLargeError(Exception):
    """Raised into the app when a streamed body passes the limit."""


class BodyLimit:
    """ASGI middleware: 413 for a body over ``limit`` bytes, declared or streamed.

    A declared ``Content-Length`` over the limit is refused before reading; otherwise the
    body is counted as it arrives and :class:`BodyTooLargeError` is raised into the app once
    it passes the limit (the upload route answers 413 with its own message).
    """

    def __init__(self, app: ASGIApp, limit: int) -> None:
        self.app = app
        self.limit = limit

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = dict(scope.get("headers") or []).get(b"content-length")
        if declared is not None and declared.isdigit() and int(declared) > self.limit:
            await _reject(send, 413, f"request body of {int(declared)} bytes is over the limit "
                                     f"of {self.limit} bytes")  # fmt: skip
            return
        seen = 0
        started = False

        async def limited() -> Message:
            nonlocal seen
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > self.limit:
                    raise BodyTooLargeError
            return message

        async def tracking_send(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, limited, tracking_send)
        except BodyTooLargeError:
            if not started:
                await _reject(send, 413, f"request body is over the limit of {self.limit} bytes")


async def _reject(send: Send, status: int, detail: str) -> None:
    body = JSONResponse({"detail": detail}).body
    await send(
        {
            "type": "http.response.start",
            "status": status,
            "headers": [(b"content-type", b"application/json"), (b"connection", b"close")],
        }
    )
    await send({"type": "http.response.body", "body": body})
