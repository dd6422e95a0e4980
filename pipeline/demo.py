"""The demo: run the shipped graphs on generated data, each step exporting for the next.

A demo description (the packaged ``configs/demo.yaml`` by default) is a mapping
with ``steps:``, each step a mapping::

    config: skin_demo.yaml        # relative to the description's folder
    name: skin                    # label (default: the config's stem)
    description: ...              # printed before the step runs
    parts: ["{out}/sim/*.c3d"]    # optional; {out} is the demo folder
    targets: [render]             # optional (default: the config's targets)
    set: {node.param: value}      # optional overrides ({out} substituted too)
    formats: {mesh: [pc2]}        # optional: output type -> export file formats
    export_to: skin               # folder under {out} (default: the config's stem)
    show: ["render/*/*.mp4"]      # optional: globs (under export_to) printed at the end
    full:                         # optional: what ``mocapflow demo --full`` changes
      set: {node.param: value}    #   merged over set:
      formats: {mesh: [vtp, pc2]} #   replaces formats:

The defaults are sized for a quick first look; ``full=True`` (``--full``) applies
every step's ``full:`` overrides (the full-size run).

Steps run in order with one executor and one store; each step's targets are
exported to ``{out}/<export_to>`` before the next step starts, so a step can
read what an earlier one exported.  Python use::

    spec = load_demo_spec()
    with make_executor("sync") as ex:
        run_demo(spec, Path("demo-output").resolve(), Store("demo-output/store"), ex)
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from importlib.resources import as_file, files
from pathlib import Path
from typing import Any

import yaml

from mocapflow.pipeline.executors import Executor
from mocapflow.pipeline.export import export_results
from mocapflow.pipeline.graph import Graph, load_graph, task_name
from mocapflow.pipeline.runner import RunResult, run
from mocapflow.pipeline.store import Store

__all__ = [
    "DemoError",
    "DemoSpec",
    "DemoStep",
    "StepSummary",
    "demo_step",
    "load_demo_spec",
    "run_demo",
    "substitute_out",
]

STEP_KEYS = {"config", "parts", "targets", "set", "export_to", "name", "description",
             "formats", "show", "full"}
FULL_KEYS = {"set", "formats"}


class DemoError(ValueError):
    """A problem with the demo description, or a step whose tasks failed."""


@dataclass(frozen=True)
class DemoSpec:
    """A demo description.

    Attributes
    ----------
    steps : list
        The raw steps (each is checked by :func:`demo_step` when its turn comes).
    base : Path or importlib.resources.abc.Traversable
        The folder the step configs are relative to.
    """

    steps: list[Any]
    base: Any


@dataclass(frozen=True)
class DemoStep:
    """One checked step, ``{out}`` substituted."""

    index: int
    config: str
    label: str
    description: str | None
    parts: list[str] | None
    sets: dict[str, Any]
    targets: list[str] | None
    export_to: Path
    formats: dict[str, list[str]] | None = None
    show: list[str] | None = None


@dataclass(frozen=True)
class StepSummary:
    """What one step produced (``shown``: each ``show:`` glob and the exported files it matches)."""

    label: str
    export_to: Path
    files: int
    counts: dict[str, int]
    shown: list[tuple[str, list[Path]]] = field(default_factory=list)


def load_demo_spec(path: str | Path | None = None) -> DemoSpec:
    """Read a demo description (default: the packaged ``configs/demo.yaml``).

    Raises
    ------
    DemoError
        Unreadable or malformed, or not a mapping with a ``steps:`` list.
    """
    if path:
        path = Path(path)
        try:
            text = path.read_text()
        except OSError as e:
            raise DemoError(f"--spec {path}: {e}") from None
        base: Any = path.parent
    else:
        base = files("mocapflow.configs")
        try:
            text = (base / "demo.yaml").read_text()
        except (FileNotFoundError, OSError):
            raise DemoError("the installed package has no configs/demo.yaml") from None
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise DemoError(f"demo.yaml: malformed YAML: {e}".replace("\n", " ")) from None
    if not isinstance(doc, dict) or not isinstance(doc.get("steps"), list):
        raise DemoError("demo.yaml: expected a mapping with a steps: list")
    return DemoSpec(steps=doc["steps"], base=base)


def substitute_out(value: Any, out: str) -> Any:
    """``value`` with ``{out}`` replaced by ``out`` in every string (lists, dicts: deep)."""
    if isinstance(value, str):
        return value.replace("{out}", out)
    if isinstance(value, list):
        return [substitute_out(v, out) for v in value]
    if isinstance(value, dict):
        return {k: substitute_out(v, out) for k, v in value.items()}
    return value


def _mapping(value: Any, where: str) -> dict:
    if value is None:
        return {}
    if not isinstance(value, dict):
        raise DemoError(f"demo.yaml: {where}: expected a mapping")
    return value


def demo_step(spec: DemoSpec, i: int, out: Path, *, full: bool = False) -> DemoStep:
    """Step ``i`` of ``spec``, checked, with ``{out}`` (the demo folder) substituted.

    ``full``: apply the step's ``full:`` overrides (``set:`` merged, ``formats:``
    replaced).

    Raises
    ------
    DemoError
        Not a mapping with ``config:``, an unknown key, or a ``full:``, ``set:``
        or ``formats:`` that is not a mapping.
    """
    step = spec.steps[i]
    if not isinstance(step, dict) or "config" not in step:
        raise DemoError(f"demo.yaml: steps[{i}]: expected a mapping with config:")
    unknown = set(step) - STEP_KEYS
    if unknown:
        raise DemoError(f"demo.yaml: steps[{i}]: unknown key {sorted(unknown)[0]!r}")
    extra = _mapping(step.get("full"), f"steps[{i}].full")
    unknown = set(extra) - FULL_KEYS
    if unknown:
        raise DemoError(f"demo.yaml: steps[{i}].full: unknown key {sorted(unknown)[0]!r} "
                        f"(it may hold {sorted(FULL_KEYS)})")
    sets = dict(_mapping(step.get("set"), f"steps[{i}].set"))
    formats = step.get("formats")
    if full:
        sets.update(_mapping(extra.get("set"), f"steps[{i}].full.set"))
        formats = extra.get("formats", formats)
    formats = _mapping(formats, f"steps[{i}].formats") or None
    cfg_name = str(step["config"])
    return DemoStep(
        index=i,
        config=cfg_name,
        label=step.get("name") or Path(cfg_name).stem,
        description=step.get("description") or None,
        parts=substitute_out(step.get("parts"), str(out)),
        sets=substitute_out(sets, str(out)),
        targets=step.get("targets"),
        export_to=out / str(step.get("export_to") or Path(cfg_name).stem),
        formats={k: [str(f) for f in v] for k, v in formats.items()} if formats else None,
        show=[str(g) for g in step.get("show") or []],
    )


def _run_checked(graph: Graph, step: DemoStep, store: Store, executor: Executor) -> RunResult:
    result = run(graph, store, executor=executor)
    if not result.ok:
        bad = next(r for r in result.records if not r.ok)
        raise DemoError(f"demo step {step.label}: {task_name(bad.node, bad.part)} "
                        f"{bad.status}: {bad.error}")
    return result


def run_demo(spec: DemoSpec, out: Path, store: Store, executor: Executor, *,
             full: bool = False,
             announce: Callable[[DemoStep], None] | None = None,
             run_graph: Callable[[Graph, DemoStep], RunResult] | None = None
             ) -> list[StepSummary]:
    """Run every step of a demo, exporting each step's targets before the next starts.

    Parameters
    ----------
    spec : DemoSpec
    out : Path
        The demo folder (``{out}``); it should be absolute and exist.
    store : Store
    executor : Executor
        Shared by every step.
    full : bool
        Apply every step's ``full:`` overrides (the full-size demo).
    announce : callable, optional
        ``announce(step)`` before a step's config is loaded.
    run_graph : callable, optional
        ``run_graph(graph, step) -> RunResult``; it decides what a failed task
        means (default: :func:`~mocapflow.pipeline.runner.run`, then
        :class:`DemoError` naming the first task that is not a hit or computed).

    Returns
    -------
    list of StepSummary
    """
    summary = []
    for i in range(len(spec.steps)):
        step = demo_step(spec, i, out, full=full)
        if announce is not None:
            announce(step)
        with as_file(spec.base / step.config) as cfg_path:
            graph = load_graph(str(cfg_path), parts=step.parts, sets=step.sets,
                               targets=step.targets)
            if run_graph is None:
                result = _run_checked(graph, step, store, executor)
            else:
                result = run_graph(graph, step)
        written = export_results(graph, store, result.records, step.export_to,
                                 formats=step.formats)
        done = set(written)
        shown = [(g, sorted(p for p in step.export_to.glob(g) if p in done))
                 for g in step.show or []]
        summary.append(StepSummary(step.label, step.export_to, len(written), result.counts,
                                   shown))
    return summary
