"""Hostile configs (benchmarks/fuzz_configs.py) through ``mocapflow plan``: every one is
refused in time, in little memory, with one typed line ``FILE:LINE: key: problem``.

All cases run in one child process under a 1 GiB address-space limit (each through
``cli.main``, its stderr captured, timed); ``benchmarks/fuzz.py`` runs them with
the shipped stages as part of the whole fuzz suite.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

from benchmarks.fuzz_configs import TOY, cases, expected
from mocapflow.pipeline.config import STAGE_MODULES_ENV

REPO = Path(__file__).resolve().parents[2]
LIMIT = 1 << 30

CHILD = r"""
import contextlib, io, json, resource, sys, time
resource.setrlimit(resource.RLIMIT_AS, (BYTES, BYTES))
from benchmarks.fuzz_configs import TOY, cases
from mocapflow.pipeline.cli import main
out_dir, store = sys.argv[1], sys.argv[2]
for name, text in cases(TOY):
    path = f"{out_dir}/{name}.yaml"
    with open(path, "w", encoding="utf-8") as f:
        f.write(text)
    err = io.StringIO()
    t0 = time.perf_counter()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = main(["plan", path, "--store", store])
    seconds = time.perf_counter() - t0
    print(json.dumps({"name": name, "path": path, "code": code, "stderr": err.getvalue(),
                      "seconds": seconds}), flush=True)
print(json.dumps({"maxrss_kb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss}))
"""


def test_hostile_configs_are_refused_fast_small_and_in_one_line(tmp_path):
    env = {**os.environ, STAGE_MODULES_ENV: "mocapflow.pipeline.testing",
           "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    store = tmp_path / "store"
    proc = subprocess.run([sys.executable, "-c", CHILD.replace("BYTES", str(LIMIT)),
                           str(tmp_path), str(store)], env=env, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    lines = [json.loads(x) for x in proc.stdout.splitlines()]
    results, rss = lines[:-1], lines[-1]["maxrss_kb"]
    exp = expected(TOY)
    assert [r["name"] for r in results] == [n for n, _ in cases(TOY)]
    assert len(results) >= 30
    bad = []
    for r in results:
        key, fragment = exp[r["name"]]
        err = r["stderr"].strip()
        prefix = rf"mocapflow: error: {re.escape(r['path'])}(:\d+)?: " + (
            re.escape(key) if key else "")
        if not (r["code"] == 2 and len(err.splitlines()) == 1 and re.match(prefix, err)
                and fragment in err and "Traceback" not in err and r["seconds"] < 10):
            bad.append((r["name"], r["code"], round(r["seconds"], 2), err[:300]))
    assert not bad, bad
    assert rss < LIMIT // 1024
    assert not store.exists()  # nothing written for a refused config
