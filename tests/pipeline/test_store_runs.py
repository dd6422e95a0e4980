"""Run records (ordering, replacement, last task record) and the file-digest memo."""

from __future__ import annotations

import uuid

import pytest

from mocapflow.pipeline.store import Store


@pytest.mark.parametrize("kind", ["local", "memory"])
def test_run_records(tmp_path, kind):
    root = str(tmp_path) if kind == "local" else f"memory://runs-{uuid.uuid4().hex[:8]}"
    st = Store(root)
    assert st.runs() == [] and st.last_task_record("clean", "t1") is None

    def task(node, part, status, key):
        return {"node": node, "part": part, "stage": node, "key": key, "components": {},
                "status": status}

    st.write_run("r2", {"started_at": 200.0, "tasks": [task("clean", "t1", "failed", "k2")]})
    st.write_run("r1", {"started_at": "1970-01-01T00:01:40+00:00",
                        "tasks": [task("clean", "t1", "computed", "k1"),
                                  task("learn", None, "computed", "g1")]})
    st.write_run("r3", {"started_at": 300.0, "tasks": [task("clean", "t2", "hit", "k3")]})
    assert [r["run_id"] for r in st.runs()] == ["r1", "r2", "r3"]
    last = st.last_task_record("clean", "t1")
    assert last["key"] == "k2" and last["run_id"] == "r2"
    assert st.last_task_record("clean", "t1", statuses={"hit", "computed"})["key"] == "k1"
    assert st.last_task_record("learn", None)["key"] == "g1"
    assert st.last_task_record("learn", "t1") is None
    st.write_run("r2", {"started_at": 50.0, "tasks": []})  # replaced: now the oldest
    assert [r["run_id"] for r in st.runs()] == ["r2", "r1", "r3"]
    assert st.last_task_record("clean", "t1")["key"] == "k1"
    with pytest.raises(ValueError, match="run id"):
        st.write_run("../x", {})


def test_file_memo(tmp_path):
    st = Store(tmp_path)
    assert st.load_file_memo() == {}
    st.save_file_memo({"/a": [1, 2, 3, "d1"]})
    st.save_file_memo({"/b": [4, 5, 6, "d2"]})  # merged, not replaced
    assert st.load_file_memo() == {"/a": [1, 2, 3, "d1"], "/b": [4, 5, 6, "d2"]}
    (tmp_path / "cache" / "file_digests.json").write_text("{broken")
    assert st.load_file_memo() == {}
