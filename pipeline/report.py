"""The session report: one self-contained HTML page per run (``mocapflow report``).

:func:`write_report` reads the record of a graph's last run (or a given run)
from the store's ``runs/`` folder and writes ``DIR/<graph>-<run id>.html``:

* the run header: graph, run id, when, executor, command, task counts;
* the summary table: every task of the run with its status, seconds, the key
  figures its stage reported (``ctx.figure``) and its warnings;
* per task whose stage has a *report provider* (registered by the stage
  family with :func:`~mocapflow.pipeline.registry.report_figures`), the figures
  the provider draws from the decoded outputs of the task's committed entry.

The page needs nothing but itself: CSS inline, figures as PNG ``data:`` URIs
(matplotlib's Agg backend), no script, no external URL.  A provider that fails,
or an entry that cannot be read any more, is a note on the page; the report
is still written.  Nothing is run: the report shows what the store holds.
"""

from __future__ import annotations

import base64
import html
import io
import os
import traceback
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from mocapflow.pipeline.codecs import decode
from mocapflow.pipeline.execute import OK
from mocapflow.pipeline.export import safe_label
from mocapflow.pipeline.graph import Graph, load_graph, part_label, task_name
from mocapflow.pipeline.registry import report_provider
from mocapflow.pipeline.store import Store, StoreError

__all__ = ["ReportEntry", "ReportError", "SessionReport", "html_table", "render_report",
           "write_report"]

#: Parts of one node whose figures are drawn (the rest are counted in a note).
MAX_PARTS_PER_NODE = 4
#: Rows of the summary table (then one line "… and N more").
MAX_ROWS = 300
#: Characters of a task's warnings shown in the summary (the whole text as a tooltip).
WARNING_CHARS = 160
#: Resolution of the figures (dots per inch of the matplotlib figures).
DPI = 80


class ReportError(Exception):
    """No run to report, or a report that cannot be written (one line)."""


@dataclass
class ReportEntry:
    """What a report provider knows of the task it draws, besides its outputs.

    Attributes
    ----------
    node, stage : str
    part : str or None
    key : str
    manifest : dict
        The entry's manifest (params under ``components``, ``figures``, ``warnings``).
    store : Store
    """

    node: str
    part: str | None
    stage: str
    key: str
    manifest: dict[str, Any]
    store: Store

    @property
    def figures(self) -> dict[str, Any]:
        """The key figures the stage reported (``ctx.figure``)."""
        return dict(self.manifest.get("figures") or {})

    @property
    def params(self) -> dict[str, Any]:
        """The task's params (from its key components)."""
        return dict((self.manifest.get("components") or {}).get("params") or {})

    def upstream(self, name: str) -> Any:
        """The decoded outputs of the entry input ``name`` was wired to.

        Returns
        -------
        dict or list of dict
            ``output -> value`` of that entry (a list for a gathered input).

        Raises
        ------
        KeyError
            ``name`` is not an input wired to an upstream entry (a file input).
        StoreError
            The upstream entry is not committed any more.
        """
        ref = (self.manifest.get("upstream") or {}).get(name)
        if ref is None:
            raise KeyError(f"input {name!r} of {self.node} is not wired to an entry")
        if isinstance(ref, list):
            return [self._load(r) for r in ref]
        return self._load(ref)

    def _load(self, ref: str) -> dict[str, Any]:
        if ref.startswith("file:"):
            raise KeyError(f"{ref} is a file, not an entry")
        stage, _, key = ref.partition("/")
        return {k: decode(v) for k, v in self.store.load_outputs(stage, key).items()}


@dataclass
class SessionReport:
    """A rendered report (:func:`render_report`).

    Attributes
    ----------
    graph : str
    run_id : str
    html : str
        The whole page.
    images : int
        Figures on the page.
    notes : list of str
        Providers that failed, entries that could not be read.
    """

    graph: str
    run_id: str
    html: str
    images: int = 0
    notes: list[str] = field(default_factory=list)

    @property
    def file_name(self) -> str:
        """``<graph>-<run id>.html`` (made safe as one file name)."""
        return safe_label(f"{self.graph}-{self.run_id}") + ".html"

    def write(self, to_dir: str | os.PathLike) -> Path:
        """Write the page as ``to_dir/<graph>-<run id>.html``; returns its path.

        Raises
        ------
        ReportError
            The directory or the file cannot be written (one line naming it).
        """
        d = Path(to_dir)
        path = d / self.file_name
        try:
            d.mkdir(parents=True, exist_ok=True)
            tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
            tmp.write_text(self.html, encoding="utf-8")
            os.replace(tmp, path)
        except OSError as e:
            raise ReportError(f"report: cannot write {path}: {e.strerror or e}") from None
        return path


# --------------------------------------------------------------------------- HTML helpers


def _esc(v: Any) -> str:
    return html.escape(str(v), quote=True)


def fmt_value(v: Any) -> str:
    """A figure or table cell as short text (``-`` for ``None``, 3 significant digits)."""
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, (float, np.floating)):
        v = float(v)
        if not np.isfinite(v):
            return str(v)
        return f"{v:.3g}" if abs(v) < 1e4 else f"{v:.0f}"
    return str(v)


def html_table(header: Sequence[Any], rows: Iterable[Sequence[Any]], *,
               caption: str | None = None) -> str:
    """An HTML ``<table>`` fragment with every cell escaped (numbers: :func:`fmt_value`).

    Parameters
    ----------
    header : sequence
        Column titles.
    rows : iterable of sequences
    caption : str, optional

    Returns
    -------
    str
    """
    out = ['<table class="data">']
    if caption:
        out.append(f"<caption>{_esc(caption)}</caption>")
    out.append("<tr>" + "".join(f"<th>{_esc(h)}</th>" for h in header) + "</tr>")
    for r in rows:
        cells = "".join(
            f'<td class="{"num" if isinstance(c, (int, float, np.number)) else "txt"}">'
            f"{_esc(fmt_value(c))}</td>" for c in r)
        out.append(f"<tr>{cells}</tr>")
    out.append("</table>")
    return "".join(out)


def _png_bytes(item: Any) -> bytes:
    """PNG of a matplotlib Figure or an ``(H, W, 3|4)`` image array."""
    buf = io.BytesIO()
    if hasattr(item, "savefig"):
        item.savefig(buf, format="png", dpi=DPI, bbox_inches="tight")
        _close(item)
        return buf.getvalue()
    arr = np.asarray(item)
    if arr.ndim != 3 or arr.shape[-1] not in (3, 4):
        raise TypeError(f"an image must be (H, W, 3|4), got shape {arr.shape}")
    if arr.dtype != np.uint8:
        arr = np.clip(np.nan_to_num(arr.astype(np.float64)), 0.0, 1.0)
    import matplotlib.image as mpimg  # noqa: PLC0415 (heavy)

    mpimg.imsave(buf, arr, format="png")
    return buf.getvalue()


def _close(fig: Any) -> None:
    """Release a pyplot-managed figure (a plain ``Figure`` needs nothing)."""
    import sys  # noqa: PLC0415

    plt = sys.modules.get("matplotlib.pyplot")
    if plt is not None:
        plt.close(fig)  # (a figure pyplot does not manage: nothing happens)


def _img(png: bytes, title: str) -> str:
    data = base64.b64encode(png).decode("ascii")
    return (f'<figure><img alt="{_esc(title)}" src="data:image/png;base64,{data}">'
            f"<figcaption>{_esc(title)}</figcaption></figure>")


CSS = """
body{font:14px/1.4 system-ui,-apple-system,'Segoe UI',Roboto,sans-serif;margin:1.2em 2em;
color:#1d232a;background:#fff}
h1{font-size:1.6em;margin:.2em 0}h2{font-size:1.25em;margin-top:1.6em;border-bottom:2px solid
#d0d7de;padding-bottom:.2em}h3{font-size:1.05em;margin:1.2em 0 .4em}
.meta{display:grid;grid-template-columns:max-content auto;gap:.15em 1em;margin:.6em 0}
.meta dt{color:#57606a}.meta dd{margin:0;font-family:ui-monospace,monospace;font-size:.92em}
table.data{border-collapse:collapse;margin:.5em 0;font-size:.9em}
table.data th,table.data td{border:1px solid #d0d7de;padding:.2em .55em}
table.data th{background:#f2f5f8;text-align:left}td.num{text-align:right;
font-variant-numeric:tabular-nums}caption{text-align:left;font-weight:600;padding:.2em 0}
.st-hit{color:#0a6b2e}.st-computed{color:#0550ae}.st-failed,.st-skipped{color:#b3261e;
font-weight:600}.warn{color:#8a5a00;font-size:.88em}
.note{background:#fff4e5;border-left:4px solid #e8a33c;padding:.4em .8em;margin:.5em 0}
.figs{display:flex;flex-wrap:wrap;gap:1em;align-items:flex-start}
figure{margin:0;max-width:100%}figure img{max-width:100%;height:auto;border:1px solid #e5e8eb}
figcaption{font-size:.88em;color:#57606a;margin-top:.2em}.counts span{margin-right:1em}
"""


# --------------------------------------------------------------------------- the run


def _when(t: Any) -> str:
    if isinstance(t, (int, float)) and not isinstance(t, bool):
        return datetime.fromtimestamp(float(t), UTC).strftime("%Y-%m-%d %H:%M:%S UTC")
    return str(t) if t is not None else "-"


def find_run(graph: Graph, store: Store, run_id: str | None = None) -> dict[str, Any]:
    """The record of the graph's last run in the store (or of run ``run_id``).

    A run counts when its record names the graph and holds at least one task of
    it (a ``(node, part)`` of ``graph``).

    Raises
    ------
    ReportError
        No such run (one line).
    """
    name = graph.config.name
    mine = {(t.node, t.part) for t in graph.tasks}
    try:
        records = store.runs()
    except StoreError as e:
        raise ReportError(f"report: cannot read the run records of {store.root}: {e}") from None
    if run_id is not None:
        for rec in records:
            if rec.get("run_id") == run_id:
                if rec.get("graph") != name:
                    raise ReportError(f"report: run {run_id} in {store.root} is a run of graph "
                                      f"{rec.get('graph')!r}, not {name!r}")
                return rec
        raise ReportError(f"report: no run {run_id} in store {store.root}")
    for rec in reversed(records):
        if rec.get("graph") != name:
            continue
        tasks = [t for t in rec.get("tasks") or [] if isinstance(t, dict)]
        if any((t.get("node"), t.get("part")) in mine for t in tasks):
            return rec
    raise ReportError(f"report: no run of graph {name!r} (with these parts) in store "
                      f"{store.root}; run it first: mocapflow run")


def _run_tasks(graph: Graph, rec: Mapping[str, Any]) -> list[dict[str, Any]]:
    """The record's tasks that belong to ``graph``, in the graph's node order."""
    order = {n: i for i, n in enumerate(graph.nodes)}
    mine = {(t.node, t.part) for t in graph.tasks}
    tasks = [t for t in rec.get("tasks") or [] if isinstance(t, dict)
             and (t.get("node"), t.get("part")) in mine]
    return sorted(tasks, key=lambda t: order.get(str(t.get("node")), len(order)))


def _header(graph: Graph, rec: Mapping[str, Any], tasks: Sequence[Mapping[str, Any]]) -> str:
    counts: dict[str, int] = {}
    for t in tasks:
        counts[str(t.get("status"))] = counts.get(str(t.get("status")), 0) + 1
    rows = [("graph", graph.config.name), ("run id", rec.get("run_id")),
            ("started", _when(rec.get("started_at"))),
            ("seconds", fmt_value(rec.get("seconds"))),
            ("targets", ", ".join(rec.get("targets") or graph.targets)),
            ("executor", rec.get("executor")),
            ("config", rec.get("config")),
            ("command", " ".join(map(str, rec.get("command") or [])) or None),
            ("host", (rec.get("host") or {}).get("hostname"))]
    meta = "".join(f"<dt>{_esc(k)}</dt><dd>{_esc(v)}</dd>" for k, v in rows if v is not None)
    cnt = "".join(f'<span class="st-{_esc(k)}"><b>{v}</b> {_esc(k)}</span>'
                  for k, v in sorted(counts.items()))
    desc = graph.config.description
    return (f"<h1>{_esc(graph.config.name)} — run {_esc(rec.get('run_id'))}</h1>"
            + (f"<p>{_esc(desc)}</p>" if desc else "")
            + f'<dl class="meta">{meta}</dl><p class="counts">{len(tasks)} task(s): {cnt}</p>')


def _summary(tasks: Sequence[Mapping[str, Any]], targets: Sequence[str]) -> str:
    names: list[str] = []
    for t in tasks:
        for k in t.get("figures") or {}:
            if k not in names:
                names.append(k)
    head = ["task", "stage", "status", "s", *names, "warnings"]
    out = ['<table class="data" id="summary"><tr>'
           + "".join(f"<th>{_esc(h)}</th>" for h in head) + "</tr>"]
    for t in tasks[:MAX_ROWS]:
        figs = t.get("figures") or {}
        status = str(t.get("status"))
        name = task_name(str(t.get("node")), part_label(t.get("part")) if t.get("part")
                         else None)
        if t.get("node") in targets:
            name = f"{name} ★"
        warns = list(dict.fromkeys(t.get("warnings") or []))
        err = t.get("error")
        full = "; ".join([*warns, *([f"error: {err}"] if err else [])])
        note = full if len(full) <= WARNING_CHARS else full[:WARNING_CHARS - 1] + "…"
        cells = [f"<td>{_esc(name)}</td>", f"<td>{_esc(t.get('stage'))}</td>",
                 f'<td class="st-{_esc(status)}">{_esc(status)}</td>',
                 f'<td class="num">{_esc(fmt_value(t.get("seconds")))}</td>',
                 *(f'<td class="num">{_esc(fmt_value(figs.get(n)))}</td>' for n in names),
                 f'<td class="warn" title="{_esc(full)}">{_esc(note)}</td>']
        out.append("<tr>" + "".join(cells) + "</tr>")
    out.append("</table>")
    if len(tasks) > MAX_ROWS:
        out.append(f"<p>… and {len(tasks) - MAX_ROWS} more task(s) (mocapflow status "
                   "--json)</p>")
    return "".join(out)


def _task_figures(store: Store, t: Mapping[str, Any], provider: Callable[..., Any],
                  notes: list[str]) -> tuple[str, int]:
    """The HTML of one task's figures and how many images it holds."""
    name = task_name(str(t.get("node")), t.get("part"))
    stage, key = str(t.get("stage")), str(t.get("key"))
    try:
        man = store.require(stage, key)
        outputs = {k: decode(v) for k, v in store.load_outputs(stage, key).items()}
    except (StoreError, OSError, ValueError, KeyError) as e:
        msg = f"{name}: entry {stage}/{key[:12]} could not be read: {e}"
        notes.append(msg)
        return f'<p class="note">{_esc(msg)}</p>', 0
    entry = ReportEntry(node=str(t.get("node")), part=t.get("part"), stage=stage, key=key,
                        manifest=man, store=store)
    try:
        items = list(provider(outputs, entry) or [])
    except Exception as e:  # a provider's bug must not cost the whole report
        msg = f"{name}: the {stage} figures could not be drawn: {type(e).__name__}: {e}"
        notes.append(msg)
        tb = traceback.format_exc(limit=-3).strip().splitlines()[-1]
        return f'<p class="note">{_esc(msg)}<br><small>{_esc(tb)}</small></p>', 0
    parts, n = [], 0
    for title, item in items:
        try:
            if isinstance(item, str):
                parts.append(f"<div>{item}</div>")
            else:
                parts.append(_img(_png_bytes(item), str(title)))
                n += 1
        except Exception as e:  # one bad figure: a note in its place
            msg = f"{name}: figure {title!r} could not be drawn: {type(e).__name__}: {e}"
            notes.append(msg)
            parts.append(f'<p class="note">{_esc(msg)}</p>')
    return f'<div class="figs">{"".join(parts)}</div>', n


def render_report(graph_or_config: Graph | str | os.PathLike, store: Store, *,
                  run_id: str | None = None,
                  max_parts: int = MAX_PARTS_PER_NODE) -> SessionReport:
    """The report page of a graph's last run (or of ``run_id``), not yet written.

    Parameters
    ----------
    graph_or_config : Graph or path-like
        The graph, or a config to load with its defaults.
    store : Store
    run_id : str, optional
        Default: the graph's last run in the store.
    max_parts : int
        Parts per node whose figures are drawn.

    Returns
    -------
    SessionReport

    Raises
    ------
    ReportError
        The store holds no such run.
    """
    graph = graph_or_config if isinstance(graph_or_config, Graph) else load_graph(
        graph_or_config)
    rec = find_run(graph, store, run_id)
    tasks = _run_tasks(graph, rec)
    targets = list(rec.get("targets") or graph.targets)
    body = [_header(graph, rec, tasks), "<h2>Summary</h2>",
            _summary(tasks, targets)]
    notes: list[str] = []
    images = 0
    by_node: dict[str, list[Mapping[str, Any]]] = {}
    for t in tasks:
        by_node.setdefault(str(t.get("node")), []).append(t)
    for node, nts in by_node.items():
        stage = str(nts[0].get("stage"))
        provider = report_provider(stage)
        if provider is None:
            continue
        body.append(f'<h2 id="node-{_esc(node)}">{_esc(node)} <small>({_esc(stage)})</small></h2>')
        shown = [t for t in nts if t.get("status") in OK and t.get("key")]
        for t in nts:
            if t not in shown:
                body.append(f'<p class="note">{_esc(task_name(node, t.get("part")))}: '
                            f'{_esc(t.get("status"))}, no figures'
                            f'{": " + _esc(t.get("error")) if t.get("error") else ""}</p>')
        for t in shown[:max_parts]:
            label = part_label(t.get("part")) if t.get("part") else None
            body.append(f"<h3>{_esc(task_name(node, label))}</h3>")
            fragment, n = _task_figures(store, t, provider, notes)
            body.append(fragment)
            images += n
        if len(shown) > max_parts:
            body.append(f"<p>… figures of {len(shown) - max_parts} more part(s) of {_esc(node)} "
                        "not shown</p>")
    if notes:
        body.insert(3, '<p class="note">' + f"{len(notes)} note(s): some figures are missing "
                    "(see below)</p>")
    title = f"{graph.config.name} — run {rec.get('run_id')}"
    page = ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<title>{_esc(title)}</title><meta name=\"viewport\" content=\"width=device-width\">"
            f"<style>{CSS}</style></head><body>\n" + "\n".join(body)
            + "\n<p class=\"warn\">mocapflow report</p></body></html>\n")
    return SessionReport(graph=graph.config.name, run_id=str(rec.get("run_id")), html=page,
                         images=images, notes=notes)


def write_report(graph_or_config: Graph | str | os.PathLike, store: Store,
                 to_dir: str | os.PathLike, *, run_id: str | None = None) -> Path:
    """Write the report page of a graph's last run (or ``run_id``) into ``to_dir``.

    Parameters
    ----------
    graph_or_config : Graph or path-like
    store : Store
    to_dir : path-like
        Created if needed.
    run_id : str, optional

    Returns
    -------
    Path
        ``to_dir/<graph>-<run id>.html``.

    Raises
    ------
    ReportError
        No such run in the store, or the page cannot be written (one line).
    """
    return render_report(graph_or_config, store, run_id=run_id).write(to_dir)
