"""Queries from flat text parameters: a URL's query string and `pmem query` options.

Each parameter is a field of the query model, given once, or several times for list fields
(`region=table&region=shelf`); every value is text the model's validators read (times as ISO
8601 or nanoseconds, a box as "x0,y0,z0,x1,y1,z1", a predicate as "type:field<op>value").
"""

from __future__ import annotations

import typing
from collections.abc import Iterable

from pydantic import BaseModel, ValidationError
from pydantic_core import InitErrorDetails, PydanticCustomError


def is_list(model: type[BaseModel], name: str) -> bool:
    annotation = model.model_fields[name].annotation
    return any(typing.get_origin(arm) is list
               for arm in (annotation, *typing.get_args(annotation)))


def from_params(model: type[BaseModel], params: Iterable[tuple[str, str]]) -> BaseModel:
    """The query of (name, text value) pairs; a ValidationError names every bad one."""
    given: dict[str, list[str]] = {}
    for name, value in params:
        given.setdefault(name, []).append(value)
    data: dict = {}
    repeated: list[InitErrorDetails] = []
    for name, values in given.items():
        listed = name in model.model_fields and is_list(model, name)
        if len(values) > 1 and not listed:
            repeated.append(InitErrorDetails(
                type=PydanticCustomError("repeated", "given {n} times: give it once",
                                         {"n": len(values)}),
                loc=(name,), input=values))
        data[name] = values if listed else values[-1]
    if repeated:
        raise ValidationError.from_exception_data(model.__name__, repeated)
    return model.model_validate(data)
