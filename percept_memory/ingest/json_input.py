"""JSON input as MongoDB can store it: checked before a scene is validated, so that hostile
input gets a 422 naming the field instead of a server error (README: Security).

- parsing: text nested too deeply for Python's parser is refused, not a RecursionError;
- nesting: at most MAX_DEPTH levels (MongoDB refuses documents deeper than 100, and a scene's
  clusters are stored a few levels down; a scene needs about 10);
- integers: 64 bits at most (MongoDB's);
- strings: UTF-8 encodable (no lone surrogate such as "\\ud800"), at most MAX_STRING
  characters (pixels and array bytes in base64 aside: their own limits apply);
- field names: no NUL, none starting with `$` (MongoDB's operators).
"""

from __future__ import annotations

import json
from typing import Any

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


def input_problems(data: Any) -> list[dict]:
    """{path, message} of each value MongoDB could not store or the memory does not keep (the
    first MAX_PROBLEMS of them)."""
    problems: list[dict] = []
    stack: list[tuple[tuple, Any]] = [((), data)]
    while stack and len(problems) < MAX_PROBLEMS:
        path, value = stack.pop()
        if isinstance(value, dict | list) and len(path) >= MAX_DEPTH:
            problems.append(_problem(path, f"nested too deeply (at most {MAX_DEPTH} levels)"))
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
