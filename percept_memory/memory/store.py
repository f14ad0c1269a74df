"""MemoryStore: scenes, clusters, annotations and blobs in MongoDB (synchronous API).

Every write is one transaction: a scene, its clusters and its blobs are stored together or not
at all, and an annotation appended to a stored cluster never half-lands. Ids are assigned before
the write, so a retried write finds its own earlier success instead of storing twice.
`AsyncMemoryStore` (async_store.py) is the same store on pymongo's native async API; both keep
the document layout in documents.py and do only the I/O here.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections import OrderedDict
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import suppress

from bson import ObjectId
from pymongo import MongoClient, UpdateOne, WriteConcern
from pymongo.errors import (
    ConfigurationError,
    DocumentTooLarge,
    OperationFailure,
    PyMongoError,
    ServerSelectionTimeoutError,
)

from percept_memory.converters import content_id

from . import documents as docs
from .errors import (
    DuplicateId,
    NotFound,
    SceneExists,
    StoreError,
    TooLarge,
    TransactionTooLarge,
    TypeHookFailed,
    Unavailable,
    duplicate_key,
    reason,
    require_replica_set,
    too_large,
    transaction_too_large,
    unreachable,
)
from .naming import renamed
from .schema import (
    BINARIES,
    CLUSTERS,
    COUNTED_COLLECTIONS,
    FIELD_INDEX_PREFIX,
    GRIDFS_CHUNKS,
    GRIDFS_FILES,
    INDEXES,
    LABELS,
    OBJECTS,
    OUTBOX,
    RETIRED_INDEXES,
    SCENES,
    TERMS,
    TYPES,
    catalogue_entry,
    field_index,
)
from .settings import Settings
from .types import Annotation, Cluster, Scene
from .types.modules import import_type_modules

CLIENT_OPTIONS = {"tz_aware": True, "appname": "percept-memory"}
log = logging.getLogger(__name__)

ClusterChange = Callable[[Cluster], Cluster | None]
AfterRewrite = Callable[[list, Cluster, object], None]


def vocabulary_upserts(entries: list[dict]) -> list[UpdateOne]:
    """Idempotent writes of vocabulary entries: a word is inserted once and never changed."""
    return [UpdateOne({"_id": e["_id"]}, {"$setOnInsert": e}, upsert=True) for e in entries]


HALVE, STORED = "halve", "stored"
# scenes kept for this process's consolidator, the oldest dropped first: it takes them within
# milliseconds of their commit, or reads them back after a burst (a 6 x 20 scene: ~150 kB)
HANDED_OVER = 64


class HandedOver:
    """Scenes this process stored and made itself (from a request's JSON), as identity reads
    them back (consolidation.as_evidence), for this process's consolidator: a scene waited
    for is consolidated without reading it, its clusters and their blobs back and decoding
    every annotation again. A scene not here (stored elsewhere, dropped, or taken once) is
    read back: one consolidated again (a rebuild) has what people appended since (a
    rejection, a split), which the copy handed over has not."""

    def __init__(self, size: int = HANDED_OVER):
        self.size = size
        self._scenes: OrderedDict[ObjectId, Scene] = OrderedDict()
        self._lock = threading.Lock()

    def put(self, scenes: Iterable[Scene]) -> None:
        with self._lock:
            for scene in scenes:
                self._scenes[scene.id] = scene
            while len(self._scenes) > self.size:
                self._scenes.popitem(last=False)

    def take(self, scene_id: ObjectId) -> Scene | None:
        """The scene as it was stored, once."""
        with self._lock:
            return self._scenes.pop(scene_id, None)


class _Abort(Exception):
    """Ends a transaction of put_scene_chunks whose chunks failed: nothing is committed."""


def halves(items: Sequence) -> tuple[Sequence, Sequence]:
    middle = len(items) // 2
    return items[:middle], items[middle:]


def sessions_refused(error: ConfigurationError) -> bool:
    """Whether a transaction failed on a connection without sessions: see StoreBase._pools."""
    return "Sessions are not supported" in str(error)


class StoreBase:
    """What the sync and async stores share: collections, settings, the catalogue memo."""

    def __init__(self, client, db_name: str, *, gridfs_threshold: int):
        self.client = client
        self.db = client[db_name]
        self.scenes = self.db[SCENES]
        self.clusters = self.db[CLUSTERS]
        self.types = self.db[TYPES]
        self.binaries = self.db[BINARIES]
        self.files = self.db[GRIDFS_FILES]
        self.chunks = self.db[GRIDFS_CHUNKS]
        self.outbox = self.db[OUTBOX]
        self.objects = self.db[OBJECTS]
        self.gridfs_threshold = gridfs_threshold
        self._catalogued: set[str] = set()
        self._known_words: set[tuple[str, str]] = set()

    def _pools(self) -> list:
        """The client's connection pools, to be emptied when a transaction is refused as
        "sessions not supported": a connection opened while mongod was starting (after a
        crash) keeps that from its handshake for as long as it lives, and pymongo keeps it in
        the pool, as it is no network error, though mongod is a primary again (pymongo's
        Connection.supports_sessions). The kill -9 test once waited 180 s on one."""
        return [server.pool for server in self.client._topology._servers.values()]

    def _not_yet_catalogued(self, type_names: set[str]) -> list[str]:
        new = sorted(type_names - self._catalogued)
        self._catalogued.update(new)
        return new

    def _new_vocabulary(self, written: docs.Documents) -> dict[str, list[dict]]:
        """The terms and labels of a write that this process has not written before."""
        known = self._known_words
        found = docs.vocabulary_documents(
            [t for t in written.terms if (TERMS, t) not in known],
            [label for label in written.labels if (LABELS, label) not in known])
        return {collection: entries for collection, entries in found.items() if entries}

    def _remember_words(self, written: docs.Documents) -> None:
        """After a commit: the words of this write are in the vocabulary."""
        self._known_words.update((TERMS, term) for term in written.terms)
        self._known_words.update((LABELS, label) for label in written.labels)

    def _refused(self, error: Exception, prepared: docs.PreparedWrite) -> str:
        """What to do about a scene write the server refused: HALVE a batch too big for one
        transaction in its cache (each scene stays atomic, assigned ids are kept), or look
        up the scenes a duplicate key says are STORED already; else a clear error."""
        if too_large(error):
            raise TooLarge(self.gridfs_threshold) from error
        if transaction_too_large(error):
            if len(prepared.scenes) == 1:
                raise TransactionTooLarge(self.gridfs_threshold) from error
            return HALVE
        if duplicate_key(error) is None:
            raise error
        return STORED

    @staticmethod
    def _no_repeats(prepared: docs.PreparedWrite) -> None:
        """Refuse the write (SceneExists) when two of its scenes differ under one robot and
        time: chunks prepared apart (put_scene_chunks) are checked only as a whole, here."""
        try:
            docs.refuse_repeats(prepared.scenes)
        except SceneExists:
            docs.undo_ids(prepared, {docs.scene_key(scene): None for scene in prepared.scenes})
            raise

    @staticmethod
    def _same_scenes(prepared: docs.PreparedWrite, scene_docs: list, cluster_docs) -> None:
        """Refuse the write (SceneExists) when one of its scenes is not the scene stored under
        its robot and time: only the same scene sent again is no write."""
        if found := docs.differing(prepared, scene_docs, cluster_docs):
            docs.undo_ids(prepared, {docs.scene_key(scene): None for scene in prepared.scenes})
            raise SceneExists(*found[0])

    @staticmethod
    def _duplicate(error: Exception) -> DuplicateId:
        return DuplicateId(
            f"not stored: {duplicate_key(error)} is already used by another document, stored "
            "or earlier in this write; "
            "give new objects no id (ids are assigned on store)"
        )


class MemoryStore(StoreBase):
    """The memory, on one MongoDB database. Open with `MemoryStore.open()` (settings from the
    environment; the embedded mongod unless MONGODB_URI is set)."""

    def __init__(self, client, db_name: str, *, gridfs_threshold: int):
        super().__init__(client, db_name, gridfs_threshold=gridfs_threshold)
        self.handed_over = HandedOver()

    @classmethod
    def open(cls, settings: Settings | None = None) -> MemoryStore:
        from .mongod import resolve_uri

        settings = settings or Settings()
        import_type_modules(settings.types)  # (what it stores and reads is of these types too)
        uri = resolve_uri(settings)
        client = MongoClient(uri, serverSelectionTimeoutMS=settings.mongo_timeout_ms,
                             **CLIENT_OPTIONS)
        store = cls(client, settings.db, gridfs_threshold=settings.gridfs_threshold)
        try:
            store.prepare()
        except PyMongoError as error:
            store.close()
            raise unreachable(uri, error) from error
        return store

    def prepare(self) -> None:
        """Check the server can do transactions, create the indexes and drop retired ones
        (idempotent)."""
        require_replica_set(self.client.admin.command("hello"))
        for name, indexes in INDEXES.items():
            self.db[name].create_indexes(indexes)
        for name, retired in RETIRED_INDEXES.items():
            for index in set(retired) & set(self.db[name].index_information()):
                self.db[name].drop_index(index)

    def field_indexes(self) -> list[str]:
        """The annotation fields (paths) indexed on a user's demand, by name."""
        return sorted(name.removeprefix(FIELD_INDEX_PREFIX)
                      for name in self.clusters.index_information()
                      if name.startswith(FIELD_INDEX_PREFIX))

    def add_field_index(self, path: str) -> bool:
        """Index the annotations' field at `path` (of every type: `confidence` serves
        classification:confidence and shape:confidence), so that a predicate on it needs
        nothing else to be fast (queries narrowed by text, region, time... are, without it).
        MongoDB builds it while reads and writes go on. False when it was there already."""
        index = field_index(path)
        if index.document["name"] in self.clusters.index_information():
            return False
        self.clusters.create_indexes([index])
        return True

    def drop_field_index(self, path: str) -> bool:
        """Drop a field index added before; False when there was none."""
        name = field_index(path).document["name"]
        if name not in self.clusters.index_information():
            return False
        self.clusters.drop_index(name)
        return True

    def close(self) -> None:
        self.client.close()

    def __enter__(self) -> MemoryStore:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # --- scenes -------------------------------------------------------------------------

    def put_scene(self, scene: Scene) -> docs.SceneIds:
        """Store one scene; see put_scenes."""
        return self.put_scenes([scene])[0]

    def put_scenes(self, scenes: Sequence[Scene]) -> list[docs.SceneIds]:
        """Store scenes with their clusters and blobs, the new ones in one transaction (all of
        them or none); ids are assigned in place. A scene is identified by its robot and
        timestamp: one stored before is not written again and its stored ids come back with
        `created=False`, so a retried or repeated ingest never duplicates anything."""
        return self.commit_scenes(self.prepare_scenes(scenes))

    def prepare_scenes(self, scenes: Sequence[Scene]) -> docs.PreparedWrite:
        """The first half of put_scenes: assign ids and encode. Separate so a pipeline can
        encode the next batch while the previous one is being written. Optimistic: the scenes
        are taken to be new; the unique robot + timestamp index tells otherwise at commit."""
        return docs.prepared(scenes, {}, self.gridfs_threshold)

    def put_scene_chunks(self, chunks: Iterable[Sequence[Scene]]) -> list[docs.SceneIds]:
        """put_scenes of the scenes of all chunks, in one transaction, each chunk encoded and
        sent while the server is still inserting the chunks before it (a writer thread), so
        that the server's work hides behind the caller's, e.g. validating the next chunk.
        An exception from `chunks` aborts the transaction: nothing is stored. What the server
        refuses (a scene stored before, a batch too large) is handled as put_scenes does."""
        prepared: list[docs.PreparedWrite] = []
        handed: queue.SimpleQueue = queue.SimpleQueue()
        sent: list[docs.Documents] = []
        all_sent = False

        def work(session):  # run again from the start when the transaction is retried
            nonlocal all_sent
            for documents in sent:
                self._insert(documents, session)
            while not all_sent:
                documents = handed.get()
                if isinstance(documents, BaseException):
                    raise documents
                if documents is None:
                    all_sent = True
                else:
                    sent.append(documents)
                    self._insert(documents, session)

        with ThreadPoolExecutor(max_workers=1, thread_name_prefix="pmem-writer") as writer:
            committed = writer.submit(self._transaction, work, retry_unreachable=False)
            try:
                for chunk in chunks:
                    prepared.append(self.prepare_scenes(chunk))
                    handed.put(prepared[-1].documents)
            except BaseException:
                handed.put(_Abort())
                with suppress(Exception):  # the caller's error is the one to tell
                    committed.result()
                raise
            handed.put(None)
            whole = docs.joined(prepared)
            try:
                committed.result()
            except (DocumentTooLarge, OperationFailure):
                return self.commit_scenes(whole)
        self._catalogue(whole.documents)
        return whole.results

    def put_document_chunks(self, chunks: Iterable[docs.Documents]) -> bool:
        """Store the documents of new scenes prepared elsewhere (ingest's worker processes) in
        one transaction, each chunk sent as it comes: True. False, and nothing written, when
        the server refuses them as they are (a scene stored before, a write too large):
        put_scenes sorts those out. An exception from `chunks` aborts the transaction."""
        remaining, sent = iter(chunks), docs.Documents()

        def work(session):  # run again from the start when the transaction is retried
            if sent.scenes:
                self._insert(sent, session)
            for documents in remaining:
                sent.add(documents)
                if documents.scenes:  # (a part of no scene: a body of fewer than the parts)
                    self._insert(documents, session)

        try:
            self._transaction(work, retry_unreachable=False)
        except (DocumentTooLarge, OperationFailure) as error:
            if too_large(error) or transaction_too_large(error) or duplicate_key(error):
                return False
            raise
        self._catalogue(sent)
        return True

    def commit_scenes(self, prepared: docs.PreparedWrite) -> list[docs.SceneIds]:
        """The second half of put_scenes: write the new scenes in one transaction. When some
        were stored already (before, or by another writer meanwhile), their stored ids are
        looked up and the others written."""
        written = prepared.documents
        if not written.scenes:
            return prepared.results
        try:
            self._transaction(lambda session: self._insert(written, session),
                              retry_unreachable=False)
        except (DocumentTooLarge, OperationFailure) as error:
            if self._refused(error, prepared) == HALVE:
                return [result for half in halves(prepared.scenes) for result in
                        self.commit_scenes(docs.prepared(half, {}, self.gridfs_threshold))]
            self._no_repeats(prepared)
            stored = self._stored(prepared.fresh)
            every = {docs.scene_key(scene): None for scene in prepared.scenes}
            if not stored and len(every) < len(prepared.fresh):  # one scene twice, in two
                docs.undo_ids(prepared, every)  # chunks prepared apart: once, as one write
                return self.commit_scenes(docs.prepared(prepared.scenes, {},
                                                        self.gridfs_threshold))
            if not stored:
                raise self._duplicate(error) from None
            scene_docs = list(self.scenes.find(docs.stored_query(stored)))
            self._same_scenes(prepared, scene_docs, self.clusters.find(
                {"_id": {"$in": [c for doc in scene_docs for c in doc["clusters"]]}}))
            docs.undo_ids(prepared, stored)
            return self.commit_scenes(docs.prepared(
                prepared.scenes, self._stored(prepared.scenes), self.gridfs_threshold))
        self._catalogue(written)
        return prepared.results

    def _stored(self, scenes: Sequence[Scene]) -> dict:
        """(robot, timestamp) -> SceneIds of those of `scenes` that are stored."""
        if not scenes:
            return {}
        found = list(self.scenes.find(
            docs.stored_query(map(docs.scene_key, scenes)), docs.STORED_IDS_PROJECTION
        ))
        if not found:  # the common case: all new, one round trip
            return {}
        cluster_ids = [c for doc in found for c in doc["clusters"]]
        clusters = self.clusters.find({"_id": {"$in": cluster_ids}}, {"annotations._id": 1})
        return docs.stored_by_key(found, clusters)

    def get_scene(self, scene_id: ObjectId) -> Scene:
        scene_id = docs.as_id(scene_id, "scene_id")
        doc = self.scenes.find_one({"_id": scene_id})
        if doc is None:
            raise NotFound("scene", scene_id)
        cluster_docs = list(self.clusters.find({"_id": {"$in": doc["clusters"]}}))
        return docs.decode_scene(doc, cluster_docs, self._blobs([doc, *cluster_docs]))

    # --- clusters and annotations -------------------------------------------------------

    def get_cluster(self, cluster_id: ObjectId) -> Cluster:
        cluster_id = docs.as_id(cluster_id, "cluster_id")
        doc = self.clusters.find_one({"_id": cluster_id})
        if doc is None:
            raise NotFound("cluster", cluster_id)
        return docs.decode_cluster(doc, self._blobs([doc]))

    def get_clusters(self, cluster_ids: Sequence[ObjectId], kinds: Sequence[str] | None = None
                     ) -> dict[ObjectId, Cluster]:
        """Several clusters at once, by id (ids not stored are left out). `kinds`: only their
        hypotheses and annotations of these stored types are read back (the server leaves the
        others out, and their blobs are not fetched): a reader that wants a few of a cluster's
        twenty parts decodes those."""
        query = {"_id": {"$in": list(cluster_ids)}}
        if kinds is None:
            found = list(self.clusters.find(query))
        else:
            kept = {part: {"$filter": {"input": f"${part}", "cond": {
                "$in": ["$$this._type", list(kinds)]}}} for part in ("hypotheses", "annotations")}
            found = list(self.clusters.aggregate([
                {"$match": query},
                {"$project": {"_type": 1, "scene_id": 1, "object_id": 1, **kept}}]))
        blobs = self._blobs(found)
        return {doc["_id"]: docs.decode_cluster(doc, blobs) for doc in found}

    def update_cluster(self, cluster: Cluster) -> None:
        """Replace a stored cluster by the given version of it."""
        docs.checked([cluster], Cluster, "cluster")
        if cluster.id is None:
            raise StoreError("the cluster has no id: store it as part of a scene first")
        self._rewrite_cluster(cluster.id, lambda stored: cluster)

    def add_annotation(self, cluster_id: ObjectId, annotation: Annotation) -> ObjectId:
        """Append an annotation to a stored cluster. Idempotent: appending the same annotation
        (same id) again changes nothing, so a retried enrichment job never duplicates."""
        return self.add_annotations(cluster_id, [annotation])[0]

    def add_annotations(
        self, cluster_id: ObjectId, annotations: Sequence[Annotation],
        then: AfterRewrite | None = None,
    ) -> list[ObjectId]:
        """Append several annotations in one transaction, all or none; idempotent by id.
        `then(before, after, session)`: more writes in the same transaction, given the
        cluster's annotations before and the cluster after."""
        cluster_id = docs.as_id(cluster_id, "cluster_id")
        docs.checked(annotations, Annotation, "annotations")
        annotation_ids = [annotation.ensure_id() for annotation in annotations]
        self._rewrite_cluster(cluster_id, lambda cluster: docs.appended(cluster, annotations),
                              then)
        return annotation_ids

    def update_annotation(self, cluster_id: ObjectId, annotation: Annotation) -> None:
        """Replace the annotation with the same id on a stored cluster."""
        cluster_id = docs.as_id(cluster_id, "cluster_id")
        docs.checked([annotation], Annotation, "annotation")
        self._rewrite_cluster(cluster_id, lambda cluster: docs.replaced(cluster, annotation))

    def _rewrite_cluster(self, cluster_id: ObjectId, change: ClusterChange,
                         then: AfterRewrite | None = None) -> None:
        """Read, change and write back one cluster in a transaction, keeping `search` current."""

        def work(session) -> set[str]:
            doc = self.clusters.find_one({"_id": cluster_id}, session=session)
            if doc is None:
                raise NotFound("cluster", cluster_id)
            stored = docs.decode_cluster(doc, self._blobs([doc], session))
            before = list(stored.annotations)
            changed = change(stored)
            if changed is None:
                return docs.Documents()
            written = docs.rewritten_cluster(changed, doc, self.gridfs_threshold)
            self._put_blobs(written.blobs, session)
            self.clusters.replace_one({"_id": cluster_id}, written.clusters[0], session=session)
            if doc.get("object_id") is not None:
                self._rename(doc["object_id"], before, changed.annotations, session)
            summary = docs.summary_change(doc, written.clusters[0])
            if summary == docs.RECOUNT:
                self._summarise(doc["scene_id"], session)
            elif summary:
                self.scenes.update_one({"_id": doc["scene_id"]}, summary, session=session)
            if then is not None:
                then(before, changed, session)
            return written

        self._catalogue(self._transaction(work))

    def reindex(self, progress: Callable[[], None] | None = None) -> int:
        """Recompute what is derived from the stored data (every cluster's search keys, every
        scene's summary, the vocabulary) after an upgrade changed how it is derived: data
        stored by an older version then answers every query. Returns the clusters rewritten."""
        count, unfit = 0, []
        for scene in self.scenes.find({}, {"map": 1}):  # (clusters stored before knew no map)
            self.clusters.update_many({"scene_id": scene["_id"]},
                                      {"$set": {"search.map": scene.get("map")}})

        def fitted(cluster: Cluster) -> Cluster:
            cluster, problems = docs.fitted(cluster)
            unfit.extend(f"cluster {cluster.id}: {problem}" for problem in problems)
            return cluster

        for doc in self.clusters.find({}, {"_id": 1}).sort("_id", 1):
            try:
                self._rewrite_cluster(doc["_id"], fitted)
            except TypeHookFailed as error:  # (its search keys stay as they were)
                unfit.append(f"cluster {doc['_id']}: {error}")
            count += 1
            if progress:
                progress()
        if unfit:
            log.warning("%d annotation(s) do not fit their type, such as %s; kept as stored, "
                        "without the labels and texts of their type", len(unfit), unfit[0])
        for doc in self.scenes.find({}, {"_id": 1}).sort("_id", 1):
            self._transaction(lambda session, scene_id=doc["_id"]:
                              self._summarise(scene_id, session))
            if progress:
                progress()
        return count

    def _rename(self, object_id, before, after, session) -> None:
        """Keep the names of the object an observation is believed to be in step with the
        annotations appended to it (naming.py)."""
        believed = self.objects.find_one({"_id": object_id}, {"label_weights": 1},
                                            session=session)
        update = renamed(believed, before, after) if believed else None
        if update:
            self.objects.update_one({"_id": object_id}, update, session=session)

    def _summarise(self, scene_id: ObjectId, session) -> None:
        """Bring the scene's inline summary up to date with its (rewritten) clusters."""
        scene = self.scenes.find_one({"_id": scene_id}, docs.SUMMARY_PROJECTION, session=session)
        clusters = list(self.clusters.find({"scene_id": scene_id}, docs.SUMMARY_PROJECTION,
                                           session=session))
        self.scenes.update_one({"_id": scene_id}, {"$set": {
            docs.SUMMARY_KEY: docs.scene_summary(scene, clusters)}}, session=session)

    # --- blobs --------------------------------------------------------------------------

    def put_blob(self, data: bytes) -> str:
        """Store bytes under their content hash (in `binaries`, or GridFS when large); returns
        the blob id."""
        docs.checked([data], (bytes, bytearray, memoryview), "data")
        blob_id = content_id(data)
        self._transaction(lambda session: self._put_blobs({blob_id: data}, session))
        return blob_id

    def get_blob(self, blob_id: str) -> bytes:
        return self._blobs_by_id([blob_id])[blob_id]

    def get_blobs(self, blob_ids: Sequence[str]) -> dict[str, bytes]:
        """Several blobs at once, by id."""
        return self._blobs_by_id(list(blob_ids))

    def _put_blobs(self, blobs: dict[str, bytes], session) -> None:
        stored = [doc["_id"] for home, ids in docs.blob_homes(blobs).items()
                  for doc in self.db[home].find({"_id": {"$in": ids}}, {"_id": 1},
                                                session=session)]
        for name, documents in docs.blob_writes(blobs, stored).items():
            self.db[name].insert_many(documents, session=session)

    def _blobs(self, stored: list[dict], session=None) -> dict[str, bytes]:
        return self._blobs_by_id(docs.blob_ids(stored), session)

    def _blobs_by_id(self, blob_ids: list[str], session=None) -> dict[str, bytes]:
        """Blobs by id: from `binaries`, and those not there (large ones, or stored by an
        older version) from GridFS."""
        if not blob_ids:
            return {}
        found = {doc["_id"]: doc["data"] for doc in self.binaries.find(
            {"_id": {"$in": blob_ids}}, session=session)}
        if rest := [blob for blob in blob_ids if blob not in found]:
            found |= docs.joined_blobs(
                rest, self.chunks.find({"files_id": {"$in": rest}}, session=session))
        return found

    # --- writing ------------------------------------------------------------------------

    def _insert(self, written: docs.Documents, session) -> None:
        self._put_blobs(written.blobs, session)
        self.scenes.insert_many(written.scenes, session=session)
        if written.clusters:
            self.clusters.insert_many(written.clusters, session=session)
        self.outbox.insert_many(written.outbox, session=session)

    def _transaction(self, work, retry_unreachable: bool = True, session=None,
                     write_concern: WriteConcern | None = None):
        """Run work(session) in a transaction, in a session of its own or the one given,
        committed with the client's write concern or the one given.
        pymongo retries it for two minutes while no server can be selected; with
        `retry_unreachable=False` that is an Unavailable error at once instead (an ingest's
        caller decides whether to send again)."""

        def attempt(session):
            try:
                return work(session)
            except ServerSelectionTimeoutError as error:
                if retry_unreachable:
                    raise
                raise Unavailable(f"not stored: {reason(error)}") from None

        def run():
            if session is not None:
                return session.with_transaction(attempt, write_concern=write_concern)
            with self.client.start_session() as own:
                return own.with_transaction(attempt, write_concern=write_concern)

        try:
            return run()
        except ConfigurationError as error:
            if not sessions_refused(error):
                raise
            for pool in self._pools():
                pool.reset_without_pause()
            return run()

    def _catalogue(self, written: docs.Documents) -> None:
        """After a commit: record the stored types in `types` and the words new to this
        process in `terms` and `labels` (outside the transaction: words are derived data that
        `reindex` restores, and in a transaction they make one that outgrows the server's
        cache fail as a write conflict instead of being split)."""
        for name in self._not_yet_catalogued(written.type_names):
            self.types.replace_one({"_id": name}, catalogue_entry(name), upsert=True)
        for collection, entries in self._new_vocabulary(written).items():
            self.db[collection].bulk_write(vocabulary_upserts(entries), ordered=False)
        self._remember_words(written)

    # --- the store as a whole -----------------------------------------------------------

    def catalogue(self) -> list[dict]:
        """The types present in the store, with their fields."""
        return list(self.types.find().sort("_id"))

    def counts(self) -> dict:
        """Documents per collection and annotations/hypotheses per type."""
        present = set(self.db.list_collection_names())
        return {
            "collections": {
                name: self.db[name].estimated_document_count() if name in present else 0
                for name in COUNTED_COLLECTIONS
            },
            "types": {
                row["_id"]: row["count"]
                for row in self.clusters.aggregate(docs.TYPE_COUNT_PIPELINE)
            },
        }
