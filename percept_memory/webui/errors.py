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
    TypeHookFailed,
    Unavailable,
)


class ApiError(Exception):
    def __init__(self, status: int, message: str, problems: list | None = None,
                 headers: Mapping[str, str] | None = None):
        super().__init__(message)
        self.status, self.message, self.problems = status, message, problems or []
        self.headers = headers


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
    if isinstance(error, TypeHookFailed):
        return 422
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


MEANINGS = {
    400: "the Host header names a host this server does not answer for",
    401: "this server needs a write token (Authorization: Bearer <token>)",
    403: "the write token is wrong, or the request comes from a page of another origin",
    404: "no such object, cluster or scene",
    409: "an id in the body is already used by another document (stored, or earlier in the "
         "body), or the robot has another scene stored at the timestamp",
    413: "the body, or a value in it, is over a limit",
    415: "the body is not Content-Type: application/json",
    422: "the request is not valid: `problems` names each field and what is wrong",
    503: "the database does not answer",
}


def error_responses(*statuses: int) -> dict:
    """The OpenAPI `responses` of these error statuses, each with the one error shape."""
    return {status: {"model": ErrorResponse, "description": MEANINGS[status]}
            for status in statuses}


READ_ERRORS = error_responses(400, 404, 422, 503)
WRITE_ERRORS = error_responses(400, 401, 403, 404, 409, 413, 415, 422, 503)
