"""Code fingerprints: the source of every definition a stage statically reaches.

A stage's key carries a fingerprint of the code it computes with.  Starting from
the stage function, :func:`code_fingerprint` follows every name the function's
source uses — module-level functions, classes and constants of its own module,
names imported from in-project modules (``from x import f``, ``import x as m``
then ``m.f``, relative imports, imports inside functions, re-exports) — and
digests the docstring-free AST of each definition reached, transitively.  So:

* editing a function the stage reaches changes its key;
* editing a function it does not reach does not, even when the two share a
  module (``read_bvh`` and ``write_bvh``): exporters, simulators and plotting
  code invalidate only the stages that call them;
* comments, docstrings, formatting and moving code within a module change
  nothing (definitions are digested without line numbers).

Granularity is the top-level definition: a class is digested whole (its
methods are not resolved separately: ``obj.method()`` cannot be resolved
statically, so every method of a reachable class counts).  A module-level name
bound several times (``try: import x / except: x = None``) counts every binding.
Top-level statements that bind nothing (``register(...)``) count for every
definition of their module that is reached.  Names that cannot be resolved
statically (attributes of objects, ``getattr`` by string) are outside the
fingerprint; a manual version pin (``@stage(version=...)``) overrides it.
Modules outside ``package`` (numpy, scipy, ...) are not followed: their versions
enter the key separately.
"""

from __future__ import annotations

import ast
import importlib.util
import os
import sys
import threading
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

from mocapflow.pipeline.keys import digest, digest_of

__all__ = ["clear_caches", "code_definitions", "code_fingerprint", "code_modules"]

_LOCK = threading.Lock()
_MODULES: dict[str, _Module | None] = {}
_FINGERPRINTS: dict[tuple[str, str, tuple[str, ...]], str] = {}
_IS_MODULE: dict[str, bool] = {}

#: ``(module, name)`` of a reached top-level definition; ``name`` is ``None`` for
#: the module's own unbound top-level statements.
Definition = tuple[str, "str | None"]


def clear_caches() -> None:
    """Forget parsed modules and memoised fingerprints (after editing source)."""
    with _LOCK:
        _MODULES.clear()
        _FINGERPRINTS.clear()
        _IS_MODULE.clear()
    importlib.invalidate_caches()


# --------------------------------------------------------------------------- parsing


def _strip_docstrings(tree: ast.AST) -> ast.AST:
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            body = node.body
            if (
                body
                and isinstance(body[0], ast.Expr)
                and isinstance(body[0].value, ast.Constant)
                and isinstance(body[0].value.value, str)
            ):
                node.body = body[1:] or [ast.Pass()]
    return tree


def _find_spec(name: str) -> Any:
    try:
        return importlib.util.find_spec(name)
    except (ImportError, ValueError, AttributeError):
        return None


def _is_module(name: str) -> bool:
    with _LOCK:
        hit = _IS_MODULE.get(name)
    if hit is None:
        hit = name in sys.modules or _find_spec(name) is not None
        with _LOCK:
            _IS_MODULE[name] = hit
    return hit


@dataclass
class _Module:
    """One parsed module: what each top-level name is bound to."""

    name: str
    package: str  # the package relative imports resolve against
    defs: dict[str, list[ast.stmt]] = field(default_factory=dict)
    imports: dict[str, tuple[str, str | None]] = field(default_factory=dict)
    unbound: list[ast.stmt] = field(default_factory=list)
    source_digest: str | None = None  # set for modules without parseable source
    #: ``id(stmt) -> (digest, name chains it uses, import bindings inside it)``
    info: dict[int, tuple[str, set[tuple[str, ...]], dict[str, tuple[str, str | None]]]] = field(
        default_factory=dict)

    def statement(self, stmt: ast.stmt
                  ) -> tuple[str, set[tuple[str, ...]], dict[str, tuple[str, str | None]]]:
        """Digest, name chains and local imports of one of this module's statements."""
        hit = self.info.get(id(stmt))
        if hit is None:
            chains, local_imports = _chains(stmt)
            bindings: dict[str, tuple[str, str | None]] = {}
            for imp in local_imports:
                bindings.update(_import_bindings(imp, self.package))
            hit = (digest(ast.dump(stmt, include_attributes=False)), chains, bindings)
            with _LOCK:
                self.info[id(stmt)] = hit
        return hit


def _targets(node: ast.AST) -> list[str]:
    """Top-level names an assignment target binds or mutates (``X[k] = v`` mutates X)."""
    if isinstance(node, ast.Name):
        return [node.id]
    if isinstance(node, (ast.Tuple, ast.List)):
        return [n for elt in node.elts for n in _targets(elt)]
    if isinstance(node, ast.Starred):
        return _targets(node.value)
    if isinstance(node, (ast.Attribute, ast.Subscript)):
        return _targets(node.value)
    return []


def _import_bindings(node: ast.Import | ast.ImportFrom, package: str
                     ) -> list[tuple[str, tuple[str, str | None]]]:
    """``(bound name, (module, attribute or None))`` for one import statement."""
    out: list[tuple[str, tuple[str, str | None]]] = []
    if isinstance(node, ast.Import):
        for alias in node.names:
            if alias.asname:
                out.append((alias.asname, (alias.name, None)))
            else:  # ``import a.b.c`` binds ``a``; ``a.b.c.f`` is resolved by attribute
                root = alias.name.split(".", 1)[0]
                out.append((root, (root, None)))
        return out
    if node.level:
        try:
            base = importlib.util.resolve_name("." * node.level + (node.module or ""), package)
        except (ImportError, ValueError):
            return out
    else:
        base = node.module or ""
    for alias in node.names:
        if alias.name != "*":
            out.append((alias.asname or alias.name, (base, alias.name)))
    return out


def _index(tree: ast.Module, mod: _Module) -> None:
    def visit(stmts: Iterable[ast.stmt]) -> None:
        for s in stmts:
            if isinstance(s, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                mod.defs.setdefault(s.name, []).append(s)
            elif isinstance(s, (ast.Import, ast.ImportFrom)):
                for name, target in _import_bindings(s, mod.package):
                    mod.imports[name] = target
            elif isinstance(s, (ast.Assign, ast.AnnAssign, ast.AugAssign)):
                targets = s.targets if isinstance(s, ast.Assign) else [s.target]
                names = [n for t in targets for n in _targets(t)]
                for n in names:
                    mod.defs.setdefault(n, []).append(s)
                if not names:
                    mod.unbound.append(s)
            elif isinstance(s, (ast.If, ast.Try, ast.With, ast.For, ast.While)):
                for attr in ("body", "orelse", "finalbody"):
                    visit(getattr(s, attr, []))
                for h in getattr(s, "handlers", []):
                    visit(h.body)
            elif isinstance(s, ast.Expr) and isinstance(s.value, ast.Constant):
                continue  # a docstring or a bare constant
            else:
                mod.unbound.append(s)

    visit(tree.body)


def _read_source(origin: str) -> bytes | None:
    """The bytes of a module's source file (``None`` when it is not a file)."""
    if not os.path.isfile(origin):
        return None
    with open(origin, "rb") as f:
        return f.read()


def _load_module(name: str) -> _Module | None:
    """The parsed module ``name`` (``None`` when it cannot be found)."""
    with _LOCK:
        if name in _MODULES:
            return _MODULES[name]
    spec = _find_spec(name)
    origin = getattr(spec, "origin", None) if spec is not None else None
    if spec is None and getattr(sys.modules.get(name), "__file__", None):
        origin = sys.modules[name].__file__  # e.g. a script run as __main__
    is_pkg = spec is not None and spec.submodule_search_locations is not None
    mod: _Module | None = None
    if spec is not None or origin:
        mod = _Module(name, name if is_pkg else name.rpartition(".")[0])
        source = _read_source(origin) if origin else None
        if source is None:
            mod.source_digest = digest(f"nosource:{name}:{origin}")
        elif not origin.endswith(".py"):
            mod.source_digest = digest(source)
        else:
            try:
                tree = ast.parse(source, filename=origin)
            except SyntaxError:
                mod.source_digest = digest(source)
            else:
                _index(_strip_docstrings(tree), mod)  # type: ignore[arg-type]
    with _LOCK:
        _MODULES[name] = mod
    return mod


# --------------------------------------------------------------------------- references


def _chains(node: ast.AST) -> tuple[set[tuple[str, ...]], list[ast.Import | ast.ImportFrom]]:
    """Dotted name chains a statement uses (``np.linalg.norm`` → 3 names) and its imports."""
    chains: set[tuple[str, ...]] = set()
    imports: list[ast.Import | ast.ImportFrom] = []
    inner: set[int] = set()
    for n in ast.walk(node):
        if isinstance(n, (ast.Import, ast.ImportFrom)):
            imports.append(n)
        elif isinstance(n, ast.Attribute) and id(n) not in inner:
            parts: list[str] = []
            cur: ast.AST = n
            while isinstance(cur, ast.Attribute):
                parts.append(cur.attr)
                inner.add(id(cur.value))
                cur = cur.value
            if isinstance(cur, ast.Name):
                inner.add(id(cur))
                chains.add((cur.id, *reversed(parts)))
        elif isinstance(n, ast.Name) and id(n) not in inner:
            chains.add((n.id,))
    return chains, imports


class _Walker:
    """Collects the definitions reachable from some roots."""

    def __init__(self, package: str, exclude: tuple[str, ...], root_module: str) -> None:
        self.root_module = root_module  # always read, even when excluded
        self.prefix = package + "."
        self.package = package
        self.exclude = exclude
        self.reached: dict[Definition, list[str]] = {}
        self.todo: list[tuple[_Module, str]] = []

    def in_project(self, module: str) -> bool:
        if module == self.root_module:
            return True
        inside = module == self.package or module.startswith(self.prefix)
        excluded = any(module == e or module.startswith(e + ".") for e in self.exclude)
        return inside and not excluded

    def add_module(self, mod: _Module) -> None:
        key: Definition = (mod.name, None)
        if key in self.reached:
            return
        if mod.source_digest is not None:
            self.reached[key] = [mod.source_digest]
            return
        self.reached[key] = [mod.statement(s)[0] for s in mod.unbound]
        for s in mod.unbound:
            self.follow(mod, s)

    def add(self, module: str, name: str) -> None:
        """Reach ``module.name`` (a definition, a re-export or a submodule)."""
        if not self.in_project(module):
            return
        mod = _load_module(module)
        if mod is None:
            self.reached.setdefault((module, name), [digest(f"missing:{module}:{name}")])
            return
        self.add_module(mod)
        if (module, name) in self.reached:
            return
        if name in mod.defs:
            self.reached[(module, name)] = [mod.statement(s)[0] for s in mod.defs[name]]
            self.todo.append((mod, name))
        elif name in mod.imports:
            self.reached[(module, name)] = ["import"]
            self.resolve(mod.imports[name], ())
        elif _is_module(f"{module}.{name}"):
            self.add_all(f"{module}.{name}")
        elif mod.source_digest is None:  # bound dynamically: count the whole module
            self.reached[(module, name)] = ["unresolved"]
            self.add_all(module)

    def add_all(self, module: str) -> None:
        """Reach every top-level definition of ``module`` (it is used as a whole)."""
        if not self.in_project(module):
            return
        mod = _load_module(module)
        if mod is None:
            return
        self.add_module(mod)
        for name in mod.defs:
            self.add(module, name)

    def resolve(self, target: tuple[str, str | None], rest: tuple[str, ...]) -> None:
        """Reach ``target`` (an import binding) then the attribute chain ``rest`` on it."""
        module, attr = target
        if attr is not None:
            if _is_module(f"{module}.{attr}") and self.in_project(f"{module}.{attr}"):
                module = f"{module}.{attr}"
            else:
                self.add(module, attr)
                return
        for part in rest:  # walk submodules, then the first non-module attribute
            if self.in_project(f"{module}.{part}") and _is_module(f"{module}.{part}"):
                module = f"{module}.{part}"
                continue
            self.add(module, part)
            return
        self.add_all(module)

    def follow(self, mod: _Module, stmt: ast.stmt) -> None:
        _, chains, local = mod.statement(stmt)
        imports = {**mod.imports, **local} if local else mod.imports
        for chain in chains:
            head, rest = chain[0], chain[1:]
            if head in mod.defs:
                self.add(mod.name, head)
            elif head in imports:
                self.resolve(imports[head], rest)

    def run(self) -> None:
        while self.todo:
            mod, name = self.todo.pop()
            for stmt in mod.defs[name]:
                self.follow(mod, stmt)


def _walk(target: str, package: str, exclude: tuple[str, ...]) -> _Walker:
    module, _, name = target.partition(":")
    w = _Walker(package, exclude, module)
    if name:
        w.add(module, name.split(".", 1)[0])
    else:
        mod = _load_module(module)
        if mod is None:
            w.reached[(module, None)] = [digest(f"missing:{module}")]
        else:
            w.add_module(mod)
            for n in mod.defs:
                w.add(module, n)
    w.run()
    return w


# --------------------------------------------------------------------------- API


def code_fingerprint(
    target: str, *, package: str = "mocapflow", exclude: tuple[str, ...] = ()
) -> str:
    """Fingerprint of the code a function (or a whole module) computes with.

    Parameters
    ----------
    target : str
        ``"module:function"`` (a stage: ``"mocapflow.stages.skin.clean:clean"``;
        a dotted qualname counts its top-level definition), or ``"module"``
        (every top-level definition of the module).
    package : str
        Top-level package whose modules count as in-project and are followed.
    exclude : tuple of str
        Modules (and their submodules) not to follow, e.g. engine modules whose
        edits should not invalidate stored results.  The target's own module is
        always read.

    Returns
    -------
    str
        Digest over the sorted ``(module:name, digests of its docstring-free
        AST)`` of every definition reached (see the module docstring).
        Memoised per process (:func:`clear_caches` resets).
    """
    exclude = tuple(exclude)
    ck = (target, package, exclude)
    with _LOCK:
        hit = _FINGERPRINTS.get(ck)
    if hit is not None:
        return hit
    w = _walk(target, package, exclude)
    items = sorted([f"{m}:{n or ''}", d] for (m, n), d in w.reached.items())
    fp = digest_of(["code", items])
    with _LOCK:
        _FINGERPRINTS[ck] = fp
    return fp


def code_definitions(
    target: str, *, package: str = "mocapflow", exclude: tuple[str, ...] = ()
) -> list[str]:
    """The definitions :func:`code_fingerprint` covers, as sorted ``"module:name"``."""
    w = _walk(target, package, tuple(exclude))
    return sorted(f"{m}:{n}" for m, n in w.reached if n is not None)


def code_modules(
    target: str, *, package: str = "mocapflow", exclude: tuple[str, ...] = ()
) -> list[str]:
    """The modules :func:`code_fingerprint` reads for ``target`` (sorted)."""
    w = _walk(target, package, tuple(exclude))
    return sorted({m for m, _ in w.reached})
