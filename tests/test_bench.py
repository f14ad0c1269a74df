"""The benchmark scripts still run and print their JSON (tiny sizes; no timing asserted)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench"


@pytest.mark.parametrize("script, args, keys", [
    ("converter.py", ["--clusters", "20", "--scenes", "6"], {"codec", "store"}),
    ("ingest.py", ["--scenes", "8", "--batch", "4", "--rounds", "1"],
     {"in_process_clusters_per_s", "http_to_in_process", "each_round"}),
    ("pipeline.py", ["--days", "1", "--synthetic-scenes", "10", "--lag-scenes", "10",
                     "--rate", "20"], {"throughput", "belief_lag_over_http"}),
    ("identity.py", ["--scenes-per-level", "40", "--levels", "0.025"], {"levels"}),
    ("catalogue.py", ["--seeds", "1", "--models", "200", "--entries", "500", "--repeat", "10",
                      "--stage-entries", "100", "--stage-scenes", "3", "--days", "1",
                      "--protocol-scenes", "40", "--protocol-seeds", "1"],
     {"simulation", "learner_cost", "stage_cost", "kitchen_week", "identity_protocol"}),
    ("belief.py", ["--quick"], {"levels", "seeds_reported", "targets_at_lowest_noise",
                                "real_data"}),
    ("queries.py", ["--clusters", "3000", "--samples", "3"], {"queries"}),
    ("export.py", ["--clusters", "300", "--sizes", "100,300", "--formats", "imagefolder"],
     {"exports"}),
    ("similarity.py", ["--days", "1", "--every", "10", "--vectors", "3000", "--scenes", "10",
                       "--words", "500", "--clustered", "2000", "--mongodb", "2000",
                       "--rounds", "1"],
     {"kitchen_week", "robosherlock_ground_truth", "meaning", "at_scale", "clustered_recall",
      "through_mongodb", "ingest"}),
    ("enrichment.py", ["--slots", "8", "--jobs-per-slot", "3", "--scenes", "20", "--days", "1",
                       "--hashes", "10000"], {"lookups_per_s", "ingest", "kitchen_week_cache"}),
    ("curation.py", ["--days", "1", "--repeat", "2"], {"keyboard", "review_page", "rejection"}),
    # FiftyOne is not installed here: its side is skipped, ours still measured
    ("vs_fiftyone.py", ["--count", "300", "--reps", "1", "--export", "50"],
     {"ingest", "queries", "footprint", "export_coco", "fiftyone"}),
    ("webui.py", ["--repeat", "2", "--map-days", "1", "--search-clusters", "3000",
                  "--playback-scenes", "3000", "--annotator-clusters", "3000",
                  "--facet-scenes", "3000"],
     {"scene_page_20_clusters", "depth_png", "map_page", "search_page", "solid_views",
      "playback", "annotators_page", "facets"}),
])
def test_benchmark_prints_its_json(mongo_uri, script, args, keys):
    done = subprocess.run([sys.executable, str(BENCH / script), *args], capture_output=True,
                          text=True, timeout=300, env={**os.environ, "MONGODB_URI": mongo_uri})
    assert done.returncode == 0, done.stderr[-2000:]
    assert keys <= set(json.loads(done.stdout))
