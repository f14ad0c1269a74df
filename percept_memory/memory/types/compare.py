"""How alike two lists of annotations are, as a matrix: identity resolution compares every new
observation with every candidate object at once (memory/identity.py), so each built-in type's
`similarities(a, b)` is one of these vectorised forms instead of a Python loop over pairs.
Every matrix is len(a) x len(b), in [0, 1], NaN where a pair has nothing to compare."""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from functools import lru_cache

import numpy as np


def pairwise(a: list, b: list, kind: Callable, prepare: Callable, combine: Callable
             ) -> np.ndarray:
    """Block by block: items compare only with items of the same `kind` (e.g. the same
    histogram shape), `prepare` turns each into a vector (None: nothing to compare) and
    `combine` compares two stacks of them."""
    out = np.full((len(a), len(b)), np.nan)
    groups: dict = {}
    for side, items in enumerate((a, b)):
        for index, item in enumerate(items):
            vector = prepare(item)
            if vector is not None:
                groups.setdefault(kind(item), ([], []))[side].append((index, vector))
    for rows, cols in groups.values():
        if rows and cols:
            block = combine(np.stack([v for _, v in rows]), np.stack([v for _, v in cols]))
            out[np.ix_([i for i, _ in rows], [j for j, _ in cols])] = block
    return out


def same_labels(a: Sequence[str | None], b: Sequence[str | None]) -> np.ndarray:
    """1 where two labels are the same word(s), case and surrounding spaces aside, else 0."""
    codes: dict[str, int] = {}

    def encode(labels):
        return np.array([codes.setdefault(label.strip().casefold(), len(codes)) if label
                         else -1 for label in labels], dtype=np.int64)

    x, y = encode(a), encode(b)
    out = (x[:, None] == y[None, :]).astype(float)
    out[(x[:, None] < 0) | (y[None, :] < 0)] = np.nan
    return out


def _dense(a: Sequence[dict[str, float]], b: Sequence[dict[str, float]]
           ) -> tuple[np.ndarray, np.ndarray]:
    """Two stacks of name -> weight maps as rows over the names of both, in sorted order (the
    same sums in any process)."""
    names = {name: i for i, name in enumerate(sorted({k for d in (*a, *b) for k in d}))}

    def rows(maps):
        out = np.zeros((len(maps), len(names)))
        for r, weights in enumerate(maps):
            for name, weight in weights.items():
                out[r, names[name]] = weight
        return out

    return rows(a), rows(b)


def _without_empty(out: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    out[(x.sum(1) <= 0)[:, None] | (y.sum(1) <= 0)[None, :]] = np.nan
    return out


def bhattacharyya(a: Sequence[dict[str, float]], b: Sequence[dict[str, float]]) -> np.ndarray:
    """Overlap of discrete distributions given as name -> weight, each normalised here."""
    x, y = (np.clip(m, 0, None) for m in _dense(a, b))
    with np.errstate(invalid="ignore", divide="ignore"):
        p = np.sqrt(x / x.sum(1, keepdims=True))
        q = np.sqrt(y / y.sum(1, keepdims=True))
    return _without_empty(np.minimum(np.nan_to_num(p) @ np.nan_to_num(q).T, 1.0), x, y)


def shared_share(a: Sequence[dict[str, float]], b: Sequence[dict[str, float]]) -> np.ndarray:
    """The sum over names of the smaller share (how much of two colour mixes is common)."""
    x, y = _dense(a, b)
    return _without_empty(np.minimum(x[:, None, :], y[None, :, :]).sum(-1), x, y)


_WORD = re.compile(r"[^\W_]+")


@lru_cache(maxsize=65536)
def words(text: str) -> frozenset[str]:
    """The words of a text (kept: identity compares the same texts again and again)."""
    return frozenset(_WORD.findall(text.casefold()))


def shared_words(a: Sequence[str], b: Sequence[str]) -> np.ndarray:
    """Jaccard index of the texts' sets of words."""
    x, y = _dense([dict.fromkeys(words(t), 1.0) for t in a],
                  [dict.fromkeys(words(t), 1.0) for t in b])
    common = x @ y.T
    with np.errstate(invalid="ignore", divide="ignore"):
        out = common / (x.sum(1)[:, None] + y.sum(1)[None, :] - common)
    return _without_empty(out, x, y)


def hash_nearness(a: Sequence[str | None], b: Sequence[str | None], sigma_bits: float
                  ) -> np.ndarray:
    """The thesis' g (eq. 6.1) of the Hamming distance of 64-bit hashes in hex."""
    def bits(hashes):
        return np.unpackbits(np.array([int(h, 16) if h else 0 for h in hashes], dtype=">u8")
                             .view(np.uint8).reshape(len(hashes), 8), axis=1)

    x, y = bits(a), bits(b)
    distance = (x[:, None, :] != y[None, :, :]).sum(-1)
    out = np.exp(-((distance / (2 * sigma_bits)) ** 2))
    out[np.array([h is None for h in a])[:, None] | np.array([h is None for h in b])[None, :]] \
        = np.nan
    return out


def top_bins(histogram: np.ndarray, count: int, prefix: str) -> list[str]:
    """The names of a histogram's `count` fullest non-empty bins (a quantised colour view)."""
    flat = np.asarray(histogram, dtype=float).ravel()
    order = np.argsort(-flat, kind="stable")[:count]
    return [f"{prefix}{i}" for i in order if flat[i] > 0]


@lru_cache(maxsize=64)
def _hyperplanes(name: str, size: int, bands: int, bits: int) -> np.ndarray:
    """The same random hyperplanes for a descriptor name and size in every process."""
    seed = int.from_bytes(name.encode()[:8].ljust(8, b"\0"), "big") ^ size
    return np.random.default_rng(seed).standard_normal((bands * bits, size))


def visual_words(name: str, vector: np.ndarray, bands: int = 4, bits: int = 8) -> list[str]:
    """A feature vector quantised into `bands` visual words: the signs of its projections on
    random hyperplanes, `bits` at a time (vectors at a small angle share most words)."""
    v = np.nan_to_num(np.asarray(vector, dtype=float).ravel())
    if not v.any():
        return []
    signs = (_hyperplanes(name, v.size, bands, bits) @ v > 0).reshape(bands, bits)
    codes = signs @ (1 << np.arange(bits))
    return [f"{name}.{band}.{code}" for band, code in enumerate(codes)]
