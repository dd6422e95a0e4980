"""Keys of tasks: code fingerprints of helper modules, ``FilePath`` params by content."""

from __future__ import annotations

import importlib
import shutil
import sys
import uuid

import numpy as np

from mocapflow.pipeline import codecs, fingerprint
from mocapflow.pipeline.plan import explain, plan
from mocapflow.pipeline.runner import run
from mocapflow.pipeline.testing import write_config
from tests.pipeline.helpers import by_node


def _write_helper_package(root, pkg, body):
    (root / pkg).mkdir(parents=True, exist_ok=True)
    (root / pkg / "__init__.py").write_text("")
    (root / pkg / "helper.py").write_text(body)
    (root / pkg / "stages.py").write_text(
        "from mocapflow.pipeline import stage\n"
        "from .helper import bump\n\n\n"
        f"@stage('toy_helped_{pkg}', outputs=('values',))\n"
        "def helped(values):\n"
        "    return {'values': bump(values)}\n")


def test_helper_module_edit_invalidates_comment_edit_does_not(tmp_path, store, monkeypatch):
    monkeypatch.setattr(sys, "dont_write_bytecode", True)
    pkg = f"mfhelp_{uuid.uuid4().hex[:8]}"
    root = tmp_path / "pkgs"
    _write_helper_package(root, pkg, '"""Helper."""\n\n\ndef bump(x):\n    return x + 1  # one\n')
    monkeypatch.syspath_prepend(str(root))
    importlib.import_module(f"{pkg}.stages")
    cfg = write_config(tmp_path / "h.yaml", f"""\
        nodes:
          src: {{stage: toy_source, params: {{n: 4}}}}
          helped: {{stage: toy_helped_{pkg}, inputs: {{values: src.values}}}}
          scale: {{stage: toy_scale, inputs: {{values: helped.values}}}}
        """)
    from mocapflow.pipeline.config import load_config
    from mocapflow.pipeline.graph import build_graph

    assert run(build_graph(load_config(cfg)), store).counts["computed"] == 3
    try:
        # comments, docstrings and formatting only: still hits
        (root / pkg / "helper.py").write_text(
            '"""Helper, reworded at length."""\n# a new comment\n\n\ndef bump(x):\n'
            '    """Add one."""\n    # inner comment\n    return x   +   1\n')
        fingerprint.clear_caches()
        assert [p.status for p in plan(build_graph(load_config(cfg)), store)] == ["hit"] * 3
        # a code change in the helper: the stage that imports it recomputes
        (root / pkg / "helper.py").write_text("def bump(x):\n    return x + 10\n")
        fingerprint.clear_caches()
        g = build_graph(load_config(cfg))
        p = plan(g, store)
        assert [x.status for x in p] == ["hit", "compute", "pending"]
        assert p[1].reason.startswith(f"code of stage toy_helped_{pkg} changed")
        assert explain(g, store, "helped")[0]["changes"][0].startswith("code of stage")
        importlib.reload(importlib.import_module(f"{pkg}.helper"))
        importlib.reload(importlib.import_module(f"{pkg}.stages"))
        r = run(g, store)
        assert by_node(r, "computed") == {"helped": 1, "scale": 1}
        out = r.records[-1]
        np.testing.assert_array_equal(
            codecs.decode(store.load("toy_scale", out["key"], "values")),
            (np.arange(4.0) + 10) * 2)
    finally:
        fingerprint.clear_caches()


def test_filepath_param_is_keyed_by_content(tmp_path, store):
    off = tmp_path / "off.txt"
    off.write_text("1 2\n")
    cfg = write_config(tmp_path / "o.yaml", f"""\
        nodes:
          src: {{stage: toy_source, params: {{n: 3}}}}
          offset: {{stage: toy_offset, inputs: {{values: src.values}},
                params: {{offset_file: "{off}"}}}}
        """)
    from mocapflow.pipeline.config import load_config
    from mocapflow.pipeline.graph import build_graph

    r = run(build_graph(load_config(cfg)), store)
    np.testing.assert_array_equal(
        codecs.decode(store.load("toy_offset", r.records[1]["key"], "values")), [3.0, 4.0, 5.0])
    moved = tmp_path / "moved.txt"
    shutil.copy(off, moved)
    g = build_graph(load_config(cfg, sets=[f"offset.offset_file={moved}"]))
    assert [p.status for p in plan(g, store)] == ["hit", "hit"]  # same content, other path
    moved.write_text("5\n")
    p = plan(build_graph(load_config(cfg, sets=[f"offset.offset_file={moved}"])), store)
    assert p[1].status == "compute" and p[1].reason.startswith("param offset_file.file:")
