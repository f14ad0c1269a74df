"""Text search: words and "quoted phrases", tolerant to misspellings, ranked.

A word matches its own term and the terms of the vocabulary (`terms`, every word any cluster
used) within a few edits of it: "prinles" finds "pringles". Candidates come from the trigram
index of the vocabulary (two words within d edits share most of their trigrams), the edit
distance decides (rapidfuzz). Words with a digit (codes, quantities) match exactly: one
character off names another thing. A phrase must appear as consecutive words in one label or
text. A cluster's score is the sum over the query's words of the best match it has: 1 for the word
itself, less for a neighbour, by how many edits away it is; by meaning (meaning.py), plus the
similarity (0..1, a related word ~0.2-0.6) of its word nearest the text's meaning.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from rapidfuzz.distance import Levenshtein

from percept_memory.memory.schema import TERMS
from percept_memory.memory.search_keys import misspellable, trigrams, words

from .ops import Aggregate, Plan

MAX_NEIGHBOURS = 8  # vocabulary terms a misspelt word may stand for
MAX_CANDIDATES = 200  # vocabulary terms sharing trigrams with it that are compared


@dataclass(frozen=True)
class TextQuery:
    words: tuple[str, ...]  # every word, the phrases' included, each once
    phrases: tuple[tuple[str, ...], ...]

    @classmethod
    def parse(cls, text: str) -> TextQuery:
        phrases = tuple(tuple(words(p)) for p in re.findall(r'"([^"]*)"', text))
        every = dict.fromkeys(words(text))
        return cls(tuple(every), tuple(p for p in phrases if len(p) > 1))


Expansions = dict[str, dict[str, float]]
"""Query word -> the terms it matches, with how well (1 = the word itself); and, in a search
by meaning, MEANING -> the terms nearest the whole text's meaning, by their similarity."""
MEANING = "~meaning"  # not a word: words are letters and digits


def max_edits(word: str) -> int:
    """How many edits a word of this length may be away from a term and still find it."""
    if not misspellable(word):
        return 0
    return 0 if len(word) <= 3 else 1 if len(word) <= 5 else 2


def expand(query_words: tuple[str, ...]) -> Plan[Expansions]:
    """Each word with its neighbours in the vocabulary."""
    out: Expansions = {}
    for word in query_words:
        out[word] = {word: 1.0}
        edits = max_edits(word)
        if not edits:
            continue
        grams = trigrams(word)
        shared_needed = max(1, len(grams) - 3 * edits)  # the q-gram lemma
        found = yield Aggregate(TERMS, [
            {"$match": {"grams": {"$in": grams}}},
            {"$project": {"shared": {"$size": {"$setIntersection": [
                "$grams", {"$literal": grams}]}}}},
            {"$match": {"shared": {"$gte": shared_needed}}},
            {"$sort": {"shared": -1, "_id": 1}},
            {"$limit": MAX_CANDIDATES},
        ])
        near = sorted((Levenshtein.distance(word, doc["_id"], score_cutoff=edits), doc["_id"])
                      for doc in found if doc["_id"] != word)
        for distance, term in near[:MAX_NEIGHBOURS]:
            if distance <= edits:
                out[word][term] = round(1 - distance / (edits + 1), 3)
    return out


def all_terms(expansions: Expansions) -> list[str]:
    return sorted({term for terms in expansions.values() for term in terms})


def phrase_pattern(phrase: tuple[str, ...]) -> str:
    """A regular expression matching the phrase's words in a row, case-insensitively. The
    words are letters and digits only and escaped besides: the pattern is data."""
    return r"(?<!\w)" + r"\W+".join(re.escape(w) for w in phrase) + r"(?!\w)"


def score_expression(expansions: Expansions, terms_field: str) -> dict:
    """An aggregation expression: the cluster's score. Terms enter as $literal values."""
    per_word = [
        {"$max": [{"$cond": [{"$in": [{"$literal": term}, {"$ifNull": [terms_field, []]}]},
                             quality, 0]}
                  for term, quality in terms.items()]}
        for terms in expansions.values()
    ]
    return {"$add": per_word} if per_word else {"$literal": 0}


def word_score(expansions: Expansions, have: dict[str, float]) -> float:
    """The same score, in Python, for words that each count for a weight in [0, 1] (an
    object's names count for how much they name it)."""
    return sum(max((q * have[term] for term, q in terms.items() if term in have), default=0.0)
               for terms in expansions.values())
