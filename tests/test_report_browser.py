"""The report page in a real headless browser (Debian's Chromium).

The page of a real texture run (or, without the sample data, of a toy run with a
figure provider) is loaded headless: it logs nothing to the console, every image
on it decodes (checked by a small script in the test's own copy of the page: the
report itself has none), and its first screen is not blank.  Chromium is Debian's
``chromium`` package, installed in the fixture when missing where we may (root
with ``apt-get``); otherwise the tests are skipped with the reason.  Each check is
first shown to catch a broken page (a console error, an image that does not
decode, a blank screen), so a pass means something.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
BVH = ROOT.parent / "shared" / "data" / "bvh" / "cmu_131_02.bvh"
INSTALL_BUDGET_S = 240.0
FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--hide-scrollbars", "--mute-audio")
#: Run in the test's copy of the page after it loaded: counts the images that did
#: not decode and writes the result into the DOM (read back with --dump-dom).
CHECK_IMAGES = """<script>
window.addEventListener("load", () => {
  const imgs = Array.from(document.images);
  const broken = imgs.filter(i => !(i.complete && i.naturalWidth > 0 && i.naturalHeight > 0));
  const p = document.createElement("pre");
  p.id = "image-check";
  p.textContent = `images=${imgs.length} broken=${broken.length}`;
  document.body.appendChild(p);
});
</script>"""


@pytest.fixture(scope="module")
def chromium() -> str:
    """Path of a ``chromium`` executable (Debian's, installed here if need be)."""
    found = shutil.which("chromium") or ("/usr/bin/chromium"
                                         if os.access("/usr/bin/chromium", os.X_OK) else None)
    if found:
        return found
    if sys.platform != "linux" or not shutil.which("apt-get") or os.geteuid() != 0:
        pytest.skip("chromium is not installed and cannot be installed here (needs root and "
                    "apt-get): `apt-get install chromium` to run this test")
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    t0 = time.monotonic()
    try:  # bounded: the whole install (update included) within INSTALL_BUDGET_S
        subprocess.run(["apt-get", "update", "-q"], capture_output=True, env=env,
                       timeout=INSTALL_BUDGET_S / 2)
        left = max(INSTALL_BUDGET_S - (time.monotonic() - t0), 10.0)
        p = subprocess.run(["apt-get", "install", "-y", "-q", "chromium"], capture_output=True,
                           text=True, env=env, timeout=left)
    except subprocess.TimeoutExpired as e:
        pytest.skip(f"installing Debian's chromium took over {e.timeout:.0f} s; skipped")
    if p.returncode != 0 or not shutil.which("chromium"):
        pytest.skip(f"could not install Debian's chromium: {p.stderr.strip()[-300:]}")
    return shutil.which("chromium")


def _browse(chromium: str, page: Path, tmp: Path, *args: str) -> subprocess.CompletedProcess:
    """Chromium headless on ``page`` with its own profile; console messages on stderr."""
    profile = tmp / f"profile-{time.monotonic_ns()}"
    return subprocess.run([chromium, *FLAGS, f"--user-data-dir={profile}",
                           "--enable-logging=stderr", "--v=0", "--virtual-time-budget=5000",
                           *args, page.resolve().as_uri()],
                          capture_output=True, text=True, timeout=120)


def console_messages(stderr: str) -> list[str]:
    """The page's console messages in Chromium's log (the report has no script: any is
    an error: a failed load, a blocked resource, a script error)."""
    return [ln for ln in stderr.splitlines() if re.search(r":CONSOLE[:(]\d*", ln)]


def image_check(chromium: str, page: Path, tmp: Path) -> tuple[int, int]:
    """``(images, broken)`` of ``page`` as the browser decoded them."""
    copy = tmp / f"checked-{page.name}"
    html = page.read_text(encoding="utf-8")
    copy.write_text(html.replace("</body>", CHECK_IMAGES + "</body>"), encoding="utf-8")
    p = _browse(chromium, copy, tmp, "--dump-dom")
    m = re.search(r'<pre id="image-check">images=(\d+) broken=(\d+)</pre>', p.stdout)
    assert m, f"the image check did not run: {p.stderr[-1500:]}"
    return int(m.group(1)), int(m.group(2))


def screenshot(chromium: str, page: Path, tmp: Path, name: str) -> np.ndarray:
    """The first screen (1280×900) of ``page`` as an RGB array."""
    import imageio.v3 as iio

    shot = tmp / name
    p = _browse(chromium, page, tmp, f"--screenshot={shot}", "--window-size=1280,900")
    assert shot.is_file(), p.stderr[-1500:]
    img = iio.imread(shot)
    assert img.shape[:2] == (900, 1280)
    return img[..., :3]


def not_blank(img: np.ndarray) -> bool:
    """Some of the screen is drawn: pixel spread and a share of non-background pixels."""
    background = np.median(img.reshape(-1, 3), axis=0)
    drawn = np.abs(img.astype(np.int16) - background).max(axis=-1) > 40
    return float(img.std()) > 10.0 and drawn.mean() > 0.01


@pytest.fixture(scope="module")
def report_page(tmp_path_factory) -> Path:
    """The report page of a real texture run (a toy run when the sample data is absent)."""
    from mocapflow.pipeline.executors import SyncExecutor
    from mocapflow.pipeline.graph import load_graph
    from mocapflow.pipeline.report import write_report
    from mocapflow.pipeline.runner import run
    from mocapflow.pipeline.store import Store

    tmp = tmp_path_factory.mktemp("report")
    if BVH.is_file():
        graph = load_graph("texture", parts=[str(BVH)],
                           sets=["synth.length=128", "synth.seeds=1"])
    else:  # the engine's toy graph, with a figure provider of its own
        from mocapflow.pipeline import registry
        from mocapflow.pipeline.testing import TOY_CONFIG, write_config, write_number_files

        def draw(outputs, entry):
            from matplotlib.figure import Figure

            fig = Figure(figsize=(4, 3))
            fig.subplots().plot(outputs["values"], "o-")
            return [("values", fig)]

        registry.discover()
        registry._REPORT_PROVIDERS.setdefault("toy_scale", draw)
        write_number_files(tmp / "data", 3)
        graph = load_graph(write_config(tmp / "toy.yaml", TOY_CONFIG,
                                        parts=f"{tmp / 'data'}/*.txt"))
    store = Store(tmp / "store")
    result = run(graph, store, executor=SyncExecutor())
    assert result.ok
    return write_report(graph, store, tmp / "out")


def test_report_page_loads_with_no_console_error(chromium, report_page, tmp_path):
    broken = tmp_path / "broken.html"
    broken.write_text('<!DOCTYPE html><html><body><img src="missing.png">'
                      "<script>undefinedFunction();</script></body></html>")
    assert console_messages(_browse(chromium, broken, tmp_path, "--dump-dom").stderr)
    p = _browse(chromium, report_page, tmp_path, "--dump-dom")
    assert p.returncode == 0, p.stderr[-1500:]
    assert "</html>" in p.stdout and 'id="summary"' in p.stdout  # the page was read
    assert console_messages(p.stderr) == []


def test_every_figure_on_the_report_page_loads(chromium, report_page, tmp_path):
    bad = tmp_path / "bad.html"
    bad.write_text('<!DOCTYPE html><html><body><img src="data:image/png;base64,AAAA">'
                   '<img src="data:image/png;base64,iVBORw0KGgo="></body></html>')
    assert image_check(chromium, bad, tmp_path) == (2, 2)
    expected = report_page.read_text(encoding="utf-8").count("<img ")
    images, broken = image_check(chromium, report_page, tmp_path)
    assert expected >= (3 if BVH.is_file() else 1)
    assert (images, broken) == (expected, 0)


def test_report_first_screen_is_not_blank(chromium, report_page, tmp_path):
    blank = tmp_path / "blank.html"
    blank.write_text("<!DOCTYPE html><html><body></body></html>")
    assert not not_blank(screenshot(chromium, blank, tmp_path, "blank.png"))
    img = screenshot(chromium, report_page, tmp_path, "report.png")
    assert not_blank(img)
