"""The importers' error. Warnings are returned as strings (``ImportResult.warnings``)."""

from __future__ import annotations

from ..dataset import DatasetError

__all__ = ["SourceError"]


class SourceError(DatasetError):
    """A source in a foreign format that cannot be read; the message names the file (and
    line, for text files) and what is wrong. A :class:`storage.DatasetError`, so the
    command line reports it like any other bad dataset (exit status 2)."""
