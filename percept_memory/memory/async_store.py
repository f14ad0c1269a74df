"""AsyncMemoryStore: the MemoryStore API on pymongo's native async client (AsyncMongoClient).

Same documents, same transactions, same guarantees as store.py; for asyncio code such as the
enrichment workers and the web app.
"""

from __future__ import annotations

from collections.abc import Sequence

from bson import ObjectId
from pymongo import AsyncMongoClient
from pymongo.errors import (
    ConfigurationError,
    DocumentTooLarge,
    OperationFailure,
    PyMongoError,
)

from percept_memory.converters import content_id

from . import documents as docs
from .errors import (
    NotFound,
    StoreError,
    require_replica_set,
    unreachable,
)
from .naming import renamed
from .schema import COUNTED_COLLECTIONS, INDEXES, RETIRED_INDEXES, catalogue_entry
from .settings import Settings
from .store import (
    CLIENT_OPTIONS,
    HALVE,
    ClusterChange,
    StoreBase,
    halves,
    sessions_refused,
    vocabulary_upserts,
)
from .types import Annotation, Cluster, Scene
from .types.modules import import_type_modules


class AsyncMemoryStore(StoreBase):
    """The memory on one MongoDB database, for asyncio. Open with `await
    AsyncMemoryStore.open()`."""

    @classmethod
    async def open(cls, settings: Settings | None = None) -> AsyncMemoryStore:
        from .mongod import resolve_uri

        settings = settings or Settings()
        import_type_modules(settings.types)  # (what it stores and reads is of these types too)
        uri = resolve_uri(settings)
        store = cls(AsyncMongoClient(uri, **CLIENT_OPTIONS), settings.db,
                    gridfs_threshold=settings.gridfs_threshold)
        try:
            await store.prepare()
        except PyMongoError as error:
            await store.close()
            raise unreachable(uri, error) from error
        return store

    async def prepare(self) -> None:
        require_replica_set(await self.client.admin.command("hello"))
        for name, indexes in INDEXES.items():
            await self.db[name].create_indexes(indexes)
        for name, retired in RETIRED_INDEXES.items():
            for index in set(retired) & set(await self.db[name].index_information()):
                await self.db[name].drop_index(index)

    async def close(self) -> None:
        await self.client.close()

    async def __aenter__(self) -> AsyncMemoryStore:
        return self

    async def __aexit__(self, *exc) -> None:
        await self.close()

    async def put_scene(self, scene: Scene) -> docs.SceneIds:
        return (await self.put_scenes([scene]))[0]

    async def put_scenes(self, scenes: Sequence[Scene]) -> list[docs.SceneIds]:
        """See MemoryStore.put_scenes: new scenes in one transaction, stored ones not again."""
        return await self.commit_scenes(await self.prepare_scenes(scenes))

    async def prepare_scenes(self, scenes: Sequence[Scene]) -> docs.PreparedWrite:
        return docs.prepared(scenes, {}, self.gridfs_threshold)

    async def commit_scenes(self, prepared: docs.PreparedWrite) -> list[docs.SceneIds]:
        written = prepared.documents
        if not written.scenes:
            return prepared.results

        async def work(session):
            await self._insert(written, session)

        try:
            await self._transaction(work)
        except (DocumentTooLarge, OperationFailure) as error:
            if self._refused(error, prepared) == HALVE:
                return [result for half in halves(prepared.scenes) for result in
                        await self.commit_scenes(docs.prepared(half, {}, self.gridfs_threshold))]
            self._no_repeats(prepared)
            stored = await self._stored(prepared.fresh)
            if not stored:
                raise self._duplicate(error) from None
            scene_docs = await self.scenes.find(docs.stored_query(stored)).to_list()
            self._same_scenes(prepared, scene_docs, await self.clusters.find(
                {"_id": {"$in": [c for doc in scene_docs for c in doc["clusters"]]}}).to_list())
            docs.undo_ids(prepared, stored)
            return await self.commit_scenes(docs.prepared(
                prepared.scenes, await self._stored(prepared.scenes), self.gridfs_threshold))
        await self._catalogue(written)
        return prepared.results

    async def _stored(self, scenes: Sequence[Scene]) -> dict:
        if not scenes:
            return {}
        query = docs.stored_query(map(docs.scene_key, scenes))
        found = await self.scenes.find(query, docs.STORED_IDS_PROJECTION).to_list()
        if not found:  # the common case: all new, one round trip
            return {}
        cluster_ids = [c for doc in found for c in doc["clusters"]]
        clusters = self.clusters.find({"_id": {"$in": cluster_ids}}, {"annotations._id": 1})
        return docs.stored_by_key(found, await clusters.to_list())

    async def get_scene(self, scene_id: ObjectId) -> Scene:
        scene_id = docs.as_id(scene_id, "scene_id")
        doc = await self.scenes.find_one({"_id": scene_id})
        if doc is None:
            raise NotFound("scene", scene_id)
        cluster_docs = await self.clusters.find({"_id": {"$in": doc["clusters"]}}).to_list()
        return docs.decode_scene(doc, cluster_docs, await self._blobs([doc, *cluster_docs]))

    async def get_cluster(self, cluster_id: ObjectId) -> Cluster:
        cluster_id = docs.as_id(cluster_id, "cluster_id")
        doc = await self.clusters.find_one({"_id": cluster_id})
        if doc is None:
            raise NotFound("cluster", cluster_id)
        return docs.decode_cluster(doc, await self._blobs([doc]))

    async def get_clusters(self, cluster_ids: Sequence[ObjectId]) -> dict[ObjectId, Cluster]:
        found = await self.clusters.find({"_id": {"$in": list(cluster_ids)}}).to_list()
        blobs = await self._blobs(found)
        return {doc["_id"]: docs.decode_cluster(doc, blobs) for doc in found}

    async def update_cluster(self, cluster: Cluster) -> None:
        docs.checked([cluster], Cluster, "cluster")
        if cluster.id is None:
            raise StoreError("the cluster has no id: store it as part of a scene first")
        await self._rewrite_cluster(cluster.id, lambda stored: cluster)

    async def add_annotation(self, cluster_id: ObjectId, annotation: Annotation) -> ObjectId:
        """See MemoryStore.add_annotation: idempotent by annotation id."""
        return (await self.add_annotations(cluster_id, [annotation]))[0]

    async def add_annotations(
        self, cluster_id: ObjectId, annotations: Sequence[Annotation], session=None
    ) -> list[ObjectId]:
        """See MemoryStore.add_annotations: one transaction, idempotent by annotation id; in
        `session`, when given (an enrichment job's: jobs.py)."""
        cluster_id = docs.as_id(cluster_id, "cluster_id")
        docs.checked(annotations, Annotation, "annotations")
        annotation_ids = [annotation.ensure_id() for annotation in annotations]
        await self._rewrite_cluster(
            cluster_id, lambda cluster: docs.appended(cluster, annotations), session)
        return annotation_ids

    async def update_annotation(self, cluster_id: ObjectId, annotation: Annotation) -> None:
        cluster_id = docs.as_id(cluster_id, "cluster_id")
        docs.checked([annotation], Annotation, "annotation")
        await self._rewrite_cluster(cluster_id, lambda cluster: docs.replaced(cluster, annotation))

    async def _rewrite_cluster(self, cluster_id: ObjectId, change: ClusterChange,
                               session=None) -> None:
        async def work(session) -> set[str]:
            doc = await self.clusters.find_one({"_id": cluster_id}, session=session)
            if doc is None:
                raise NotFound("cluster", cluster_id)
            stored = docs.decode_cluster(doc, await self._blobs([doc], session))
            before = list(stored.annotations)
            changed = change(stored)
            if changed is None:
                return docs.Documents()
            written = docs.rewritten_cluster(changed, doc, self.gridfs_threshold)
            await self._put_blobs(written.blobs, session)
            await self.clusters.replace_one(
                {"_id": cluster_id}, written.clusters[0], session=session
            )
            if doc.get("object_id") is not None:
                await self._rename(doc["object_id"], before, changed.annotations, session)
            summary = docs.summary_change(doc, written.clusters[0])
            if summary == docs.RECOUNT:
                await self._summarise(doc["scene_id"], session)
            elif summary:
                await self.scenes.update_one({"_id": doc["scene_id"]}, summary, session=session)
            return written

        await self._catalogue(await self._transaction(work, session))

    async def _rename(self, object_id, before, after, session) -> None:
        """Keep the names of the object an observation is believed to be in step with the
        annotations appended to it (naming.py)."""
        believed = await self.objects.find_one({"_id": object_id}, {"label_weights": 1},
                                            session=session)
        update = renamed(believed, before, after) if believed else None
        if update:
            await self.objects.update_one({"_id": object_id}, update, session=session)

    async def _summarise(self, scene_id: ObjectId, session) -> None:
        """See MemoryStore._summarise."""
        scene = await self.scenes.find_one({"_id": scene_id}, docs.SUMMARY_PROJECTION,
                                           session=session)
        clusters = await self.clusters.find({"scene_id": scene_id}, docs.SUMMARY_PROJECTION,
                                            session=session).to_list()
        await self.scenes.update_one({"_id": scene_id}, {"$set": {
            docs.SUMMARY_KEY: docs.scene_summary(scene, clusters)}}, session=session)

    async def put_blob(self, data: bytes) -> str:
        blob_id = content_id(data)

        async def work(session):
            await self._put_blobs({blob_id: data}, session)

        await self._transaction(work)
        return blob_id

    async def get_blob(self, blob_id: str) -> bytes:
        return (await self._blobs_by_id([blob_id]))[blob_id]

    async def _put_blobs(self, blobs: dict[str, bytes], session) -> None:
        stored = [doc["_id"] for home, ids in docs.blob_homes(blobs).items()
                  async for doc in self.db[home].find({"_id": {"$in": ids}}, {"_id": 1},
                                                      session=session)]
        for name, documents in docs.blob_writes(blobs, stored).items():
            await self.db[name].insert_many(documents, session=session)

    async def _blobs(self, stored: list[dict], session=None) -> dict[str, bytes]:
        return await self._blobs_by_id(docs.blob_ids(stored), session)

    async def _blobs_by_id(self, blob_ids: list[str], session=None) -> dict[str, bytes]:
        if not blob_ids:
            return {}
        found = {doc["_id"]: doc["data"] async for doc in self.binaries.find(
            {"_id": {"$in": blob_ids}}, session=session)}
        if rest := [blob for blob in blob_ids if blob not in found]:
            cursor = self.chunks.find({"files_id": {"$in": rest}}, session=session)
            found |= docs.joined_blobs(rest, await cursor.to_list())
        return found

    async def _insert(self, written: docs.Documents, session) -> None:
        await self._put_blobs(written.blobs, session)
        await self.scenes.insert_many(written.scenes, session=session)
        if written.clusters:
            await self.clusters.insert_many(written.clusters, session=session)
        await self.outbox.insert_many(written.outbox, session=session)

    async def _transaction(self, work, session=None):
        """Run work(session) in a transaction, in a session of its own or the one given (once
        more on fresh connections when refused as "sessions not supported": StoreBase._pools)."""

        async def run():
            if session is not None:
                return await session.with_transaction(work)
            async with self.client.start_session() as own:
                return await own.with_transaction(work)

        try:
            return await run()
        except ConfigurationError as error:
            if not sessions_refused(error):
                raise
            for pool in self._pools():
                await pool.reset_without_pause()
            return await run()

    async def _catalogue(self, written: docs.Documents) -> None:
        for name in self._not_yet_catalogued(written.type_names):
            await self.types.replace_one({"_id": name}, catalogue_entry(name), upsert=True)
        for collection, entries in self._new_vocabulary(written).items():
            await self.db[collection].bulk_write(vocabulary_upserts(entries), ordered=False)
        self._remember_words(written)

    async def catalogue(self) -> list[dict]:
        return await self.types.find().sort("_id").to_list()

    async def counts(self) -> dict:
        present = set(await self.db.list_collection_names())
        collections = {
            name: await self.db[name].estimated_document_count() if name in present else 0
            for name in COUNTED_COLLECTIONS
        }
        rows = await (await self.clusters.aggregate(docs.TYPE_COUNT_PIPELINE)).to_list()
        return {"collections": collections, "types": {r["_id"]: r["count"] for r in rows}}
