"""Lock the demo's steps, or replay them ``--frozen`` (a driver the shipped-graph tests run).

usage: python tests/frozen_demo.py lock|frozen --out DIR --store STORE --locks DIR
                                   [--executor sync|local] [--workers N]

``lock``: every step of the packaged demo on ``STORE`` (hits where the demo already
ran), one lock file per step (``DIR/<step>.lock.json``).  ``frozen``: every step again
on ``STORE`` against its lock.  Nothing is exported: a step reads the files the demo
exported to ``--out`` (the demo must have run there), and a step that reproduces its
lock has the outputs, digest for digest, that those files were written from.  Exit 0
when every step matched; else 1 with one line naming the step and the first problem.
"""

from __future__ import annotations

import argparse
import sys
from importlib.resources import as_file
from pathlib import Path

from mocapflow.pipeline.demo import DemoStep, demo_step, load_demo_spec
from mocapflow.pipeline.executors import make_executor
from mocapflow.pipeline.graph import Graph, load_graph, task_name
from mocapflow.pipeline.lock import FrozenError, lock_document, read_lock, write_lock
from mocapflow.pipeline.runner import RunResult, run
from mocapflow.pipeline.store import Store


class StepFailed(Exception):
    """A step whose run did not commit every task or did not match its lock."""


def _check(step: DemoStep, result: RunResult) -> None:
    bad = [r for r in result.records if not r.ok]
    if bad:
        raise StepFailed(f"{step.label}: {task_name(bad[0].node, bad[0].part)} "
                         f"{bad[0].status}: {bad[0].error}")
    if result.frozen_problems:
        raise StepFailed(f"{step.label}: {result.frozen_problems[0]} "
                         f"({len(result.frozen_problems)} problem(s))")


def main(argv: list[str] | None = None) -> int:
    """Run the driver; returns the exit code."""
    ap = argparse.ArgumentParser()
    ap.add_argument("mode", choices=("lock", "frozen"))
    ap.add_argument("--out", required=True)
    ap.add_argument("--store", required=True)
    ap.add_argument("--locks", required=True)
    ap.add_argument("--executor", default="sync")
    ap.add_argument("--workers", type=int, default=None)
    args = ap.parse_args(argv)
    locks = Path(args.locks)
    store = Store(args.store)
    counts: dict[str, dict[str, int]] = {}
    with make_executor(args.executor, workers=args.workers) as ex:

        def step_run(graph: Graph, step: DemoStep) -> RunResult:
            path = locks / f"{step.label}.lock.json"
            if args.mode == "lock":
                result = run(graph, store, executor=ex)
                _check(step, result)
                write_lock(path, lock_document(graph, result.records))
            else:
                try:
                    result = run(graph, store, executor=ex, lock=read_lock(path))
                except FrozenError as e:
                    raise StepFailed(f"{step.label}: {e}") from None
                _check(step, result)
            counts[step.label] = result.counts
            return result

        spec, out = load_demo_spec(), Path(args.out).resolve()
        try:
            for i in range(len(spec.steps)):
                step = demo_step(spec, i, out)
                with as_file(spec.base / step.config) as cfg:
                    graph = load_graph(str(cfg), parts=step.parts, sets=step.sets,
                                       targets=step.targets)
                step_run(graph, step)
        except StepFailed as e:
            print(f"frozen_demo {args.mode}: {e}", file=sys.stderr)
            return 1
    for label, c in counts.items():
        print(f"{label}: {c['computed']} computed, {c['hit']} hit")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
