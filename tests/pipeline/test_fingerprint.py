"""Code fingerprints: every definition a stage reaches, and nothing else."""

from __future__ import annotations

import sys
import textwrap
import uuid

import pytest

from mocapflow.pipeline.fingerprint import (
    clear_caches,
    code_definitions,
    code_fingerprint,
    code_modules,
)


@pytest.fixture
def temp_package(tmp_path, monkeypatch):
    """A throw-away package ``pkg`` on sys.path; yields (name, root dir, write)."""
    name = f"fp_{uuid.uuid4().hex[:8]}"
    root = tmp_path / name
    files = {
        "__init__.py": "",
        "stage.py": '''
            """Stage module."""
            import json  # not in the project: not followed

            from . import consts
            from {pkg}.helpers import util
            from {pkg}.io import read_table


            def clean(x):
                """Clean it."""
                import {pkg}.deep.inner  # lazy import, still followed

                return util.scale(x) + consts.OFFSET + {pkg}.deep.inner.ONE


            def load(path):
                return read_table(path)


            def unused_here(x):
                return x - 1
            ''',
        "consts.py": "OFFSET = 1\nOTHER = 2\n",
        "helpers/__init__.py": "HELPERS_INIT = 1\n",
        "helpers/util.py": '''
            """Helpers."""
            from ..shared.base import FACTOR


            def scale(x):
                # multiply
                return x * FACTOR * _unit()


            def _unit():
                return UNIT


            UNIT = 1
            ''',
        "io.py": '''
            """A reader and a writer sharing one module."""
            from .shared.base import Table


            def read_table(path):
                return Table(path)


            def write_table(table, path):
                return str(table) + path
            ''',
        "shared/__init__.py": "",
        "shared/base.py": '''
            FACTOR = 2


            class Table:
                def __init__(self, path):
                    self.path = path

                def rows(self):
                    return [self.path]
            ''',
        "deep/__init__.py": "",
        "deep/inner.py": "ONE = 1\n",
        "unrelated.py": "Z = 0\n",
    }

    def write(rel: str, text: str) -> None:
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(textwrap.dedent(text).format(pkg=name).lstrip())

    for rel, text in files.items():
        write(rel, text)
    monkeypatch.syspath_prepend(str(tmp_path))
    clear_caches()
    yield name, root, write
    for mod in [m for m in sys.modules if m == name or m.startswith(name + ".")]:
        del sys.modules[mod]
    clear_caches()


def _fp(name: str, func: str = "clean") -> str:
    clear_caches()
    return code_fingerprint(f"{name}.stage:{func}", package=name)


def test_follows_names_through_imports(temp_package):
    name, _, _ = temp_package
    got = code_definitions(f"{name}.stage:clean", package=name)
    assert got == sorted(f"{name}.{d}" for d in (
        "stage:clean", "consts:OFFSET", "helpers.util:scale", "helpers.util:_unit",
        "helpers.util:UNIT", "shared.base:FACTOR", "deep.inner:ONE"))
    assert code_modules(f"{name}.stage:clean", package=name) == sorted(
        f"{name}.{m}" for m in ("stage", "consts", "helpers.util", "shared.base", "deep.inner"))
    # a class is reached whole, through the function that builds it
    assert f"{name}.shared.base:Table" in code_definitions(f"{name}.stage:load", package=name)


@pytest.mark.parametrize(
    ("rel", "text"),
    [
        ("helpers/util.py", '"""Helpers."""\nfrom ..shared.base import FACTOR\n\n'
         "def scale(x):\n    return x * FACTOR * 1.0 * _unit()\n\n"
         "def _unit():\n    return UNIT\n\nUNIT = 1\n"),
        ("helpers/util.py", '"""Helpers."""\nfrom ..shared.base import FACTOR\n\n'
         "def scale(x):\n    return x * FACTOR * _unit()\n\n"
         "def _unit():\n    return UNIT\n\nUNIT = 2\n"),  # a constant two calls away
        ("shared/base.py", "FACTOR = 3\n\nclass Table:\n    pass\n"),  # transitive
        ("consts.py", "OFFSET = 2\nOTHER = 2\n"),  # relative import
        ("deep/inner.py", "ONE = 1.0\n"),  # lazy import inside the function
        ("stage.py", "def clean(x):\n    return x\n"),
    ],
)
def test_changes_with_code_it_reaches(temp_package, rel, text):
    name, _, write = temp_package
    before = _fp(name)
    write(rel, text)
    assert _fp(name) != before


@pytest.mark.parametrize(
    ("rel", "text"),
    [
        # comments, docstrings and formatting only
        ("helpers/util.py", '"""Helpers, now documented at length."""\n'
         "from ..shared.base import FACTOR  # the factor\n\n\n"
         'def scale(x):\n    """Scale x."""\n    # multiply by the factor\n'
         "    return x*FACTOR*_unit()\n\n\ndef _unit():\n    return UNIT\n\n\nUNIT = 1\n"),
        # definitions moved around within their module
        ("helpers/util.py", '"""Helpers."""\nfrom ..shared.base import FACTOR\n\nUNIT = 1\n\n'
         "def _unit():\n    return UNIT\n\ndef scale(x):\n    return x * FACTOR * _unit()\n"),
        # other definitions of modules it does use
        ("stage.py", '"""Stage module."""\nfrom . import consts\n'
         "from {pkg}.helpers import util\nfrom {pkg}.io import read_table\n\n\n"
         "def clean(x):\n    import {pkg}.deep.inner\n\n"
         "    return util.scale(x) + consts.OFFSET + {pkg}.deep.inner.ONE\n\n\n"
         "def load(path):\n    return read_table(path) + 1\n\n\n"
         "def unused_here(x):\n    return x + 100\n"),
        ("consts.py", "OFFSET = 1\nOTHER = 3\n"),
        ("io.py", "from .shared.base import Table\n\n\ndef read_table(path):\n"
         "    return Table(path)\n\n\ndef write_table(table, path):\n    return path\n"),
        # modules the stage does not import
        ("unrelated.py", "Z = 1\n"),
        ("helpers/__init__.py", "HELPERS_INIT = 2\n"),  # `from pkg.helpers import util`
    ],
)
def test_ignores_comments_docstrings_and_what_it_does_not_reach(temp_package, rel, text):
    name, _, write = temp_package
    before = _fp(name)
    write(rel, text)
    assert _fp(name) == before


def test_a_shared_module_reader_and_writer(temp_package):
    """Editing the writer leaves the reader's users alone; editing the reader does not."""
    name, _, write = temp_package
    before = _fp(name, "load")
    write("io.py", "from .shared.base import Table\n\n\ndef read_table(path):\n"
          "    return Table(path)\n\n\ndef write_table(table, path):\n    return 0\n")
    assert _fp(name, "load") == before
    write("io.py", "from .shared.base import Table\n\n\ndef read_table(path):\n"
          "    return Table(path + '/')\n\n\ndef write_table(table, path):\n    return 0\n")
    edited = _fp(name, "load")
    assert edited != before
    clean_before = _fp(name, "clean")  # reaches FACTOR, beside Table in shared/base.py
    # a method of a class it builds (methods count through their class)
    write("shared/base.py", "FACTOR = 2\n\n\nclass Table:\n    def __init__(self, path):\n"
          "        self.path = path\n\n    def rows(self):\n        return []\n")
    assert _fp(name, "load") != edited
    assert _fp(name, "clean") == clean_before


def test_exclude(temp_package):
    name, _, write = temp_package
    kw = {"package": name, "exclude": (f"{name}.shared",)}
    target = f"{name}.stage:clean"
    assert f"{name}.shared.base" not in code_modules(target, **kw)
    before = code_fingerprint(target, **kw)
    write("shared/base.py", "FACTOR = 7\n")
    clear_caches()
    assert code_fingerprint(target, **kw) == before
    write("consts.py", "OFFSET = 7\n")
    clear_caches()
    assert code_fingerprint(target, **kw) != before


def test_memoised_until_cleared(temp_package):
    name, _, write = temp_package
    before = _fp(name)
    write("shared/base.py", "FACTOR = 5\n")
    assert code_fingerprint(f"{name}.stage:clean", package=name) == before  # memoised
    clear_caches()
    assert code_fingerprint(f"{name}.stage:clean", package=name) != before


def test_whole_module_target():
    fp = code_fingerprint("mocapflow.pipeline.codecs")
    assert len(fp) == 64
    assert code_modules("mocapflow.pipeline.codecs") == ["mocapflow.pipeline.codecs"]
    assert "mocapflow.pipeline.codecs:encode" in code_definitions("mocapflow.pipeline.codecs")
