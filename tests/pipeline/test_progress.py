"""Run progress: a bar on a terminal, plain lines otherwise."""

from __future__ import annotations


def test_progress_bar_and_plain_lines():
    import io

    from mocapflow.pipeline.progress import Progress

    tty = io.StringIO()
    p = Progress(3, stream=tty, tty=True)
    for status in ("hit", "computed", "failed"):
        p.update({"node": "n", "part": "a.bvh", "status": status, "seconds": 0.5,
                  "error": "ValueError: bad" if status == "failed" else None})
    p.close()
    text = tty.getvalue()
    assert "\r" in text and "] 3/3 hit 1 computed 1 failed 1" in text
    assert "failed   n/a.bvh: ValueError: bad" in text
    assert text.endswith("3 tasks: 1 hit, 1 computed, 1 failed, 0 skipped in 0.0s\n")
    plain = io.StringIO()
    p = Progress(2, stream=plain, tty=False)
    p.update({"node": "n", "part": None, "status": "hit"})
    p.update({"node": "m", "part": "b", "status": "computed", "seconds": 1.25})
    p.close()
    assert plain.getvalue().splitlines() == [
        "[2/2] computed m/b 1.25s", "2 tasks: 1 hit, 1 computed, 0 failed, 0 skipped in 0.0s"]
