"""The ``mocapflow`` command line.

Verbs: ``run``, ``plan``, ``status``, ``explain``, ``dag``, ``stages``, ``show``,
``export``, ``verify``, ``gc``, ``lock``, ``demo`` (``mocapflow VERB --help``).
User errors (bad config, missing file, bad flag, ``--frozen`` mismatch, failed
tasks) print one line on stderr and exit non-zero (2 for usage/config errors,
1 for failed tasks, store problems and lock mismatches); ``--debug`` adds the
traceback.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import traceback
from collections.abc import Sequence
from pathlib import Path
from typing import Any

__all__ = ["build_parser", "export_results", "main"]

DEFAULT_STORE = ".mocapflow"
EXPORT_LAYOUT = ("Files are written as DIR/<node>/<part label>/<output>.<ext>; the part label "
                 "is the part file's stem, '.seed<S>' appended per seed fan-out, 'seed<S>' for "
                 "a seed-only part and 'all' for a gather node ('-<6 hex>' is appended when two "
                 "parts share a stem). Registered types use their exporter (BVH, C3D, OBJ, "
                 "PNG/MP4, …); JSON outputs become <output>.json, arrays <output>.npy, records "
                 "<output>.json + <output>.<array>.npy.")
EPILOG = """examples:
  mocapflow run configs/texture.yaml --parts 'takes/*.bvh' --set synth.length=2048
  mocapflow plan configs/skin.yaml --json
  mocapflow explain configs/skin.yaml clean/take01
  mocapflow export configs/texture.yaml --target synth --to out/
  mocapflow lock configs/variation.yaml && mocapflow run configs/variation.yaml --frozen
  mocapflow run configs/skin.yaml --scheduler-file ~/scheduler.json

environment:
  MOCAPFLOW_STORE          default --store (else ./.mocapflow)
  MOCAPFLOW_STAGE_MODULES  comma-separated modules to import for their @stage registrations
"""


class UserError(Exception):
    """A problem the user can fix; printed as one line."""

    exit_code = 2


class Failed(Exception):
    """The command ran but something failed (tasks, verify, frozen); exit 1."""

    exit_code = 1


# --------------------------------------------------------------------------- parser


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--store", default=None,
                   help=f"store root: a directory or fsspec URL (default: $MOCAPFLOW_STORE or "
                        f"./{DEFAULT_STORE})")
    p.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                   help="show tracebacks")
    p.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS,
                   help="no progress output")


def _config_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", metavar="CONFIG", help="graph config (YAML)")
    p.add_argument("--parts", action="append", metavar="GLOB",
                   help="input files/globs replacing the config's parts (repeatable)")
    p.add_argument("--set", action="append", dest="sets", metavar="NODE.PARAM=VALUE",
                   default=[], help="override a param; VALUE is parsed as YAML (repeatable; "
                                    "params.NAME=VALUE sets a shared param)")
    p.add_argument("--target", action="append", dest="targets", metavar="NODE",
                   help="target node (repeatable; default: the config's targets)")


def _exec_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("execution")
    g.add_argument("--executor", choices=("sync", "local", "slurm"), default="local",
                   help="sync: in-process; local: a LocalCluster of worker processes "
                        "(default); slurm: dask-jobqueue SLURMCluster")
    g.add_argument("--workers", type=int, default=None, metavar="N",
                   help="local: worker processes (one thread each; default: CPU count)")
    g.add_argument("--address", default=None, metavar="tcp://HOST:PORT",
                   help="use an existing Dask scheduler (never shut down)")
    g.add_argument("--scheduler-file", default=None, metavar="PATH",
                   help="use the Dask scheduler described by this file")
    g.add_argument("--force", action="append", default=[], metavar="NODE",
                   help="recompute NODE even when cached (repeatable)")
    g.add_argument("--fail-fast", action="store_true",
                   help="stop at the first failed task (default: run all independent work)")
    s = p.add_argument_group("slurm (--executor slurm)")
    s.add_argument("--slurm-queue", default=None, help="partition")
    s.add_argument("--slurm-account", default=None, help="account")
    s.add_argument("--slurm-cores", type=int, default=4, help="cores per job (default 4)")
    s.add_argument("--slurm-memory", default="8GB", help="memory per job (default 8GB)")
    s.add_argument("--slurm-walltime", default="01:00:00", help="walltime (default 01:00:00)")
    s.add_argument("--slurm-jobs", type=int, default=1, help="number of jobs (default 1)")
    s.add_argument("--print-job-script", action="store_true",
                   help="print the Slurm job script and exit (needs no Slurm)")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``mocapflow``."""
    parser = argparse.ArgumentParser(
        prog="mocapflow",
        description="Declarative motion-capture stage graphs under Dask over a "
                    "content-addressed Zarr store.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--debug", action="store_true", dest="debug_top",
                        help="show tracebacks")
    sub = parser.add_subparsers(dest="verb", metavar="VERB", required=True)

    p = sub.add_parser("run", help="run a graph (only what changed is recomputed)")
    _config_args(p)
    _exec_args(p)
    _common(p)
    p.add_argument("--frozen", action="store_true",
                   help="fail if any key or output digest differs from the lock file")
    p.add_argument("--lock", default=None, metavar="PATH",
                   help="lock file (default: <config stem>.lock.json next to the config)")
    p.add_argument("--json", action="store_true", help="print a JSON document of the tasks")

    p = sub.add_parser("plan", help="what would run and why (runs nothing)")
    _config_args(p)
    _common(p)
    p.add_argument("--force", action="append", default=[], metavar="NODE")
    p.add_argument("--json", action="store_true")

    p = sub.add_parser("status", help="state of every task: up to date, last run status")
    _config_args(p)
    _common(p)
    p.add_argument("--json", action="store_true")

    p = sub.add_parser("explain", help="which key components changed since the last run")
    _config_args(p)
    p.add_argument("node", metavar="NODE[/PART]")
    _common(p)
    p.add_argument("--json", action="store_true")

    p = sub.add_parser("dag", help="show the graph")
    _config_args(p)
    _common(p)
    p.add_argument("--dot", action="store_true", help="Graphviz dot output")

    p = sub.add_parser("stages", help="list registered stages")
    _common(p)
    p.add_argument("--json", action="store_true")

    p = sub.add_parser("show", help="manifest and arrays of a store entry")
    p.add_argument("entry", metavar="ENTRY", help="STAGE/KEY or a key prefix")
    _common(p)
    p.add_argument("--json", action="store_true")

    p = sub.add_parser("export", help="write the targets' outputs as ordinary files",
                       description="Run the graph if needed, then export. " + EXPORT_LAYOUT)
    _config_args(p)
    p.add_argument("--to", required=True, metavar="DIR", help="output directory")
    _exec_args(p)
    _common(p)

    p = sub.add_parser("verify", help="re-read every entry and check its digests")
    _common(p)
    p.add_argument("--json", action="store_true")

    p = sub.add_parser("gc", help="remove staging debris (and, with --keep-*, unreachable "
                                  "entries)")
    _common(p)
    p.add_argument("--keep-config", action="append", default=[], metavar="CONFIG",
                   help="keep the current entries of this config; remove every other entry "
                        "(repeatable)")
    p.add_argument("--keep-runs", type=int, default=None, metavar="N",
                   help="keep entries recorded by the last N runs; remove every other entry")
    p.add_argument("--dry-run", action="store_true", help="report only")
    p.add_argument("--min-age", type=float, default=600.0, metavar="SECONDS",
                   help="staging dirs whose writer cannot be checked (another host) are "
                        "removed once this old (default 600)")
    p.add_argument("--json", action="store_true")

    p = sub.add_parser("lock", help="run, then write every node/part key and output digest")
    _config_args(p)
    _exec_args(p)
    _common(p)
    p.add_argument("--lock", default=None, metavar="PATH",
                   help="lock file (default: <config stem>.lock.json next to the config; "
                        ".yaml for YAML)")

    p = sub.add_parser("demo", help="run the shipped graphs on generated data")
    p.add_argument("--out", default="demo-output", metavar="DIR",
                   help="output folder (default ./demo-output); the store is DIR/store")
    p.add_argument("--spec", default=None, metavar="PATH",
                   help="demo description (default: the packaged configs/demo.yaml)")
    _exec_args(p)
    _common(p)
    return parser


# --------------------------------------------------------------------------- helpers


def _store(args: argparse.Namespace):
    from mocapflow.pipeline.store import Store

    root = args.store or os.environ.get("MOCAPFLOW_STORE") or DEFAULT_STORE
    try:
        return Store(root)
    except (ValueError, ImportError, OSError) as e:
        raise UserError(f"--store {root}: {e}") from None


def _load(args: argparse.Namespace, config: str | None = None, *, parts=None, sets=None,
          targets=None, all_nodes: bool = False):
    from mocapflow.pipeline.config import load_config, load_stage_modules
    from mocapflow.pipeline.graph import build_graph

    load_stage_modules()
    cfg = load_config(config or args.config,
                      sets=sets if sets is not None else (getattr(args, "sets", None) or []),
                      parts=parts if parts is not None else getattr(args, "parts", None))
    if all_nodes:
        targets = list(cfg.nodes)
    return build_graph(cfg, targets if targets is not None else getattr(args, "targets", None))


def _executor(args: argparse.Namespace):
    from mocapflow.pipeline.executors import make_executor

    if args.workers is not None and args.workers < 1:
        raise UserError(f"--workers must be at least 1, got {args.workers}")
    slurm = ex_opts(args)
    return make_executor(args.executor, workers=args.workers, address=args.address,
                         scheduler_file=args.scheduler_file, slurm=slurm)


def _progress(args: argparse.Namespace, total: int, label: str = ""):
    from mocapflow.pipeline.progress import Progress

    return Progress(total, enabled=not getattr(args, "quiet", False), label=label)


def _name(node: str, part: str | None) -> str:
    return node if part is None else f"{node}/{part}"


def _task_json(r: dict[str, Any]) -> dict[str, Any]:
    return {k: r.get(k) for k in ("node", "part", "stage", "status", "key", "seconds", "error",
                                  "outputs", "warnings")}


def _print_json(doc: Any) -> None:
    sys.stdout.write(json.dumps(doc, indent=1, default=str) + "\n")


def _run_graph(args: argparse.Namespace, graph, store, executor, *, lock=None, label=""):
    from mocapflow.pipeline.runner import run

    progress = _progress(args, len(graph.tasks), label)
    return run(graph, store, executor=executor, force=getattr(args, "force", None) or (),
               fail_fast=getattr(args, "fail_fast", False), lock=lock, progress=progress,
               command=sys.argv)


def _raise_failures(result, args: argparse.Namespace | None = None, store=None) -> None:
    failed = result.failed()
    if failed:
        if args is not None and getattr(args, "debug", False):
            for r in failed:
                print(f"--- {_name(r['node'], r['part'])}\n{r.get('traceback') or r['error']}",
                      file=sys.stderr)
        r = failed[0]
        more = f" (and {len(failed) - 1} more failed)" if len(failed) > 1 else ""
        skipped = result.counts["skipped"]
        tail = f"; {skipped} skipped" if skipped else ""
        where = (f" [tracebacks: {store.root}/runs/{result.run_id}.json]"
                 if store is not None else "")
        raise Failed(f"{len(failed)} task(s) failed: {_name(r['node'], r['part'])}: "
                     f"{r['error']}{more}{tail}{where}")
    if not result.ok:
        r = next(r for r in result.records if r["status"] not in ("hit", "computed"))
        raise Failed(f"{_name(r['node'], r['part'])} {r['status']}: {r['error']}")


def _print_warnings(result) -> None:
    for r in result.records:
        for w in r.get("warnings") or []:
            print(f"warning: {_name(r['node'], r['part'])}: {w}", file=sys.stderr)


# --------------------------------------------------------------------------- verbs


def cmd_run(args: argparse.Namespace) -> int:
    from mocapflow.pipeline.executors import slurm_job_script
    from mocapflow.pipeline.runner import FrozenError, default_lock_path, read_lock

    if args.print_job_script:
        if args.executor != "slurm":
            raise UserError("--print-job-script needs --executor slurm")
        print(slurm_job_script(ex_opts(args)))
        return 0
    graph = _load(args)
    store = _store(args)
    lock = None
    if args.frozen:
        lock = read_lock(args.lock or default_lock_path(args.config))
    elif args.lock:
        raise UserError("--lock is used with --frozen (to write a lock: mocapflow lock)")
    with _executor(args) as ex:
        try:
            result = _run_graph(args, graph, store, ex, lock=lock)
        except FrozenError as e:
            raise Failed(str(e)) from None
    _print_warnings(result)
    if args.json:
        _print_json({"run_id": result.run_id, "ok": result.ok, "counts": result.counts,
                     "seconds": result.seconds, "executor": result.executor,
                     "frozen_problems": result.frozen_problems,
                     "tasks": [_task_json(r) for r in result.records]})
    _raise_failures(result, args, store)
    if result.frozen_problems:
        p = result.frozen_problems
        raise Failed(f"frozen: {p[0]}" + (f" (and {len(p) - 1} more)" if len(p) > 1 else ""))
    return 0


def ex_opts(args: argparse.Namespace):
    """Slurm options from parsed arguments."""
    from mocapflow.pipeline.executors import SlurmOptions

    return SlurmOptions(queue=args.slurm_queue, cores=args.slurm_cores, memory=args.slurm_memory,
                        walltime=args.slurm_walltime, jobs=args.slurm_jobs,
                        account=args.slurm_account)


def cmd_plan(args: argparse.Namespace) -> int:
    from mocapflow.pipeline.runner import plan

    graph = _load(args)
    plans = plan(graph, _store(args), force=args.force)
    if args.json:
        _print_json({"graph": graph.config.name, "tasks": [p.as_dict() for p in plans]})
        return 0
    counts: dict[str, int] = {}
    for p in plans:
        counts[p.status] = counts.get(p.status, 0) + 1
        print(f"{p.status:<8} {_name(p.node, p.part)}: {p.reason}")
    print(f"{len(plans)} tasks: " + ", ".join(f"{v} {k}" for k, v in sorted(counts.items())),
          file=sys.stderr)
    return 0


def cmd_status(args: argparse.Namespace) -> int:
    from mocapflow.pipeline.runner import last_records, plan

    graph = _load(args)
    store = _store(args)
    plans = plan(graph, store, reasons=False)
    history = last_records(store, statuses=None)
    rows = []
    for p in plans:
        last = history.get((p.node, p.part))
        rows.append({
            "node": p.node, "part": p.part, "stage": p.stage,
            "status": last.get("status") if last else None,
            "up_to_date": p.status == "hit",
            "key": p.key if p.key is not None else (last.get("key") if last else None),
            "seconds": last.get("seconds") if last else None,
            "error": last.get("error") if last else None,
            "last_run": last.get("run_id") if last else None,
        })
    if args.json:
        _print_json({"graph": graph.config.name, "tasks": rows})
        return 0
    for node in graph.nodes:
        nr = [r for r in rows if r["node"] == node]
        fresh = sum(r["up_to_date"] for r in nr)
        last: dict[str, int] = {}
        for r in nr:
            last[str(r["status"] or "never run")] = last.get(str(r["status"] or "never run"),
                                                               0) + 1
        lt = ", ".join(f"{v} {k}" for k, v in sorted(last.items()))
        print(f"{node}: {fresh}/{len(nr)} up to date; last run: {lt}")
        for r in nr:
            if r["status"] == "failed":
                print(f"  failed {_name(r['node'], r['part'])}: {r['error']}")
    return 0


def cmd_explain(args: argparse.Namespace) -> int:
    from mocapflow.pipeline.runner import explain

    graph = _load(args)
    try:
        items = explain(graph, _store(args), args.node)
    except KeyError as e:
        raise UserError(f"explain {args.node}: {e.args[0]}") from None
    if args.json:
        _print_json({"tasks": items})
        return 0
    for it in items:
        name = _name(it["node"], it["part"])
        if not it["changes"]:
            print(f"{name}: unchanged since run {it['last_run']} (key {str(it['key'])[:12]})")
            continue
        head = {"hit": "committed", "compute": "will recompute", "pending": "may recompute"}
        print(f"{name}: {head.get(it['status'], it['status'])}")
        for c in it["changes"]:
            print(f"  {c}")
    return 0


def cmd_dag(args: argparse.Namespace) -> int:
    from mocapflow.pipeline.graph import file_overrides

    graph = _load(args)
    cfg = graph.config
    if args.dot:
        print(f'digraph "{cfg.name}" {{\n  rankdir=LR;')
        for n in graph.nodes:
            node = cfg.nodes[n]
            shape = "box3d" if node.gather else "box"
            print(f'  "{n}" [shape={shape}, label="{n}\\n{node.stage}\\n'
                  f'{len(graph.node_parts[n])} task(s)"];')
        for n in graph.nodes:
            for iname, w in cfg.nodes[n].inputs.items():
                if isinstance(w, tuple):
                    print(f'  "{w[0]}" -> "{n}" [label="{w[1]} → {iname}"];')
        print("}")
        return 0
    print(f"graph {cfg.name}: {len(graph.nodes)} nodes, {len(graph.tasks)} tasks "
          f"(targets: {', '.join(graph.targets)}; parts: {len(cfg.parts)})")
    width = max(len(n) for n in graph.nodes)
    swidth = max(len(cfg.nodes[n].stage) for n in graph.nodes)
    rows = []
    for n in graph.nodes:
        node = cfg.nodes[n]
        over = file_overrides(node)  # part inputs replaced by one file: read once
        wires = ", ".join(
            f"{i}=file:{Path(over[i]).name}" if i in over
            else f"{i}={'part' if w == 'part' else '.'.join(w)}"
            for i, w in node.inputs.items())
        fan = "gather" if node.gather else f"×{len(graph.node_parts[n])}"
        if node.seeds is not None and len(node.seeds) > 1:
            fan += f" (seeds {node.seeds[0]}..{node.seeds[-1]})"
        rows.append((n, node.stage, fan, wires or "-"))
    fwidth = max(len(r[2]) for r in rows)
    for n, st, fan, wires in rows:
        print(f"  {n:<{width}}  {st:<{swidth}}  {fan:<{fwidth}}  <- {wires}")
    return 0


def _fmt_ann(ann: Any) -> str:
    if isinstance(ann, type):
        return ann.__name__
    return str(ann).replace("typing.", "").replace("mocapflow.pipeline.registry.", "")


def cmd_stages(args: argparse.Namespace) -> int:
    import inspect

    from mocapflow.pipeline import registry
    from mocapflow.pipeline.config import load_stage_modules

    load_stage_modules(discover=True)
    stages = registry.registered_stages()
    if args.json:
        _print_json([{
            "name": s.name, "module": s.module, "inputs": list(s.inputs),
            "outputs": list(s.outputs), "description": s.description, "version": s.version,
            "params": {p: {"type": _fmt_ann(a),
                           "default": None if d is inspect.Parameter.empty else d,
                           "required": d is inspect.Parameter.empty}
                       for p, (a, d) in s.params.items()},
        } for s in stages.values()])
        return 0
    for s in stages.values():
        params = ", ".join(
            f"{p}: {_fmt_ann(a)}" + ("" if d is inspect.Parameter.empty else f" = {d!r}")
            for p, (a, d) in s.params.items())
        print(f"{s.name}  ({s.module})")
        if s.description:
            print(f"    {s.description}")
        print(f"    inputs: {', '.join(s.inputs) or '-'}   outputs: {', '.join(s.outputs)}")
        if params:
            print(f"    params: {params}")
    return 0


def _resolve_entry(store, entry: str) -> tuple[str, str]:
    stage, sep, key = entry.partition("/")
    entries = store.entries()
    if sep:
        cands = [(s, k) for s, k in entries if s == stage and k.startswith(key)]
    else:
        cands = [(s, k) for s, k in entries if k.startswith(entry)]
    if not cands:
        raise UserError(f"show {entry}: no committed entry matches in store {store.root}")
    if len(cands) > 1:
        names = ", ".join(f"{s}/{k[:12]}" for s, k in cands[:5])
        raise UserError(f"show {entry}: {len(cands)} entries match ({names}…); give more of "
                        "the key")
    return cands[0]


def _entry_summary(store, stage: str, key: str) -> dict[str, Any]:
    import zarr

    man = store.manifest(stage, key)
    group = zarr.open_group(store.entry_path(stage, key), mode="r")
    outputs = {}
    for out, info in sorted(man["outputs"].items()):
        g = group[out]
        meta = dict(g.attrs).get("mocapflow", {})
        arrays = {}
        for name in meta.get("arrays", []):
            a = g[name]
            arrays[name] = {"shape": list(a.shape), "dtype": str(a.dtype),
                            "dims": list(a.metadata.dimension_names or ()),
                            "chunks": list(a.chunks)}
        outputs[out] = {"type": info.get("type"), "digest": info.get("digest"),
                        "arrays": arrays, "attrs": meta.get("attrs", {})}
    return {"entry": f"{stage}/{key}", "path": store.entry_path(stage, key), "manifest": man,
            "outputs": outputs}


def cmd_show(args: argparse.Namespace) -> int:
    store = _store(args)
    stage, key = _resolve_entry(store, args.entry)
    doc = _entry_summary(store, stage, key)
    if args.json:
        _print_json(doc)
        return 0
    man = doc["manifest"]
    print(f"entry {stage}/{key}")
    print(f"  path      {doc['path']}")
    for k in ("node", "part", "run_id", "committed_at", "host", "attempts"):
        if man.get(k) is not None:
            print(f"  {k:<9} {man[k]}")
    t = man.get("timings") or {}
    if t:
        print("  timings   " + ", ".join(f"{k} {v:.3f}s" for k, v in t.items()))
    comps = man.get("components") or {}
    if comps:
        print(f"  params    {json.dumps(comps.get('params'), default=str)}")
        print(f"  code      {str(comps.get('code'))[:16]}")
        print(f"  versions  {json.dumps(comps.get('versions'))}")
    for name, up in (man.get("upstream") or {}).items():
        print(f"  input {name}: {up}")
    for w in man.get("warnings") or []:
        print(f"  warning   {w}")
    for out, o in doc["outputs"].items():
        print(f"  output {out}: {o['type']} digest {str(o['digest'])[:16]}")
        for an, a in o["arrays"].items():
            dims = ", ".join(f"{d}={s}" for d, s in zip(a["dims"], a["shape"]))
            print(f"    {an}: {a['dtype']} ({dims}) chunks {tuple(a['chunks'])}")
        if o["attrs"]:
            text = json.dumps(o["attrs"], default=str)
            if len(text) > 200 and isinstance(o["attrs"], dict):
                text = "keys " + ", ".join(map(str, o["attrs"]))
            print(f"    attrs: {text[:200]}{'…' if len(text) > 200 else ''}")
    return 0


def _export_value(enc, value: Any, directory: Path, stem: str) -> list[Path]:
    import numpy as np

    from mocapflow.pipeline.codecs import find_exporter

    directory.mkdir(parents=True, exist_ok=True)
    fn = find_exporter(enc.type)
    if fn is not None:
        return [Path(p) for p in fn(value, directory, stem)]
    written = []
    if enc.type == "ndarray":
        p = directory / f"{stem}.npy"
        np.save(p, enc.arrays["data"][0])
        return [p]
    if enc.type == "json":
        p = directory / f"{stem}.json"
        p.write_text(json.dumps(enc.attrs.get("value"), indent=1) + "\n")
        return [p]
    attrs = dict(enc.attrs)
    if enc.type != "record":
        attrs = {"type": enc.type, "attrs": attrs}
    attrs_arrays = {n: f"{stem}.{n}.npy" for n in enc.arrays}
    if attrs_arrays:
        attrs = {**attrs, "_arrays": attrs_arrays}
    p = directory / f"{stem}.json"
    p.write_text(json.dumps(attrs, indent=1) + "\n")
    written.append(p)
    for n, (a, _) in enc.arrays.items():
        q = directory / attrs_arrays[n]
        np.save(q, a)
        written.append(q)
    return written


def export_results(graph, store, records: Sequence[dict[str, Any]], directory: str | Path
                   ) -> list[Path]:
    """Write the outputs of the graph's target nodes as files (see ``EXPORT_LAYOUT``).

    Returns
    -------
    list of Path
        Every file written.
    """
    from mocapflow.pipeline.codecs import decode
    from mocapflow.pipeline.graph import part_label
    from mocapflow.pipeline.registry import discover

    discover()  # every family's codecs and exporters
    directory = Path(directory)
    written: list[Path] = []
    for node in graph.targets:
        recs = [r for r in records if r["node"] == node]
        labels = [part_label(r["part"]) for r in recs]
        for r, label in zip(recs, labels):
            if labels.count(label) > 1:  # same stem in two folders: add a short part digest
                from mocapflow.pipeline.keys import digest

                label = f"{label}-{digest(str(r['part']))[:6]}"
            for out, enc in store.load_outputs(r["stage"], r["key"]).items():
                value = decode(enc)
                written += _export_value(enc, value, directory / node / label, out)
    return written


def cmd_export(args: argparse.Namespace) -> int:
    graph = _load(args)
    store = _store(args)
    with _executor(args) as ex:
        result = _run_graph(args, graph, store, ex)
    _print_warnings(result)
    _raise_failures(result, args, store)
    files = export_results(graph, store, result.records, args.to)
    for f in files:
        print(f)
    print(f"exported {len(files)} file(s) to {args.to}", file=sys.stderr)
    return 0


def cmd_verify(args: argparse.Namespace) -> int:
    store = _store(args)
    entries = store.entries()
    problems = store.verify()
    if args.json:
        _print_json({"entries": len(entries), "problems": problems})
    else:
        for p in problems:
            print(p)
    if problems:
        raise Failed(f"verify: {len(problems)} problem(s) in {store.root}")
    if not args.json:
        print(f"{len(entries)} entries verified in {store.root}: OK", file=sys.stderr)
    return 0


def cmd_gc(args: argparse.Namespace) -> int:
    from mocapflow.pipeline.runner import plan

    store = _store(args)
    keep = None
    if args.keep_config or args.keep_runs is not None:
        keep = set()
        for cfg in args.keep_config:
            graph = _load(args, cfg, sets=[], all_nodes=True)
            for p in plan(graph, store, reasons=False):
                if p.key is not None:
                    keep.add((p.stage, p.key))
        if args.keep_runs is not None:
            runs = store.runs()
            for rec in runs[-args.keep_runs:] if args.keep_runs > 0 else []:
                for t in rec.get("tasks") or []:
                    if t.get("key") and t.get("stage"):
                        keep.add((t["stage"], t["key"]))
    report = store.gc(keep=keep, dry_run=args.dry_run, staging_min_age_s=args.min_age)
    if args.json:
        _print_json(report)
        return 0
    verb = "would remove" if args.dry_run else "removed"
    print(f"gc {verb}: {len(report['staging'])} staging dir(s), {len(report['incomplete'])} "
          f"incomplete entr(y/ies), {len(report['unreachable'])} unreachable entr(y/ies); "
          f"{report['bytes'] / 1e6:.1f} MB")
    return 0


def cmd_lock(args: argparse.Namespace) -> int:
    from mocapflow.pipeline.runner import default_lock_path, lock_document, write_lock

    graph = _load(args)
    store = _store(args)
    with _executor(args) as ex:
        result = _run_graph(args, graph, store, ex)
    _raise_failures(result, args, store)
    path = write_lock(args.lock or default_lock_path(args.config),
                      lock_document(graph, result.records))
    print(path)
    print(f"locked {len(result.records)} task(s) of {graph.config.name}", file=sys.stderr)
    return 0


def _demo_spec(args: argparse.Namespace) -> tuple[dict, Any]:
    import yaml

    if args.spec:
        path = Path(args.spec)
        try:
            text = path.read_text()
        except OSError as e:
            raise UserError(f"--spec {path}: {e}") from None
        base: Any = path.parent
    else:
        from importlib.resources import files

        base = files("mocapflow.configs")
        try:
            text = (base / "demo.yaml").read_text()
        except (FileNotFoundError, OSError):
            raise UserError("the installed package has no configs/demo.yaml") from None
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise UserError(f"demo.yaml: malformed YAML: {e}".replace("\n", " ")) from None
    if not isinstance(doc, dict) or not isinstance(doc.get("steps"), list):
        raise UserError("demo.yaml: expected a mapping with a steps: list")
    return doc, base


def _subst_out(value: Any, out: str) -> Any:
    if isinstance(value, str):
        return value.replace("{out}", out)
    if isinstance(value, list):
        return [_subst_out(v, out) for v in value]
    if isinstance(value, dict):
        return {k: _subst_out(v, out) for k, v in value.items()}
    return value


def cmd_demo(args: argparse.Namespace) -> int:
    from importlib.resources import as_file

    from mocapflow.pipeline.store import Store

    doc, base = _demo_spec(args)
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    store = Store(args.store or out / "store")
    summary = []
    with _executor(args) as ex:
        for i, step in enumerate(doc["steps"]):
            if not isinstance(step, dict) or "config" not in step:
                raise UserError(f"demo.yaml: steps[{i}]: expected a mapping with config:")
            unknown = set(step) - {"config", "parts", "targets", "set", "export_to", "name",
                                   "description"}
            if unknown:
                raise UserError(f"demo.yaml: steps[{i}]: unknown key {sorted(unknown)[0]!r}")
            cfg_name = str(step["config"])
            parts = _subst_out(step.get("parts"), str(out))
            sets = _subst_out(step.get("set") or {}, str(out))
            targets = step.get("targets")
            export_to = out / str(step.get("export_to") or Path(cfg_name).stem)
            label = step.get("name") or Path(cfg_name).stem
            if step.get("description"):
                print(f"== {label}: {step['description']}", file=sys.stderr)
            with as_file(base / cfg_name) as cfg_path:
                graph = _load(args, str(cfg_path), parts=parts, sets=sets, targets=targets)
                result = _run_graph(args, graph, store, ex, label=label)
            _print_warnings(result)
            _raise_failures(result, args, store)
            files = export_results(graph, store, result.records, export_to)
            summary.append((label, export_to, len(files), result.counts))
    print(f"demo results in {out}")
    for label, where, n, counts in summary:
        print(f"  {label}: {n} file(s) in {where}  ({counts['computed']} computed, "
              f"{counts['hit']} hit)")
    print(f"  store: {store.root}")
    return 0


VERBS = {
    "run": cmd_run, "plan": cmd_plan, "status": cmd_status, "explain": cmd_explain,
    "dag": cmd_dag, "stages": cmd_stages, "show": cmd_show, "export": cmd_export,
    "verify": cmd_verify, "gc": cmd_gc, "lock": cmd_lock, "demo": cmd_demo,
}


def _setup_logging(debug: bool) -> None:
    """Stage warnings (logger ``mocapflow``) on stderr; Dask's chatter only with --debug."""
    log = logging.getLogger("mocapflow")
    if not any(getattr(h, "_mocapflow", False) for h in log.handlers):
        h = logging.StreamHandler(sys.stderr)
        h.setFormatter(logging.Formatter("%(levelname)s: %(message)s"))
        h._mocapflow = True  # type: ignore[attr-defined]
        log.addHandler(h)
        log.propagate = False
    log.setLevel(logging.INFO if debug else logging.WARNING)
    for name in ("distributed", "dask_jobqueue", "tornado", "bokeh"):
        logging.getLogger(name).setLevel(logging.INFO if debug else logging.ERROR)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``mocapflow``; returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    debug = bool(getattr(args, "debug", False) or args.debug_top)
    _setup_logging(debug)
    from mocapflow.pipeline.config import ConfigError
    from mocapflow.pipeline.executors import ExecutorError
    from mocapflow.pipeline.registry import ParamError
    from mocapflow.pipeline.runner import FrozenError

    try:
        return VERBS[args.verb](args)
    except (UserError, Failed) as e:
        code = e.exit_code
        msg = str(e)
    except (ConfigError, ParamError, ExecutorError) as e:
        code, msg = 2, str(e)
    except FrozenError as e:
        code, msg = 1, str(e)
    except FileNotFoundError as e:
        code, msg = 2, str(e)
    except KeyboardInterrupt:
        print("mocapflow: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # `mocapflow stages | head`
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 0
    if debug:
        traceback.print_exc()
    print(f"mocapflow: error: {msg}".replace("\n", " "), file=sys.stderr)
    return code


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
