"""Training data out of the memory: any cluster query exported as COCO, YOLO, ImageFolder or
JSONL feature vectors, each with a provenance sidecar, streamed (never all in memory).

Start at run.py: selection.py walks the selected clusters a page at a time, grouped by scene;
labels.py names each one from the chosen label source; one module per format (coco.py,
yolo.py, imagefolder.py, jsonl.py) writes entries into an archive (archive.py: a streamed zip
or a folder). Same store and same query give the same bytes.
"""
