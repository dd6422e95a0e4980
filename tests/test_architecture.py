"""The shape of the code: import rules, lazy registration, code fingerprints per definition.

The import graph is built from the source (imports inside functions included;
imports under ``if TYPE_CHECKING:`` left out, they never run):

* no import cycle among the modules of ``pipeline/`` and ``stages/``;
* ``pipeline`` never imports ``stages``;
* a paper package (skin, texture, variation) imports its own modules,
  ``motion``, ``metrics`` and the engine, never another paper's package;
  ``metrics`` imports ``motion`` and the engine; ``motion`` only itself and
  the engine.
"""

from __future__ import annotations

import ast
import json
import re
import subprocess
import sys
import tomllib
from importlib import metadata
from pathlib import Path

import pytest

from mocapflow.pipeline import fingerprint
from mocapflow.pipeline.registry import ENTRY_POINT_GROUP, family_modules, registered_stages
from mocapflow.pipeline.task_keys import stage_fingerprint

ROOT = Path(__file__).resolve().parents[1]
TREES = {"pipeline": "mocapflow.pipeline", "stages": "mocapflow.stages"}
PAPERS = ("skin", "texture", "variation")


# --------------------------------------------------------------------------- import graph


def module_name(path: Path) -> tuple[str, bool]:
    """``(dotted module name, is_package)`` of a source file of the two trees."""
    rel = path.relative_to(ROOT)
    parts = [TREES[rel.parts[0]], *rel.parts[1:]]
    if parts[-1] == "__init__.py":
        return ".".join(parts[:-1]), True
    parts[-1] = parts[-1][:-3]
    return ".".join(parts), False


def _type_checking_nodes(tree: ast.Module) -> set[int]:
    skip: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            skip.update(id(n) for stmt in node.body for n in ast.walk(stmt))
    return skip


def import_graph() -> dict[str, set[str]]:
    """``module -> in-project modules it imports`` for every module of the two trees."""
    files = {p: module_name(p) for tree in TREES for p in (ROOT / tree).rglob("*.py")}
    modules = {name for name, _ in files.values()}
    graph: dict[str, set[str]] = {}
    for path, (name, is_pkg) in files.items():
        tree = ast.parse(path.read_text(), filename=str(path))
        skip = _type_checking_nodes(tree)
        package = name if is_pkg else name.rpartition(".")[0]
        deps: set[str] = set()
        for node in ast.walk(tree):
            if id(node) in skip:
                continue
            if isinstance(node, ast.Import):
                deps.update(a.name for a in node.names)
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    base = ".".join(package.split(".")[: len(package.split(".")) - node.level + 1]
                                    + ([base] if base else []))
                subs = [f"{base}.{a.name}" for a in node.names if f"{base}.{a.name}" in modules]
                deps.update(subs or [base])
        graph[name] = {d for d in deps if d in modules and d != name}
    return graph


def family(module: str) -> str:
    """``pipeline``, ``motion``, ``metrics``, a paper's name, or ``stages`` (the root)."""
    parts = module.split(".")
    if parts[1] == "pipeline":
        return "pipeline"
    return parts[2] if len(parts) > 2 else "stages"


ALLOWED = {
    "pipeline": {"pipeline"},
    "stages": {"pipeline"},
    "motion": {"motion", "pipeline"},
    "metrics": {"metrics", "motion", "pipeline"},
    **{p: {p, "motion", "metrics", "pipeline"} for p in PAPERS},
}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def violations(graph: dict[str, set[str]]) -> list[str]:
    """Every broken import rule of the module docstring, one line each."""
    bad = [f"import cycle: {' -> '.join(c)}" for c in cycles(graph)]
    for mod, deps in sorted(graph.items()):
        fam = family(mod)
        for d in sorted(deps):
            if family(d) not in ALLOWED[fam]:
                bad.append(f"{mod} imports {d} ({fam} may import {sorted(ALLOWED[fam])})")
    return bad


def test_import_rules_hold():
    graph = import_graph()
    assert len(graph) > 40 and "mocapflow.stages.skin.clean" in graph
    assert violations(graph) == []


def test_import_rules_catch_cycles_engine_to_domain_and_paper_to_paper():
    graph = {
        "mocapflow.pipeline.runner": {"mocapflow.stages.motion.kinematics"},
        "mocapflow.stages.skin.a": {"mocapflow.stages.skin.b", "mocapflow.stages.texture.x"},
        "mocapflow.stages.skin.b": {"mocapflow.stages.skin.a", "mocapflow.stages.metrics.q"},
        "mocapflow.stages.metrics.q": {"mocapflow.stages.variation.y"},
        "mocapflow.stages.motion.kinematics": {"mocapflow.stages.metrics.q"},
    }
    bad = violations(graph)
    assert "import cycle: mocapflow.stages.skin.a -> mocapflow.stages.skin.b" in bad
    assert any(b.startswith("mocapflow.pipeline.runner imports mocapflow.stages") for b in bad)
    assert any(b.startswith("mocapflow.stages.skin.a imports mocapflow.stages.texture")
               for b in bad)
    assert any(b.startswith("mocapflow.stages.metrics.q imports mocapflow.stages.variation")
               for b in bad)
    assert any(b.startswith("mocapflow.stages.motion.kinematics imports") for b in bad)
    assert len(bad) == 5


def test_function_level_imports_count():
    """Imports inside functions are seen (a lazy cross-paper import would be caught)."""
    src = "def f():\n    from mocapflow.stages.texture.synth import synth\n"
    tree = ast.parse(src)
    found = [n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
    assert found == ["mocapflow.stages.texture.synth"]


# --------------------------------------------------------------------------- lazy registration


def _python(code: str) -> str:
    return subprocess.run([sys.executable, "-c", code], check=True, capture_output=True,
                          text=True, cwd=ROOT).stdout


def test_importing_kinematics_loads_no_paper_package():
    out = _python("import sys, json, mocapflow.stages.motion.kinematics\n"
                  "print(json.dumps(sorted(m for m in sys.modules if m.startswith('mocapflow'))))")
    loaded = json.loads(out)
    assert "mocapflow.stages.motion.kinematics" in loaded
    papers = [m for m in loaded if any(f"mocapflow.stages.{p}" in m for p in PAPERS)]
    assert papers == []
    assert not any(m.startswith("mocapflow.stages.metrics") for m in loaded)


def test_cli_lists_every_stage_of_the_source():
    names = set()
    for p in (ROOT / "stages").rglob("*.py"):
        names.update(re.findall(r'^@stage\(\s*"([a-z_0-9]+)"', p.read_text(), re.M))
    assert len(names) >= 27
    out = subprocess.run([sys.executable, "-m", "mocapflow", "stages", "--json"], check=True,
                         capture_output=True, text=True, cwd=ROOT).stdout
    listed = {s["name"] for s in json.loads(out)}
    assert names <= listed


# --------------------------------------------------------------------------- fingerprints


def _edit_function(source: str, name: str) -> str:
    """``source`` with one statement added at the top of function ``name``'s body."""
    tree = ast.parse(source)
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef) and node.name == name:
            node.body.insert(0, ast.parse("_edited = 1").body[0])
            return ast.unparse(tree)
    raise AssertionError(f"no function {name}")


def _fingerprints_with(monkeypatch, module: str, function: str) -> dict[str, str]:
    """Every stage's code fingerprint with ``module.function`` edited."""
    real = fingerprint._read_source
    path = Path(sys.modules[module].__file__).resolve()
    edited = _edit_function(path.read_text(), function).encode()

    def read(origin: str) -> bytes | None:
        return edited if Path(origin).resolve() == path else real(origin)

    monkeypatch.setattr(fingerprint, "_read_source", read)
    fingerprint.clear_caches()
    try:
        return {n: stage_fingerprint(s) for n, s in registered_stages().items()}
    finally:
        monkeypatch.setattr(fingerprint, "_read_source", real)
        fingerprint.clear_caches()


@pytest.fixture(scope="module")
def fingerprints() -> dict[str, str]:
    fingerprint.clear_caches()
    return {n: stage_fingerprint(s) for n, s in registered_stages().items()}


@pytest.mark.parametrize(("module", "function", "reaching"), [
    # an exporter sharing its module with the reader every BVH stage uses
    ("mocapflow.stages.motion.formats.bvh", "write_bvh", set()),
    ("mocapflow.stages.motion.formats.c3d", "write_c3d", set()),
    ("mocapflow.stages.motion.export", "export_motion_bvh", set()),
    # code a stage computes with
    ("mocapflow.stages.motion.formats.bvh", "read_bvh", {"ingest_bvh"}),
])
def test_editing_code_changes_exactly_the_stages_that_reach_it(monkeypatch, fingerprints,
                                                               module, function, reaching):
    __import__(module)
    edited = _fingerprints_with(monkeypatch, module, function)
    changed = {n for n in fingerprints if edited[n] != fingerprints[n]}
    if reaching:
        assert reaching <= changed
    else:
        assert changed == set()
    untouched = {n for n, s in registered_stages().items()
                 if not any(d.endswith(f":{function}") for d in fingerprint.code_definitions(
                     f"{s.module}:{s.func.__qualname__}", exclude=("mocapflow.pipeline",)))}
    assert not (changed & untouched), "a stage that does not reach the code changed"
    assert changed == set(registered_stages()) - untouched


def test_every_package_directory_is_in_the_wheel():
    """A sub-package missing from pyproject's ``packages`` works editable, not from a wheel."""
    tool = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    dirs = tool["package-dir"]

    def directory(package: str) -> Path:
        prefix = max((p for p in dirs if package == p or package.startswith(p + ".")), key=len)
        rest = package[len(prefix):].lstrip(".").replace(".", "/")
        return (ROOT / dirs[prefix] / rest).resolve()

    listed = {directory(p) for p in tool["packages"]}
    on_disk = {p.parent.resolve() for d in ("pipeline", "stages", "configs", "mocapflow")
               for p in (ROOT / d).rglob("__init__.py")}
    assert sorted(map(str, on_disk - listed)) == []
    assert sorted(map(str, listed - on_disk)) == []


def test_declared_stage_names_match_the_decorators():
    """Each family's STAGE_MODULES names exactly the stages its modules register."""
    stages = registered_stages()
    seen = set()
    for ep in metadata.entry_points(group=ENTRY_POINT_GROUP):
        package, modules = family_modules(ep.value)
        for module, names in modules.items():
            defined = {n for n, s in stages.items() if s.module == module}
            assert names is not None, f"{package}: declare the stage names of {module}"
            assert set(names) == defined, module
            seen |= defined
    assert seen == {n for n, s in stages.items() if s.module.startswith("mocapflow.stages")}


def test_a_stage_name_imports_only_its_module():
    out = _python("import sys, json\nfrom mocapflow.pipeline.config import resolve_stage\n"
                  "resolve_stage('pyramid')\n"
                  "print(json.dumps(sorted(m for m in sys.modules if m.startswith('mocapflow'))))")
    loaded = json.loads(out)
    assert "mocapflow.stages.texture.pyramid" in loaded
    assert not [m for m in loaded if m.startswith(("mocapflow.stages.skin.",
                                                   "mocapflow.stages.variation.",
                                                   "mocapflow.stages.texture.synth"))]
