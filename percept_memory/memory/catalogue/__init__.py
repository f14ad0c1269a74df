"""The long-term object catalogue (Duceux ch. 5-6): what the objects of a home look like,
learnt from partial views without supervision.

- graph_of_views.py: the model (views as nodes, co-occurrence as edges) and its measures;
- learning.py: incremental clustering of partial models by their similarity graph;
- views.py: an observation's view descriptors, declared by the evidence types themselves;
- stage.py: the memory pipeline stage that keeps each map's catalogue in MongoDB.
"""
