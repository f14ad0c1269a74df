"""The OpenAPI description, and Schemathesis over the whole API as it gives it (scene bodies by
the scene JSON Schema included): no answer is a server error, and every status an operation
answers with is one its description declares."""

from __future__ import annotations

import schemathesis
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, given, settings
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import status_code_conformance

from percept_memory.memory.settings import Settings
from percept_memory.memory.types import Scene
from percept_memory.webui.app import create_app

from .conftest import LOCAL

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


def test_the_description_types_parameters_declares_errors_and_takes_scenes(store):
    app = create_app(store, Settings(consolidator=False))
    description = TestClient(app, base_url=LOCAL).get("/openapi.json").json()
    parameters = {p["name"]: p["schema"]
                  for p in description["paths"]["/api/clusters"]["get"]["parameters"]}
    assert parameters["limit"] == {"type": "integer", "minimum": 0, "maximum": 500, "default": 50}
    assert parameters["count"]["type"] == "boolean"
    assert parameters["sort"]["enum"] == ["newest", "oldest", "relevance", "distance"]
    assert parameters["region"]["type"] == "array"
    assert parameters["sphere"] == {"type": "string"}  # x,y,z,radius
    for path, operations in description["paths"].items():
        for method, operation in operations.items():
            errors = {status: response["content"]["application/json"]["schema"]
                      for status, response in operation["responses"].items()
                      if status.startswith(("4", "5"))}
            assert {"400", "422", "503"} <= set(errors), (method, path)
            assert all(s == {"$ref": "#/components/schemas/ErrorResponse"}
                       for s in errors.values())
    body = description["paths"]["/api/scenes"]["post"]["requestBody"]
    scene = {"$ref": "#/components/schemas/Scene"}
    assert body["content"]["application/json"]["schema"]["oneOf"][0] == scene
    assert description["components"]["schemas"]["Scene"]["properties"] == \
        Scene.model_json_schema(ref_template="#/components/schemas/{model}")["properties"]
