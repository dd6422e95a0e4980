"""Part globs: the same matches as ``glob.glob``, but bounded (entries looked at, symlink
loops, matches) with a one-line error naming the ``parts`` entry."""

from __future__ import annotations

import glob
import os

import pytest

from mocapflow.pipeline import config_parts
from mocapflow.pipeline.config import ConfigError, load_config
from mocapflow.pipeline.config_parts import GlobLimitError, bounded_glob
from mocapflow.pipeline.testing import write_config

FILES = ["d/x.txt", "d/a/y.txt", "d/a/sub/z.txt", "d/a/sub/q.c3d", "d/a/deep/er/w.txt",
         "d/b/.hid/h.txt", "d/.h/k.txt", "d/.top.txt", "d/b/sub.txt"]
PATTERNS = ["d/**/*.txt", "d/**", "**/*.txt", "d/*/**/*.txt", "d/**/sub/*.txt", "d/**/.*",
            "d/**/*", "**", "d/**/sub", "d/a/**/w.txt", "d/**/**/*.txt", "d/**/.hid/*.txt",
            "d/[ab]/**/*.txt", "d/a/sub/**", "d/**/nope/*.txt", "d/*.txt", "d/?/*.txt"]


@pytest.fixture
def tree(tmp_path, monkeypatch):
    for f in FILES:
        (tmp_path / f).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / f).write_text("1\n")
    monkeypatch.chdir(tmp_path)
    return tmp_path


def _norm(paths):
    return sorted({p.rstrip("/") for p in paths} - {""})


@pytest.mark.parametrize("pattern", PATTERNS)
def test_matches_like_glob(tree, pattern):
    assert _norm(bounded_glob(pattern)) == _norm(glob.glob(pattern, recursive=True))
    absolute = f"{tree}/{pattern}"
    assert _norm(bounded_glob(absolute)) == _norm(glob.glob(absolute, recursive=True))


def test_symlink_loops_are_cut_links_elsewhere_followed(tree):
    os.symlink("..", "d/a/up")  # a loop: glob.glob would follow it until the path is too long
    os.symlink("../b", "d/a/to_b")
    found = bounded_glob("d/**/*.txt")
    assert sorted(found) == ["d/a/deep/er/w.txt", "d/a/sub/z.txt", "d/a/to_b/sub.txt",
                             "d/a/y.txt", "d/b/sub.txt", "d/x.txt"]


def test_walks_are_bounded_with_an_error_naming_the_entry(tree, monkeypatch):
    monkeypatch.setattr(config_parts, "MAX_GLOB_ENTRIES", 5)
    with pytest.raises(GlobLimitError, match=r"^looks at more than 5 files and directories"):
        bounded_glob("d/**/*.txt")
    cfg = write_config(tree / "g.yaml", """\
        parts:
          - d/x.txt
          - d/**/*.txt
        nodes:
          read: {stage: toy_read_file, inputs: {path: part}}
        """)
    with pytest.raises(ConfigError) as e:
        load_config(cfg)
    assert str(e.value) == (f"{cfg}:3: parts[1]: 'd/**/*.txt': looks at more than 5 files and "
                            "directories (narrow the pattern)")
    monkeypatch.setattr(config_parts, "MAX_GLOB_MATCHES", 2)
    with pytest.raises(GlobLimitError, match=r"^matches more than 2 paths"):
        bounded_glob("d/a/*")
