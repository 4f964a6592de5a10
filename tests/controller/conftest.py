"""The controller's async tests run on asyncio (anyio's pytest plugin asks this fixture)."""

import pytest


@pytest.fixture
def anyio_backend() -> str:
    return "asyncio"
