"""Test helpers: toy stages, temp-config writers and a stage contract check.

Importing this module registers toy stages (names start with ``toy_``).  They are
cheap, deterministic and importable by Dask workers, so engine tests can run on
any executor.  Set ``MOCAPFLOW_STAGE_MODULES=mocapflow.pipeline.testing`` to use
them from the ``mocapflow`` command line.

Toy stages
----------
``toy_source``     no inputs; ``values = value * arange(n) + noise * N(0, 1)``.
``toy_read_file``  ``path: FilePath`` → numbers of a text file (``#`` comments
                   ignored); a non-number raises ``ValueError`` naming file and line.
``toy_add``        ``values + amount``.
``toy_scale``      ``values * factor``.
``toy_clip``       ``clip(values, lo, hi)`` (a param change that may leave the output identical).
``toy_sum``        gather: per-part sums and a JSON report.
``toy_stats``      a record output (arrays + attrs) and a JSON output.
``toy_slow_cpu``   CPU-bound pure-Python loop (holds the GIL).
``toy_fail_on``    raises when the part id contains ``pattern``.
``toy_flaky``      fails its first ``fail_times`` attempts (counted in ``marker_dir``).
``toy_map``        squares the values through ``ctx.map`` in ``chunks`` pieces.
``toy_sleep``      sleeps ``seconds`` then passes its input through.
``toy_map_sleep``  ``ctx.map`` of a ``seconds`` sleep over ``items`` items, with progress.
``toy_warn``       passes its input through, warning ``message`` ``times`` times.
``toy_die``        kills its own process when the part id contains ``pattern`` (a crash).
"""

from __future__ import annotations

import functools
import os
import textwrap
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mocapflow.pipeline import codecs
from mocapflow.pipeline.context import Context
from mocapflow.pipeline.registry import FilePath, get_stage, stage, validate_params

__all__ = [
    "TOY_CONFIG",
    "assert_stage_contract",
    "write_config",
    "write_number_files",
]

MODULE = __name__


@stage("toy_source", outputs=("values",))
def toy_source(*, n: int = 8, value: float = 1.0, noise: float = 0.0, seed: int = 0,
               ctx: Context) -> dict:
    """Make a ramp, optionally noisy.

    Returns
    -------
    values : (n,) float ndarray
        ``value * arange(n) + noise * N(0, 1)`` (noise from ``ctx.rng``).
    """
    values = value * np.arange(n, dtype=np.float64)
    if noise:
        values = values + noise * ctx.rng.standard_normal(n)
    return {"values": values}


def read_numbers(path: str) -> np.ndarray:
    """Numbers of a text file, whitespace separated; ``#`` starts a comment (``.npy``: the array).

    Raises
    ------
    ValueError
        Naming the file and line of the first token that is not a number.
    """
    if str(path).endswith(".npy"):
        return np.asarray(np.load(path), dtype=np.float64).ravel()
    out: list[float] = []
    with open(path, encoding="utf-8", errors="replace") as f:
        for lineno, line in enumerate(f, 1):
            for tok in line.split("#", 1)[0].split():
                try:
                    out.append(float(tok))
                except ValueError:
                    raise ValueError(f"{path}: line {lineno}: not a number {tok!r}") from None
    return np.asarray(out, dtype=np.float64)


@stage("toy_read_file", outputs=("values",))
def toy_read_file(path: FilePath) -> dict:
    """Read numbers from a text file.

    Returns
    -------
    values : (N,) float ndarray
    """
    return {"values": read_numbers(path)}


@stage("toy_add", outputs=("values",))
def toy_add(values: np.ndarray, *, amount: float = 1.0) -> dict:
    """Add a constant: ``values : (N,) float ndarray`` → ``values + amount``.

    Parameters
    ----------
    values : (N,) float ndarray
    amount : float
        Added to every value.
    """
    return {"values": np.asarray(values) + amount}


@stage("toy_offset", outputs=("values",))
def toy_offset(values: np.ndarray, *, offset_file: FilePath | None = None) -> dict:
    """Add the sum of the numbers in ``offset_file`` (a param hashed by file content)."""
    extra = float(read_numbers(offset_file).sum()) if offset_file else 0.0
    return {"values": np.asarray(values) + extra}


@stage("toy_scale", outputs=("values",))
def toy_scale(values: np.ndarray, *, factor: float = 2.0) -> dict:
    """Multiply by a constant: ``values : (N,) float ndarray`` → ``values * factor``."""
    return {"values": np.asarray(values) * factor}


@stage("toy_clip", outputs=("values",))
def toy_clip(values: np.ndarray, *, lo: float = -1e9, hi: float = 1e9) -> dict:
    """Clip to ``[lo, hi]``: ``values : (N,) float ndarray``."""
    return {"values": np.clip(np.asarray(values), lo, hi)}


@stage("toy_sum", outputs=("total", "report"))
def toy_sum(values: list) -> dict:
    """Gather: per-part sums.

    Parameters
    ----------
    values : list of (N_i,) float ndarray
        One array per part, in part order.

    Returns
    -------
    total : (P,) float ndarray
        Sum of each part.
    report : dict
        ``{"parts": P, "grand_total": float}``.
    """
    sums = np.array([float(np.sum(v)) for v in values])
    return {"total": sums, "report": {"parts": len(values), "grand_total": float(sums.sum())}}


@stage("toy_stats", outputs=("stats", "summary"))
def toy_stats(values: np.ndarray, *, bins: int = 4) -> dict:
    """A record output (arrays + attrs) and a JSON output.

    Returns
    -------
    stats : dict
        ``{"hist": (bins,) int ndarray, "edges": (bins+1,) float ndarray, "mean": float}``.
    summary : dict
        ``{"n": int, "min": float, "max": float}``.
    """
    v = np.asarray(values)
    hist, edges = np.histogram(v, bins=bins)
    return {
        "stats": {"hist": hist, "edges": edges, "mean": float(v.mean()) if v.size else 0.0},
        "summary": {"n": int(v.size), "min": float(v.min()) if v.size else 0.0,
                    "max": float(v.max()) if v.size else 0.0},
    }


def spin(iterations: int) -> int:
    """A pure-Python loop that holds the GIL (``iterations`` steps)."""
    s = 0
    for i in range(iterations):
        s = (s * 31 + i) % 1_000_003
    return s


@stage("toy_slow_cpu", outputs=("values",))
def toy_slow_cpu(values: np.ndarray, *, iterations: int = 1_000_000) -> dict:
    """CPU-bound work: ``values + spin(iterations) % 7``."""
    return {"values": np.asarray(values) + spin(iterations) % 7}


@stage("toy_fail_on", outputs=("values",))
def toy_fail_on(values: np.ndarray, *, pattern: str = "bad", ctx: Context) -> dict:
    """Pass through, but raise ``ValueError`` when the part id contains ``pattern``."""
    if pattern and ctx.part is not None and pattern in ctx.part:
        raise ValueError(f"part {ctx.part!r} matches {pattern!r}")
    return {"values": np.asarray(values)}


@stage("toy_flaky", outputs=("values",), retries=2)
def toy_flaky(values: np.ndarray, *, marker_dir: str, fail_times: int = 1,
              ctx: Context) -> dict:
    """Fail the first ``fail_times`` attempts (attempts counted as files in ``marker_dir``)."""
    d = Path(marker_dir)
    d.mkdir(parents=True, exist_ok=True)
    attempt = len(list(d.iterdir()))
    (d / f"attempt{attempt}").write_text(str(ctx.part))
    if attempt < fail_times:
        raise RuntimeError(f"flaky failure {attempt + 1} of {fail_times}")
    return {"values": np.asarray(values)}


def _square_chunk(chunk: np.ndarray) -> tuple[np.ndarray, int]:
    return chunk**2, os.getpid()


@stage("toy_map", outputs=("values", "pids"))
def toy_map(values: np.ndarray, *, chunks: int = 4, ctx: Context) -> dict:
    """Square the values through ``ctx.map`` over ``chunks`` pieces.

    Returns
    -------
    values : (N,) float ndarray
    pids : list of int
        Process id that computed each chunk (shows where the map ran).
    """
    pieces = np.array_split(np.asarray(values), chunks)
    res = ctx.map(_square_chunk, pieces)
    return {"values": np.concatenate([r[0] for r in res]), "pids": [int(r[1]) for r in res]}


@stage("toy_sleep", outputs=("values",))
def toy_sleep(values: np.ndarray, *, seconds: float = 0.5) -> dict:
    """Sleep, then pass ``values`` through."""
    time.sleep(seconds)
    return {"values": np.asarray(values)}


def _sleep_item(i: int, *, seconds: float) -> int:
    time.sleep(seconds)
    return i * i


@stage("toy_map_sleep", outputs=("values",))
def toy_map_sleep(values: np.ndarray, *, items: int = 8, seconds: float = 0.5,
                  ctx: Context) -> dict:
    """``ctx.map`` a ``seconds`` sleep over ``items`` items, reporting ``"items"`` progress.

    Returns
    -------
    values : (items,) int ndarray
        ``i**2`` for item ``i``, in item order (``values`` is ignored).
    """
    res = ctx.map(functools.partial(_sleep_item, seconds=seconds), range(items),
                  progress="items")
    return {"values": np.asarray(res, dtype=np.int64)}


@stage("toy_warn", outputs=("values",))
def toy_warn(values: np.ndarray, *, message: str = "toy warning", times: int = 1,
             ctx: Context) -> dict:
    """Pass ``values`` through; ``ctx.warn(message)`` ``times`` times."""
    for _ in range(times):
        ctx.warn(message)
    return {"values": np.asarray(values)}


@stage("toy_die", outputs=("values",))
def toy_die(values: np.ndarray, *, pattern: str = "die", ctx: Context) -> dict:
    """Pass through, but end this process at once (``os._exit``) when the part matches."""
    if pattern and ctx.part is not None and pattern in ctx.part:
        os._exit(17)
    return {"values": np.asarray(values)}


# --------------------------------------------------------------------------- helpers

#: A toy graph: read files → add → scale → (per part) and a gather sum.
TOY_CONFIG = """\
graph: toy
description: toy graph for engine tests
params:
  amount: 1.0
parts:
  - {parts}
targets: [total]
nodes:
  read:
    stage: toy_read_file
    inputs: {{path: part}}
  add:
    stage: toy_add
    inputs: {{values: read.values}}
    params: {{amount: ${{params.amount}}}}
  scale:
    stage: toy_scale
    inputs: {{values: add.values}}
    params: {{factor: 2.0}}
  total:
    stage: toy_sum
    inputs: {{values: scale.values}}
    gather: true
"""


def write_number_files(directory: str | os.PathLike, n: int, *, length: int = 5,
                       prefix: str = "trial") -> list[Path]:
    """Write ``n`` text files of numbers (``trial000.txt`` … holds ``i, i+1, …``).

    Returns
    -------
    list of Path
    """
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    out = []
    for i in range(n):
        p = d / f"{prefix}{i:03d}.txt"
        p.write_text(" ".join(str(float(i + j)) for j in range(length)) + "\n")
        out.append(p)
    return out


def write_config(path: str | os.PathLike, text: str, **fmt: Any) -> Path:
    """Write a (dedented) config, ``str.format``-ing ``fmt`` into it when given."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    body = textwrap.dedent(text)
    p.write_text(body.format(**fmt) if fmt else body)
    return p


def assert_stage_contract(name: str, inputs: Sequence[Any] = (),
                          params: Mapping[str, Any] | None = None, *,
                          part: str | None = "contract") -> dict:
    """Check a registered stage against the engine contract and return its outputs.

    Checks: the params validate; the stage returns exactly its declared outputs;
    every output encodes and decodes to the same digest; two calls with the same
    part and seed give identical digests (purity, randomness only from ``ctx``),
    the second with a ``ctx.map`` as on 3 workers (outputs must not depend on how
    the work was cut).

    Parameters
    ----------
    name : str
        Registered stage name.
    inputs : sequence
        Positional inputs.
    params : mapping, optional
        Params (validated, defaults filled).
    part : str or None
        Part id for the context.

    Returns
    -------
    dict
        The outputs of the first call.
    """
    spec = get_stage(name)
    full = validate_params(spec, dict(params or {}))

    def call(**ctx_kw: Any) -> dict:
        kw = dict(full)
        if spec.wants_ctx:
            kw["ctx"] = Context(part=part, seed=int(full.get("seed", 0) or 0), **ctx_kw)
        return dict(spec.func(*inputs, **kw))

    first = call()
    assert set(first) == set(spec.outputs), (
        f"stage {name!r} returned {sorted(first)}, declared {sorted(spec.outputs)}")
    # the second call as on a 3-worker cluster: ``ctx.map`` work cut in other chunks
    second = call(mapper=lambda fn, items: [fn(x) for x in items], workers=3)
    for out in spec.outputs:
        enc = codecs.encode(first[out])
        d1 = codecs.digest_encoded(enc)
        back = codecs.encode(codecs.decode(enc))
        assert codecs.digest_encoded(back) == d1, f"{name}.{out}: codec round trip differs"
        assert codecs.digest_encoded(codecs.encode(second[out])) == d1, (
            f"{name}.{out}: two calls with the same part and seed differ (impure stage, or "
            "one whose result depends on ctx.workers?)")
    return first


@stage("toy_progress", outputs=("values",))
def toy_progress(values: np.ndarray, *, steps: int = 100, seconds: float = 0.0,
                 message: str = "", hint: str = "", ctx: Context) -> dict:
    """Pass ``values`` through, calling ``ctx.progress(i, steps, "steps")`` for i = 1..steps.

    ``seconds`` are slept over the steps; a ``message`` is warned once, with ``hint``.
    """
    for i in range(1, steps + 1):
        if seconds:
            time.sleep(seconds / steps)
        ctx.progress(i, steps, "steps")
    if message:
        ctx.warn(message, hint=hint or None)
    return {"values": np.asarray(values)}


@stage("toy_read_ref", outputs=("values",), file_overrides={"path": "ref"})
def toy_read_ref(path: FilePath, *, ref: FilePath | None = None) -> dict:
    """Numbers of the reference file ``ref`` or, without one, of the part ``path``.

    A file override (``file_overrides={"path": "ref"}``): when ``ref`` is set the
    engine passes it as ``path`` too, and runs one task per distinct ``ref`` file
    (a toy range-of-motion trial, for session tests).
    """
    return {"values": read_numbers(ref if ref is not None else path)}
