"""Stable type names: the `_type` written into every stored document.

A name is given once, where the class is defined (like RoboSherlock's type traits), and never
changes, so documents written years ago still find their class. Aliases let foreign names
(RoboSherlock's `rs.*`) resolve to our classes.
"""

from __future__ import annotations

import difflib
from collections.abc import Callable
from typing import TypeVar

from pydantic import BaseModel

T = TypeVar("T", bound=type)

_class_by_name: dict[str, type] = {}
_reserved_prefixes: set[str] = set()
_name_by_class: dict[type, str] = {}


class Typed(BaseModel):
    """Base of every stored model.

    Keeps the fields a newer version of the program wrote that this version does not know,
    so reading and writing back an object never loses them (`unknown_fields`).
    """

    def unknown_fields(self) -> dict | None:
        """The fields a newer program wrote that this one does not know, if any."""
        private = self.__pydantic_private__
        return private.get(UNKNOWN_FIELDS) if private else None

    def keep_unknown_fields(self, fields: dict) -> None:
        # In pydantic's private slot, but not declared as a PrivateAttr: a declared one makes
        # pydantic call a Python hook for every instance it builds (a fifth of validating a
        # scene), though almost no object has unknown fields.
        private = {**(self.__pydantic_private__ or {}), UNKNOWN_FIELDS: fields}
        object.__setattr__(self, "__pydantic_private__", private)


UNKNOWN_FIELDS = "_unknown_fields"


def register_type(name: str, *, aliases: tuple[str, ...] = ()) -> Callable[[T], T]:
    """Class decorator: store instances of the class under `_type` = `name`."""

    def decorate(cls: T) -> T:
        for key in (name, *aliases):
            owner = _class_by_name.get(key)
            if owner is not None and _where(owner) != _where(cls):
                raise ValueError(f"type name {key!r} is already taken by {_where(owner)}")
            _class_by_name[key] = cls  # the same class defined again (a reload) replaces it
        _name_by_class[cls] = name
        return cls

    return decorate


def _where(cls: type) -> str:
    return f"{cls.__module__}.{cls.__qualname__}"


def class_for(name: str) -> type | None:
    """The class registered under a name or alias, or None when nobody registered it."""
    return _class_by_name.get(name)


def name_of(cls: type) -> str | None:
    """The stable name of a registered class (exactly that class, not a parent's)."""
    return _name_by_class.get(cls)


def registered_types() -> dict[str, type]:
    """Every registered class by its own name (aliases left out)."""
    return {name: cls for cls, name in _name_by_class.items()}


def aliases_of(cls: type) -> list[str]:
    """The foreign names that resolve to `cls`."""
    own = _name_by_class.get(cls)
    return sorted(key for key, owner in _class_by_name.items() if owner is cls and key != own)


def reserve_namespace(prefix: str) -> None:
    """Names under `prefix` belong to this program: an unregistered one is a mistake (a typo,
    a removed type) rather than another program's type to keep as it is."""
    _reserved_prefixes.add(prefix)


def is_reserved(name: str) -> bool:
    """Whether the name is in a namespace of ours, in any case (PM.annotation.X is a typo)."""
    return any(name.lower().startswith(prefix.lower()) for prefix in _reserved_prefixes)


def close_names(name: str) -> list[str]:
    """Registered names that look like `name`, for "did you mean" messages: first those it
    is the short name of (`Classification`: pm.annotation.Classification)."""
    short = [full for full in _class_by_name
             if full.rpartition(".")[2].lower() == name.rpartition(".")[2].lower()]
    return list(dict.fromkeys(short + difflib.get_close_matches(name, list(_class_by_name),
                                                               n=3)))[:3]
