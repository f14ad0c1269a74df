"""The app's one error shape, {"error": {"status", "message", "problems"}}: the routes raise
ApiError, and the guard in front of them (guard.py) answers with error_response directly.
Errors of the store get their HTTP status here (`store_status`)."""

from __future__ import annotations

from collections.abc import Mapping

from fastapi.responses import JSONResponse
from pydantic import BaseModel

from percept_memory.memory.errors import (
    DuplicateId,
    NotFound,
    TooLarge,
    TransactionTooLarge,
    Unavailable,
)


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


def store_status(error: Exception) -> int:
    """The HTTP status of a request the store refused."""
    if isinstance(error, TooLarge | TransactionTooLarge):
        return 413
    if isinstance(error, DuplicateId):
        return 409
    if isinstance(error, Unavailable):
        return 503
    return 404 if isinstance(error, NotFound) else 500


UNAVAILABLE = ("the database does not answer (MONGODB_URI, or the embedded mongod: "
               "`pmem db status`); try again later")


class Problem(BaseModel):
    path: str = ""
    message: str


class ErrorBody(BaseModel):
    status: int
    message: str
    problems: list[Problem]


class ErrorResponse(BaseModel):
    """What every error answer holds (the OpenAPI description's error responses)."""

    error: ErrorBody
