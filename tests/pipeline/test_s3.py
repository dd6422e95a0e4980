"""A store on a real S3 API on loopback (moto's server): run, re-run (all hits), verify and
export through the command line, with ``--storage-option`` and ``$MOCAPFLOW_STORAGE_OPTIONS``;
one-line errors for a missing bucket, an unreachable endpoint and options on a local store;
no secret in anything the store writes."""

from __future__ import annotations

import json
import logging
import socket
import sys
import uuid
from pathlib import Path

import pytest

from mocapflow.pipeline.store_backends import STORAGE_OPTIONS_ENV
from mocapflow.pipeline.testing import write_number_files

moto_server = pytest.importorskip("moto.server", reason="moto[server] is not installed")
import boto3  # noqa: E402  (a dependency of moto; s3fs, the [s3] extra, is not skipped)

KEY = "mocapflow-test-key"
SECRET = "s3cr3t-" + uuid.uuid4().hex  # must never be printed nor stored
SYNC = ("--executor", "sync")
TASKS = 7  # read, add, scale of 2 parts, and total
EXPORT = ("--target", "scale", "--target", "total", "-q")


@pytest.fixture
def cli(cli, monkeypatch):
    """The conftest's ``cli``, with ``sys.argv`` set as the command would have it (the run
    record keeps the command line); nothing it prints may hold the secret."""

    def call(*args):
        monkeypatch.setattr(sys, "argv", ["mocapflow", *map(str, args)])
        code, out, err = cli(*args)
        assert SECRET not in out and SECRET not in err
        return code, out, err

    return call


@pytest.fixture
def data_dir(tmp_path: Path) -> Path:
    """Two number files (the toy graph's 7 tasks: each request to moto takes ~20 ms)."""
    d = tmp_path / "data"
    write_number_files(d, 2)
    return d


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def endpoint():
    """URL of a moto S3 server on 127.0.0.1, for this module."""
    port = _free_port()
    log = logging.getLogger("werkzeug")  # the server logs every request at INFO
    level = log.level
    log.setLevel(logging.WARNING)
    server = moto_server.ThreadedMotoServer(ip_address="127.0.0.1", port=port, verbose=False)
    server.start()
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.stop()
        log.setLevel(level)


@pytest.fixture
def bucket(endpoint) -> str:
    """A new, empty bucket on the server."""
    name = f"mf-{uuid.uuid4().hex[:12]}"
    _s3(endpoint).create_bucket(Bucket=name)
    return name


def _s3(endpoint: str):
    return boto3.client("s3", endpoint_url=endpoint, aws_access_key_id=KEY,
                        aws_secret_access_key=SECRET, region_name="us-east-1")


def _objects(endpoint: str, bucket: str) -> dict[str, bytes]:
    """Every object of the bucket: key -> bytes."""
    s3 = _s3(endpoint)
    out = {}
    for page in s3.get_paginator("list_objects_v2").paginate(Bucket=bucket):
        for o in page.get("Contents", []):
            out[o["Key"]] = s3.get_object(Bucket=bucket, Key=o["Key"])["Body"].read()
    return out


def _options(endpoint: str) -> list[str]:
    return ["--storage-option", f"client_kwargs.endpoint_url={endpoint}",
            "--storage-option", f"key={KEY}", "--storage-option", f"secret={SECRET}"]


def _run(cli, *args) -> tuple[int, dict, str]:
    code, out, err = cli("run", *args, "--json", "-q")
    return code, (json.loads(out) if out.strip() else {}), err


def _files(root: Path) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): p.read_bytes()
            for p in sorted(root.rglob("*")) if p.is_file()}


def _one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "Traceback" not in err and SECRET not in err
    return lines[0]


def test_s3_round_trip(cli, toy_config, tmp_path, endpoint, bucket):
    """run (all computed), re-run (all hits), verify, export = a local store's export."""
    url = f"s3://{bucket}/runs/store"
    opts = _options(endpoint)
    code, doc, err = _run(cli, toy_config, "--store", url, *opts, *SYNC)
    assert code == 0 and doc["ok"], err
    assert doc["counts"] == {"hit": 0, "computed": TASKS, "failed": 0, "skipped": 0}
    keys = _objects(endpoint, bucket)
    assert any(k.startswith("runs/store/entries/") and k.endswith("/_COMMIT.json")
               for k in keys), sorted(keys)[:10]
    code, doc, err = _run(cli, toy_config, "--store", url, *opts, *SYNC)
    assert code == 0 and doc["counts"]["hit"] == TASKS and doc["counts"]["computed"] == 0, err
    code, out, err = cli("verify", "--store", url, *opts, "--json")
    assert code == 0, err
    report = json.loads(out)
    assert report["problems"] == [] and report["entries"] == TASKS
    # export from the bucket equals the export of a run on a local directory store
    code, out, err = cli("export", toy_config, "--to", tmp_path / "from_s3", "--store", url,
                         *opts, *SYNC, *EXPORT)
    assert code == 0, err
    code, out, err = cli("export", toy_config, "--to", tmp_path / "from_dir", "--store",
                         tmp_path / "local", *SYNC, *EXPORT)
    assert code == 0, err
    from_s3, from_dir = _files(tmp_path / "from_s3"), _files(tmp_path / "from_dir")
    assert sorted(from_s3) == ["scale/trial000/values.npy", "scale/trial001/values.npy",
                               "total/all/report.json", "total/all/total.npy"]
    assert from_s3 == from_dir
    # nothing the store wrote (manifests, run records, arrays) holds the secret or the
    # endpoint; the run records keep the command line with the option values hidden
    after = _objects(endpoint, bucket)
    records = [json.loads(v) for k, v in after.items() if k.startswith("runs/store/runs/")]
    assert len(records) == 3
    for rec in records:
        assert rec["command"][1] in ("run", "export") and "secret=***" in rec["command"]
    for k, data in after.items():
        assert SECRET.encode() not in data and endpoint.encode() not in data, k


def test_s3_local_cluster_workers_get_the_options(cli, toy_config, endpoint, bucket):
    """Worker processes of a local cluster open the store from its pickled options."""
    url = f"s3://{bucket}/store"
    code, doc, err = _run(cli, toy_config, "--store", url, *_options(endpoint),
                          "--executor", "local", "--workers", "1")
    assert code == 0 and doc["ok"], err
    assert doc["executor"].startswith("local") and doc["counts"]["computed"] == TASKS
    code, doc, err = _run(cli, toy_config, "--store", url, *_options(endpoint), *SYNC)
    assert code == 0 and doc["counts"]["hit"] == TASKS, err


def test_s3_options_from_the_environment(cli, toy_config, endpoint, bucket, monkeypatch):
    """$MOCAPFLOW_STORAGE_OPTIONS (JSON) alone, and with --storage-option on top."""
    url = f"s3://{bucket}/store"
    env = {"client_kwargs": {"endpoint_url": endpoint}, "key": KEY, "secret": SECRET}
    monkeypatch.setenv(STORAGE_OPTIONS_ENV, json.dumps(env))
    code, doc, err = _run(cli, toy_config, "--store", url, *SYNC)
    assert code == 0 and doc["counts"]["computed"] == TASKS, err
    code, doc, err = _run(cli, toy_config, "--store", url, *SYNC)
    assert code == 0 and doc["counts"]["hit"] == TASKS, err
    # --storage-option updates the environment's options key by key: the endpoint here,
    # the credentials from there
    env["client_kwargs"]["endpoint_url"] = f"http://127.0.0.1:{_free_port()}"
    monkeypatch.setenv(STORAGE_OPTIONS_ENV, json.dumps(env))
    code, out, err = cli("verify", "--store", url, "--json",
                         "--storage-option", f"client_kwargs.endpoint_url={endpoint}")
    assert code == 0 and json.loads(out) == {"entries": TASKS, "problems": []}, err
    monkeypatch.setenv(STORAGE_OPTIONS_ENV, "{not json")
    code, out, err = cli("verify", "--store", url)
    assert code != 0 and STORAGE_OPTIONS_ENV in _one_line(err)


def test_s3_missing_bucket_one_line(cli, toy_config, endpoint):
    code, doc, err = _run(cli, toy_config, "--store", "s3://no-such-bucket-mf/store",
                          *_options(endpoint), *SYNC)
    line = _one_line(err)
    assert code != 0 and "no-such-bucket-mf" in line and "does not exist" in line
    code, out, err = cli("verify", "--store", "s3://no-such-bucket-mf/store",
                         *_options(endpoint))
    assert code != 0 and "no-such-bucket-mf" in _one_line(err)
    # no bucket at all: not a store over the whole account (gc would list every bucket)
    code, out, err = cli("gc", "--store", "s3://", *_options(endpoint))
    assert code != 0 and "names no bucket" in _one_line(err) and out == ""


def test_s3_unreachable_endpoint_one_line(cli, toy_config):
    dead = f"http://127.0.0.1:{_free_port()}"
    # (one attempt per try: botocore retries a refused connection too, ~8 s by default)
    code, doc, err = _run(cli, toy_config, "--store", "s3://bucket/store", *_options(dead),
                          "--storage-option", "config_kwargs.retries.max_attempts=1", *SYNC)
    line = _one_line(err)
    assert code != 0 and "s3://bucket/store" in line and dead in line


def test_storage_option_on_a_local_store_is_an_error(cli, toy_config, tmp_path):
    code, doc, err = _run(cli, toy_config, "--store", tmp_path / "s",
                          "--storage-option", f"secret={SECRET}", *SYNC)
    line = _one_line(err)
    assert code != 0 and "--storage-option" in line and str(tmp_path / "s") in line
    assert not (tmp_path / "s").exists()
