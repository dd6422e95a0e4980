"""Compare the outputs of two stores task by task, whatever their cache keys.

A refactor that changes code fingerprints changes every key, so two stores built
by two versions of mocapflow from the same inputs share no key.  This script
matches their committed entries by what the task *is* — stage, node, part id and
params (a param that only the newer store has is ignored) — and compares output
digests; an output whose digests differ is decoded in both stores and compared
again with every field named like a wall-clock timing removed (``time``,
``second``, ``timing``, ``elapsed``), which tells a timing from a real change.

Part ids are file paths, and some outputs record their source path: build both
stores from inputs at the same paths (for the demo: the same ``--out``; run one
version, move its folder away, run the other).

usage::

    python benchmarks/compare_stores.py OLD_STORE NEW_STORE [--json]

Prints one line per output that differs and a table per stage: outputs identical,
equal but for timing fields, different.  Exit status 1 when any output differs
beyond timing fields or a task of the old store has no match in the new one.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from collections import Counter
from typing import Any

import numpy as np

from mocapflow.pipeline import codecs
from mocapflow.pipeline.registry import discover
from mocapflow.pipeline.store import Store

TIMING = re.compile(r"time|second|timing|elapsed", re.I)


def tasks(store: Store) -> dict[tuple[str, str, str], list[tuple[dict, str]]]:
    """``(stage, node, part) -> [(params, key), ...]`` of every committed entry."""
    out: dict[tuple[str, str, str], list[tuple[dict, str]]] = {}
    for stage, key in store.entries():
        man = store.manifest(stage, key) or {}
        head = (stage, str(man.get("node")), str(man.get("part")))
        out.setdefault(head, []).append(((man.get("components") or {}).get("params") or {}, key))
    return out


def match(old: dict, new: dict) -> dict[tuple, str | None]:
    """``(stage, node, part, old key) -> new key`` (None: no single match)."""
    pairs: dict[tuple, str | None] = {}
    for head, entries in old.items():
        for params, key in entries:
            cands = [k for p, k in new.get(head, [])
                     if all(p.get(n, object()) == v for n, v in params.items())]
            pairs[(*head, key)] = cands[0] if len(cands) == 1 else None
    return pairs


def without_timings(value: Any) -> Any:
    """A JSON-comparable copy of a decoded output with timing-named fields removed."""
    if isinstance(value, dict):
        return {str(k): without_timings(v) for k, v in value.items() if not TIMING.search(str(k))}
    if isinstance(value, (list, tuple)):
        return [without_timings(v) for v in value]
    if isinstance(value, np.ndarray):
        return ["ndarray", value.dtype.str, list(value.shape), value.tobytes().hex()]
    if hasattr(value, "__dict__") and not isinstance(value, type):
        return {k: without_timings(v) for k, v in vars(value).items() if not TIMING.search(k)}
    return value


def _plain(store: Store, stage: str, key: str, output: str) -> str:
    value = codecs.decode(store.load(stage, key, output))
    return json.dumps(without_timings(value), sort_keys=True, default=str)


def compare(old_root: str, new_root: str) -> tuple[list[dict], bool]:
    """One row per output of the old store, and whether every output matched."""
    discover()
    old, new = Store(old_root), Store(new_root)
    rows, ok = [], True
    for (stage, node, part, okey), nkey in sorted(match(tasks(old), tasks(new)).items()):
        if nkey is None:
            rows.append({"stage": stage, "node": node, "part": part, "output": None,
                         "verdict": "no match"})
            ok = False
            continue
        od = old.manifest(stage, okey)["outputs"]
        nd = new.manifest(stage, nkey)["outputs"]
        for out in sorted(od):
            if out in nd and od[out]["digest"] == nd[out]["digest"]:
                verdict = "identical"
            elif out in nd and _plain(old, stage, okey, out) == _plain(new, stage, nkey, out):
                verdict = "timings only"
            else:
                verdict = "differs"
                ok = False
            rows.append({"stage": stage, "node": node, "part": part, "output": out,
                         "verdict": verdict})
    return rows, ok


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("old")
    ap.add_argument("new")
    ap.add_argument("--json", action="store_true", help="print the rows as JSON")
    args = ap.parse_args(argv)
    rows, ok = compare(args.old, args.new)
    if args.json:
        print(json.dumps({"rows": rows, "ok": ok}, indent=1))
        return 0 if ok else 1
    for r in rows:
        if r["verdict"] in ("differs", "no match"):
            print(f"{r['verdict']:>9}: {r['stage']} / {r['node']} / {r['part']} :: {r['output']}")
    counts = Counter((r["stage"], r["verdict"]) for r in rows)
    print(f"\n{'stage':<26}{'identical':>10}{'timings only':>14}{'differs':>9}{'no match':>10}")
    for stage in sorted({s for s, _ in counts}):
        print(f"{stage:<26}" + "".join(f"{counts[(stage, v)]:>{w}}" for v, w in (
            ("identical", 10), ("timings only", 14), ("differs", 9), ("no match", 10))))
    total = Counter(r["verdict"] for r in rows)
    print(f"{'all':<26}{total['identical']:>10}{total['timings only']:>14}{total['differs']:>9}"
          f"{total['no match']:>10}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
