"""Ways out of the memory: the typed query model, its compilation to MongoDB, the questions
(where is, where was, what is at, changes) and statistics. Start at engine.py."""
