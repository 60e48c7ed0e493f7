"""The one error type of the server's request handling: what is wrong with a request."""
from __future__ import annotations

from omnire.api import UserError


class RequestError(UserError):
    """A request the server refuses: ``field`` names the request field at fault (dotted,
    e.g. ``pose`` or ``0.timestamps.3``), ``status`` the HTTP status it is answered with.
    The server answers it as JSON ``{"error": {"field": ..., "message": ...}}``."""

    def __init__(self, field: str, message: str, status: int = 400) -> None:
        super().__init__(f"{field}: {message}" if field else message)
        self.field, self.message, self.status = field, message, status

    def as_json(self) -> dict:
        return {"error": {"field": self.field, "message": self.message}}
