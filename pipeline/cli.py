"""The ``mocapflow`` command line.

Verbs: ``run``, ``plan``, ``status``, ``explain``, ``dag``, ``stages``, ``show``,
``export``, ``report``, ``verify``, ``gc``, ``lock``, ``demo`` (``mocapflow VERB --help``).
User errors (bad config, missing file, bad flag, ``--frozen`` mismatch, failed
tasks) print one line on stderr and exit non-zero (2 for usage/config errors,
1 for failed tasks, store problems and lock mismatches); ``--debug`` adds the
traceback.  A store that cannot be written (read-only, full) still serves
every verb that only reads it (``run`` with every task a hit, ``export``,
``show``, ``status``, ``plan``, ``verify``); a run whose record cannot be
written warns once.

This module parses arguments and prints; what the verbs do lives in library
modules: :mod:`~mocapflow.pipeline.runner` (run), :mod:`~mocapflow.pipeline.plan`
(plan, status, explain, the gc keep set), :mod:`~mocapflow.pipeline.lock`,
:mod:`~mocapflow.pipeline.export`, :mod:`~mocapflow.pipeline.show`,
:mod:`~mocapflow.pipeline.demo` and the :class:`~mocapflow.pipeline.store.Store`
(verify, gc).
"""

from __future__ import annotations

import argparse
import inspect
import json
import logging
import os
import sys
import textwrap
import traceback
from collections.abc import Sequence
from importlib import metadata
from pathlib import Path
from typing import Any

from rich import box
from rich.console import Console
from rich.table import Table

from mocapflow.blender import write_addon
from mocapflow.pipeline import registry
from mocapflow.pipeline.config import ConfigError, load_stage_modules, shipped_configs
from mocapflow.pipeline.config_yaml import close_match
from mocapflow.pipeline.demo import DemoError, DemoStep, load_demo_spec, run_demo
from mocapflow.pipeline.execute import OK, TaskRecord
from mocapflow.pipeline.executors import (
    Executor,
    ExecutorError,
    SlurmOptions,
    make_executor,
    slurm_job_script,
)
from mocapflow.pipeline.export import EXPORT_LAYOUT, ExportError, export_results
from mocapflow.pipeline.graph import Graph, file_overrides, load_graph, part_label, task_name
from mocapflow.pipeline.lock import (
    FrozenError,
    default_lock_path,
    lock_document,
    read_lock,
    write_lock,
)
from mocapflow.pipeline.plan import explain, gc_keep_set, paused_gc, plan, task_status
from mocapflow.pipeline.progress import Progress, StageWarningFilter, warning_lines
from mocapflow.pipeline.registry import ParamError
from mocapflow.pipeline.runner import RunResult, run
from mocapflow.pipeline.show import entry_summary, find_entry
from mocapflow.pipeline.stage_docs import config_schema, param_docs
from mocapflow.pipeline.store import Store, StoreError
from mocapflow.pipeline.store_backends import STORAGE_OPTIONS_ENV, parse_storage_options

__all__ = ["build_parser", "main"]

DEFAULT_STORE = ".mocapflow"
EPILOG = """examples:
  mocapflow run configs/texture.yaml --parts 'takes/*.bvh' --set synth.length=2048
  mocapflow plan configs/skin.yaml --json
  mocapflow explain configs/skin.yaml clean/take01
  mocapflow export configs/texture.yaml --target synth --to out/
  mocapflow lock configs/variation.yaml && mocapflow run configs/variation.yaml --frozen
  mocapflow run configs/skin.yaml --scheduler-file ~/scheduler.json
  mocapflow run skin --store s3://bucket/store --storage-option client_kwargs.endpoint_url=URL
  mocapflow run skin --executor slurm --slurm-partition gpu --slurm-gres gpu:1 --print-job-script

environment:
  MOCAPFLOW_STORE            default --store (else ./.mocapflow)
  MOCAPFLOW_STORAGE_OPTIONS  fsspec options of a URL store, a JSON object that --storage-option
                             items update, e.g. {"client_kwargs": {"endpoint_url": "URL"}}
  MOCAPFLOW_STAGE_MODULES    comma-separated modules to import for their @stage registrations
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
    p.add_argument("--storage-option", action="append", dest="storage_options", default=[],
                   metavar="KEY=VALUE",
                   help="fsspec option of a URL store (repeatable; VALUE is parsed as YAML, a "
                        "dotted KEY sets a nested option: client_kwargs.endpoint_url=URL; "
                        "on top of $MOCAPFLOW_STORAGE_OPTIONS, a JSON object)")
    p.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                   help="show tracebacks")
    p.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS,
                   help="no progress output")


def _json_flag(p: argparse.ArgumentParser, what: str = "the result") -> None:
    p.add_argument("--json", action="store_true",
                   help=f"print {what} as one JSON document on stdout")


def _config_args(p: argparse.ArgumentParser, *, target_help: str =
                 "target node (repeatable; default: the config's targets)") -> None:
    p.add_argument("config", metavar="CONFIG",
                   help="graph config (YAML), or a shipped graph by name: "
                        + ", ".join(shipped_configs()))
    p.add_argument("--parts", action="append", metavar="GLOB",
                   help="input files/globs replacing the config's parts (repeatable); a "
                        "session file (YAML with trials:, or CSV whose first column is "
                        "trial) gives its trials and their fields")
    p.add_argument("--set", action="append", dest="sets", metavar="NODE.PARAM=VALUE",
                   default=[], help="override a param; VALUE is parsed as YAML (repeatable; "
                                    "params.NAME=VALUE sets a shared param; NODE.seeds=N, "
                                    "=[0, 7, 9] or =null sets the node's seed fan-out)")
    p.add_argument("--target", action="append", dest="targets", metavar="NODE",
                   help=target_help)


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
    g.add_argument("--worker-timeout", type=float, default=None, metavar="SECONDS",
                   help="wait this long for a first Dask worker, and at most this long with "
                        "none during a run (default 60; slurm 600; 0: for ever)")
    g.add_argument("--fail-fast", action="store_true",
                   help="stop at the first failed task (default: run all independent work)")
    s = p.add_argument_group("slurm (--executor slurm)")
    s.add_argument("--slurm-queue", "--slurm-partition", default=None, metavar="PARTITION",
                   help="partition (#SBATCH -p)")
    s.add_argument("--slurm-account", default=None, help="account (#SBATCH -A)")
    s.add_argument("--slurm-cores", type=int, default=4, help="cores per job (default 4)")
    s.add_argument("--slurm-memory", default="8GB", help="memory per job (default 8GB)")
    s.add_argument("--slurm-walltime", default="01:00:00", help="walltime (default 01:00:00)")
    s.add_argument("--slurm-jobs", type=int, default=1, help="number of jobs (default 1)")
    s.add_argument("--slurm-gres", default=None, metavar="GRES",
                   help="generic resources per job, e.g. gpu:1 (#SBATCH --gres)")
    s.add_argument("--slurm-log-dir", default=None, metavar="DIR",
                   help="folder of the jobs' output and error files (default: the folder "
                        "sbatch runs in)")
    s.add_argument("--slurm-job-extra", action="append", default=[], metavar="DIRECTIVE",
                   help="a further #SBATCH directive, e.g. --constraint=avx2 (repeatable)")
    s.add_argument("--print-job-script", action="store_true",
                   help="print the Slurm job script and exit (needs no Slurm)")


def _version() -> str:
    """The installed distribution's version."""
    try:
        return metadata.version("mocapflow")
    except metadata.PackageNotFoundError:  # pragma: no cover - not installed
        return "(not installed)"


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``mocapflow``."""
    parser = argparse.ArgumentParser(
        prog="mocapflow",
        description="Declarative motion-capture stage graphs under Dask over a "
                    "content-addressed Zarr store.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--debug", action="store_true", dest="debug_top",
                        help="show tracebacks")
    parser.add_argument("--version", action="version", version=f"mocapflow {_version()}",
                        help="print the installed version and exit")
    sub = parser.add_subparsers(dest="verb", metavar="VERB", required=True)

    p = sub.add_parser("run", help="run a graph (only what changed is recomputed)")
    _config_args(p)
    _exec_args(p)
    _common(p)
    p.add_argument("--frozen", action="store_true",
                   help="fail if any key or output digest differs from the lock file")
    p.add_argument("--lock", default=None, metavar="PATH",
                   help="lock file (default: <config stem>.lock.json next to the config)")
    _json_flag(p, "the tasks (node, part, status, key, seconds, outputs, warnings)")

    p = sub.add_parser("plan", help="what would run and why (runs nothing)")
    _config_args(p)
    _common(p)
    p.add_argument("--force", action="append", default=[], metavar="NODE",
                   help="plan NODE as recomputed even when cached (repeatable)")
    _json_flag(p, "each task's status, key and reason")

    p = sub.add_parser("status", help="state of every task: up to date, last run status")
    _config_args(p)
    _common(p)
    _json_flag(p, "each task's state")

    p = sub.add_parser("explain", help="which key components changed since the last run")
    _config_args(p)
    p.add_argument("node", metavar="NODE[/PART]",
                   help="a node, or one of its parts (id, unique suffix or file stem)")
    _common(p)
    _json_flag(p, "the changes of each task")

    p = sub.add_parser("dag", help="show the graph")
    _config_args(p)
    _common(p)
    p.add_argument("--dot", action="store_true", help="Graphviz dot output")
    _json_flag(p, "the nodes (stage, tasks, inputs) and targets")

    p = sub.add_parser("stages", help="list registered stages and what their params mean")
    p.add_argument("name", nargs="?", metavar="NAME",
                   help="one stage, or a family (skin, texture, variation, motion): every "
                        "param with its type, default and meaning")
    _common(p)
    _json_flag(p, "the stages (inputs, outputs, params with type, default and doc)")

    p = sub.add_parser("schema", help="JSON Schema of graph configs (for editors)")
    p.add_argument("--out", default=None, metavar="PATH",
                   help="write it to PATH (default: stdout)")
    _common(p)

    p = sub.add_parser("show", help="manifest and arrays of a store entry")
    p.add_argument("entry", metavar="ENTRY",
                   help="STAGE/KEY, a key prefix, or NODE[/PART] as in explain")
    _common(p)
    _json_flag(p, "the manifest and outputs")

    p = sub.add_parser("export", help="write the targets' outputs as ordinary files",
                       description="Run the graph if needed, then export. " + EXPORT_LAYOUT)
    _config_args(p, target_help="target NODE, or NODE/PART for one part's outputs "
                                "(repeatable; default: the config's targets)")
    p.add_argument("--to", required=True, metavar="DIR", help="output directory")
    p.add_argument("--format", action="append", default=[], metavar="TYPE=F1,F2",
                   help="file formats of one output type (repeatable), e.g. "
                        "mesh=vtp,pc2,usd,ply (ply: an animated mesh also as one PLY per "
                        "frame)")
    _exec_args(p)
    _common(p)
    _json_flag(p, "the files written")

    p = sub.add_parser("report", help="write an HTML page of the last run: summary and figures",
                       description="Write DIR/<graph>-<run id>.html: the run's summary table "
                                   "and the figures of each task (one self-contained page, "
                                   "no scripts). Runs nothing: reports the last run of the "
                                   "graph in the store.")
    _config_args(p)
    p.add_argument("--to", required=True, metavar="DIR", help="output directory")
    p.add_argument("--run-id", default=None, metavar="ID",
                   help="report this run (default: the graph's last run in the store)")
    _common(p)
    _json_flag(p, "the page's path, run id, figure count and notes")

    p = sub.add_parser("verify", help="re-read every entry and check its digests")
    _common(p)
    _json_flag(p, "the entry count and the problems found")

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
    _json_flag(p, "what was (or would be) removed")

    p = sub.add_parser("lock", help="run, then write every node/part key and output digest")
    _config_args(p)
    _exec_args(p)
    _common(p)
    p.add_argument("--lock", default=None, metavar="PATH",
                   help="lock file (default: <config stem>.lock.json next to the config; "
                        ".yaml for YAML)")
    _json_flag(p, "the lock path and task count")

    p = sub.add_parser("demo", help="run the shipped graphs on generated data",
                       description="Run every shipped graph on data the project generates "
                                   "itself, each step exporting for the next; sized for a "
                                   "quick first look (a few minutes, ~100 MB) unless --full.")
    p.add_argument("--out", default="demo-output", metavar="DIR",
                   help="output folder (default ./demo-output); the store is DIR/store")
    p.add_argument("--spec", default=None, metavar="PATH",
                   help="demo description (default: the packaged configs/demo.yaml)")
    p.add_argument("--full", action="store_true",
                   help="full sizes (each step's full: overrides in the demo description: "
                        "longer captures and walk, more seeds, larger renders, per-frame "
                        "mesh files; ~8 min on 2 cores, ~0.5 GB)")
    _exec_args(p)
    _common(p)
    _json_flag(p, "each step's files and counts")

    p = sub.add_parser("blender-addon", help="write the Blender add-on (zip, or its folder)",
                       description="Write mocapflow's Blender add-on (Blender >= 3.4): a zip "
                                   "to install in Blender (Edit > Preferences > Add-ons > "
                                   "Install...), or, for an --out not ending in .zip, the "
                                   "folder OUT/mocapflow_blender to copy into Blender's "
                                   "scripts/addons. The add-on runs this mocapflow command.")
    p.add_argument("--out", default="mocapflow_blender.zip", metavar="PATH",
                   help="zip file, or folder (default ./mocapflow_blender.zip)")
    _json_flag(p, "the written path")
    return parser


# --------------------------------------------------------------------------- helpers


def _store(args: argparse.Namespace) -> Store:
    root = args.store or os.environ.get("MOCAPFLOW_STORE") or DEFAULT_STORE
    items = getattr(args, "storage_options", None) or ()
    local = "://" not in str(root) or str(root).startswith("file://")
    if items and local:
        raise UserError(f"--storage-option is for fsspec URL stores (s3://...), not the local "
                        f"directory {root}")
    try:  # $MOCAPFLOW_STORAGE_OPTIONS is ignored by local stores
        options = None if local else parse_storage_options(
            items, os.environ.get(STORAGE_OPTIONS_ENV))
    except ValueError as e:
        raise UserError(str(e)) from None
    try:
        store = Store(root, storage_options=options or None)
    except ImportError as e:
        extra = " (pip install 'mocapflow[s3]')" if str(root).startswith("s3") else ""
        raise UserError(f"--store {root}: {e}{extra}") from None
    except (ValueError, OSError, TypeError) as e:
        raise UserError(f"--store {root}: {e}") from None
    store.probe()  # a bad endpoint, option or bucket: one line now, not a failure per task
    return store


def _redacted_command(argv: Sequence[str]) -> list[str]:
    """``argv`` with each ``--storage-option`` value shown as ``***`` (it may be a secret).

    The command line goes into the run record, which is stored with the results.
    """
    out: list[str] = []
    hide_next = False
    for arg in argv:
        flag, eq, value = arg.partition("=")
        if hide_next:
            out.append(f"{flag}=***" if eq else "***")
            hide_next = False
        elif flag.startswith("--stora") and "--storage-option".startswith(flag):  # abbrev too
            if eq:
                key, sep, _ = value.partition("=")
                out.append(f"{flag}={key}=***" if sep else f"{flag}=***")
            else:
                out.append(arg)
                hide_next = True
        else:
            out.append(arg)
    return out


def _load(args: argparse.Namespace, config: str | None = None, *, parts=None, sets=None,
          targets=None, all_nodes: bool = False) -> Graph:
    with paused_gc():  # a task per part: many objects, no cycles
        return load_graph(config or args.config,
                          sets=sets if sets is not None else (getattr(args, "sets", None) or []),
                          parts=parts if parts is not None else getattr(args, "parts", None),
                          targets=(targets if targets is not None
                                   else getattr(args, "targets", None)),
                          all_nodes=all_nodes)


def _executor(args: argparse.Namespace) -> Executor:
    if args.workers is not None and args.workers < 1:
        raise UserError(f"--workers must be at least 1, got {args.workers}")
    slurm = ex_opts(args)

    def show_dashboard(link: str | None) -> None:
        print(f"dashboard: {link or 'none (the scheduler serves no dashboard)'}",
              file=sys.stderr, flush=True)

    return make_executor(args.executor, workers=args.workers, address=args.address,
                         scheduler_file=args.scheduler_file, slurm=slurm,
                         store=args.store or os.environ.get("MOCAPFLOW_STORE"),
                         worker_timeout=args.worker_timeout,
                         on_dashboard=None if getattr(args, "quiet", False) else show_dashboard)


def _progress(args: argparse.Namespace, total: int, label: str = "") -> Progress:
    return Progress(total, enabled=not getattr(args, "quiet", False), label=label)


def _task_json(r: TaskRecord) -> dict[str, Any]:
    return {k: r.get(k) for k in ("node", "part", "stage", "status", "key", "seconds", "error",
                                  "outputs", "warnings")}


def _print_json(doc: Any) -> None:
    sys.stdout.write(json.dumps(doc, indent=1, default=str) + "\n")


def _run_graph(args: argparse.Namespace, graph: Graph, store: Store, executor: Executor, *,
               lock=None, label: str = "") -> RunResult:
    progress = _progress(args, len(graph.tasks), label)
    return run(graph, store, executor=executor, force=getattr(args, "force", None) or (),
               fail_fast=getattr(args, "fail_fast", False), lock=lock, progress=progress,
               command=_redacted_command(sys.argv))


def _raise_failures(result: RunResult, args: argparse.Namespace | None = None,
                    store: Store | None = None) -> None:
    failed = result.failed()
    if failed:
        if args is not None and getattr(args, "debug", False):
            for r in failed:
                print(f"--- {task_name(r.node, r.part)}\n{r.traceback or r.error}",
                      file=sys.stderr)
        r = failed[0]
        more = f" (and {len(failed) - 1} more failed)" if len(failed) > 1 else ""
        skipped = result.counts["skipped"]
        tail = f"; {skipped} skipped" if skipped else ""
        where = (f" [tracebacks: {store.root}/runs/{result.run_id}.json]"
                 if store is not None and store.has_run(result.run_id) else "")
        raise Failed(f"{len(failed)} task(s) failed: {task_name(r.node, r.part)}: "
                     f"{r.error}{more}{tail}{where}")
    r = next((r for r in result.records if r.status not in OK), None)
    if r is not None:  # (every task committed but the lock differs: the caller says so)
        raise Failed(f"{task_name(r.node, r.part)} {r.status}: {r.error}")


#: Figures shown per row of the run summary (the first ones the target stages report).
SUMMARY_FIGURES = 6
#: Rows of the run summary (then one line "… and N more").
SUMMARY_ROWS = 40


def summary_table(graph: Graph, result: RunResult) -> Table | None:
    """The run summary: one row per target task, its status, seconds and key figures.

    Returns
    -------
    rich.table.Table or None
        ``None`` when the run has no target task.
    """
    recs = [r for r in result.records if r.node in graph.targets]
    if not recs:
        return None
    names: list[str] = []
    for r in recs:
        for k in r.figures or {}:
            if k not in names and len(names) < SUMMARY_FIGURES:
                names.append(k)
    table = Table(title=f"{graph.config.name}: {len(recs)} target task(s)", title_justify="left",
                  box=box.SIMPLE_HEAD, pad_edge=False)
    for col in ("task", "status", "s", *names):
        table.add_column(col, justify="left" if col in ("task", "status") else "right",
                         overflow="fold")
    for r in recs[:SUMMARY_ROWS]:
        figs = r.figures or {}
        table.add_row(task_name(r.node, part_label(r.part) if r.part else None), r.status,
                      f"{r.seconds:.1f}", *(_fmt_figure(figs.get(n)) for n in names))
    if len(recs) > SUMMARY_ROWS:
        table.caption = f"… and {len(recs) - SUMMARY_ROWS} more (mocapflow status --json)"
    return table


def _fmt_figure(v: Any) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.3g}" if abs(v) < 1e4 else f"{v:.0f}"
    return str(v)


def _print_summary(args: argparse.Namespace, graph: Graph, result: RunResult) -> None:
    if getattr(args, "quiet", False) or getattr(args, "json", False):
        return
    table = summary_table(graph, result)
    if table is not None:
        Console(stderr=True, highlight=False).print(table)


def _print_warnings(result: RunResult) -> None:
    for line in warning_lines(result.records):  # once per message, with a count
        print(line, file=sys.stderr)


# --------------------------------------------------------------------------- verbs


def cmd_run(args: argparse.Namespace) -> int:
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
    _print_summary(args, graph, result)
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


def ex_opts(args: argparse.Namespace) -> SlurmOptions:
    """Slurm options from parsed arguments."""
    return SlurmOptions(queue=args.slurm_queue, cores=args.slurm_cores, memory=args.slurm_memory,
                        walltime=args.slurm_walltime, jobs=args.slurm_jobs,
                        account=args.slurm_account, gres=args.slurm_gres,
                        log_dir=args.slurm_log_dir, job_extra=tuple(args.slurm_job_extra))


def cmd_plan(args: argparse.Namespace) -> int:
    graph = _load(args)
    plans = plan(graph, _store(args), force=args.force)
    if args.json:
        _print_json({"graph": graph.config.name, "tasks": [p.as_dict() for p in plans]})
        return 0
    counts: dict[str, int] = {}
    for p in plans:
        counts[p.status] = counts.get(p.status, 0) + 1
        print(f"{p.status:<8} {task_name(p.node, p.part)}: {p.reason}")
    print(f"{len(plans)} tasks: " + ", ".join(f"{v} {k}" for k, v in sorted(counts.items())),
          file=sys.stderr)
    return 0


def cmd_status(args: argparse.Namespace) -> int:
    graph = _load(args)
    rows = task_status(graph, _store(args))
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
                print(f"  failed {task_name(r['node'], r['part'])}: {r['error']}")
    return 0


def cmd_explain(args: argparse.Namespace) -> int:
    graph = _load(args)
    try:
        items = explain(graph, _store(args), args.node)
    except KeyError as e:
        raise UserError(f"explain {args.node}: {e.args[0]}") from None
    if args.json:
        _print_json({"tasks": items})
        return 0
    for it in items:
        name = task_name(it["node"], it["part"])
        if not it["changes"]:
            print(f"{name}: unchanged since run {it['last_run']} (key {str(it['key'])[:12]})")
            continue
        head = {"hit": "committed", "compute": "will recompute", "pending": "may recompute"}
        print(f"{name}: {head.get(it['status'], it['status'])}")
        for c in it["changes"]:
            print(f"  {c}")
    return 0


def cmd_dag(args: argparse.Namespace) -> int:
    graph = _load(args)
    cfg = graph.config
    if args.json:
        _print_json({"graph": cfg.name, "targets": list(graph.targets), "nodes": [
            {"name": n, "stage": cfg.nodes[n].stage, "gather": bool(cfg.nodes[n].gather),
             "tasks": len(graph.node_parts[n]),
             "seeds": None if cfg.nodes[n].seeds is None else list(cfg.nodes[n].seeds),
             "inputs": {i: w if w == "part" else list(w) if isinstance(w, tuple) else w
                        for i, w in cfg.nodes[n].inputs.items()}}
            for n in graph.nodes]})
        return 0
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


def _first_sentence(text: str) -> str:
    head = text.split(". ")[0].rstrip(".")
    return head if len(head) <= 90 else head[:89] + "…"


def cmd_stages(args: argparse.Namespace) -> int:
    load_stage_modules(discover=True)
    stages = registry.registered_stages()
    if args.name is not None:
        family = {n: s for n, s in stages.items()
                  if f".{args.name}." in f"{s.module}." and n != args.name}
        if args.name in stages:
            stages = {args.name: stages[args.name]}
        elif family:  # a family (``texture``): its stages
            stages = family
        else:
            raise UserError(f"no stage or stage family named {args.name!r}"
                            f"{close_match(args.name, stages)} ({len(stages)} stages "
                            "registered: mocapflow stages)")
    docs = {n: param_docs(s.func) for n, s in stages.items()}
    if args.json:
        _print_json([{
            "name": s.name, "module": s.module, "inputs": list(s.inputs),
            "outputs": list(s.outputs), "description": s.description, "version": s.version,
            "params": {p: {"type": _fmt_ann(a),
                           "default": None if d is inspect.Parameter.empty else d,
                           "required": d is inspect.Parameter.empty,
                           "doc": docs[s.name].get(p, "")}
                       for p, (a, d) in s.params.items()},
        } for s in stages.values()])
        return 0
    for s in stages.values():
        print(f"{s.name}  ({s.module})")
        if s.description:
            print(f"    {s.description}")
        ins = [f"{i} (optional)" if i in s.optional_inputs else i for i in s.inputs]
        print(f"    inputs: {', '.join(ins) or '-'}   outputs: {', '.join(s.outputs)}")
        for p, (a, d) in s.params.items():
            sig = f"{p}: {_fmt_ann(a)}" + ("" if d is inspect.Parameter.empty else f" = {d!r}")
            doc = docs[s.name].get(p, "")
            if args.name is not None:  # one stage: the whole text
                print(f"    {sig}")
                if doc:
                    print(textwrap.fill(doc, width=96, initial_indent="        ",
                                        subsequent_indent="        "))
            else:
                print(f"    {sig}" + (f"  — {_first_sentence(doc)}" if doc else ""))
    return 0


def cmd_schema(args: argparse.Namespace) -> int:
    load_stage_modules(discover=True)
    text = json.dumps(config_schema(registry.registered_stages()), indent=1, default=str)
    if args.out is None:
        sys.stdout.write(text + "\n")
        return 0
    try:
        Path(args.out).write_text(text + "\n", encoding="utf-8")
    except OSError as e:
        raise UserError(f"--out {args.out}: {e.strerror or e}") from None
    if not getattr(args, "quiet", False):
        print(f"wrote {args.out}", file=sys.stderr)
    return 0


def _flat_timings(t: dict[str, Any], prefix: str = "") -> list[tuple[str, float]]:
    """``{"compute": 2.8, "steps": {"search": 2.0}}`` → ``compute``, ``steps.search``."""
    out: list[tuple[str, float]] = []
    for k, v in t.items():
        if isinstance(v, dict):
            out += _flat_timings(v, f"{prefix}{k}.")
        elif isinstance(v, (int, float)):
            out.append((f"{prefix}{k}", float(v)))
    return out


def cmd_show(args: argparse.Namespace) -> int:
    store = _store(args)
    try:
        stage, key = find_entry(store, args.entry)
    except StoreError as e:
        raise UserError(f"show {args.entry}: {e}") from None
    doc = entry_summary(store, stage, key)
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
        print("  timings   " + ", ".join(f"{k} {v:.3f}s" for k, v in _flat_timings(t)))
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


def _export_formats(items: Sequence[str]) -> dict[str, tuple[str, ...]]:
    """``--format TYPE=F1,F2`` options as ``{type: (f1, f2)}``."""
    out: dict[str, tuple[str, ...]] = {}
    for item in items:
        kind, eq, fmts = item.partition("=")
        names = tuple(f.strip() for f in fmts.split(",") if f.strip())
        if not eq or not kind.strip() or not names:
            raise UserError(f"--format {item!r}: expected TYPE=FORMAT[,FORMAT...], "
                            "e.g. mesh=vtp,pc2,usd")
        out[kind.strip()] = names
    return out


def _part_targets(graph: Graph, specs: Sequence[str]) -> set[tuple[str, str | None]] | None:
    """The ``(node, part)`` tasks named by ``--target NODE/PART`` values (``None``: every
    task of the targets)."""
    if not any("/" in s for s in specs):
        return None
    keep: set[tuple[str, str | None]] = set()
    for spec in specs:
        try:
            keep.update((t.node, t.part) for t in graph.find(spec))
        except KeyError as e:
            raise UserError(f"--target {spec}: {e.args[0]}") from None
    return keep


def cmd_export(args: argparse.Namespace) -> int:
    specs = args.targets or []
    graph = _load(args, targets=[s.partition("/")[0] for s in specs] or None)
    keep = _part_targets(graph, specs)
    store = _store(args)
    with _executor(args) as ex:
        result = _run_graph(args, graph, store, ex)
    _print_warnings(result)
    _raise_failures(result, args, store)
    records = [r for r in result.records if keep is None or (r.node, r.part) in keep]
    files = export_results(graph, store, records, args.to,
                           formats=_export_formats(args.format))
    if args.json:
        _print_json({"directory": str(args.to), "files": [str(f) for f in files]})
        return 0
    if not getattr(args, "quiet", False):
        for f in files:
            print(f)
    print(f"exported {len(files)} file(s) to {args.to}", file=sys.stderr)
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    from mocapflow.pipeline.report import ReportError, render_report  # noqa: PLC0415

    graph = _load(args)
    store = _store(args)
    try:
        rep = render_report(graph, store, run_id=args.run_id)
        path = rep.write(args.to)
    except ReportError as e:
        raise UserError(str(e)) from None
    if args.json:
        _print_json({"path": str(path), "graph": rep.graph, "run_id": rep.run_id,
                     "figures": rep.images, "notes": rep.notes})
        return 0
    print(path)
    if not getattr(args, "quiet", False):
        print(f"report of run {rep.run_id}: {rep.images} figure(s)"
              + (f", {len(rep.notes)} note(s)" if rep.notes else ""), file=sys.stderr)
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
    store = _store(args)
    keep = None
    if args.keep_config or args.keep_runs is not None:
        graphs = (_load(args, cfg, sets=[], all_nodes=True) for cfg in args.keep_config)
        keep = gc_keep_set(store, graphs, last_runs=args.keep_runs)
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
    graph = _load(args)
    store = _store(args)
    with _executor(args) as ex:
        result = _run_graph(args, graph, store, ex)
    _raise_failures(result, args, store)
    path = write_lock(args.lock or default_lock_path(args.config),
                      lock_document(graph, result.records))
    if args.json:
        _print_json({"lock": str(path), "tasks": len(result.records)})
        return 0
    print(path)
    print(f"locked {len(result.records)} task(s) of {graph.config.name}", file=sys.stderr)
    return 0


def cmd_blender_addon(args: argparse.Namespace) -> int:
    path = write_addon(args.out)
    print(json.dumps({"path": str(path)}) if args.json else path)
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    spec = load_demo_spec(args.spec)
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    store = Store(args.store or out / "store")

    def announce(step: DemoStep) -> None:
        if step.description:
            print(f"== {step.label}: {step.description}", file=sys.stderr)

    ran: list[tuple[Graph, str]] = []  # (graph, run id) of each step, for the report

    with _executor(args) as ex:

        def run_step(graph: Graph, step: DemoStep) -> RunResult:
            result = _run_graph(args, graph, store, ex, label=step.label)
            _print_warnings(result)
            _raise_failures(result, args, store)
            ran.append((graph, result.run_id))
            return result

        summary = run_demo(spec, out, store, ex, full=args.full, announce=announce,
                           run_graph=run_step)
    # --- REPORT CALL SITE: one page per step's run in DIR/report, when
    # mocapflow.pipeline.report (write_report) is installed; skipped without it
    reports: list[Path] = []
    try:
        from mocapflow.pipeline.report import ReportError, write_report  # noqa: PLC0415
    except ImportError:
        pass
    else:
        try:
            reports = [write_report(g, store, out / "report", run_id=rid) for g, rid in ran]
        except ReportError as e:
            print(f"warning: demo report not written: {e}", file=sys.stderr)
    # --- end of the report call site
    if args.json:
        _print_json({"out": str(out), "store": str(store.root), "full": args.full,
                     "reports": [str(r) for r in reports], "steps": [
            {"label": s.label, "files": s.files, "export_to": str(s.export_to),
             "counts": s.counts, "look_at": [str(p) for _, ps in s.shown for p in ps]}
            for s in summary]})
        return 0
    print(f"demo results in {out}")
    for s in summary:
        print(f"  {s.label}: {s.files} file(s) in {s.export_to}  ({s.counts['computed']} "
              f"computed, {s.counts['hit']} hit)")
    print(f"  store: {store.root}")
    print("where to look:")
    for s in summary:  # one file: its path; several: the glob and how many
        shown = ", ".join(str(ps[0].relative_to(s.export_to)) if len(ps) == 1 else
                          f"{g} ({len(ps)})" for g, ps in s.shown if ps)
        print(f"  {s.label}: {s.export_to}/" + (f"  {shown}" if shown else ""))
    for r in reports:
        print(f"report: {r}")
    return 0


VERBS = {
    "run": cmd_run, "plan": cmd_plan, "status": cmd_status, "explain": cmd_explain,
    "dag": cmd_dag, "stages": cmd_stages, "schema": cmd_schema, "show": cmd_show,
    "export": cmd_export, "report": cmd_report, "verify": cmd_verify, "gc": cmd_gc,
    "lock": cmd_lock, "demo": cmd_demo, "blender-addon": cmd_blender_addon,
}


def _setup_logging(debug: bool) -> None:
    """Stage warnings (logger ``mocapflow``) on stderr; Dask's chatter only with --debug."""
    log = logging.getLogger("mocapflow")
    if not any(getattr(h, "_mocapflow", False) for h in log.handlers):
        h = logging.StreamHandler(sys.stderr)
        h.setFormatter(logging.Formatter("%(levelname)s: %(message)s"))
        h.addFilter(StageWarningFilter())  # stage warnings: printed from the records
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
    try:
        return VERBS[args.verb](args)
    except (UserError, Failed) as e:
        code = e.exit_code
        msg = str(e)
    except (ConfigError, ParamError, ExecutorError, DemoError) as e:
        code, msg = 2, str(e)
    except (StoreError, ExportError) as e:  # a store or export path that cannot be used
        code, msg = 1, str(e)
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
