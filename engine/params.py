"""The scene's parameters: one name per concept, everywhere.

Before the names were unified, stored scenes and archived scans recorded some parameters
under names with a unit suffix (``voxel_size_m``, ``eps_m`` ...). :func:`current_names`
reads such a record under today's names, so stores written then still open.
"""

from __future__ import annotations

from typing import Any

__all__ = ["LEGACY_NAMES", "current_names"]

#: Names that stored records used before, and the name each goes by now.
LEGACY_NAMES = {
    "voxel_size_m": "voxel_size",
    "tile_size_vox": "tile_size",
    "bounds_m": "bounds",
    "eps_m": "eps",
    "falloff_m": "falloff",
    "max_discontinuity_m": "max_discontinuity",
}


def current_names(data: dict[str, Any]) -> dict[str, Any]:
    """``data`` with every legacy key renamed (a key given under both names keeps today's)."""
    out = {LEGACY_NAMES.get(k, k): v for k, v in data.items() if k in LEGACY_NAMES}
    out.update({k: v for k, v in data.items() if k not in LEGACY_NAMES})
    return out
