"""Store maintenance: verify catches missing and corrupt chunks, symlinks and special files
(never read through them); gc rules for debris and links."""

from __future__ import annotations

import json
import os
import time
import uuid
from pathlib import Path

import numpy as np
import pytest

from mocapflow.pipeline import store_maintenance
from mocapflow.pipeline.codecs import encode
from mocapflow.pipeline.show import entry_summary
from mocapflow.pipeline.store import EntryNotFoundError, Store, StoreError
from tests.pipeline.helpers import sample_outputs

# --------------------------------------------------------------------------- verify


def _chunk_files(entry: Path, output: str, array: str) -> list[Path]:
    return sorted(p for p in (entry / output / array / "c").rglob("*") if p.is_file())


def test_verify_catches_deleted_and_corrupted_chunks(tmp_path):
    st = Store(tmp_path, chunk_frames=4)
    st.commit("clean", "k1", sample_outputs(12), {})
    st.commit("clean", "k2", sample_outputs(12), {})
    assert st.verify() == []
    e1 = Path(st.entry_path("clean", "k1"))
    chunks = _chunk_files(e1, "markers", "positions")
    assert len(chunks) == 3
    chunks[1].unlink()
    # Zarr itself does not notice: the missing chunk reads back as the fill value
    silently = st.load("clean", "k1", "markers").arrays["positions"][0]
    assert np.all(silently[4:8] == 0.0)
    problems = st.verify()
    assert any("clean/k1: missing file markers/positions/c/1/0/0" in p for p in problems)
    assert any(p.startswith("clean/k1/markers: digest mismatch") for p in problems)
    assert not any("clean/k2" in p for p in problems)

    e2 = Path(st.entry_path("clean", "k2"))
    target = _chunk_files(e2, "record", "basis")[0]
    data = bytearray(target.read_bytes())
    data[len(data) // 2] ^= 0x01
    target.write_bytes(bytes(data))
    (e2 / "record" / "stray.bin").write_bytes(b"x")
    problems = st.verify(entries=[("clean", "k2")])
    assert any(p.startswith("clean/k2: corrupt chunk record/basis/c/0/0") for p in problems)
    assert "clean/k2: unexpected file record/stray.bin" in problems
    assert st.verify(entries=[("clean", "nope")]) == ["clean/nope: not committed (no readable "
                                                       "_COMMIT.json)"]


def test_verify_on_memory_url():
    import fsspec

    name = f"mocapflow-test-{uuid.uuid4().hex[:8]}"
    st = Store(f"memory://{name}", chunk_frames=4)
    st.commit("clean", "k1", sample_outputs(12), {})
    assert st.verify() == []
    fs = fsspec.filesystem("memory")
    fs.rm(f"/{name}/entries/clean/k1/markers/positions/c/2/0/0")
    problems = st.verify()
    assert any("missing file markers/positions/c/2/0/0" in p for p in problems)
    assert any("digest mismatch" in p for p in problems)
    fs.rm(f"/{name}", recursive=True)


# --------------------------------------------------------------------------- gc


def test_half_written_url_entry_is_collected():
    import fsspec

    name = f"mocapflow-test-{uuid.uuid4().hex[:8]}"
    st = Store(f"memory://{name}")
    st.commit("s", "a", {"x": encode(np.arange(3.0))}, {})
    st.commit("s", "b", {"x": encode(np.arange(4.0))}, {})
    fs = fsspec.filesystem("memory")
    fs.rm(f"/{name}/entries/s/b/_COMMIT.json")  # as if the writer died before the manifest
    assert not st.has("s", "b") and st.entries() == [("s", "a")] and st.verify() == []
    report = st.gc()
    assert report["incomplete"] == [f"memory:///{name}/entries/s/b"]
    assert not fs.exists(f"/{name}/entries/s/b") and st.has("s", "a")
    st.gc(keep=set())
    assert st.entries() == []
    fs.rm(f"/{name}", recursive=True)


def test_gc_rules(tmp_path):
    st = Store(tmp_path)
    for k in ("a", "b", "c"):
        st.commit("s", k, {"x": encode(np.arange(3.0) + ord(k))}, {})
    staging = tmp_path / "staging"
    live = staging / "s-live-1"
    live.mkdir(parents=True)
    (live / "_WRITER.json").write_text(json.dumps(store_maintenance.writer_info()))  # us: alive
    unknown = staging / "s-unknown-1"
    unknown.mkdir()
    report = st.gc(staging_min_age_s=3600)
    assert report["staging"] == [] and live.exists() and unknown.exists()
    old = time.time() - 7200
    os.utime(unknown, (old, old))
    report = st.gc(staging_min_age_s=3600, keep={("s", "a"), ("s", "c")}, dry_run=True)
    assert report["staging"] == [str(unknown)]
    assert report["unreachable"] == [st.entry_path("s", "b")]
    assert st.has("s", "b") and unknown.exists()
    st.gc(staging_min_age_s=3600, keep={("s", "a"), ("s", "c")})
    assert st.entries() == [("s", "a"), ("s", "c")] and not unknown.exists() and live.exists()
    assert st.delete("s", "a") and not st.has("s", "a") and not st.delete("s", "a")


# --------------------------------------------------------------------------- symlinks


def _linked_store(tmp_path):
    """A store whose entry s/far is a symlink to an entry of another store (outside)."""
    st = Store(tmp_path / "s")
    st.commit("s", "near", {"x": encode(np.arange(3.0))}, {})
    other = Store(tmp_path / "elsewhere")
    other.commit("s", "far", {"x": encode(np.arange(5.0))}, {})
    target = Path(other.entry_path("s", "far"))
    (tmp_path / "s" / "entries" / "s" / "far").symlink_to(target)
    return st, target


def test_symlinked_entry_is_flagged_and_never_followed(tmp_path):
    st, target = _linked_store(tmp_path)
    assert st.entries() == [("s", "near")]
    assert not st.has("s", "far") and st.manifest("s", "far") is None
    problems = st.verify()
    assert problems == [f"s/far: the entry directory is a symlink to {target} (not followed)"]
    assert st.verify(entries=[("s", "far")]) == problems
    with pytest.raises(EntryNotFoundError, match=r"\(the entry directory is a symlink to "):
        st.load("s", "far", "x")
    # a run recomputing it replaces the link by a real entry; the target is untouched
    st.commit("s", "far", {"x": encode(np.arange(5.0))}, {})
    assert not (tmp_path / "s" / "entries" / "s" / "far").is_symlink()
    assert st.verify() == [] and (target / "_COMMIT.json").is_file()


def test_symlinked_chunk_and_stage_dir_are_flagged(tmp_path):
    st = Store(tmp_path / "s", chunk_frames=4)
    st.commit("clean", "k1", sample_outputs(12), {})
    chunk = _chunk_files(Path(st.entry_path("clean", "k1")), "markers", "positions")[1]
    outside = tmp_path / "secret.bin"
    outside.write_bytes(chunk.read_bytes())  # the same bytes: only the link is wrong
    chunk.unlink()
    chunk.symlink_to(outside)
    rel = chunk.relative_to(st.entry_path("clean", "k1"))
    assert st.verify() == [f"clean/k1: {rel} is a symlink to {outside} (not followed)"]
    with pytest.raises(StoreError, match=r"^entry clean/k1: markers/positions/c/1/0/0 is a "
                                         r"symlink to .*; refusing to read it"):
        st.load_outputs("clean", "k1")
    with pytest.raises(StoreError, match="refusing to read it"):
        entry_summary(st, "clean", "k1")
    # a symlinked stage directory: not listed, reported, never written through
    other = Store(tmp_path / "o")
    other.commit("t", "k", {"x": encode(np.arange(2.0))}, {})
    (tmp_path / "s" / "entries" / "t").symlink_to(tmp_path / "o" / "entries" / "t")
    assert ("t", "k") not in st.entries() and not st.has("t", "k")
    assert f"entries/t is a symlink to {tmp_path / 'o' / 'entries' / 't'} (not followed)" in (
        st.verify())
    with pytest.raises(StoreError, match=r"entries/t is a symlink to .*; not writing through"):
        st.commit("t", "k2", {"x": encode(np.arange(2.0))}, {})
    assert sorted(os.listdir(tmp_path / "o" / "entries" / "t")) == ["k"]


def test_gc_removes_links_not_their_targets(tmp_path):
    st, target = _linked_store(tmp_path)
    report = st.gc()
    assert report["incomplete"] == [str(tmp_path / "s" / "entries" / "s" / "far")]
    assert report["bytes"] == 0  # nothing outside the store is measured
    assert not os.path.lexists(tmp_path / "s" / "entries" / "s" / "far")
    assert (target / "_COMMIT.json").is_file() and st.verify() == []


def test_verify_and_show_never_open_a_fifo(tmp_path, cli_proc):
    """A chunk replaced by a FIFO (a read would block for ever): flagged, not opened."""
    st = Store(tmp_path / "s", chunk_frames=4)
    st.commit("clean", "k1", sample_outputs(12), {})
    entry = Path(st.entry_path("clean", "k1"))
    chunk = _chunk_files(entry, "markers", "positions")[0]
    chunk.unlink()
    os.mkfifo(chunk)
    os.mkfifo(entry / "markers" / "zarr.json.fifo")
    (entry / "markers" / "zarr.json").unlink()
    os.rename(entry / "markers" / "zarr.json.fifo", entry / "markers" / "zarr.json")
    p = cli_proc("verify", "--store", tmp_path / "s")
    out, err = p.communicate(timeout=60)
    assert p.returncode == 1 and sorted(out.splitlines()) == [
        "clean/k1: markers/positions/c/0/0/0 is not a regular file (not followed)",
        "clean/k1: markers/zarr.json is not a regular file (not followed)"]
    p = cli_proc("show", "clean/k1", "--store", tmp_path / "s")
    out, err = p.communicate(timeout=60)
    assert p.returncode == 1 and len(err.strip().splitlines()) == 1, err
    assert "is not a regular file (not followed)" in err and "refusing to read it" in err
