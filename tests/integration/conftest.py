"""Teardown shared by the integration tests."""

from __future__ import annotations

import sys
from collections.abc import Iterator

import pytest


@pytest.fixture(autouse=True)
def _close_live_rigs() -> Iterator[None]:
    """Stop any `hil up` a test started through test_supervision.Rig and did not finish (it failed
    half-way): the rig's processes and its hub session must not outlive the test."""
    yield
    mod = sys.modules.get("tests.integration.test_supervision")
    if mod is not None:
        mod.Rig.close_all()
