"""Cache-key building blocks: canonical encoding, digests, code fingerprints, key diffs."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np
import pytest

from mocapflow.pipeline.keys import (
    KEY_LENGTH,
    canonical,
    clear_caches,
    content_digest,
    diff_components,
    digest,
    digest_of,
    file_digest,
    package_versions,
    real_path,
    task_key,
)

# --------------------------------------------------------------------------- canonical


def test_canonical_tags_types():
    variants = [1, 1.0, "1", True]
    encodings = [canonical(v) for v in variants]
    assert len(set(encodings)) == 4
    assert canonical(0) != canonical(False) != canonical(None)
    assert canonical(np.int64(1)) == canonical(1)
    assert canonical(np.float64(1.0)) == canonical(1.0)
    assert canonical(np.bool_(True)) == canonical(True)
    assert canonical({1: "a"}) != canonical({"1": "a"})
    assert canonical([1, 2]) == canonical((1, 2))
    assert canonical([1, [2]]) != canonical([1, 2])


def test_canonical_dict_order_independent():
    a = {"alpha1": 0.5, "alpha2": 0.6, "nested": {"x": [1, 2], "y": None}}
    b = {"nested": {"y": None, "x": [1, 2]}, "alpha2": 0.6, "alpha1": 0.5}
    assert canonical(a) == canonical(b)
    assert digest_of(a) == digest_of(b)
    assert canonical(a) != canonical({**a, "alpha1": 0.50000000000000011})


def test_canonical_floats_exact_and_nonfinite():
    assert canonical(0.1 + 0.2) != canonical(0.3)
    assert canonical(np.float32(0.1)) != canonical(0.1)
    assert canonical(-0.0) != canonical(0.0)
    nan = canonical(float("nan"))
    assert nan == canonical(np.nan) == canonical(np.float32("nan"))
    assert len({nan, canonical(float("inf")), canonical(float("-inf")), canonical("nan")}) == 4
    json.loads(canonical([float("nan"), float("inf")]))  # strict JSON, no NaN literals


def test_canonical_arrays():
    a = np.arange(6, dtype="<i4").reshape(2, 3)
    assert canonical(a) == canonical(a.copy())
    assert canonical(a) == canonical(a.astype(">i4"))  # same values, other byte order
    assert canonical(a) != canonical(a.astype(np.int64))
    assert canonical(a) != canonical(a.reshape(3, 2))
    assert canonical(a) != canonical(a + (a == 5))


@pytest.mark.parametrize("bad", [{1, 2}, object(), Path("x"), b"bytes"])
def test_canonical_rejects_other_types(bad):
    with pytest.raises(TypeError, match=type(bad).__name__):
        canonical({"p": [bad]})


def test_digest():
    assert digest("abc") == digest(b"abc") == hashlib.blake2b(b"abc", digest_size=32).hexdigest()
    assert len(digest(b"")) == 64
    assert digest_of({"a": 1}) == digest(canonical({"a": 1}))


# --------------------------------------------------------------------------- files


def _old(path: Path) -> None:
    """Push the mtime out of the racy window so the digest may be memoised."""
    st = path.stat()
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns - 10**10))


def test_file_digest_content_and_memo(tmp_path):
    clear_caches()
    f = tmp_path / "a.bvh"
    f.write_bytes(b"HIERARCHY\n" * 1000)
    _old(f)
    want = hashlib.blake2b(f.read_bytes(), digest_size=32).hexdigest()
    memo: dict = {}
    assert file_digest(f, memo) == want
    st = f.stat()
    assert memo[os.path.realpath(f)] == [st.st_size, st.st_mtime_ns, st.st_ino, st.st_ctime_ns,
                                         want]
    # same content under another name: same digest (content, not path)
    g = tmp_path / "b.bvh"
    g.write_bytes(f.read_bytes())
    assert file_digest(g) == want
    # the persistent memo is trusted when the stat matches ...
    clear_caches()
    fake = {os.path.realpath(f): [st.st_size, st.st_mtime_ns, st.st_ino, st.st_ctime_ns,
                                  "f" * 64]}
    assert file_digest(f, fake) == "f" * 64
    # ... and ignored once the file changes
    clear_caches()
    f.write_bytes(b"HIERARCHY\n" * 999 + b"MOTION!!!\n")
    assert file_digest(f, fake) == hashlib.blake2b(f.read_bytes(), digest_size=32).hexdigest()
    assert file_digest(f, fake) != want


def test_file_digest_recent_file_not_memoised(tmp_path):
    clear_caches()
    f = tmp_path / "fresh.c3d"
    f.write_bytes(b"x")
    memo: dict = {}
    file_digest(f, memo)
    assert memo == {}  # mtime within the racy window


def test_file_digest_missing_and_directory(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.c3d"):
        file_digest(tmp_path / "nope.c3d")
    d = tmp_path / "trial"
    (d / "sub").mkdir(parents=True)
    (d / "a.txt").write_text("1")
    (d / "sub" / "b.txt").write_text("2")
    before = file_digest(d)
    (d / "sub" / "b.txt").write_text("3")
    clear_caches()
    assert file_digest(d) != before


# --------------------------------------------------------------------------- keys


def test_package_versions():
    v = package_versions()
    assert set(v) == {"numpy", "scipy", "ezc3d"}
    assert v["numpy"] == np.__version__
    assert package_versions(("surely_not_installed_pkg_e1",)) == {
        "surely_not_installed_pkg_e1": "absent"
    }


def _key(**over):
    base = dict(
        stage="clean",
        fingerprint="c" * 64,
        params={"alpha1": 0.5, "variance": 0.99},
        part="trial1.c3d",
        inputs={"markers": "a" * 64},
        versions={"numpy": "2.3.0"},
    )
    base.update(over)
    return task_key(**base)


def test_task_key_components_and_sensitivity():
    key, comp = _key()
    assert len(key) == KEY_LENGTH == 32 and int(key, 16) >= 0
    assert key == digest_of(comp)[:32]
    assert set(comp) == {"format", "stage", "code", "params", "part", "inputs", "versions"}
    assert _key(params={"variance": 0.99, "alpha1": 0.5})[0] == key  # order
    changed = [
        _key(stage="clean2"),
        _key(fingerprint="d" * 64),
        _key(params={"alpha1": 0.7, "variance": 0.99}),
        _key(params={"alpha1": 0.5, "variance": 1}),  # 0.99 -> int 1
        _key(part="trial2.c3d"),
        _key(part=None),
        _key(part="None"),
        _key(inputs={"markers": "b" * 64}),
        _key(inputs={"markers": ["a" * 64]}),  # gather list vs single
        _key(versions={"numpy": "2.4.0"}),
    ]
    keys = {key} | {k for k, _ in changed}
    assert len(keys) == len(changed) + 1


def test_task_key_shared_parts_encoded_once_give_the_full_encoding():
    """Versions and input kinds are memoised: the key stays digest_of(components)."""
    kinds = {"markers": "upstream", "extra": "file"}
    for versions in ({"numpy": "2.3.0", "scipy": "1.1"}, {"scipy": "1.1", "numpy": "2.3.0"},
                     {"numpy": "2.3.0", "scipy": "1.2"}, {}):
        for _ in range(2):  # the second call is a memo hit
            key, comp = _key(versions=versions, input_kinds=kinds)
            assert key == digest_of(comp)[:32]
    assert _key(versions={"numpy": "2.3.0", "scipy": "1.1"})[0] != \
        _key(versions={"numpy": "2.3.0", "scipy": "1.2"})[0]


def test_task_key_survives_json_round_trip():
    key, comp = _key(params={"a": 1, "b": 1.0, "c": "1", "d": True, "e": [0.1, None]})
    back = json.loads(json.dumps(comp))
    assert digest_of(back)[:32] == key
    assert diff_components(back, comp) == []


def test_diff_components_words():
    _, old = _key(input_kinds={"markers": "upstream"})
    _, new = _key(
        fingerprint="d" * 64,
        params={"alpha1": 0.7, "variance": 0.99, "extra": 3},
        part="trial2.c3d",
        inputs={"markers": "b" * 64},
        versions={"numpy": "2.4.0", "scipy": "1.0"},
        input_kinds={"markers": "upstream"},
    )
    lines = diff_components(old, new)
    assert "param alpha1: 0.5 -> 0.7" in lines
    assert "param extra added (= 3)" in lines
    assert any(s.startswith("code of stage clean changed") for s in lines)
    assert "part changed: trial1.c3d -> trial2.c3d" in lines
    assert "input markers changed (upstream output digest aaaaaaaa.. -> bbbbbbbb..)" in lines
    assert "package numpy 2.3.0 -> 2.4.0" in lines
    assert "package scipy absent -> 1.0" in lines
    assert len(lines) == 7
    assert diff_components(old, old) == []
    assert diff_components(None, new) == ["no previous record"]


def test_diff_components_types_lists_and_pins():
    _, old = _key(params={"n": 1, "opts": {"k": 1}}, inputs={"clips": ["a" * 64, "b" * 64]})
    _, new = _key(
        fingerprint="pin:2",
        params={"n": 1.0, "opts": {"k": 2}},
        inputs={"clips": ["a" * 64, "c" * 64]},
    )
    lines = diff_components(old, new)
    assert "param n: 1 -> 1.0" in lines
    assert "param opts.k: 1 -> 2" in lines
    assert any(s.startswith("version pin of stage clean") for s in lines)
    assert any(s.startswith("input clips changed (1 of 2 items") for s in lines)


# --------------------------------------------------------------------------- fast encoding


def _reference_canonical(obj) -> bytes:
    """The canonical encoding as first written: a type-tagged tree, then one ``json.dumps``
    (dict items sorted by the dump of their tagged key).  The fast encoder must match it."""

    def dumps(tree):
        return json.dumps(tree, separators=(",", ":"), ensure_ascii=False, allow_nan=False)

    def tag(o):
        if o is None:
            return None
        if isinstance(o, (bool, np.bool_)):
            return ["bool", bool(o)]
        if isinstance(o, (int, np.integer)):
            return ["int", str(int(o))]
        if isinstance(o, (float, np.floating)):
            return ["float", float(o).hex()]
        if isinstance(o, str):
            return ["str", o]
        if isinstance(o, (list, tuple)):
            return ["list", [tag(v) for v in o]]
        if isinstance(o, dict):
            items = sorted(((tag(k), tag(v)) for k, v in o.items()), key=lambda kv: dumps(kv[0]))
            return ["dict", [[k, v] for k, v in items]]
        if isinstance(o, np.ndarray):
            a = np.ascontiguousarray(o)
            return ["ndarray", a.dtype.str, list(a.shape), digest(a.tobytes())]
        raise TypeError(type(o))

    return dumps(tag(obj)).encode("utf-8", errors="surrogatepass")


def _random_tree(rng, depth=0):
    kind = rng.integers(0, 9 if depth < 4 else 6)
    chars = ['"', "\\", "\n", "\x00", "\x1f", " ", "!", "#", "a", "Z", "é", "☃", "\ud800", "/"]
    if kind == 0:
        return None
    if kind == 1:
        return bool(rng.integers(2))
    if kind == 2:
        return int(rng.integers(-10**12, 10**12))
    if kind == 3:
        return float(rng.choice([0.1, -0.0, 1e308, float("inf"), float("nan"), 3.0]))
    if kind in (4, 5):
        return "".join(rng.choice(chars, size=rng.integers(0, 5)))
    if kind == 6:
        return [_random_tree(rng, depth + 1) for _ in range(rng.integers(0, 4))]
    if kind == 7:
        return tuple(_random_tree(rng, depth + 1) for _ in range(rng.integers(0, 3)))
    keys = [_random_tree(rng, 99) for _ in range(rng.integers(0, 6))]
    return {k: _random_tree(rng, depth + 1) for k in keys if not isinstance(k, list)}


def test_fast_canonical_matches_the_reference_encoding():
    rng = np.random.default_rng(7)
    for _ in range(3000):
        tree = _random_tree(rng)
        assert canonical(tree) == _reference_canonical(tree), tree
    # numpy values, arrays and subclasses go the general way, to the same bytes
    odd = {"np": [np.int64(7), np.float32(0.5), np.bool_(True)], "arr": np.eye(2),
           "sub": type("S", (str,), {})("x"), 3: {2: "int keys", "2": "str keys", 1.5: None}}
    assert canonical(odd) == _reference_canonical(odd)


def test_canonical_digests_are_unchanged():
    """Digests from the code before the fast encoder (keys of existing stores stay valid)."""
    obj = {"stage": "toy_add", "params": {
        "amount": 1.0, "n": 3, "flag": True, "none": None, "name": 'a "quoted"\\ \n\t é ☃ \x01',
        "nested": [1, [2.5, {"z": -0.0, "a": float("inf")}], (3,)]},
        2: "int key", "2": "str key", 1.5: "float key", None: [], "": {},
        "arr": np.arange(6, dtype=np.float32).reshape(2, 3),
        "np": [np.int64(7), np.float64(0.1), np.bool_(False)]}
    assert digest_of(obj) == "00175db937fd53db0df7e04c9ca50e330213d70657a6e5433898d4f4a4ebb5c7"
    key, _ = task_key(stage="s", fingerprint="pin:1", params={"k": [1, 2.0, "3"]},
                      part="a/b.c3d#seed=1", inputs={"x": "d" * 64, "y": ["e" * 64, "f" * 64]},
                      versions={"numpy": "2.0"}, input_kinds={"x": "file", "y": "upstream"})
    assert key == "0f20b2309ab99a451dc15a03e6992191"


def test_real_path_with_folder_cache_equals_realpath(tmp_path, monkeypatch):
    """Linked folders and linked files resolve as os.path.realpath does (relative paths too)."""
    (tmp_path / "data").mkdir()
    (tmp_path / "other").mkdir()
    for name in ("a.c3d", "b.c3d"):
        (tmp_path / "data" / name).write_text(name)
    (tmp_path / "other" / "c.c3d").write_text("c")
    (tmp_path / "link").symlink_to(tmp_path / "data")
    (tmp_path / "other" / "deep").mkdir()
    (tmp_path / "deep").symlink_to(tmp_path / "other" / "deep")  # deep/.. is other/
    (tmp_path / "data" / "c.c3d").symlink_to(tmp_path / "other" / "c.c3d")
    monkeypatch.chdir(tmp_path)
    dirs: dict[str, str] = {}
    paths = ["link/a.c3d", str(tmp_path / "link" / "b.c3d"), "data/c.c3d", "link/c.c3d",
             "link/../data/a.c3d", "deep/../c.c3d", "./data/a.c3d", "missing/x.c3d"]
    for p in paths:
        assert real_path(p, dirs) == os.path.realpath(p), p
    assert dirs[str(tmp_path / "link")] == str(tmp_path / "data")
    assert file_digest("link/c.c3d", dirs=dirs) == file_digest(tmp_path / "other" / "c.c3d")


def test_content_digest_is_file_digest_without_memos(tmp_path):
    """What workers check (content_digest) is what the driver keyed (file_digest)."""
    d = tmp_path / "take"
    (d / "sub").mkdir(parents=True)
    (d / "a.c3d").write_bytes(b"abc")
    (d / "sub" / "b.c3d").write_bytes(b"def")
    for p in (d / "a.c3d", d):
        assert content_digest(p) == file_digest(p, {})
    before = content_digest(d)
    (d / "sub" / "b.c3d").write_bytes(b"deg")
    assert content_digest(d) != before
