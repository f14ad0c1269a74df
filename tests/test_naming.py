"""Names from evidence (memory/naming.py): weighted by how reliable each annotation is and by how
many annotators agree; the same sums in any order; and what the user sees: an object's name and
where-is, live and after a rebuild."""

from __future__ import annotations

import random
from collections import Counter

import pytest
from bson import ObjectId

from percept_memory.ingest.backends import Finding
from percept_memory.ingest.lookups import annotations_for
from percept_memory.ingest.service import IngestService
from percept_memory.memory.naming import naming_fields, naming_labels, renamed, stored_weights
from percept_memory.memory.pipeline import request_rebuild
from percept_memory.memory.types import (
    Classification,
    Cluster,
    GroundTruth,
    ImageROI,
    Location,
    Logo,
    Product,
    Scene,
)
from percept_memory.memory.types.annotations import LookupProvenance
from percept_memory.queries.engine import QueryEngine

T0 = 1_700_000_000_000_000_000
ROI = ImageROI(box=(0, 0, 40, 40))
STORCK = [Finding(category="logo", title="Storck", box=None),
          Finding(category="product", title="Storck Knoppers", brand="Storck", box=None)]


def lookup(distance: int, findings=STORCK) -> list:
    """What a lookup job appends for a cached answer `distance` bits away (lookups.py)."""
    provenance = LookupProvenance(backend="simulated", cached=distance > 0,
                                  hash_distance=distance, job_id=ObjectId())
    return annotations_for(findings, provenance, ROI, (40, 40, 3))


def jar(confidence: float = 0.8) -> list:
    """What the kitchen's annotators say about a Nutella jar."""
    return [Classification(source="SVMClassifier", class_name="spread", confidence=confidence),
            Logo(source="LogoDetector", brand="Ferrero", confidence=confidence),
            Product(source="ProductRecognizer", name="Nutella", brand="Ferrero")]


def name_of(*observations: list) -> str:
    return naming_fields(sum(map(naming_labels, observations), Counter()))["name"]


def test_a_web_lookup_is_weak_evidence_weaker_the_further_its_cached_hash():
    assert name_of(*[jar() + lookup(0) for _ in range(5)]) == "ferrero"
    mug = [Classification(source="SVMClassifier", class_name="mug", confidence=0.7)]
    assert name_of(*[mug + lookup(0) for _ in range(5)]) == "mug"
    near, far = naming_labels(lookup(0)), naming_labels(lookup(8))
    assert near["storck"] == pytest.approx(4 * far["storck"]) and far["storck"] > 0


def test_ground_truth_outweighs_classifiers_and_a_confident_verdict_a_doubtful_one():
    assert name_of([Classification(source="SVM", class_name="cup", confidence=0.95),
                    Classification(source="kNN", class_name="cup", confidence=0.9),
                    GroundTruth(source="labels", class_name="mug")]) == "mug"
    assert name_of([Classification(source="SVM", class_name="cup", confidence=0.9)],
                   [Classification(source="SVM", class_name="mug", confidence=0.4)],
                   [Classification(source="SVM", class_name="mug", confidence=0.4)]) == "cup"


def test_annotators_agreeing_outweigh_one_repeating_itself():
    weights = naming_labels([
        Logo(source="OneAnnotator", brand="Storck"),
        Product(source="OneAnnotator", name="Storck", brand="Storck"),
        Logo(source="LogoDetector", brand="Nutella"),
        Product(source="ProductRecognizer", name="Nutella"),
    ])
    assert weights == {"nutella": 1.5 + 2, "storck": 2 + 2 / 2 + 1.5 / 4}  # not 2 + 2 + 1.5


def test_identifiers_name_an_object_in_words():
    found = naming_labels([Classification(source="SVM", class_name="SiggBottle"),
                           Classification(source="kNN", class_name="sigg_bottle")])
    assert set(found) == {"sigg bottle"}


def test_the_sums_are_the_same_in_any_order_and_appended_lookups_as_if_there_from_the_start():
    rng = random.Random(7)
    observations = [jar(round(rng.uniform(0.3, 1), 3)) + lookup(rng.randrange(11))
                    for _ in range(30)]
    built = [naming_fields(sum(map(naming_labels, order), Counter()))
             for order in (rng.sample(observations, len(observations)) for _ in range(20))]
    assert all(fields == built[0] for fields in built)
    live = naming_fields(Counter())  # each observation first as it arrived, without its lookup
    for observation in rng.sample(observations, len(observations)):
        live = naming_fields(stored_weights(live) + naming_labels(observation[:3]))
    for observation in rng.sample(observations, len(observations)):
        live = renamed(live, observation[:3], observation)["$set"]
    assert live == built[0]


def scene(i: int, annotations: list) -> Scene:
    return Scene(timestamp=T0 + i * 10**9, robot="pr2", clusters=[Cluster(annotations=[
        Location(source="RegionFilter", region="shelf", position=(1.0, 0.5, 1.2)),
        *annotations])])


def test_lookups_appended_later_do_not_rename_the_jar_live_or_rebuilt(store):
    scenes = [scene(i, [*jar(), Classification(source="kNN", class_name="SiggBottle")])
              for i in range(4)]
    service = IngestService(store)
    service.ingest_batch(scenes, wait=60)
    for s in scenes:
        store.add_annotations(s.clusters[0].id, lookup(2))
    engine = QueryEngine(store)
    (found,) = engine.where_is("ferrero")
    assert found.name == "ferrero" and "storck" not in found.names[:2]
    live = store.db.objects.find_one({}, {"_id": 0, "names": 1, "label_weights": 1})
    request_rebuild(store)
    service.pipeline.drain(timeout=60)
    assert store.db.objects.find_one({}, {"_id": 0, "names": 1, "label_weights": 1}) == live
    (jar_id,) = [o.object_id for o in engine.where_is("ferrero")]
    for question in ("sigg bottle", "sigg", "SiggBottle", "sigg_bottle"):
        assert [o.object_id for o in engine.where_is(question)] == [jar_id], question
        assert len(engine.clusters(text=question).items) == len(scenes), question


def test_a_lookup_s_long_or_odd_title_makes_a_name_not_a_failed_job():
    """A brand or product name is a name (one line, 200 characters); a service's title is
    any text: it is made one, not refused (the job failed on it)."""
    odd = [Finding(category="logo", title="Storck\n\x1b[2J" + "x" * 300, box=None),
           Finding(category="product", title="Knoppers " * 40, brand="Storck\tGmbH", box=None)]
    logo, product = [a for a in lookup(0, odd) if isinstance(a, Logo | Product)]
    assert logo.brand.startswith("Storck  [2J") and len(logo.brand) == 200
    assert len(product.name) == 200 and product.brand == "Storck GmbH"
    assert Logo.model_validate(logo.model_dump()) and Product.model_validate(product.model_dump())
