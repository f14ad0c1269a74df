"""The index keys derived from what a cluster says, so every kind of query has an index to use.

- words: the terms of labels and texts (`search.terms`), and the trigrams that find a
  misspelt word's neighbours in the vocabulary (words without digits: codes are exact);
- cells: 3D voxel keys at several sizes (`search.cells`). MongoDB's geo indexes are 2D
  only, so a box, a sphere or the k nearest are found as the cells around them, then filtered
  exactly by position; x, y and z are kept as scalars beside them (`search.x`...), so that the
  index of the cells holds the coordinates too and ranks the k nearest without reading a
  document;
Predicates on other annotation fields (classification:confidence>0.8) are looked up in the
annotations themselves: narrowed by these keys, or by an index a user adds on that field
(store.py: add_field_index).
Pure functions; documents.py writes their results, queries/ computes the same keys to look up.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable
from functools import lru_cache

from percept_memory.converters import escape_key

# --- words --------------------------------------------------------------------------------

_WORD = re.compile(r"[^\W_]+")
_DIGIT = re.compile(r"\d")
_CAMEL = re.compile(r"(?<=[a-z])(?=[A-Z])|(?<=[A-Z])(?=[A-Z][a-z])")  # fooBar, HTTPServer
_JOINED = re.compile(r"(?<=[^\W_])[_-]+(?=[^\W_])")  # snake_case, kebab-case


def words(text: str) -> tuple[str, ...]:
    """The terms of a text, casefolded, in order: "Kellogg's Corn-Flakes" -> kellogg, s, corn,
    flakes. Letters and digits only, so a term is never query syntax. Identifiers are words
    too: "SiggBottle" and "sigg_bottle" -> sigg, bottle, as a person would say them."""
    return _words_of_short(text) if len(text) <= SHORT else _words(text)


def normal_label(label: str) -> str:
    """A label as the name it is stored and found by: its identifier parts as words, casefolded,
    single-spaced ("SiggBottle", "sigg_bottle", " Sigg  bottle" -> "sigg bottle"); other
    punctuation stays ("kellogg's")."""
    return _normal_short(label) if len(label) <= SHORT else _normal(label)


def _words(text: str) -> tuple[str, ...]:
    return tuple(_WORD.findall(_CAMEL.sub(" ", text).casefold()))


def _normal(label: str) -> str:
    return " ".join(_JOINED.sub(" ", _CAMEL.sub(" ", label)).casefold().split())


# Every stored cluster's labels and texts go through these, and they repeat (class names,
# brands, annotator output): short ones are remembered, a bounded number of them.
SHORT = 200
_words_of_short = lru_cache(maxsize=16384)(_words)
_normal_short = lru_cache(maxsize=16384)(_normal)


def misspellable(word: str) -> bool:
    """Whether a misspelt query word should find this one: not when it holds a digit (a code
    or a quantity, "4006381333931", "500g"), where one character off names another thing."""
    return _DIGIT.search(word) is None


def one_word(label: str) -> bool:
    """Whether a label is a single term as it stands ("cereal", not "Ja!" or "corn flakes"):
    found by that term itself, it needs no entry mapping its words to it."""
    return words(label) == (label,)


def trigrams(word: str) -> list[str]:
    """The trigrams of a word padded with a space each side: " pr", "pri", ..., "es "."""
    padded = f" {word} "
    return sorted({padded[i:i + 3] for i in range(len(padded) - 2)})


# --- cells --------------------------------------------------------------------------------

CELL_SIZES = tuple(0.0625 * 4**level for level in range(8))  # 6.25 cm ... 1024 m: exact
# powers of two, so a position's cell (floor of position / size) involves no rounding
EVERYWHERE = "*"  # the one cell of every positioned cluster: the k-nearest search's last resort


def cell(level: int, index: tuple[int, int, int]) -> str:
    return f"{level}:{index[0]}:{index[1]}:{index[2]}"


MAX_INDEX = 2**53  # cells further out are the border cells: clamping keeps the order of
# cells, so a volume's covering cells still hold every point in it, and 1e308 / 0.0625 (inf)
# has a cell too


def cell_index(level: int, point: Iterable[float]) -> tuple[int, int, int]:
    size = CELL_SIZES[level]
    x, y, z = (math.floor(min(max(v / size, -MAX_INDEX), MAX_INDEX)) for v in point)
    return x, y, z


def cells_of(position: Iterable[float] | None) -> list[str]:
    """The cell keys of a position, one per level, plus EVERYWHERE; none without a position."""
    if position is None:
        return []
    point = tuple(position)
    return [cell(level, cell_index(level, point)) for level in range(len(CELL_SIZES))] + [
        EVERYWHERE
    ]


AXES = ("x", "y", "z")


def place(position: Iterable[float] | None) -> dict:
    """The place keys of a position: the position itself, its cells and its coordinates as
    scalars (an index can hold scalars, not the elements of an array beside the cells)."""
    if position is None:
        return {"position": None, "cells": []}
    point = [*position]
    return {"position": point, "cells": cells_of(point), **dict(zip(AXES, point, strict=True))}


def cells_covering(low: Iterable[float], high: Iterable[float], max_cells: int) -> list[str]:
    """The cells of the finest level whose cells over the box [low, high] number at most
    `max_cells` (every point of the box lies in one of them)."""
    low, high = tuple(low), tuple(high)
    for level in range(len(CELL_SIZES)):
        first, last = cell_index(level, low), cell_index(level, high)
        spans = [b - a + 1 for a, b in zip(first, last, strict=True)]
        if math.prod(spans) <= max_cells:
            return [cell(level, (x, y, z))
                    for x in range(first[0], last[0] + 1)
                    for y in range(first[1], last[1] + 1)
                    for z in range(first[2], last[2] + 1)]
    return [EVERYWHERE]


# --- fields -------------------------------------------------------------------------------


def field_key(type_name: str, path: str) -> str:
    """How a field of a type is named to people and in index names: `type:path`."""
    return f"{type_name}:{path}"


def field_path(first: str, rest: Iterable[str]) -> str:
    """The stored path of a field: the field's own name, then escaped mapping keys."""
    return ".".join([first, *(escape_key(part) for part in rest)])
