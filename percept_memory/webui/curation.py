"""Corrections by people over HTTP (memory/curation.py), and the audit page listing them.

    POST /api/clusters/{id}/relabel   {"label": "mug", "author": "ana"}
    POST /api/clusters/{id}/reject    {"author": "ana", "reason": "a reflection"}
    POST /api/clusters/{id}/corrections/{correction_id}/undo   {"author": "bo"}
    POST /api/clusters/{id}/merge     {"other": "<cluster id>", "author": "ana"}: one object
    POST /api/objects/{id}/relabel    {"label": "mug", "author": "ana"}: its latest observation
    POST /api/objects/{id}/merge      {"other": "<object id>", "author": "ana"}
    POST /api/objects/{id}/split      {"clusters": ["<cluster id>", ...], "author": "ana"}:
                                      these observations of the object are another object
    GET  /api/corrections             the audit: every correction, newest first, and counts

Writes need the write token when one is configured; the guard (guard.py) refuses them from
pages of other origins and without a JSON body, so a page cannot be made to send them by
another site. The forms on the cluster, object, audit and review pages send the same requests
from this site's own script (static/curate.js), with the token a person types in once the
server asks for it.
"""

# no `from __future__ import annotations`: FastAPI reads the endpoints' annotations

from typing import Annotated, Any

from bson import ObjectId
from fastapi import APIRouter, Depends, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import HTMLResponse
from pydantic import BaseModel, ConfigDict, Field

from percept_memory.memory import curation
from percept_memory.memory.errors import NotFound
from percept_memory.memory.schema import EVENTS, OBJECTS
from percept_memory.memory.search_keys import normal_label
from percept_memory.memory.settings import Settings
from percept_memory.memory.store import MemoryStore
from percept_memory.memory.types import Annotation, Cluster, GroundTruth, Id
from percept_memory.memory.types.curation import Correction, in_force

from .errors import READ_ERRORS, WRITE_ERRORS, ApiError
from .guard import authorise
from .html import SCRIPT_CSP, page
from .queries import small_body

AUDIT_SHOWN = 200
MERGE_CANDIDATES = 20
BODY_FIELDS = {"class_name": "label"}  # a correction's fields as the request bodies name them


class Body(BaseModel):
    """A correction's request body: a field it does not know is an error, not dropped (a
    misspelt `reson` would lose the reason)."""

    model_config = ConfigDict(extra="forbid")


class Relabelling(Body):
    label: str = Field(description="the class or name of the object seen (1-200 characters)")
    author: str = Field(description="who corrects (1-100 characters)")


class Rejecting(Body):
    author: str = Field(description="who corrects (1-100 characters)")
    reason: str = Field(default="", description="why the detection is wrong (optional)")


class Merging(Body):
    other: Id = Field(description="the other cluster (or object) showing the same object")
    author: str = Field(description="who corrects (1-100 characters)")


class Splitting(Body):
    clusters: list[Id] = Field(description="the object's observations that show another object")
    author: str = Field(description="who corrects (1-100 characters)")


class Undoing(Body):
    author: str = Field(description="who takes the correction back (1-100 characters)")


def routes(store: MemoryStore, settings: Settings) -> APIRouter:
    router = APIRouter()
    objects = store.db[OBJECTS]

    def writer(request: Request, _: Annotated[None, Depends(small_body)]) -> None:
        authorise(request, settings.token)

    async def corrected(make, *args) -> dict[str, Any]:
        """The correction made, and the map whose belief follows it (a merge, split, reject
        or undo has it rebuilt: the page waits for that map before it shows the result)."""
        made = await correcting(make, *args)
        return {"correction": described(made), "map": await run_in_threadpool(map_of, args[0])}

    def map_of(key: ObjectId) -> str | None:
        """The map of the object or the cluster corrected."""
        believed = objects.find_one({"_id": key}, {"map": 1})
        if believed is not None:
            return believed.get("map")
        cluster = store.clusters.find_one({"_id": key}, {"scene_id": 1})
        scene = cluster and store.scenes.find_one({"_id": cluster["scene_id"]}, {"map": 1})
        return scene and scene.get("map")

    async def correcting(make, *args):
        try:
            return await run_in_threadpool(make, store, *args)
        except curation.NotCorrectable as error:
            field = BODY_FIELDS.get(error.field, error.field)
            raise ApiError(422, "the correction is not valid", [
                {"path": f"body.{field}" if field else "", "message": str(error)}]) from None

    def latest_observations(*object_ids) -> list:
        """The latest cluster of each object: a correction of an object is one of what was
        seen of it, so it outlives a rebuild of the belief (which makes objects afresh)."""
        found = {o["_id"]: o["last_cluster"] for o in objects.find(
            {"_id": {"$in": list(object_ids)}}, {"last_cluster": 1})}
        for key in object_ids:
            if key not in found:
                raise NotFound("object", key)
        return [found[key] for key in object_ids]

    write = {"status_code": 201, "responses": WRITE_ERRORS, "tags": ["corrections"],
             "dependencies": [Depends(writer)]}

    @router.post("/api/clusters/{cluster_id}/relabel", summary="Say what a cluster shows",
                 **write)
    async def relabel_cluster(cluster_id: Id, body: Relabelling) -> dict[str, Any]:
        """A person's class or name for the object seen in the cluster: stored beside the
        annotators' annotations (never changing them), it names the object above every
        annotator, and exports take it as the cluster's label."""
        return await corrected(curation.relabel, cluster_id, body.label, body.author)

    @router.post("/api/clusters/{cluster_id}/reject", summary="Say a detection is wrong",
                 **write)
    async def reject_cluster(cluster_id: Id, body: Rejecting) -> dict[str, Any]:
        """No object is here: identity leaves the cluster out (its map's belief is rebuilt
        by the memory pipeline, see GET /api/pipeline) and exports skip it."""
        return await corrected(curation.reject, cluster_id, body.author, body.reason)

    @router.post("/api/clusters/{cluster_id}/merge", summary="Say two clusters show one object",
                 **write)
    async def merge_clusters(cluster_id: Id, body: Merging) -> dict[str, Any]:
        """The object seen in the cluster is the one seen in `other` (same map): identity
        merges their objects (the map's belief is rebuilt by the memory pipeline). Stored on
        the later of the two clusters."""
        return await corrected(curation.merge, cluster_id, body.other, body.author)

    @router.post("/api/objects/{object_id}/merge", summary="Say two objects are one", **write)
    async def merge_objects(object_id: Id, body: Merging) -> dict[str, Any]:
        """The object is the object `other`: a merge of their latest observations."""
        mine, other = await run_in_threadpool(latest_observations, object_id, body.other)
        return await corrected(curation.merge, mine, other, body.author)

    @router.post("/api/objects/{object_id}/split",
                 summary="Say some observations of an object show another object", **write)
    async def split_object(object_id: Id, body: Splitting) -> dict[str, Any]:
        """The observations in `clusters` show another object than the object's other
        observations: identity never takes one of either side for an object one of the other
        side was taken for (the map's belief is rebuilt by the memory pipeline). One
        correction, stored on the earliest cluster split off and undone there."""
        return await corrected(curation.split, object_id, body.clusters, body.author)

    @router.post("/api/clusters/{cluster_id}/corrections/{correction_id}/undo",
                 summary="Take a correction back", **write)
    async def undo_correction(cluster_id: Id, correction_id: Id,
                              body: Undoing) -> dict[str, Any]:
        """Itself recorded: the audit lists the correction, undone, and the undo."""
        return await corrected(curation.undo, cluster_id, correction_id, body.author)

    @router.post("/api/objects/{object_id}/relabel", summary="Say what an object is", **write)
    async def relabel_object(object_id: Id, body: Relabelling) -> dict[str, Any]:
        """A relabel of the object's latest observation: the object is named by it."""
        (latest,) = await run_in_threadpool(latest_observations, object_id)
        return await corrected(curation.relabel, latest, body.label, body.author)

    @router.get("/api/corrections", summary="The corrections, newest first",
                tags=["corrections"], responses=READ_ERRORS)
    def audit(author: Annotated[str | None, Query(max_length=100)] = None,
              limit: Annotated[int, Query(ge=1, le=curation.AUDIT_LIMIT)] = AUDIT_SHOWN,
              ) -> dict[str, Any]:
        """Who corrected what and when: kind (relabel, reject, merge, split, undo), label or
        reason, the cluster, scene and object, and who undid it; `counts` of each kind."""
        rows = curation.audit(store, limit, author)
        return {"counts": curation.counts(store), "corrections": [as_json(r) for r in rows]}

    @router.get("/corrections", include_in_schema=False, response_class=HTMLResponse)
    async def audit_page(request: Request, author: str | None = None) -> HTMLResponse:
        rows, counts = await run_in_threadpool(
            lambda: (curation.audit(store, AUDIT_SHOWN, author or None), curation.counts(store)))
        return page(request, "corrections.html", {
            "rows": rows, "counts": counts, "author": author or "", "shown": AUDIT_SHOWN,
        }, policy=SCRIPT_CSP)

    return router


def merge_candidates(store: MemoryStore, believed: dict, history: list[dict]) -> list[dict]:
    """The objects of the object's map a person may find it is one with: those identity
    weighed it against (its events' alternatives) and those of its names (the `names`
    index), never seen in one scene with it, at most MERGE_CANDIDATES."""
    weighed = {a["object_id"] for e in history for a in e.get("alternatives", [])
               if a.get("object_id") not in (None, believed["_id"])}
    found = store.db[OBJECTS].find({"_id": {"$in": list(weighed)}}, {"name": 1}).limit(
        MERGE_CANDIDATES)
    alike = store.db[OBJECTS].find({"names": {"$in": believed.get("names") or []},
                                    "map": believed.get("map"), "_id": {"$ne": believed["_id"]}},
                                   {"name": 1}).limit(MERGE_CANDIDATES)
    unique = {o["_id"]: o for o in [*found, *alike]}
    # not those seen beside it in a scene: two observations of one scene are two objects
    # (a merge of them is refused)
    events = store.db[EVENTS]
    scenes = events.distinct("scene_id", {"object_id": believed["_id"],
                                          "cluster_id": {"$ne": None}})
    beside = set(events.distinct("object_id", {"scene_id": {"$in": scenes},
                                               "object_id": {"$in": list(unique)},
                                               "cluster_id": {"$ne": None}}))
    return [o for key, o in unique.items() if key not in beside][:MERGE_CANDIDATES]


def versus_truth(cluster: Cluster) -> list[dict[str, Any]]:
    """What each annotator (and person) named the cluster beside its ground truth (a labelled
    data set's, RoboSherlock's PnP09): source, name, confidence, whether it is the true
    class; none without a ground truth."""
    truths = {normal_label(t.class_name) for t in cluster.annotations_of(GroundTruth)}
    if not truths:
        return []
    said = [a for a in in_force(cluster.annotations) if isinstance(a, Annotation)
            and not isinstance(a, GroundTruth) and a.naming_weight > 0]
    return [{"source": a.author if isinstance(a, Correction) else a.source, "name": label,
             "confidence": getattr(a, "confidence", None), "kind": a.type_name,
             "true": normal_label(label) in truths}
            for a in said for label in a.labels()]


def described(correction: Correction) -> dict[str, Any]:
    return correction.model_dump(mode="json", by_alias=True)


def as_json(value: Any) -> Any:
    """An audit row with its ids as strings."""
    if isinstance(value, dict):
        return {key: as_json(item) for key, item in value.items()}
    if isinstance(value, list):
        return [as_json(item) for item in value]
    return str(value) if isinstance(value, ObjectId) else value
