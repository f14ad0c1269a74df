"""The vocabulary behind misspelling-tolerant search: which words and labels it holds, and that
codes are found exactly while names are found misspelt, by text search and by where_is."""

from __future__ import annotations

import pytest

from percept_memory.ingest.service import IngestService
from percept_memory.memory.schema import LABELS, TERMS
from percept_memory.memory.types import Barcode, Classification, Cluster, Location, Product, Scene
from percept_memory.queries.engine import QueryEngine

CODE = "4006381333931"
T0 = 1_700_000_000_000_000_000


def packet(x: float, product: str, code: str, label: str) -> Cluster:
    return Cluster(annotations=[
        Location(source="RegionFilter", region="counter", position=(x, 0.0, 0.9)),
        Classification(source="SVM", class_name=label, confidence=0.9),
        Product(source="Goggles", name=product, brand="Kellogg's"),
        Barcode(source="ZBar", code=code, symbology="EAN13"),
    ])


@pytest.fixture(scope="module")
def engine(store):
    scenes = [Scene(timestamp=T0 + i * 10**9, robot="pr2", clusters=[
        packet(0.0, "Corn Flakes 500g", CODE, "cereal"),
        packet(0.5, "Frosties", "5000127000125", "cereal box"),
    ]) for i in range(2)]
    IngestService(store).ingest_batch(scenes, wait=60)
    return QueryEngine(store)


def test_the_vocabulary_holds_spellable_words_and_labels_of_several_words(store, engine):
    terms = {doc["_id"] for doc in store.db[TERMS].find()}
    assert {"corn", "flakes", "frosties", "kellogg", "cereal", "box"} <= terms
    assert not {t for t in terms if any(c.isdigit() for c in t)}  # no codes, no "500g"
    labels = {doc["_id"]: doc["words"] for doc in store.db[LABELS].find()}
    assert labels == {"corn flakes 500g": ["500g", "corn", "flakes"],
                      "kellogg's": ["kellogg", "s"], "cereal box": ["box", "cereal"]}


def test_a_misspelt_name_is_found_and_a_code_only_exactly(engine):
    assert len(engine.clusters(text="Frostis").items) == 2
    assert len(engine.clusters(text=CODE).items) == 2
    assert len(engine.clusters(text="500g").items) == 2
    assert engine.clusters(text=CODE[:-1] + "2").items == []
    assert engine.clusters(text="501g").items == []


def test_where_is_finds_objects_by_a_one_word_name_and_by_any_word_of_a_longer_one(engine):
    for question, name in [("frosties", "frosties"), ("Frostis", "frosties"),
                           ("cereal", "cereal"), ("box", "cereal box"),
                           ("corn flakes", "corn flakes 500g")]:
        found = engine.where_is(question, limit=1)
        assert found and name in found[0].names, question
    assert not engine.where_is("crisps")
