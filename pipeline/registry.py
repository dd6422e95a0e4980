"""Stage registry: the ``@stage`` decorator, parameter validation and discovery.

A *stage* is a plain function.  Its positional parameters are **inputs** (wired
from the graph; one defaulting to ``None`` is optional and may be left
unwired); its keyword-only parameters are **params** (validated from the
type hints, defaults filled).  A keyword-only parameter named ``ctx`` is not a
param: the engine passes a :class:`~mocapflow.pipeline.context.Context` there.
The function returns a mapping of named outputs (the names declared in
``outputs=``).

The engine never imports the domain package.  Built-in stage families are found
through the ``mocapflow.stages`` entry-point group (the project declares its own
``mocapflow.stages`` package there), so third-party families plug in the same way.
"""

from __future__ import annotations

import difflib
import functools
import importlib
import inspect
import math
import reprlib
import types
import typing
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from importlib import metadata
from typing import Any, Literal, NewType, get_args, get_origin

from mocapflow.pipeline.blas import single_threaded_blas
from mocapflow.pipeline.context import Context

__all__ = [
    "MAX_PARAM_MAGNITUDE",
    "FilePath",
    "ParamError",
    "StageSpec",
    "discover",
    "family_modules",
    "find_stage",
    "get_stage",
    "lookup",
    "registered_stages",
    "report_figures",
    "report_provider",
    "stage",
    "validate_params",
]

#: Annotation for an input that is a raw file on disk (a part's file).  The engine
#: passes its path as a ``str`` and keys the task on the file's *content*.
FilePath = NewType("FilePath", str)

ENTRY_POINT_GROUP = "mocapflow.stages"
#: Largest magnitude of a number param (``int`` or ``float``); see :func:`coerce`.
MAX_PARAM_MAGNITUDE = 1e12
#: A ``seed`` param is an integer in ``[0, SEED_LIMIT)`` (the context keeps 32 bits).
SEED_LIMIT = 2**32
_show = reprlib.Repr()
_show.maxstring = _show.maxother = 60
_show.maxlong = 30


class ParamError(ValueError):
    """A param value does not fit the stage's signature."""


@dataclass(frozen=True)
class StageSpec:
    """What the engine knows about one registered stage.

    Attributes
    ----------
    name : str
        Registry name used in graph configs (``stage: clean``).
    func : callable
        The stage function.
    inputs : tuple of str
        Positional parameter names, in order.
    optional_inputs : tuple of str
        Inputs with a default of ``None``: they may be left unwired in a graph
        (and left out in a Python call); the stage then gets ``None``.
    input_types : dict
        Annotation of each input (resolved where possible).
    params : dict
        ``name -> (annotation, default)``; default is ``inspect.Parameter.empty``
        for a required param.
    outputs : tuple of str
        Names of the outputs the function returns.
    version : str or None
        Manual version pin: when set it replaces the code fingerprint in the key.
    wants_ctx : bool
        Whether the function takes the keyword-only ``ctx``.
    module : str
        Module in which the function is defined (for code fingerprints).
    description : str
        First line of the docstring.
    """

    name: str
    func: Callable[..., Mapping[str, Any]]
    inputs: tuple[str, ...]
    input_types: dict[str, Any]
    params: dict[str, tuple[Any, Any]]
    outputs: tuple[str, ...]
    version: str | None
    wants_ctx: bool
    module: str
    description: str = ""
    retries: int = 0
    extra: dict[str, Any] = field(default_factory=dict)
    optional_inputs: tuple[str, ...] = ()

    def file_inputs(self) -> tuple[str, ...]:
        """Names of inputs annotated as :data:`FilePath`."""
        return tuple(n for n in self.inputs if self.input_types.get(n) is FilePath)


_REGISTRY: dict[str, StageSpec] = {}
_DISCOVERED = False


def stage(
    name: str | None = None,
    *,
    outputs: tuple[str, ...] | list[str],
    version: str | None = None,
    retries: int = 0,
    sidecars: Mapping[str, Callable[[str], str]] | None = None,
    file_overrides: Mapping[str, str] | None = None,
    output_dims: Mapping[str, Sequence[str]] | None = None,
) -> Callable[[Callable[..., Mapping[str, Any]]], Callable[..., Mapping[str, Any]]]:
    """Register a function as a stage.

    Parameters
    ----------
    name : str, optional
        Registry name; defaults to the function name.
    outputs : sequence of str
        Names of the outputs in the mapping the function returns.
    version : str, optional
        Manual version pin; when given, the code fingerprint is replaced by it
        (bump it to invalidate, or keep it to survive a refactor).
    retries : int
        How many times the engine retries a failed task of this stage.
    sidecars : mapping, optional
        ``param -> resolver(input_file) -> path`` for ``FilePath`` params whose
        default is a file found beside the task's input file (an AMC's ASF).
        When the param is left ``None`` the engine resolves the path while
        building the graph, so the stage receives it explicitly and the file's
        content enters the cache key like any declared file.
    file_overrides : mapping, optional
        ``input -> param``: when a node sets ``param`` (a ``FilePath`` param),
        its ``input`` wired to ``part`` reads that file instead of each part's
        file, so the node runs once and is broadcast to every part (a
        range-of-motion trial shared by all trials).
    output_dims : mapping, optional
        ``output -> dimension names`` of an output returned as a bare ndarray
        (stored with these ``dimension_names`` instead of ``dim_0 …``).

    Returns
    -------
    decorator
        Returns the stage itself, callable from Python exactly as the engine
        calls it: inputs positional (or by name), params by keyword, validated
        and defaults filled as in a graph (:func:`validate_params`); ``ctx``
        may be left out (a :class:`~mocapflow.pipeline.context.Context` seeded
        from the ``seed`` param is made).  It returns the mapping of outputs.
        The undecorated function is ``StageSpec.func`` (and ``__wrapped__``).
    """

    def decorate(func: Callable[..., Mapping[str, Any]]) -> Callable[..., Mapping[str, Any]]:
        spec = _build_spec(func, name or func.__name__, tuple(outputs), version, retries)
        if sidecars:
            unknown = set(sidecars) - set(spec.params)
            if unknown:
                raise TypeError(f"stage {spec.name!r}: sidecars for unknown params {unknown}")
            spec.extra["sidecars"] = dict(sidecars)
        if file_overrides:
            bad = {i for i in file_overrides if i not in spec.inputs} | {
                p for p in file_overrides.values() if p not in spec.params}
            if bad:
                raise TypeError(f"stage {spec.name!r}: file_overrides name unknown inputs or "
                                f"params {sorted(bad)}")
            spec.extra["file_overrides"] = dict(file_overrides)
        if output_dims:
            unknown = set(output_dims) - set(spec.outputs)
            if unknown:
                raise TypeError(f"stage {spec.name!r}: output_dims for unknown outputs "
                                f"{sorted(unknown)}")
            spec.extra["output_dims"] = {o: tuple(d) for o, d in output_dims.items()}
        previous = _REGISTRY.get(spec.name)
        if previous is not None and (
            previous.module != spec.module or previous.func.__qualname__ != func.__qualname__
        ):
            first = f"{previous.module}.{previous.func.__qualname__}"
            second = f"{spec.module}.{func.__qualname__}"
            raise ValueError(f"stage name {spec.name!r} registered twice: {first} and {second}")
        _REGISTRY[spec.name] = spec

        @functools.wraps(func)
        def call_stage(*args: Any, **kwargs: Any) -> Mapping[str, Any]:
            return call(spec, *args, **kwargs)

        call_stage.__mocapflow_stage__ = spec  # type: ignore[attr-defined]
        return call_stage

    return decorate


def call(spec: StageSpec, *args: Any, **kwargs: Any) -> Mapping[str, Any]:
    """Call a stage from Python as the engine does: params validated, a context made, BLAS
    and OpenMP at one thread while it runs (:func:`~mocapflow.pipeline.blas.single_threaded_blas`).

    Parameters
    ----------
    spec : StageSpec
    *args
        Inputs, in the stage's order.
    **kwargs
        Inputs by name, params, and optionally ``ctx``.

    Returns
    -------
    mapping
        The stage's outputs.

    Raises
    ------
    TypeError
        A missing or unexpected input (as for any Python call).
    ParamError
        A param that does not validate (the message names it).
    """
    ctx = kwargs.pop("ctx", None)
    if len(args) > len(spec.inputs):
        raise TypeError(f"stage {spec.name!r} takes {len(spec.inputs)} inputs "
                        f"({', '.join(spec.inputs) or 'none'}), got {len(args)}")
    inputs = dict(zip(spec.inputs, args))
    for name in spec.inputs[len(args):]:
        if name not in kwargs and name not in spec.optional_inputs:
            raise TypeError(f"stage {spec.name!r}: missing input {name!r}")
        inputs[name] = kwargs.pop(name, None)
    params = validate_params(spec, kwargs)
    if spec.wants_ctx:
        if ctx is None:
            ctx = Context(seed=int(params.get("seed", 0) or 0))
        params["ctx"] = ctx
    with single_threaded_blas():  # as the engine runs it: the same bits, no oversubscription
        return spec.func(*(inputs[n] for n in spec.inputs), **params)


def _build_spec(func, name, outputs, version, retries) -> StageSpec:
    sig = inspect.signature(func)
    try:
        hints = typing.get_type_hints(func)
    except Exception:  # unresolved forward references: fall back to raw annotations
        hints = {k: v.annotation for k, v in sig.parameters.items()}
    inputs: list[str] = []
    optional: list[str] = []
    input_types: dict[str, Any] = {}
    params: dict[str, tuple[Any, Any]] = {}
    wants_ctx = False
    for p in sig.parameters.values():
        if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD):
            inputs.append(p.name)
            input_types[p.name] = hints.get(p.name, Any)
            if p.default is not p.empty:
                if p.default is not None:
                    raise TypeError(f"stage {name!r}: input {p.name!r} may only default to "
                                    f"None (an optional input), got {p.default!r}")
                optional.append(p.name)
        elif p.kind == p.KEYWORD_ONLY:
            if p.name == "ctx":
                wants_ctx = True
                continue
            params[p.name] = (hints.get(p.name, Any), p.default)
        else:
            raise TypeError(f"stage {name!r}: *args/**kwargs are not allowed ({p.name})")
    doc = inspect.getdoc(func) or ""
    return StageSpec(
        name=name,
        func=func,
        inputs=tuple(inputs),
        input_types=input_types,
        params=params,
        outputs=outputs,
        version=version,
        wants_ctx=wants_ctx,
        module=func.__module__,
        description=doc.splitlines()[0] if doc else "",
        retries=retries,
        optional_inputs=tuple(optional),
    )


def discover() -> None:
    """Import every stage family registered under the ``mocapflow.stages`` entry points."""
    global _DISCOVERED
    if _DISCOVERED:
        return
    _DISCOVERED = True
    for ep in metadata.entry_points(group=ENTRY_POINT_GROUP):
        load_family(ep.value)


def family_modules(target: str) -> tuple[str, dict[str, tuple[str, ...] | None]]:
    """The modules of one stage family named like an entry point value.

    Parameters
    ----------
    target : str
        ``"package.module"`` (a module imported for its registrations), or
        ``"package:ATTR"`` where ``ATTR`` names the family's submodules that
        register stages, codecs or exporters: a mapping ``submodule -> stage
        names it defines`` (the engine then imports only the submodule of a
        stage it needs), or a plain sequence of submodule names.

    Returns
    -------
    package : str
    modules : dict
        ``full module name -> stage names`` (``None``: not declared).
    """
    module, _, attr = target.partition(":")
    mod = importlib.import_module(module.strip())
    if not attr:
        return mod.__name__, {mod.__name__: None}
    declared = getattr(mod, attr.strip())
    if isinstance(declared, Mapping):
        return mod.__name__, {f"{mod.__name__}.{m}": tuple(n) for m, n in declared.items()}
    return mod.__name__, {f"{mod.__name__}.{m}": None for m in declared}


def load_family(target: str) -> None:
    """Import every module of one stage family (see :func:`family_modules`)."""
    for name in family_modules(target)[1]:
        importlib.import_module(name)


def find_stage(name: str) -> StageSpec:
    """The stage ``name``, importing only the module that declares it where possible.

    Families that declare their stage names (:func:`family_modules`) are looked
    up without importing their other modules; otherwise every family is loaded.

    Raises
    ------
    KeyError
        Unknown stage (the message has close matches).
    """
    spec = _REGISTRY.get(name)
    if spec is not None:
        return spec
    for ep in metadata.entry_points(group=ENTRY_POINT_GROUP):
        for module, names in family_modules(ep.value)[1].items():
            if names is not None and name in names:
                importlib.import_module(module)
                if name in _REGISTRY:
                    return _REGISTRY[name]
    return get_stage(name)


def registered_stages() -> dict[str, StageSpec]:
    """All registered stages, after discovery, by name."""
    discover()
    return dict(sorted(_REGISTRY.items()))


def lookup(name: str) -> StageSpec | None:
    """The stage registered under ``name`` so far, without discovery (``None`` if none yet)."""
    return _REGISTRY.get(name)


def get_stage(name: str) -> StageSpec:
    """Look a stage up by name; ``KeyError`` with close matches when unknown."""
    discover()
    try:
        return _REGISTRY[name]
    except KeyError:
        close = difflib.get_close_matches(name, list(_REGISTRY), n=3)
        hint = f" (did you mean {', '.join(close)}?)" if close else ""
        raise KeyError(f"unknown stage {name!r}{hint}") from None


# --------------------------------------------------------------------------- report figures

#: ``stage name -> provider`` of the figures ``mocapflow report`` shows per task.
_REPORT_PROVIDERS: dict[str, Callable[..., Any]] = {}


def report_figures(*names: str) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """Register the report provider of one or more stages (``@report_figures("clean")``).

    A provider is ``fn(outputs, entry) -> list of (title, item)``: ``outputs`` maps
    each output name of a committed entry to its decoded value, ``entry`` is a
    :class:`~mocapflow.pipeline.report.ReportEntry` (node, part, manifest, and
    ``entry.upstream(input)`` for the decoded outputs an input was wired to).  An
    item is a matplotlib ``Figure``, an ``(H, W, 3|4)`` uint8 image or an HTML
    fragment (:func:`~mocapflow.pipeline.report.html_table`).  Families register
    providers in a module listed in their ``STAGE_MODULES``, so discovery finds them.

    Parameters
    ----------
    *names : str
        Stage names the provider draws.

    Returns
    -------
    decorator
        Returns the function unchanged.
    """
    if not names:
        raise TypeError("report_figures needs at least one stage name")

    def decorate(fn: Callable[..., Any]) -> Callable[..., Any]:
        for n in names:
            previous = _REPORT_PROVIDERS.get(n)
            if previous is not None and (previous.__module__, previous.__qualname__) != (
                    fn.__module__, fn.__qualname__):
                raise ValueError(f"report figures of stage {n!r} registered twice: "
                                 f"{previous.__module__}.{previous.__qualname__} and "
                                 f"{fn.__module__}.{fn.__qualname__}")
            _REPORT_PROVIDERS[n] = fn
        return fn

    return decorate


def report_provider(name: str) -> Callable[..., Any] | None:
    """The report provider of stage ``name`` after discovery (``None``: the stage has none)."""
    discover()
    return _REPORT_PROVIDERS.get(name)


# --------------------------------------------------------------------------- params


def validate_params(spec: StageSpec, given: Mapping[str, Any]) -> dict[str, Any]:
    """Check ``given`` against the stage's keyword-only params and fill defaults.

    Parameters
    ----------
    spec : StageSpec
    given : mapping
        Params from the graph config / command line.

    Returns
    -------
    dict
        Every param of the stage, in signature order, with defaults filled.

    Raises
    ------
    ParamError
        Unknown param, missing required param, a value of the wrong type or out
        of range (see :func:`coerce`; a ``seed`` param must be an integer in
        ``[0, 2**32)``: the context keeps 32 bits of it, so larger seeds would
        repeat smaller ones).  The message names the param.
    """
    unknown = sorted(set(given) - set(spec.params))
    if unknown:
        hints = []
        for u in unknown:
            close = difflib.get_close_matches(u, list(spec.params), n=1)
            hints.append(f"{u!r}" + (f" (did you mean {close[0]!r}?)" if close else ""))
        raise ParamError(f"unknown param {', '.join(hints)} for stage {spec.name!r}")
    out: dict[str, Any] = {}
    for pname, (ann, default) in spec.params.items():
        if pname in given:
            out[pname] = coerce(given[pname], ann, where=f"{spec.name}.{pname}")
            v = out[pname]
            if pname == "seed" and isinstance(v, int) and not 0 <= v < SEED_LIMIT:
                raise ParamError(f"param {spec.name}.seed: a seed must be in [0, 2**32), got "
                                 f"{_show.repr(v)}")
        elif default is inspect.Parameter.empty:
            raise ParamError(f"missing required param {pname!r} for stage {spec.name!r}")
        else:
            out[pname] = default
    return out


def coerce(value: Any, ann: Any, *, where: str) -> Any:
    """Validate ``value`` against annotation ``ann`` (lenient int→float only).

    Supported annotations: ``Any``, ``bool``, ``int``, ``float``, ``str``,
    ``None``, ``Literal[...]``, ``X | Y`` / ``Optional``, ``list[T]``,
    ``tuple[T, ...]``, ``dict[K, V]``.

    Numbers: an ``int`` param takes an integer (not a bool, not ``3.0``), a
    ``float`` param an integer or a float; either must be finite (``.inf`` and
    ``.nan`` are refused) and at most :data:`MAX_PARAM_MAGNITUDE` (``1e12``) in
    magnitude, so a value no stage can mean (``1e14`` frames, a 400-digit
    number) fails here, naming the param, not later in a worker.  Values of an
    ``Any`` annotation are passed as given.

    Raises
    ------
    ParamError
        ``"param STAGE.NAME: ..."`` (values shown shortened).
    """
    if ann is Any or ann is inspect.Parameter.empty:
        return value
    origin = get_origin(ann)
    args = get_args(ann)
    if origin in (typing.Union, types.UnionType):
        errors = []
        for a in args:
            try:
                return coerce(value, a, where=where)
            except ParamError as e:
                errors.append(e)
        for e in errors:  # a member of the value's kind found a deeper problem: say it
            if isinstance(e, _RangeError) or not str(e).startswith(f"param {where}: "):
                raise e
        raise ParamError(f"param {where}: {_show.repr(value)} does not fit {_fmt(ann)}")
    if origin is Literal:
        if value in args and type(value) in {type(a) for a in args}:
            return value
        raise ParamError(f"param {where}: {_show.repr(value)} is not one of {list(args)}")
    if ann is type(None) or ann is None:
        if value is None:
            return None
        raise ParamError(f"param {where}: expected null, got {_show.repr(value)}")
    if ann is bool:
        if isinstance(value, bool):
            return value
        raise ParamError(f"param {where}: expected a boolean, got {_show.repr(value)}")
    if ann is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return _check_number(value, where)
        raise ParamError(f"param {where}: expected an integer, got {_show.repr(value)}")
    if ann is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(_check_number(value, where))
        raise ParamError(f"param {where}: expected a number, got {_show.repr(value)}")
    if ann is str:
        if isinstance(value, str):
            return value
        raise ParamError(f"param {where}: expected a string, got {_show.repr(value)}")
    if origin in (list, tuple) or ann in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise ParamError(f"param {where}: expected a list, got {_show.repr(value)}")
        if origin is tuple and args and not (len(args) == 2 and args[1] is Ellipsis):
            if len(args) != len(value):
                raise ParamError(f"param {where}: expected {len(args)} items, got {len(value)}")
            pairs = enumerate(zip(value, args))
            return [coerce(v, a, where=f"{where}[{i}]") for i, (v, a) in pairs]
        item = args[0] if args else Any
        return [coerce(v, item, where=f"{where}[{i}]") for i, v in enumerate(value)]
    if origin is dict or ann is dict:
        if not isinstance(value, Mapping):
            raise ParamError(f"param {where}: expected a mapping, got {_show.repr(value)}")
        kt, vt = args if args else (Any, Any)
        return {
            coerce(k, kt, where=f"{where} key"): coerce(v, vt, where=f"{where}.{k}")
            for k, v in value.items()
        }
    return value


class _RangeError(ParamError):
    """A number of the right kind, but not finite or too large."""


def _check_number(value: int | float, where: str) -> int | float:
    """``value`` if finite and at most :data:`MAX_PARAM_MAGNITUDE` in magnitude."""
    if isinstance(value, float) and not math.isfinite(value):
        raise _RangeError(f"param {where}: expected a finite number, got {value!r}")
    if abs(value) > MAX_PARAM_MAGNITUDE:
        raise _RangeError(f"param {where}: {_show.repr(value)} is out of range (at most 1e12 in "
                         "magnitude)")
    return value


def _fmt(ann: Any) -> str:
    return getattr(ann, "__name__", None) or str(ann).replace("typing.", "")
