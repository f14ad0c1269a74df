"""What a text means, offline: the words of the vocabulary (`terms`, every word a cluster's
labels, names, OCR texts and web-lookup titles used) nearest in meaning to a query, so that
"something to drink" finds clusters whose words are "beverage", "juice" or "milk".

Meanings are WordLlama's static token embeddings (`l2_supercat`: the token-embedding tables of
LLaMA 2 70B and Phi-3 medium, concatenated and trained for general-purpose text embedding;
a 16 MB table, 256 dimensions), whose weights and tokenizer ship inside the `wordllama`
wheel: nothing is downloaded, ever. A text's vector is the pooled vectors of its tokens:
cheap (tens of microseconds a word, no layers to run), weaker than a transformer, and
English above all.

Nothing is computed at ingest: the vocabulary of distinct words is small and grows slowly, so
a query reads it (when it grew) and embeds the words this process has not seen yet, kept for
the next query.
"""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np

from percept_memory.memory.schema import TERMS

from .ops import Aggregate, Find, Plan

MIN_SIMILARITY = 0.2  # cosine below which a word means something else (0.1-0.15: unrelated)
MAX_MEANINGS = 8  # vocabulary words a text may stand for
MAX_CACHED = 500_000  # words whose vectors a process keeps (1 kB each); a vocabulary larger
# than this would be embedded anew by every query (seconds)


class WordVectors:
    """The model, loaded on first use, and the vectors of the words embedded so far, as the
    rows of one matrix (a query scores them all at once). Thread-safe: the web app answers
    queries from a thread pool."""

    def __init__(self) -> None:
        self._model = None
        self._row: dict[str, int] = {}
        self._matrix = np.zeros((0, 0), np.float32)  # a row per word of _row
        self._lock = threading.Lock()

    def _embedded(self, texts: list[str]) -> np.ndarray:
        if self._model is None:
            import wordllama
            from wordllama import WordLlama

            # The wheel holds weights/ and tokenizers/; WordLlama.load finds the weights in
            # the package but looks for the tokenizer in tokenizer/ (singular), then in
            # cache_dir/tokenizers/: pointing cache_dir at the package finds both there.
            self._model = WordLlama.load(cache_dir=Path(wordllama.__file__).parent,
                                         disable_download=True)
        return self._model.embed(texts, norm=True).astype(np.float32)

    def embed(self, texts: list[str]) -> np.ndarray:
        """Unit vectors of texts (not kept: a query's text is asked once)."""
        with self._lock:
            return self._embedded(texts)

    def similarities(self, words: list[str], text: str) -> np.ndarray:
        """The cosine similarity of each word to the text; the words not seen before are
        embedded in one batch and kept."""
        with self._lock:
            new = [w for w in dict.fromkeys(words) if w not in self._row]
            if len(self._row) + len(new) > MAX_CACHED:
                self._row, new = {}, list(dict.fromkeys(words))
            if new:
                held = len(self._row)
                vectors = self._embedded(new)
                self._matrix = np.concatenate([self._matrix[:held] if held else vectors[:0],
                                               vectors])
                self._row.update((w, held + i) for i, w in enumerate(new))
            rows = np.fromiter((self._row[w] for w in words), np.int64, len(words))
            return (self._matrix @ self._embedded([text])[0])[rows]


VECTORS = WordVectors()  # one per process
_VOCABULARIES: dict[str, tuple[int, list[str]]] = {}  # terms' namespace -> (count, words)


def vocabulary() -> Plan[list[str]]:
    """Every word of the vocabulary, read again only when the count of words changed: words
    are only ever added, so the same count means the same words (the count is the
    collection's own, read in a millisecond, where reading 50,000 words takes ~100 ms; one
    document per shard on a sharded cluster)."""
    shards = yield Aggregate(TERMS, [{"$collStats": {"count": {}}}])
    namespace = shards[0]["ns"] if shards else TERMS
    count = sum(shard.get("count", 0) for shard in shards)
    known = _VOCABULARIES.get(namespace)
    if known is None or known[0] != count:
        known = count, [doc["_id"] for doc in (yield Find(TERMS, {}, {"_id": 1}))]
        _VOCABULARIES[namespace] = known
    return known[1]


def neighbours(text: str) -> Plan[dict[str, float]]:
    """The vocabulary words nearest the text's meaning, with their cosine similarity (at
    least MIN_SIMILARITY, the MAX_MEANINGS best)."""
    words = yield from vocabulary()
    if not words:
        return {}
    scores = VECTORS.similarities(words, text)
    best = np.argsort(-scores, kind="stable")[:MAX_MEANINGS]
    return {words[i]: round(float(scores[i]), 3) for i in best if scores[i] >= MIN_SIMILARITY}
