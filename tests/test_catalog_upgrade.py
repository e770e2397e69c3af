"""Catalog version 3 (a row per tile, docs/storage.md "Catalog version 3"): catalogs of
versions 1 and 2 are rewritten when opened, a failed upgrade leaves them as they were, and
a newer one is refused."""

from __future__ import annotations

import numpy as np
import pytest
from rangefuse.engine.grid import pack_keys
from rangefuse.engine.synth import make_dataset
from rangefuse.storage import open_store

from tests.test_lidar import _pairs
from tests.test_store import PARAMS, _fill, _grid, _memory, _same_dense


@pytest.fixture(scope="module")
def room():
    return make_dataset("room", views=6)


def _catalog_to_version_2(path) -> None:
    """A version-3 catalog's ``tile_scans`` written back as version 2 held it (a row per
    scan and tile)."""
    import sqlite3

    db = sqlite3.connect(path)
    rows = db.execute("SELECT scene, tile, scans FROM tile_scans").fetchall()
    db.executescript(
        "DROP TABLE tile_scans;"
        "CREATE TABLE tile_scans(scene INTEGER NOT NULL, tile INTEGER NOT NULL, "
        "scan INTEGER NOT NULL, owner INTEGER NOT NULL, PRIMARY KEY(scene, tile, scan)) "
        "WITHOUT ROWID;"
        "CREATE INDEX tile_scans_scan ON tile_scans(scene, scan);"
        "UPDATE meta SET value = '2' WHERE key = 'version';"
    )
    db.executemany(
        "INSERT INTO tile_scans VALUES(?,?,?,?)",
        [(scene, tile, e >> 1, e & 1) for scene, tile, blob in rows
         for e in np.frombuffer(blob, "<i8").tolist()],
    )  # fmt: skip
    db.commit()
    db.close()


#: A version-2 catalog's ``tile_scans`` written back as version 1 held it (ids as text).
_CATALOG_TO_VERSION_1 = """
CREATE TABLE tile_scans_v1(
    scene_id TEXT NOT NULL, tile INTEGER NOT NULL, scan_id TEXT NOT NULL,
    owner INTEGER NOT NULL, PRIMARY KEY(scene_id, tile, scan_id)) WITHOUT ROWID;
INSERT INTO tile_scans_v1 SELECT n.id, t.tile, m.id, t.owner FROM tile_scans t
    JOIN scene_nums n ON n.num = t.scene JOIN scan_nums m ON m.num = t.scan;
DROP TABLE tile_scans;
DROP TABLE scan_nums;
ALTER TABLE tile_scans_v1 RENAME TO tile_scans;
CREATE INDEX tile_scans_scan ON tile_scans(scene_id, scan_id);
DROP TABLE scene_nums;
UPDATE meta SET value = '1' WHERE key = 'version';
"""


def _catalog_to_version(path, version: int) -> None:
    import sqlite3

    _catalog_to_version_2(path)
    if version == 1:
        db = sqlite3.connect(path)
        db.executescript(_CATALOG_TO_VERSION_1)
        db.close()


@pytest.mark.parametrize("version", [1, 2])
def test_an_older_catalog_is_upgraded_and_its_scene_goes_on(tmp_path, room, version, monkeypatch):
    """Catalog version 3 holds a row per tile (its scans in a blob): a version-2 catalog (a
    row per scan and tile) or a version-1 one (the same, ids as text) is rewritten when
    opened, and its scene removes and adds scans exactly. Version 2's rows are read in runs
    of 7 here, so that a tile's rows straddle two runs."""
    from rangefuse.storage import _catalog_schema

    monkeypatch.setattr(_catalog_schema, "_RUN", 7)
    grid = _grid()
    with open_store(tmp_path / "s", grid, PARAMS) as scene:
        _fill(scene, room.scans[:4])
        before = scene.catalog.tile_scans(scene.scene_id, pack_keys(scene.tile_keys()))
        n_rows = scene.catalog.count("tile_scans", scene.scene_id)
        catalog_path = scene.catalog.path
    assert any(len(v) > 1 for v in before.values())
    _catalog_to_version(catalog_path, version)
    with open_store(tmp_path / "s") as scene:
        assert scene.catalog._db.execute("SELECT value FROM meta").fetchone()[0] == "3"
        keys = pack_keys(scene.tile_keys())
        assert {t: sorted(v) for t, v in scene.catalog.tile_scans(scene.scene_id, keys).items()} \
            == {t: sorted(v) for t, v in before.items()}  # fmt: skip
        assert scene.catalog.count("tile_scans", scene.scene_id) == n_rows
        scene.remove(room.scans[1][0])
        left = {scan for _, scan, _ in _pairs(scene.catalog, scene.scene_id)}
        assert room.scans[1][0] not in left and room.scans[0][0] in left
        _same_dense(scene.to_dense(), _memory([room.scans[0], *room.scans[2:4]], grid).to_dense())
        _fill(scene, room.scans[4:6])
        expected = _memory([room.scans[0], *room.scans[2:6]], grid)
        _same_dense(scene.to_dense(), expected.to_dense())


def _broken_from_2(db) -> None:
    db.execute("INSERT INTO no_such_table VALUES(1)")


@pytest.mark.parametrize("version", [1, 2])
def test_an_upgrade_that_fails_leaves_the_old_version_and_a_newer_catalog_is_refused(
    tmp_path, room, monkeypatch, version
):
    import sqlite3

    from rangefuse.storage import _catalog_schema
    from rangefuse.storage.catalog import Catalog, CatalogError

    with open_store(tmp_path / "s", _grid(), PARAMS) as scene:
        _fill(scene, room.scans[:2])
        path = scene.catalog.path
    _catalog_to_version(path, version)
    db = sqlite3.connect(path)
    rows = db.execute("SELECT * FROM tile_scans ORDER BY 1, 2, 3").fetchall()
    db.close()
    assert rows
    if version == 1:
        broken = (*_catalog_schema._FROM_1[:-1], "INSERT INTO no_such_table VALUES(1)")
        monkeypatch.setattr(_catalog_schema, "_FROM_1", broken)
    else:
        monkeypatch.setattr(_catalog_schema, "_from_2", _broken_from_2)
    with pytest.raises(CatalogError, match=f"from version {version} to 3 failed.*no_such_table"):
        Catalog(path)
    db = sqlite3.connect(path)
    assert db.execute("SELECT value FROM meta WHERE key='version'").fetchone() == (str(version),)
    assert db.execute("SELECT * FROM tile_scans ORDER BY 1, 2, 3").fetchall() == rows
    db.execute("UPDATE meta SET value = '7' WHERE key = 'version'")
    db.commit()
    db.close()
    with pytest.raises(CatalogError, match="catalog version 7, this rangefuse reads versions 1"):
        Catalog(path)
