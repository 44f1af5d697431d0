"""Server-sent events (the WHATWG ``text/event-stream`` format), decoded line by line.

The decoder is fed the lines of a streamed response (httpx's ``iter_lines``/``aiter_lines``) by the
sync and the async client alike and returns an event at each blank line that ends one.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class ServerSentEvent:
    event: str = "message"
    data: str = ""
    id: str | None = None


@dataclass
class SSEDecoder:
    """``decode(line)`` for each line without its line ending; returns the finished event or None."""

    _event: str | None = None
    _data: list[str] = field(default_factory=list)
    _id: str | None = None

    def decode(self, line: str) -> ServerSentEvent | None:
        if not line:
            return self._dispatch()
        if line.startswith(":"):  # a comment, e.g. a keep-alive
            return None
        name, _, value = line.partition(":")
        value = value.removeprefix(" ")
        if name == "event":
            self._event = value
        elif name == "data":
            self._data.append(value)
        elif name == "id" and "\0" not in value:
            self._id = value
        return None

    def _dispatch(self) -> ServerSentEvent | None:
        if not self._data and self._event is None:
            return None
        event = ServerSentEvent(self._event or "message", "\n".join(self._data), self._id)
        self._event, self._data = None, []
        return event
