"""percept-memory: a long-term spatio-temporal memory for robot perception.

Folders, with dependencies pointing one way: converters <- memory <- {ingest, queries} <- webui.
"""
