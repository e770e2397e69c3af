"""Groups of stored scans, fused between two checkpoints (docs/storage.md, "Groups").

A tile is read, staged and published once per group however many of the group's scans see
it, so scans that share tiles (a drive's consecutive scans, the views of one room) share
those costs. A group's size is bounded by a count and by the scans' reach: a scan farther
from the group's first one than :data:`GROUP_SPAN` times the sum of their radii starts a
new group. Its planner then takes the group's scans while their (scan, tile) pairs fit
:data:`GROUP_PAIRS`. A unit holds a scan or two at a time, not the group's scans, so the
pixels do not bound a group.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence

from rangefuse.engine.sensors import sensor_from_dict

from .archive import ScanArchive
from .catalog import ScanRow

__all__ = ["GROUP_PAIRS", "GROUP_SCANS", "GROUP_SPAN", "scan_groups"]

#: Most scans integrated between two checkpoints: what a cancelled or killed job loses.
GROUP_SCANS = 512
#: A scan joins a group while its origin lies within this many times the sum of its radius and
#: the group's first scan's (1: the spheres meet). A tile is written once per group: on a
#: drive of reach R and spacing s, a group of n scans writes about (2 R + n s) / n tiles'
#: worth per scan, so a span of k about s (1 + k) / k: 1.25 s at 4.
GROUP_SPAN = 4.0
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
    fewer than ``most`` scans and the scan's origin lies within :data:`GROUP_SPAN` times
    the sum of its radius and the group's first scan's. An unreadable archive entry is a
    group of its own: its fusion fails, not the groups before it."""
    group: list[str] = []
    first: ScanRow | None = None
    for row in pending:
        readable = _readable(archive, row.id)
        if first is not None and (
            not readable
            or len(group) >= most
            or math.dist(first.origin, row.origin) > GROUP_SPAN * (first.reach_m + row.reach_m)
        ):
            yield group
            group, first = [], None
        first = first or row
        group.append(row.id)
        if not readable:
            yield group
            group, first = [], None
    if group:
        yield group


def _readable(archive: ScanArchive, scan_id: str) -> bool:
    """Whether an archived scan's metadata reads (else its group's fusion says what is
    wrong)."""
    try:
        sensor_from_dict(archive.placement(scan_id)["sensor"])
    except (ValueError, TypeError, KeyError):  # ArchiveError, InvalidInputError
        return False
    return True
