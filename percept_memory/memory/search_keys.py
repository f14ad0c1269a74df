"""The index keys derived from what a cluster says, so every kind of query has an index to use.

- words: the terms of labels and texts (`search.terms`), and the trigrams that find a
  misspelt word's neighbours in the vocabulary (words without digits: codes are exact);
- place: one Morton (Z-order) key per position (`search.morton`). MongoDB's geo indexes are
  2D only, so a box, a sphere or the k nearest are found as a few ranges of keys, then
  filtered exactly by position; x, y and z are kept as scalars beside it (`search.x`...), so
  that the key's index holds the coordinates too, decides a box and ranks the k nearest
  without reading a document;
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


# --- place: one Morton key ---------------------------------------------------------------

MORTON_BITS = 21  # per axis: 63 bits in all, a positive int64
MORTON_UNIT = 0.0625  # metres: the grid a position is keyed on (an exact power of two)
_HALF = 1 << (MORTON_BITS - 1)
EVERYWHERE = (0, (1 << 3 * MORTON_BITS) - 1)  # the range of every key: the k nearest's last
# resort


def grid(v: float) -> int:
    """A coordinate's step on the grid, 0 ... 2**21 - 1. Coordinates beyond +-65 km share the
    border steps: clamping keeps the order, so a box's steps still hold every point in it."""
    return math.floor(min(max(v / MORTON_UNIT, -_HALF), _HALF - 1)) + _HALF


def _spread(n: int) -> int:
    """The 21 bits of n, two zero bits after each (the standard bit-twiddling steps)."""
    n = (n | n << 32) & 0x1F00000000FFFF
    n = (n | n << 16) & 0x1F0000FF0000FF
    n = (n | n << 8) & 0x100F00F00F00F00F
    n = (n | n << 4) & 0x10C30C30C30C30C3
    return (n | n << 2) & 0x1249249249249249


def _interleaved(x: int, y: int, z: int) -> int:
    return _spread(x) | _spread(y) << 1 | _spread(z) << 2


def morton(point: Iterable[float]) -> int:
    """The Morton (Z-order) key of a position: its grid steps' bits interleaved, so that
    positions near each other mostly have keys near each other, and any box is a few key
    ranges. One int64 an index holds instead of a cell per size (MongoDB's geo indexes are
    2D only)."""
    x, y, z = map(grid, point)
    return _interleaved(x, y, z)


AXES = ("x", "y", "z")


def place(position: Iterable[float] | None) -> dict:
    """The place keys of a position: the position itself, its Morton key and its coordinates
    as scalars (the key's index holds them: a box is decided without reading a document)."""
    if position is None:
        return {"position": None}
    point = [*position]
    return {"position": point, "morton": morton(point), **dict(zip(AXES, point, strict=True))}


def morton_ranges(low: Iterable[float], high: Iterable[float],
                  max_ranges: int) -> list[tuple[int, int]]:
    """At most `max_ranges` key ranges (first, last) holding every position of the box
    [low, high]: octree nodes inside the box are whole ranges, those across its border are
    split while the budget allows and taken whole after (the exact test drops the extra)."""
    lo, hi = [*map(grid, low)], [*map(grid, high)]
    # the smallest node holding the whole box: where the steps of its corners part
    level = max((a ^ b).bit_length() for a, b in zip(lo, hi, strict=True))
    ranges: list[tuple[int, int]] = []
    across = [tuple(a >> level << level for a in lo)]  # nodes of side 2**level
    while level:
        side = 1 << (level - 1)
        whole, split = [], []
        for x, y, z in across:
            for child in ((x, y, z), (x + side, y, z), (x, y + side, z), (x + side, y + side, z),
                          (x, y, z + side), (x + side, y, z + side), (x, y + side, z + side),
                          (x + side, y + side, z + side)):
                if _apart(child, side, lo, hi):
                    continue
                (whole if side == 1 or _within(child, side, lo, hi) else split).append(child)
        if len(ranges) + len(whole) + len(split) > max_ranges:
            return _merged(ranges + [_node_range(c, 2 * side) for c in across])
        ranges += [_node_range(c, side) for c in whole]
        across, level = split, level - 1
    return _merged(ranges + [_node_range(c, 1) for c in across])


def _apart(corner, side: int, lo: list[int], hi: list[int]) -> bool:
    return any(c + side <= a or c > b for c, a, b in zip(corner, lo, hi, strict=True))


def _within(corner, side: int, lo: list[int], hi: list[int]) -> bool:
    return all(a <= c and c + side - 1 <= b for c, a, b in zip(corner, lo, hi, strict=True))


def _node_range(corner: tuple[int, int, int], side: int) -> tuple[int, int]:
    first = _interleaved(*corner)
    return first, first + side**3 - 1


def _merged(ranges: list[tuple[int, int]]) -> list[tuple[int, int]]:
    out: list[tuple[int, int]] = []
    for first, last in sorted(ranges):
        if out and first <= out[-1][1] + 1:
            out[-1] = (out[-1][0], max(out[-1][1], last))
        else:
            out.append((first, last))
    return out


# --- fields -------------------------------------------------------------------------------


def field_key(type_name: str, path: str) -> str:
    """How a field of a type is named to people and in index names: `type:path`."""
    return f"{type_name}:{path}"


def field_path(first: str, rest: Iterable[str]) -> str:
    """The stored path of a field: the field's own name, then escaped mapping keys."""
    return ".".join([first, *(escape_key(part) for part in rest)])
