"""The scan archive (storage.archive) on real files: each entry a zip of a Zarr v3 group
(layout 3), the folders of layouts 1 and 2 still read."""

from __future__ import annotations

import json
import os
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import zarr
from rangefuse.engine import NoiseModel, Scan
from rangefuse.storage import archive as archive_module
from rangefuse.storage.archive import ArchiveError, ScanArchive, check_scan_id, scan_checksum
from zarr.storage import LocalStore, ZipStore

from tests import scenes


def _scan(name: str, seed: int = 0, noise: NoiseModel | None = None) -> Scan:
    sensor = scenes.sensor(name)
    rng = np.random.default_rng(seed)
    ranges = rng.uniform(0.1, 3.0, sensor.shape).astype(np.float32)
    flat = ranges.reshape(-1).view(np.uint32)
    flat[0] = 0x7FC00000  # NaN
    flat[1] = 0xFFC00001  # a negative NaN with a payload: kept bit for bit too
    flat[2] = 0x7F800000  # +inf
    ranges[-1, :] = np.inf  # a row of no return
    pose = scenes.poses(name, 3)[seed % 3]
    return Scan(ranges, pose, sensor, noise)


@pytest.mark.parametrize("name", sorted(scenes.SENSORS))
def test_round_trip_every_sensor(tmp_path: Path, name: str) -> None:
    archive = ScanArchive(tmp_path / "scene.zarr")
    noise = NoiseModel(0.01, 0.002, falloff=0.05) if name.startswith("sph") else None
    scan = _scan(name, noise=noise)
    checksum = archive.put(name, scan, name=f"{name}.npz")
    assert checksum == scan_checksum(scan) == archive.checksum(name)
    assert checksum.startswith("sha256:") and len(checksum) == 7 + 64
    back = archive.get(name)
    assert back.range_m.dtype == np.float32
    assert back.range_m.tobytes() == scan.range_m.tobytes()
    assert back.T_W_S.tobytes() == scan.T_W_S.tobytes()
    assert back.sensor == scan.sensor
    assert back.noise == scan.noise
    assert archive.name(name) == f"{name}.npz"
    # a plain zarr group any tool can read, through zarr's ZipStore
    entry = zarr.open_group(ZipStore(archive.path / f"{name}.zip", mode="r"), mode="r")
    assert entry.attrs["sensor"] == scan.sensor.to_dict()
    assert entry.attrs["checksum"] == checksum
    assert np.array_equal(entry["range"][...], scan.range_m, equal_nan=True)


def test_ids_delete_and_missing(tmp_path: Path) -> None:
    archive = ScanArchive(tmp_path / "g")
    assert archive.ids() == []
    for scan_id in ("b-2", "a.1", "C_3"):
        archive.put(scan_id, _scan("orthographic"))
    assert archive.ids() == ["C_3", "a.1", "b-2"]
    assert "a.1" in archive and "zz" not in archive and "../x" not in archive
    archive.delete("a.1")
    archive.delete("a.1")  # already gone: nothing to do
    assert archive.ids() == ["C_3", "b-2"]
    assert not (archive.path / "a.1.zip").exists()
    assert not [p for p in archive.path.iterdir() if p.name.startswith(".")]
    with pytest.raises(ArchiveError, match="scan 'a.1' is not in the archive"):
        archive.get("a.1")
    with pytest.raises(ArchiveError, match="scan 'a.1' is not in the archive"):
        archive.checksum("a.1")


def test_duplicate_id_refused(tmp_path: Path) -> None:
    archive = ScanArchive(tmp_path / "g")
    first = _scan("pinhole_z", seed=1)
    archive.put("s1", first)
    with pytest.raises(ArchiveError, match="scan 's1' is already in the archive"):
        archive.put("s1", _scan("pinhole_z", seed=2))
    assert archive.get("s1").range_m.tobytes() == first.range_m.tobytes()
    assert archive.ids() == ["s1"]
    assert archive.remove_temporaries() == 0


@pytest.mark.parametrize(
    "bad",
    ["", ".hidden", "..", ".", "a/b", "../up", "a b", "x" * 129, "é", "a\n", "zarr.json", "a\\b"],
)
def test_bad_ids_refused(tmp_path: Path, bad: str) -> None:
    archive = ScanArchive(tmp_path / "g")
    with pytest.raises(ArchiveError, match="is not allowed: use 1 to 128 letters"):
        archive.put(bad, _scan("orthographic"))
    with pytest.raises(ArchiveError, match="is not allowed"):
        archive.get(bad)
    with pytest.raises(ArchiveError, match="is not allowed"):
        archive.delete(bad)
    assert archive.ids() == []


def test_good_ids_accepted() -> None:
    for good in ("a", "-x", "_", "scan.001", "A-b_c.d", "x" * 128, "0"):
        assert check_scan_id(good) == good
    with pytest.raises(ArchiveError, match="must be a string"):
        check_scan_id(3)  # type: ignore[arg-type]


def _rewrite(entry: Path, name: str, change: Callable[[bytes], bytes | None]) -> None:
    """Rewrite the member ``name`` of an entry's zip (``change`` returns None: drop it)."""
    with zipfile.ZipFile(entry) as zf:
        members = {n: zf.read(n) for n in zf.namelist()}
    with zipfile.ZipFile(entry, "w") as zf:
        for n, content in members.items():
            new = change(content) if n == name else content
            if new is not None:
                zf.writestr(n, new)


def _flip(content: bytes) -> bytes:
    data = bytearray(content)
    data[len(data) // 2] ^= 0x01
    return bytes(data)


def test_corrupt_range_chunk_detected(tmp_path: Path) -> None:
    archive = ScanArchive(tmp_path / "g")
    archive.put("s", _scan("pinhole_ray"))
    _rewrite(archive.path / "s.zip", "range/c/0/0", _flip)
    with pytest.raises(ArchiveError, match="scan 's'"):
        archive.get("s")
    (archive.path / "t.zip").write_bytes(b"not a zip")
    with pytest.raises(ArchiveError, match="scan 't': archive entry is unreadable"):
        archive.get("t")


def test_tampered_pose_fails_the_checksum(tmp_path: Path) -> None:
    archive = ScanArchive(tmp_path / "g")
    archive.put("s", _scan("spherical"))

    def nudge(content: bytes) -> bytes:
        meta = json.loads(content)
        meta["attributes"]["pose"][0][3] += 1e-9
        return json.dumps(meta).encode()

    _rewrite(archive.path / "s.zip", "zarr.json", nudge)
    with pytest.raises(ArchiveError, match="scan 's': checksum mismatch"):
        archive.get("s")


def test_missing_parts_detected(tmp_path: Path) -> None:
    archive = ScanArchive(tmp_path / "g")
    archive.put("s", _scan("linescan"))
    archive.put("t", _scan("linescan"))
    _rewrite(archive.path / "s.zip", "range/c/0/0", lambda _: None)
    with pytest.raises(ArchiveError, match="scan 's': .*missing"):
        archive.get("s")
    _rewrite(archive.path / "t.zip", "zarr.json", lambda _: None)
    with pytest.raises(ArchiveError, match="scan 't': archive entry is incomplete"):
        archive.get("t")


def test_temporaries_removed_and_ignored(tmp_path: Path) -> None:
    archive = ScanArchive(tmp_path / "g")
    archive.put("kept", _scan("orthographic"))
    leftover = archive.path / ".tmp-lost-0123456789abcdef.zip"  # a put killed midway
    leftover.write_bytes(b"PK")
    old = archive.path / ".tmp-older-0123456789abcdef"  # one of layout 2
    (old / "range").mkdir(parents=True)
    (old / "zarr.json").write_text("{}")
    assert archive.ids() == ["kept"]
    assert archive.remove_temporaries() == 2
    assert not leftover.exists() and not old.exists()
    assert archive.ids() == ["kept"]
    assert archive.remove_temporaries() == 0


def test_failed_rename_leaves_nothing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    archive = ScanArchive(tmp_path / "g")
    link = os.link

    def refuse(src: str | Path, dst: str | Path) -> None:
        # Only the entry's own link fails: zarr-python creates the group with os.link too
        # (its exclusive writes), and failing those made the group's creation fail instead,
        # with its concurrent writes still in flight when the folder was listed.
        if str(dst).endswith(archive_module.ENTRY_SUFFIX):
            raise OSError("disk on fire")
        link(src, dst)

    monkeypatch.setattr(archive_module.os, "link", refuse)
    with pytest.raises(OSError, match="disk on fire"):
        archive.put("s", _scan("orthographic"))
    assert archive.ids() == []
    assert [p.name for p in archive.path.iterdir()] == ["zarr.json"]


def _zarr_python_entry(path: Path, scan: Scan, attrs: dict | None = None) -> None:
    """What zarr-python writes for an entry's group at ``path`` (a folder: the entries of
    layouts 1 and 2 were these files)."""
    group = zarr.create_group(LocalStore(path), zarr_format=3, attributes=attrs or {})
    group.create_array(
        "range",
        data=scan.range_m,
        chunks=scan.range_m.shape,
        fill_value=np.float32("nan"),
        compressors=zarr.codecs.ZstdCodec(level=archive_module.RANGE_ZSTD_LEVEL),
        config={"write_empty_chunks": True},
    )


def test_entries_are_what_zarr_python_writes(tmp_path: Path) -> None:
    """The archive writes its entries without zarr-python; the metadata is the same as
    zarr-python writes for the same array, and the chunk the same bytes."""
    scan = _scan("pinhole_z")
    ScanArchive(tmp_path / "scene.zarr").put("a", scan)
    _zarr_python_entry(tmp_path / "theirs", scan)
    theirs = tmp_path / "theirs" / "range"
    with zipfile.ZipFile(tmp_path / "scene.zarr" / "scans" / "a.zip") as ours:
        assert {i.compress_type for i in ours.infolist()} == {zipfile.ZIP_STORED}
        assert json.loads(ours.read("range/zarr.json")) == json.loads(
            (theirs / "zarr.json").read_text()
        )
        assert ours.read("range/c/0/0") == (theirs / "c" / "0" / "0").read_bytes()


def test_entries_of_earlier_layouts_are_read_listed_and_deleted(tmp_path: Path) -> None:
    """A folder entry, as layouts 1 and 2 wrote it, beside the files of layout 3."""
    archive = ScanArchive(tmp_path / "scene.zarr")
    new, old = _scan("pinhole_z", seed=1), _scan("spherical", seed=2)
    archive.put("new", new)
    attrs = {"sensor": old.sensor.to_dict(), "pose": old.T_W_S.tolist(), "noise": None,
             "name": "old.npz", "checksum": scan_checksum(old)}  # fmt: skip
    _zarr_python_entry(archive.path / "old", old, attrs)
    assert archive.ids() == ["new", "old"] and "old" in archive
    back = archive.get("old")
    assert back.range_m.tobytes() == old.range_m.tobytes() and archive.name("old") == "old.npz"
    with pytest.raises(ArchiveError, match="scan 'old' is already in the archive"):
        archive.put("old", new)
    archive.delete("old")
    assert archive.ids() == ["new"] and not (archive.path / "old").exists()
    assert archive.remove_temporaries() == 0


def test_publishing_several_staged_scans_at_once(tmp_path: Path) -> None:
    archive = ScanArchive(tmp_path / "scene.zarr")
    scans = {f"s{i}": _scan("pinhole_z", seed=i) for i in range(5)}
    staged = [archive.stage(k, v) for k, v in scans.items()]
    assert archive.ids() == []  # staged: not visible yet
    archive.publish(staged)
    assert archive.ids() == sorted(scans)
    for k, v in scans.items():
        assert archive.get(k).range_m.tobytes() == v.range_m.tobytes()
    # a batch with one id already archived publishes nothing of its own
    again = [archive.stage("t0", scans["s0"]), archive.stage("t1", scans["s1"])]
    (tmp_path / "scene.zarr" / "scans" / "t1.zip").write_text("taken")  # never overwritten
    with pytest.raises(ArchiveError, match="already in the archive"):
        archive.publish(again)
    assert "t0" not in archive.ids()
    assert (tmp_path / "scene.zarr" / "scans" / "t1.zip").read_text() == "taken"
    assert not [p for p in (tmp_path / "scene.zarr" / "scans").iterdir() if p.name.startswith(".")]


def test_the_checksum_is_the_documented_one() -> None:
    """SHA-256 over the ranges, the pose, the sensor and noise JSON, each after its length:
    what every stored entry carries, whatever the layout (strided input included)."""
    scan = _scan("pinhole_z")
    import hashlib

    h = hashlib.sha256()
    for part in (
        np.ascontiguousarray(scan.range_m, "<f4").tobytes(),
        np.ascontiguousarray(scan.T_W_S, "<f8").tobytes(),
        json.dumps(scan.sensor.to_dict(), sort_keys=True).encode(),
        b"null",
    ):
        h.update(len(part).to_bytes(8, "little"))
        h.update(part)
    assert scan_checksum(scan) == "sha256:" + h.hexdigest()
