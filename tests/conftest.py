"""Fixtures shared by several test modules."""

from __future__ import annotations

import pytest

# first: it points numba's cache at the machine's one folder (docs/scale-out.md), shared with
# the command line, the service and the workers these tests start
import rangefuse.service  # noqa: F401
from rangefuse.engine.synth import SyntheticDataset, make_dataset


@pytest.fixture(scope="module")
def datasets() -> dict[str, SyntheticDataset]:
    """One small dataset per synthetic scene."""
    return {
        "object": make_dataset("object", views=3),
        "room": make_dataset("room", views=3),
        "street": make_dataset("street", views=2),
    }
