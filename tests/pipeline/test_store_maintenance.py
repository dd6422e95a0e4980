"""Store maintenance: verify catches missing and corrupt chunks; gc rules for debris."""

from __future__ import annotations

import json
import os
import time
import uuid
from pathlib import Path

import numpy as np

from mocapflow.pipeline import store_maintenance
from mocapflow.pipeline.codecs import encode
from mocapflow.pipeline.store import Store
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
