"""The errors of the ways in, apart from the code that raises them, so that catching them
(the CLI does, around every command) imports nothing heavy."""

from __future__ import annotations


class IngestError(ValueError):
    """Input that is not a valid scene. `problems` holds one entry per problem: which item of
    the batch, the field path (e.g. `clusters.0.annotations.2.confidence`) and what is wrong.
    The message is one line (the CLI prints it as `Error: ...`)."""

    def __init__(self, problems: list[dict]):
        self.problems = problems
        named = [f"{p['item']}: {p['path'] or '(scene)'}: {p['message']}" for p in problems[:10]]
        more = f"; ... and {len(problems) - 10} more" if len(problems) > 10 else ""
        super().__init__(f"{len(problems)} problem(s) in the input: " + "; ".join(named) + more)


class SourceError(ValueError):
    """A file, folder or database that cannot be read as percepts; the message names it and
    says what is wrong (importers' errors derive from this)."""


class BackendSetupError(ValueError):
    """A backend cannot be set up as configured (no URL, no catalogue): the message says why."""
