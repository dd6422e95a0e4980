"""The store: exact round trips on every backend, commit once, crash safety, races."""

from __future__ import annotations

import errno
import json
import os
import pickle
import re
import shlex
import shutil
import signal
import subprocess
import sys
import textwrap
import time
import uuid
from pathlib import Path

import numpy as np
import pytest

from mocapflow.pipeline import store as store_mod
from mocapflow.pipeline import store_zarr
from mocapflow.pipeline.codecs import Encoded, digest_encoded, encode
from mocapflow.pipeline.store import EntryNotFoundError, Store, StoreAccessError
from mocapflow.pipeline.store_backends import LocalBackend
from tests.pipeline.helpers import sample_outputs

REPO = Path(__file__).resolve().parents[2]


# --------------------------------------------------------------------------- fixtures


def _same_array(a: np.ndarray, b: np.ndarray) -> bool:
    return (
        a.shape == b.shape
        and a.dtype.newbyteorder("=") == b.dtype.newbyteorder("=")
        and a.tobytes() == b.astype(a.dtype).tobytes()
    )


@pytest.fixture(params=["local", "memory", "file-url", "direct"])
def any_store(request, tmp_path):
    if request.param == "local":
        yield Store(tmp_path / "store", chunk_frames=4)
    elif request.param == "file-url":
        yield Store(f"file://{tmp_path}/store", chunk_frames=4)
    elif request.param == "direct":  # in-place writes, manifest last (the fsspec protocol)
        yield Store(tmp_path / "store", chunk_frames=4, atomic_rename=False)
    else:
        import fsspec

        name = f"mocapflow-test-{uuid.uuid4().hex[:8]}"
        yield Store(f"memory://{name}", chunk_frames=4)
        fsspec.filesystem("memory").rm(f"/{name}", recursive=True)


# --------------------------------------------------------------------------- round trip


def test_round_trip_exact(any_store):
    st = any_store
    outs = sample_outputs()
    assert not st.has("clean", "k1")
    digests = st.commit("clean", "k1", outs, {"components": {"params": {"alpha1": 0.5}}})
    assert st.has("clean", "k1") and st.entries() == [("clean", "k1")]
    back = st.load_outputs("clean", "k1")
    assert set(back) == set(outs)
    for name, enc in outs.items():
        got = back[name]
        assert got.type == enc.type
        assert digest_encoded(got) == digests[name], name
        assert set(got.arrays) == set(enc.arrays)
        for an, (arr, dims) in enc.arrays.items():
            garr, gdims = got.arrays[an]
            assert gdims == tuple(dims), (name, an)
            if arr.dtype == object:
                assert garr.dtype.kind == "U" and garr.tolist() == arr.tolist()
            else:
                assert _same_array(arr, garr), (name, an)
    pos = back["markers"].arrays["positions"][0]
    assert pos.dtype == np.float64 and np.isnan(pos[2, 1]).all() and np.isnan(pos[5:, 3]).all()
    assert np.array_equal(pos, outs["markers"].arrays["positions"][0], equal_nan=True)
    attrs = back["markers"].attrs
    assert attrs["big"] == 2**60 and attrs["rate"] == 120.0 and np.isnan(attrs["nan"])
    assert attrs["first_frame"] == 7 and attrs["names"] == ["a"] and attrs["by_id"] == {"3": "x"}
    assert back["report"].attrs == outs["report"].attrs
    assert back["empty"].arrays["data"][0].shape == (0, 5, 3)
    one = st.load("clean", "k1", "record")
    assert np.array_equal(one.arrays["basis"][0], outs["record"].arrays["basis"][0])
    man = st.manifest("clean", "k1")
    assert man["stage"] == "clean" and man["key"] == "k1" and man["format"] == 1
    assert man["components"] == {"params": {"alpha1": 0.5}}
    assert man["outputs"]["markers"] == {"digest": digests["markers"], "type": "markers"}
    assert store_mod.output_digests(outs) == digests
    assert "committed_at" in man
    assert st.verify() == []


def test_commit_existing_entry_writes_nothing(tmp_path):
    st = Store(tmp_path)
    d1 = st.commit("s", "k", {"x": encode(np.arange(3.0))}, {"n": 1})
    man = Path(st.entry_path("s", "k")) / "_COMMIT.json"
    before = man.read_bytes()
    d2 = st.commit("s", "k", {"x": encode(np.arange(3.0))}, {"n": 2})
    assert d1 == d2 and man.read_bytes() == before


def test_errors_name_what_is_wrong(tmp_path, monkeypatch):
    st = Store(tmp_path)
    with pytest.raises(EntryNotFoundError, match="clean/nokey"):
        st.load("clean", "nokey", "markers")
    st.commit("s", "k", {"x": encode(np.arange(3.0))}, {})
    with pytest.raises(EntryNotFoundError, match="no output 'y'.*x"):
        st.load("s", "k", "y")
    with pytest.raises(ValueError, match="invalid stage name"):
        st.has("../etc", "k")
    with pytest.raises(ValueError, match="invalid output name"):
        st.commit("s", "k2", {"a/b": encode(np.arange(3.0))}, {})
    with pytest.raises(TypeError, match="array 'o'.*object array"):
        st.commit("s", "k2", {"x": Encoded("t", {"o": (np.array([1, "a"], object), ("i",))})}, {})
    with pytest.raises(TypeError, match="output 'x'.*attrs value of type set"):
        st.commit("s", "k2", {"x": Encoded("t", {}, {"s": {1}})}, {})
    with pytest.raises(ValueError, match="dims"):
        st.commit("s", "k2", {"x": Encoded("t", {"a": (np.zeros((2, 3)), ("frame",))})}, {})

    def boom(sink, buffer, **kw):
        raise OSError("disk full")

    monkeypatch.setattr(store_zarr, "_flush", boom)
    with pytest.raises(OSError, match="disk full"):
        st.commit("s", "k3", {"x": encode(np.arange(3.0))}, {})
    assert not st.has("s", "k3")
    assert os.listdir(tmp_path / "staging") == []  # a failed writer cleans up after itself


def test_pickle_carries_only_root_and_options(tmp_path):
    st = Store(tmp_path, chunk_frames=16)
    st.commit("s", "k", {"x": encode(np.arange(3.0))}, {})
    blob = pickle.dumps(st)
    assert len(blob) < 400
    st2 = pickle.loads(blob)
    assert st2 == st and st2.chunk_frames == 16 and st2.has("s", "k") and st2.is_local


def test_corrupt_manifest_means_not_committed(tmp_path):
    st = Store(tmp_path)
    st.commit("s", "k", {"x": encode(np.arange(3.0))}, {})
    (Path(st.entry_path("s", "k")) / "_COMMIT.json").write_text('{"outputs": ')
    assert not st.has("s", "k") and st.manifest("s", "k") is None


# --------------------------------------------------------------------------- crash, race


_WRITER_SCRIPT = """
import json, os, sys, time
import numpy as np
from mocapflow.pipeline import store_zarr
from mocapflow.pipeline.codecs import Encoded
from mocapflow.pipeline.store import Store

root, key, mode, go, ready = sys.argv[1:6]
original_flush = store_zarr._flush
calls = []

def slow_flush(sink, buffer, **kw):
    original_flush(sink, buffer, **kw)
    calls.append(1)
    if mode == "crash" and len(calls) == 1:
        open(ready, "w").close()  # first array is on disk: the parent may kill us now
        time.sleep(60)
    if mode == "race":
        time.sleep(0.15)

store_zarr._flush = slow_flush
saw_existing = []
original_publish = Store._publish

def publish(self, staging, entry, *a):
    saw_existing.append(os.path.exists(entry))
    return original_publish(self, staging, entry, *a)

Store._publish = publish
st = Store(root, chunk_frames=64, atomic_rename=(os.environ.get("DIRECT") != "1"))
rng = np.random.default_rng(1)
outs = {
    f"out{i}": Encoded("t", {"a": (rng.normal(size=(256, 8, 3)), ("frame", "m", "xyz")),
                             "b": (np.arange(5.0), ("k",))}, {"i": i})
    for i in range(3)
}
if go != "-":
    open(ready, "w").close()  # waiting at the start line
    while not os.path.exists(go):
        time.sleep(0.005)
digests = st.commit("synth", key, outs, {"writer": os.getpid()})
print(json.dumps({"digests": digests, "saw_existing": saw_existing, "pid": os.getpid()}))
"""


def _spawn(tmp_path: Path, root: str, key: str, mode: str, go: str = "-", direct: bool = False):
    script = tmp_path / "writer.py"
    script.write_text(textwrap.dedent(_WRITER_SCRIPT))
    ready = tmp_path / f"ready-{uuid.uuid4().hex[:6]}"
    env = dict(os.environ, DIRECT="1" if direct else "0")
    proc = subprocess.Popen(
        [sys.executable, str(script), root, key, mode, go, str(ready)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        cwd=REPO,
    )
    return proc, ready


def _kill_mid_write(tmp_path: Path, root: str, key: str, direct: bool) -> None:
    proc, ready = _spawn(tmp_path, root, key, "crash", direct=direct)
    deadline = time.monotonic() + 30
    while not ready.exists():
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, "writer never reached the first array"
        time.sleep(0.01)
    proc.send_signal(signal.SIGKILL)
    proc.communicate()
    assert proc.returncode == -signal.SIGKILL


def test_sigkill_mid_commit_leaves_no_entry(tmp_path):
    root = str(tmp_path / "store")
    st = Store(root, chunk_frames=64)
    st.commit("synth", "other", {"x": encode(np.arange(4.0))}, {})
    _kill_mid_write(tmp_path, root, "k1", direct=False)
    assert not st.has("synth", "k1")
    assert st.entries() == [("synth", "other")]
    assert not (tmp_path / "store" / "entries" / "synth" / "k1").exists()
    debris = os.listdir(tmp_path / "store" / "staging")
    assert len(debris) == 1 and debris[0].startswith("synth-k1-")
    writer = json.loads((tmp_path / "store" / "staging" / debris[0] / "_WRITER.json").read_text())
    assert {"pid", "host", "started"} <= set(writer)
    assert st.verify() == []
    # the dead writer's debris goes even with a large min age; dry run first
    report = st.gc(dry_run=True, staging_min_age_s=3600)
    assert len(report["staging"]) == 1 and report["bytes"] > 0
    assert len(os.listdir(tmp_path / "store" / "staging")) == 1
    report = st.gc(staging_min_age_s=3600)
    assert len(report["staging"]) == 1 and report["incomplete"] == []
    assert os.listdir(tmp_path / "store" / "staging") == []
    assert st.entries() == [("synth", "other")]  # gc without keep leaves entries alone
    # the re-run completes
    proc, _ = _spawn(tmp_path, root, "k1", "normal")
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    assert st.has("synth", "k1") and st.verify() == []
    assert set(json.loads(out)["digests"]) == {"out0", "out1", "out2"}


def test_sigkill_mid_direct_write_is_not_an_entry(tmp_path):
    root = str(tmp_path / "store")
    st = Store(root, atomic_rename=False)
    _kill_mid_write(tmp_path, root, "k1", direct=True)
    entry = tmp_path / "store" / "entries" / "synth" / "k1"
    assert entry.is_dir() and not (entry / "_COMMIT.json").exists()  # half-written in place
    assert not st.has("synth", "k1") and st.entries() == []
    assert st.verify() == []
    report = st.gc()
    assert report["incomplete"] == [str(entry)]
    assert not entry.exists()
    proc, _ = _spawn(tmp_path, root, "k1", "normal", direct=True)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    assert st.has("synth", "k1") and st.verify() == []


def test_two_writers_race_on_one_key(tmp_path):
    root = str(tmp_path / "store")
    go = tmp_path / "go"
    spawned = [_spawn(tmp_path, root, "k1", "race", go=str(go)) for _ in range(2)]
    procs = [p for p, _ in spawned]
    deadline = time.monotonic() + 30
    while not all(ready.exists() for _, ready in spawned):
        assert all(p.poll() is None for p in procs), [p.communicate() for p in procs]
        assert time.monotonic() < deadline
        time.sleep(0.01)
    go.touch()
    results = []
    for p in procs:
        out, err = p.communicate(timeout=60)
        assert p.returncode == 0, err
        results.append(json.loads(out))
    assert results[0]["digests"] == results[1]["digests"]
    # both were writing at once: at most one found the entry already published (when
    # both reach the rename within the same instant, neither sees it and the atomic
    # rename alone decides; that happens on a loaded machine)
    saw = [r["saw_existing"][0] for r in results]
    assert sum(saw) <= 1
    st = Store(root)
    assert st.entries() == [("synth", "k1")]
    writers = {r["pid"] for r in results if not r["saw_existing"][0]}
    assert st.manifest("synth", "k1")["writer"] in writers  # the loser did not replace it
    assert st.verify() == []
    assert os.listdir(tmp_path / "store" / "staging") == []


# --------------------------------------------------------------------------- unwritable stores


def test_write_failures_are_one_line_naming_the_store(tmp_path, monkeypatch, caplog):
    """Simulated (monkeypatched backend writes; the mount tests below use real ones)."""
    st = Store(tmp_path / "s")
    st.commit("clean", "k0", {"x": encode(np.arange(3.0))}, {})

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(LocalBackend, "put_many", full)
    with pytest.raises(StoreAccessError) as e:
        st.commit("clean", "k1", sample_outputs(4), {})
    assert str(e.value) == f"store {st.root}: no space left on device (writing entry clean/k1)"
    assert isinstance(e.value, OSError) and e.value.errno == errno.ENOSPC
    assert pickle.loads(pickle.dumps(e.value)).args == e.value.args
    assert not st.has("clean", "k1") and os.listdir(tmp_path / "s" / "staging") == []

    def denied(*a, **k):
        raise PermissionError(errno.EACCES, "Permission denied")

    monkeypatch.setattr(LocalBackend, "write_atomic", denied)
    with caplog.at_level("WARNING", logger="mocapflow"):
        assert st.write_run("r1", {"tasks": []}) is None  # best-effort: one warning
    assert [r.getMessage() for r in caplog.records] == [
        f"run record not written: store {st.root}: permission denied (writing the run record "
        "runs/r1.json)"]
    with pytest.raises(StoreAccessError, match="permission denied"):
        st.write_run("r1", {"tasks": []}, required=True)
    with pytest.raises(OSError, match=r"^store .*: permission denied \(writing the file-digest"):
        st.save_file_memo({"x": [1]})
    assert st.load("clean", "k0", "x").arrays["data"][0].tolist() == [0.0, 1.0, 2.0]


def _can_mount() -> bool:
    if shutil.which("unshare") is None:
        return False
    probe = subprocess.run(["unshare", "-m", "--propagation", "private", "sh", "-c",
                            "mount -t tmpfs -o size=64k tmpfs /tmp"], capture_output=True)
    return probe.returncode == 0


needs_mounts = pytest.mark.skipif(not _can_mount(), reason="needs unshare -m and mount (root "
                                                           "in a mount namespace)")

#: Runs ``mocapflow`` verbs in one interpreter (argv[1]: JSON list of argument lists).
_CLI_SCRIPT = r"""
import contextlib, io, json, logging, os, sys
from mocapflow.pipeline.cli import main
results = []
for args in json.loads(sys.argv[1]):
    if args[0] == "fill":  # write a file until the disk is full
        with open(args[1], "wb") as f:
            try:
                while True:
                    f.write(b"x" * 65536)
                    f.flush()
            except OSError:
                pass
        results.append({"args": args, "code": 0, "out": "", "err": ""})
        continue
    if args[0] == "rm":
        os.unlink(args[1])
        results.append({"args": args, "code": 0, "out": "", "err": ""})
        continue
    logging.getLogger("mocapflow").handlers.clear()  # the CLI binds its handler to stderr
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(args)
    results.append({"args": args, "code": code, "out": out.getvalue(), "err": err.getvalue()})
print(json.dumps(results))
"""


def _in_mount_namespace(setup: str, commands: list[list], env: dict, cwd: Path) -> list[dict]:
    """Run ``setup`` (mounts) then the CLI commands, in a private mount namespace."""
    py = f"{shlex.quote(sys.executable)} -c {shlex.quote(_CLI_SCRIPT)} " + shlex.quote(
        json.dumps([[str(a) for a in c] for c in commands]))
    proc = subprocess.run(["unshare", "-m", "--propagation", "private", "sh", "-c",
                           f"{setup} && exec {py}"], env=env, cwd=cwd, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.splitlines()[-1])


def _tree(root: Path) -> dict[str, tuple[int, int]]:
    return {str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns)
            for p in root.rglob("*")}


@needs_mounts
def test_read_only_store_serves_every_read(cli, cli_env, toy_config, tmp_path):
    """A real read-only bind mount of the store (``unshare -m``; root ignores chmod)."""
    s = tmp_path / "s"
    code, _, _ = cli("run", toy_config, "--store", s, "--executor", "sync", "-q")
    assert code == 0
    debris = s / "staging" / "dead-writer"
    debris.mkdir(parents=True)
    (debris / "_WRITER.json").write_text('{"pid": 999999999, "host": "elsewhere", '
                                         '"started": 0}')
    stage, key = Store(s).entries()[0]
    before = _tree(s)
    sync = ("--store", s, "--executor", "sync", "-q")
    res = _in_mount_namespace(f"mount --bind {s} {s} && mount -o remount,bind,ro {s} {s}", [
        ["run", toy_config, *sync],
        ["export", toy_config, *sync, "--to", tmp_path / "out"],
        ["show", key[:12], "--store", s],
        ["status", toy_config, "--store", s],
        ["plan", toy_config, "--store", s],
        ["verify", "--store", s],
        ["run", toy_config, *sync, "--set", "add.amount=5"],
        ["gc", "--store", s],
    ], cli_env, tmp_path)
    by = {r["args"][0] + ("-changed" if "--set" in r["args"] else ""): r for r in res}
    warn = re.compile(rf"^WARNING: run record not written: store {re.escape(str(s))}: "
                      r"read-only file system \(writing the run record runs/[\w.-]+\.json\)$")
    for verb in ("run", "export"):  # every task a hit: exit 0, one warning
        assert by[verb]["code"] == 0, by[verb]
        lines = [x for x in by[verb]["err"].splitlines() if not x.startswith("exported ")]
        assert len(lines) == 1 and warn.match(lines[0]), by[verb]["err"]
    assert (tmp_path / "out" / "total" / "all" / "total.npy").is_file()
    for verb in ("show", "status", "plan", "verify"):
        assert by[verb]["code"] == 0 and "Traceback" not in by[verb]["err"], by[verb]
    assert "WARNING" not in by["verify"]["err"] and "entries verified" in by["verify"]["err"]
    assert by["show"]["out"].startswith(f"entry {stage}/{key}")
    changed = by["run-changed"]  # work to do: each task fails in one line, nothing hidden
    err = changed["err"].strip().splitlines()
    assert changed["code"] == 1 and len(err) == 2 and warn.match(err[0]), changed["err"]
    assert err[1].startswith("mocapflow: error: 5 task(s) failed: add/") and (
        f"StoreAccessError: store {s}: read-only file system (writing entry toy_add/" in err[1])
    assert "[tracebacks:" not in err[1]  # the run record could not be written
    assert by["gc"]["code"] == 1 and by["gc"]["err"] == (
        f"mocapflow: error: store {s}: read-only file system (collecting garbage)\n")
    assert _tree(s) == before  # nothing changed in the store


@needs_mounts
def test_full_store_one_line_task_error_not_hidden(cli_env, toy_config, tmp_path):
    """A real full disk: a 2 MiB tmpfs holding the store, filled up by a file."""
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    s = mnt / "s"
    sync = ("--store", s, "--executor", "sync", "-q")
    res = _in_mount_namespace(f"mount -t tmpfs -o size=2m tmpfs {mnt}", [
        ["run", toy_config, *sync],
        ["fill", mnt / "filler"],
        ["run", toy_config, *sync, "--set", "add.amount=5"],
        ["run", toy_config, *sync],
        ["verify", "--store", s],
        ["rm", mnt / "filler"],
        ["run", toy_config, *sync, "--set", "add.amount=5"],
        ["verify", "--store", s],
    ], cli_env, tmp_path)
    assert res[0]["code"] == 0 and res[0]["err"] == ""
    full = res[2]
    err = full["err"].strip().splitlines()
    assert full["code"] == 1 and len(err) == 2, full["err"]
    assert re.match(rf"^WARNING: run record not written: store {re.escape(str(s))}: no space "
                    r"left on device \(writing the run record runs/", err[0]), err[0]
    assert err[1].startswith("mocapflow: error: 5 task(s) failed: add/"), err[1]
    assert f"StoreAccessError: store {s}: no space left on device (writing entry toy_add/" in err[1]
    assert "Traceback" not in full["err"]
    assert res[3]["code"] == 0 and "no space left on device" in res[3]["err"]  # all hits
    assert res[4]["code"] == 0 and "entries verified" in res[4]["err"]
    assert res[6]["code"] == 0 and res[6]["err"] == "" and res[7]["code"] == 0  # room again
