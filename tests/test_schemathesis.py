"""Schemathesis over the whole API, as its OpenAPI description gives it (scene bodies by the
scene JSON Schema included): no answer is a server error, and every status an operation answers
with is one its description declares."""

from __future__ import annotations

import schemathesis
from hypothesis import HealthCheck, given, settings
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import status_code_conformance

from percept_memory.memory.settings import Settings
from percept_memory.webui.app import create_app

HOST = {"host": "127.0.0.1"}  # the guard answers for loopback names only
EXAMPLES = 20  # per operation: the whole API in well under a minute


def test_no_operation_answers_with_a_server_error_or_an_undeclared_status(store):
    app = create_app(store, Settings(consolidator=False))
    schema = schemathesis.openapi.from_asgi("/openapi.json", app, headers=HOST)
    failures = {}
    for result in schema.get_all_operations():
        operation = result.ok()

        @given(case=operation.as_strategy())
        @settings(max_examples=EXAMPLES, deadline=None, database=None,
                  suppress_health_check=list(HealthCheck))
        def answers_well(case) -> None:
            case.call_and_validate(headers=HOST,
                                   checks=[not_a_server_error, status_code_conformance])

        try:
            answers_well()
        except Exception as error:  # noqa: BLE001 - every operation's failure is reported
            failures[operation.label] = error
    assert not failures, "\n\n".join(f"{label}: {error}" for label, error in failures.items())
