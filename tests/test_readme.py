"""The README's "Using it" block, run exactly as written in a fresh venv.

The venv is new (``python -m venv``) and gets the ``mocapflow`` command by
``pip install -e`` of this checkout, as the README's set-up command does; so that
the install takes seconds, it sees the already-installed dependencies (and pip)
through a ``.pth`` file (the test checks the command, not PyPI).  The block runs from a
folder laid out like a clone, the sample data in ``../shared/data`` beside it
(a link to the real one), with ``MOCAPFLOW_STORE`` and ``MOCAPFLOW_DATA`` unset.
Each line's exit code is checked.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"


def using_it_block(readme: str) -> list[str]:
    """The command lines of the first ``bash`` block under ``## Using it``."""
    section = readme.split("\n## Using it\n", 1)[1]
    block = re.search(r"```bash\n(.*?)```", section, re.S)
    assert block is not None, "no bash block under ## Using it"
    return [line for line in block.group(1).splitlines()
            if line.strip() and not line.lstrip().startswith("#")]


@pytest.fixture(scope="module")
def fresh_venv(tmp_path_factory) -> Path:
    """``clone/.venv``: a new venv with ``mocapflow`` installed from this checkout."""
    clone = tmp_path_factory.mktemp("readme") / "clone"
    clone.mkdir()
    venv = clone / ".venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True,
                   timeout=300)
    site = next((venv / "lib").glob("python*/site-packages"))
    (site / "_mocapflow_deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    subprocess.run([str(venv / "bin" / "python"), "-m", "pip", "install", "-q", "--no-deps",
                    "-e", str(ROOT)], check=True, timeout=600, capture_output=True)
    assert (venv / "bin" / "mocapflow").exists()
    return venv


@pytest.mark.slow
@pytest.mark.skipif(not (SHARED / "data").is_dir(), reason="sample data ../shared/data absent")
def test_readme_using_it_block_runs_as_written(fresh_venv):
    clone = fresh_venv.parent
    (clone.parent / "shared").symlink_to(SHARED)
    lines = using_it_block((ROOT / "README.md").read_text())
    assert lines[0].startswith("source .venv/bin/activate") and len(lines) >= 10
    script = "\n".join(f'{line}\necho "__rc=$? {i}"' for i, line in enumerate(lines))
    env = {k: v for k, v in os.environ.items()
           if k not in ("MOCAPFLOW_STORE", "MOCAPFLOW_DATA", "VIRTUAL_ENV", "PYTHONPATH")}
    env["PATH"] = "/usr/bin:/bin"  # no mocapflow on PATH but the one the block activates
    proc = subprocess.run(["bash", "-c", script], cwd=clone, env=env, capture_output=True,
                          text=True, timeout=1500)
    codes = {int(i): int(rc) for rc, i in re.findall(r"__rc=(\d+) (\d+)", proc.stdout)}
    failed = {lines[i]: rc for i, rc in codes.items() if rc}
    assert len(codes) == len(lines), proc.stderr[-2000:]
    assert failed == {}, proc.stderr[-3000:]
    assert (clone / "out" / "synth" / "cmu_131_02.seed1" / "motion.bvh").is_file()
    assert (clone / "texture.lock.json").is_file() and (clone / ".mocapflow").is_dir()
    assert not list(ROOT.glob("*.lock.json"))  # nothing written into the checkout
