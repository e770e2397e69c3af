"""Fixtures shared by several test modules."""

from __future__ import annotations

import pytest
from rangefuse.engine.synth import SyntheticDataset, make_dataset


@pytest.fixture(scope="module")
def datasets() -> dict[str, SyntheticDataset]:
    """One small dataset per synthetic scene."""
    return {
        "object": make_dataset("object", views=3),
        "room": make_dataset("room", views=3),
        "street": make_dataset("street", views=2),
    }
