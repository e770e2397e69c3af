"""Groups of stored scans, fused between two checkpoints (docs/storage.md, "Groups").

A tile is read, staged and published once per group however many of the group's scans see
it, so scans that share tiles (a drive's consecutive scans, the views of one room) share
those costs. A group's size is bounded by a count, by the pixels its units hold, and by
the scans' reach: a scan farther from the group's first one than :data:`GROUP_SPAN` times
the sum of their radii starts a new group. Its planner then takes the group's scans while
their (scan, tile) pairs fit :data:`GROUP_PAIRS`.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence

from rangefuse.engine.sensors import sensor_from_dict

from .archive import ScanArchive
from .catalog import ScanRow

__all__ = ["GROUP_PAIRS", "GROUP_PIXELS", "GROUP_SCANS", "GROUP_SPAN", "scan_groups"]

#: Most scans integrated between two checkpoints.
GROUP_SCANS = 128
#: Most pixels in a group's scans: each unit of a group holds the scans it fuses.
GROUP_PIXELS = 2**23
#: A scan joins a group while its origin lies within this many times the sum of its radius and
#: the group's first scan's (1: the spheres meet). A tile is written once per group: on a
#: drive of reach R and spacing s, about (2 R + n s) / n tiles' worth per scan for n scans.
GROUP_SPAN = 1.5
#: Most (scan, tile) pairs in a group's plan: each scan's allocated tiles and the tiles it may
#: have in view, and the created tiles earlier scans may see (``engine.planner.plan_add``'s
#: ``max_pairs``). A group's plan, its views and its units hold arrays of these pairs, and
#: the count does not follow from the others: a 1 cm scan of a street has about a million
#: tiles of 16^3 in reach, a 10 cm one a few thousand. The planner takes the scans of a
#: group while they fit; the next group starts with the rest. 2^25 keeps the 128 m street at
#: 1 cm under 1.5 GB with a 512 MB cache (peak 1,412 MB; ``docs/lidar.md``, "Memory between a
#: store's groups").
GROUP_PAIRS = 2**25


def scan_groups(
    pending: Sequence[ScanRow], archive: ScanArchive, most: int = GROUP_SCANS
) -> Iterator[list[str]]:
    """The ids of ``pending`` (in order) in groups: a group takes the next scan while it has
    fewer than ``most`` scans and :data:`GROUP_PIXELS` pixels, and the scan's origin lies
    within :data:`GROUP_SPAN` times the sum of its radius and the group's first scan's. An
    unreadable archive entry is a group of its own: its fusion fails, not the groups before
    it."""
    group: list[str] = []
    first: ScanRow | None = None
    pixels = 0
    for row in pending:
        n = _pixels(archive, row.id)
        if first is not None and (
            len(group) >= most
            or pixels + n > GROUP_PIXELS
            or math.dist(first.origin, row.origin) > GROUP_SPAN * (first.reach_m + row.reach_m)
        ):
            yield group
            group, first, pixels = [], None, 0
        first = first or row
        group.append(row.id)
        pixels += n
    if group:
        yield group


def _pixels(archive: ScanArchive, scan_id: str) -> int:
    """Pixels of an archived scan, from its metadata; an unreadable entry counts as more
    than a group holds (a group of its own, whose fusion says what is wrong)."""
    try:
        h, w = sensor_from_dict(archive.placement(scan_id)["sensor"]).shape
    except (ValueError, TypeError, KeyError):  # ArchiveError, InvalidInputError
        return GROUP_PIXELS + 1
    return h * w
