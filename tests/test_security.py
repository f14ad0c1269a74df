"""Who may read and write (README: Security), through the real app on the real store."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

from percept_memory.memory.settings import Settings
from percept_memory.webui.app import create_app


@pytest.fixture(scope="module")
def client(store):
    return TestClient(create_app(store, Settings()), base_url="http://127.0.0.1:8000")


def test_a_wrong_method_gets_405_with_allow(client):
    response = client.get("/api/scenes")
    assert response.status_code == 405
    assert response.headers["allow"] == "POST"
    assert response.json()["error"]["status"] == 405
