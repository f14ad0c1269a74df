"""JSON input as MongoDB can store it: checked before a scene is validated, so that hostile
input gets a 422 naming the field instead of a server error (README: Security).

- parsing: text nested too deeply for Python's parser is refused, not a RecursionError;
- nesting: at most MAX_DEPTH levels (MongoDB refuses documents deeper than 100, and a scene's
  clusters are stored a few levels down; a scene needs about 10);
- integers: 64 bits at most (MongoDB's);
- strings: UTF-8 encodable (no lone surrogate such as "\\ud800"), at most MAX_STRING
  characters (pixels and array bytes in base64 aside: their own limits apply);
- field names: no NUL, none starting with `$` (MongoDB's operators), but for the MongoDB
  Extended JSON values (`{"$oid": ...}`) that an unknown type's fields may hold, checked here
  as the values they stand for (converters/extended_json.py).

Walking every value of a parsed batch costs more than parsing it, so `parse` first screens the
raw bytes: what the screen clears cannot hold any of these problems and need not be walked;
anything else is walked as before (`parse` says which).
"""

from __future__ import annotations

import json
import re
from typing import Any

from pydantic_core import from_json

from percept_memory.converters.extended_json import WRAPPERS, from_extended_json

MAX_DEPTH = 32
MAX_STRING = 2**20  # characters of one text, label, log message...
BASE64_KEYS = frozenset({"png", "jpeg", "base64"})  # limited by image and array sizes
MAX_PROBLEMS = 20


def loads(text: str | bytes) -> Any:
    """json.loads, with every way it can fail as a ValueError saying why."""
    try:
        return json.loads(text)
    except RecursionError:
        raise ValueError(f"it is nested too deeply (at most {MAX_DEPTH} levels)") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise ValueError(str(error)) from None


def parse(body: bytes) -> tuple[Any, bool]:
    """The JSON value of a request body or file, and whether `input_problems` can find nothing
    in it (True: the bytes passed `screened` and parsed as JSON, so that walk can be skipped).
    Raises what `loads` raises."""
    if screened(body):
        try:
            return from_json(body), True  # pydantic-core's parser: twice as fast as json's
        except ValueError:
            pass  # e.g. a byte order mark: json's parser takes it, or says what is wrong
    return loads(body), False


NOT_A_MARK = bytes(range(256)).translate(None, b'[]{}"')  # all but quotes and brackets
EMPTY_PAIRS = re.compile(rb"\[\]|\{\}")  # one pass removes the pairs empty before it
DIGITS_AS_ZERO = bytes.maketrans(b"123456789", b"0" * 9)
DIGITS = re.compile(rb"\d+")
LONG_DIGITS = b"0" * 19  # the fewest digits of an integer beyond 64 bits


def screened(body: bytes) -> bool:
    """True when the raw JSON text cannot hold anything `input_problems` refuses, judged from its
    bytes without parsing it (False: it may, walk it):
    - no backslash: no escape, so no lone surrogate or NUL (only escapes write those), and a
      `"` always starts or ends a string; UTF-8 (raw surrogates are not), no NUL byte;
    - no `"$`: no field name starts with `$`;
    - no string longer than MAX_STRING bytes, so none of more characters;
    - no integer beyond 64 bits;
    - brackets outside strings nested at most MAX_DEPTH levels."""
    if b"\\" in body or b"\0" in body or (b"$" in body and b'"$' in body):  # one byte: 20x faster
        return False
    if _big_integer(body) or _long_string(body):
        return False
    if not body.isascii():
        try:
            body.decode("utf-8")
        except UnicodeDecodeError:
            return False
    marks = body.translate(None, NOT_A_MARK).split(b'"')  # strings (now empty) at odd places
    brackets = b"".join(marks[::2])
    for _ in range(MAX_DEPTH):  # each pass takes one level off
        brackets = EMPTY_PAIRS.sub(b"", brackets)
    return not brackets


def _long_string(body: bytes) -> bool:
    """Whether a string is longer than MAX_STRING bytes. Each string is measured only when some
    stretch of MAX_STRING // 2 bytes holds no quote, as any longer string does (cutting the
    text at each `"` costs more than the rest of the screen)."""
    stretch = MAX_STRING // 2
    if all(body.find(b'"', start, start + stretch) != -1
           for start in range(0, len(body) - stretch + 1, stretch)):
        return False
    return max(map(len, body.split(b'"')[1::2]), default=0) > MAX_STRING


def _big_integer(body: bytes) -> bool:
    """Whether a run of digits, not a fraction's, may be an integer beyond 64 bits (runs of
    19 digits or more found by a plain search: a regular expression takes 20 times longer)."""
    zeros = body.translate(DIGITS_AS_ZERO)
    start = zeros.find(LONG_DIGITS)
    while start != -1:
        run = DIGITS.match(body, start).group()
        if body[start - 1 : start] != b"." and (len(run) > 19 or int(run) >= 2**63 - 1):
            return True
        start = zeros.find(LONG_DIGITS, start + len(run))
    return False


def input_problems(data: Any) -> list[dict]:
    """{path, message} of each value MongoDB could not store or the memory does not keep (the
    first MAX_PROBLEMS of them)."""
    problems: list[dict] = []
    stack: list[tuple[tuple, Any]] = [((), data)]
    while stack and len(problems) < MAX_PROBLEMS:
        path, value = stack.pop()
        if isinstance(value, dict | list) and len(path) >= MAX_DEPTH:
            problems.append(_problem(path, f"nested too deeply (at most {MAX_DEPTH} levels)"))
        elif isinstance(value, dict) and next(iter(value), None) in WRAPPERS:
            try:
                from_extended_json(value)
            except ValueError as error:
                problems.append(_problem(path, str(error)))
        elif isinstance(value, dict):
            for key, item in value.items():
                if message := _bad_key(str(key)):  # named by the object that has it
                    problems.append(_problem(path, message))
                elif key not in BASE64_KEYS or not isinstance(item, str):
                    stack.append(((*path, key), item))
        elif isinstance(value, list):
            stack.extend(((*path, index), item) for index, item in enumerate(value)
                         if isinstance(item, dict | list | str | int))
        elif isinstance(value, str) and (message := _bad_text(value)):
            problems.append(_problem(path, message))
        elif isinstance(value, int) and not -(2**63) <= value < 2**63:
            problems.append(_problem(path, "an integer beyond MongoDB's 64 bits: it must be "
                                           "at least -2**63 and less than 2**63"))
    return problems


def _bad_key(key: str) -> str | None:
    if "\0" in key or key.startswith("$"):
        return f"the field name {key[:40]!r} holds a NUL or starts with '$'"
    if message := _bad_text(key):
        return f"a field name: {message}"
    return None


def _bad_text(text: str) -> str | None:
    if len(text) > MAX_STRING:
        return f"a text of {len(text)} characters is over the limit of {MAX_STRING}"
    if not text.isascii():
        try:
            text.encode("utf-8")
        except UnicodeEncodeError:
            return "the text holds a lone surrogate (\\ud800-\\udfff), which is not Unicode"
    return None


def _problem(path: tuple, message: str) -> dict:
    return {"path": ".".join(map(str, path)), "message": message, "type": "json_invalid"}
