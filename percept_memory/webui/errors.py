"""The app's one error shape, {"error": {"status", "message", "problems"}}: the routes raise
ApiError, and the guard in front of them (guard.py) answers with error_response directly."""

from __future__ import annotations

from collections.abc import Mapping

from fastapi.responses import JSONResponse


class ApiError(Exception):
    def __init__(self, status: int, message: str, problems: list | None = None):
        super().__init__(message)
        self.status, self.message, self.problems = status, message, problems or []


def error_response(status: int, message: str, problems: list | None = None,
                   headers: Mapping[str, str] | None = None) -> JSONResponse:
    return JSONResponse(
        {"error": {"status": status, "message": message, "problems": problems or []}},
        status_code=status, headers=headers,
    )
