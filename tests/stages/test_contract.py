"""Every registered stage meets the engine contract (``assert_stage_contract``).

Each stage runs twice on small inputs made by the stages themselves (a short
simulated walk and dense capture, files written by our own writers): its params
validate, it returns exactly its declared outputs, every output survives the
codec round trip with the same digest, and two calls with the same part and seed
give identical digests (pure; randomness only from ``ctx``).  A stage without an
example here fails the test, so a new stage must bring one.
"""

from __future__ import annotations

import functools
import shutil
from pathlib import Path

import numpy as np
import pytest

from mocapflow.pipeline import Context
from mocapflow.pipeline.codecs import digest_encoded, encode
from mocapflow.pipeline.registry import registered_stages
from mocapflow.pipeline.testing import assert_stage_contract
from mocapflow.stages.motion.datatypes import Strokes
from mocapflow.stages.motion.formats.bvh import write_bvh
from mocapflow.stages.motion.formats.c3d import write_c3d
from mocapflow.stages.motion.formats.strokes import write_strokes_csv
from mocapflow.stages.motion.ingest import amc_skeleton_path
from mocapflow.stages.motion.simulate.capture import simulate_capture
from mocapflow.stages.motion.simulate.motion import simulate_walk
from mocapflow.stages.skin.clean import clean
from mocapflow.stages.skin.deform import deform
from mocapflow.stages.skin.mesh_fit import fit_mesh, template_mesh
from mocapflow.stages.skin.render import offscreen_available
from mocapflow.stages.skin.segment import segment
from mocapflow.stages.texture.pyramid import pyramid
from mocapflow.stages.variation.inputs import clips
from mocapflow.stages.variation.learn import learn
from mocapflow.stages.variation.sample import sample

SHARED = Path(__file__).resolve().parents[2] / ".." / "shared" / "data"
LEARN = {"k": 8, "max_parents": 3, "candidates": 6, "restarts": 1, "score": "one_step"}


class Chain:
    """Small inputs for every stage, each made once, on demand."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp

    @functools.cached_property
    def walk(self):
        return simulate_walk(n_frames=150, rate=30.0, ctx=Context(part="contract"))["motion"]

    @functools.cached_property
    def bvh(self) -> str:
        return str(write_bvh(self.walk, self.tmp / "walk.bvh"))

    @functools.cached_property
    def capture(self) -> dict:
        return simulate_capture(n_markers=60, n_frames=40, motion="walk", body_vertices=800,
                                ctx=Context(part="contract"))

    @functools.cached_property
    def c3d(self) -> str:
        return str(write_c3d(self.capture["markers"], self.tmp / "capture.c3d"))

    @functools.cached_property
    def cleaned(self) -> dict:
        return clean(self.capture["markers"], ctx=Context(part="contract"))

    @functools.cached_property
    def segmentation(self):
        return segment(self.cleaned["markers"], self.cleaned["surface"])["segmentation"]

    @functools.cached_property
    def template(self):
        return template_mesh(n_vertices=1500)["mesh"]

    @functools.cached_property
    def fitted(self):
        return fit_mesh(self.template, self.segmentation)["mesh"]

    @functools.cached_property
    def deformed(self):
        return deform(self.cleaned["markers"], self.segmentation, self.fitted)["mesh"]

    @functools.cached_property
    def clips(self):
        return clips([self.walk], ctx=Context(part=None))["clips"]

    @functools.cached_property
    def model(self):
        return learn(self.clips, **LEARN, ctx=Context())["model"]

    @functools.cached_property
    def variants(self):
        return sample(self.model, length=40, ctx=Context(part="seed=0"))["variants"]

    @functools.cached_property
    def strokes_csv(self) -> str:
        """Three examples of a letter "a" (two strokes each), as our CSV."""
        t = np.linspace(0.0, 1.0, 60)
        examples = [
            Strokes(np.stack([np.cos(6 * t + k), np.sin(4 * t)], -1), stroke_starts=[0, 35],
                    rate=60.0, attrs={"letter": "a", "example": k})
            for k in range(3)
        ]
        return str(write_strokes_csv(examples, self.tmp / "strokes.csv"))


def _need_shared(name: str) -> str:
    path = (SHARED / name).resolve()
    if not path.exists():
        pytest.skip(f"shared sample data not found at {path}")
    return str(path)


def _need_render() -> None:
    if not offscreen_available():
        pytest.skip("no off-screen rendering here (pyvista/VTK)")


#: stage name -> (chain -> (inputs, params))
EXAMPLES = {
    "simulate_walk": lambda c: ((), {"n_frames": 40, "rate": 30.0}),
    "simulate_range_of_motion": lambda c: ((), {"n_frames": 60, "rate": 30.0}),
    "simulate_capture": lambda c: ((), {"n_markers": 30, "n_frames": 20, "motion": "walk",
                                        "body_vertices": 600}),
    "ingest_c3d": lambda c: ((c.c3d,), {}),
    "ingest_bvh": lambda c: ((c.bvh,), {"rate": 15.0}),
    "ingest_amc": lambda c: ((_need_shared("bvh/cmu_11_01.amc"),), {}),
    "ingest_strokes": lambda c: ((c.strokes_csv,), {"letter": "a", "example": 1}),
    "ingest_strokes_set": lambda c: ((c.strokes_csv,), {}),
    "clean": lambda c: ((c.capture["markers"],), {}),
    "ingest_rom": lambda c: ((c.c3d,), {}),
    "segment": lambda c: ((c.cleaned["markers"], c.cleaned["surface"]), {}),
    "template_mesh": lambda c: ((), {"n_vertices": 1500}),
    "fit_mesh": lambda c: ((c.template, c.segmentation), {"marker_offset": 0.007}),
    "match_markers": lambda c: ((c.cleaned["markers"], c.segmentation), {}),
    "deform": lambda c: ((c.cleaned["markers"], c.segmentation, c.fitted), {}),
    "render": lambda c: (_need_render(), ((c.deformed, c.cleaned["markers"]),
                                          {"width": 96, "height": 96, "stride": 10}))[1],
    "render_modes": lambda c: (_need_render(), (
        (c.cleaned["markers"], c.segmentation, c.fitted),
        {"width": 96, "height": 96, "stride": 10, "modes": ["rigid", "quadratic"]}))[1],
    "render_error": lambda c: (_need_render(), ((c.deformed, c.deformed),
                                                {"width": 96, "height": 96, "stride": 10}))[1],
    "pyramid": lambda c: ((c.walk,), {"levels": 3}),
    "synth": lambda c: ((pyramid(c.walk, levels=3)["pyramid"], c.walk), {"length": 200}),
    "stickfigure": lambda c: ((c.walk,), {"n_panels": 3}),
    "clips": lambda c: (([c.walk],), {}),
    "learn": lambda c: ((c.clips,), LEARN),
    "sample": lambda c: ((c.model,), {"length": 40}),
    "sample_noise": lambda c: ((c.clips,), {"length": 40}),
    "ik": lambda c: ((c.variants,), {"max_iter": 20}),
    "variation_plots": lambda c: ((c.clips, c.variants), {}),
}


@pytest.fixture(scope="module")
def chain(tmp_path_factory) -> Chain:
    return Chain(tmp_path_factory.mktemp("contract"))


DOMAIN = sorted(n for n, s in registered_stages().items()
                if s.module.startswith("mocapflow.stages"))


def test_every_domain_stage_has_an_example():
    assert len(DOMAIN) >= 27
    assert sorted(set(DOMAIN) - set(EXAMPLES)) == []


@pytest.mark.parametrize("name", DOMAIN)
def test_stage_meets_the_contract(name, chain):
    assert name in EXAMPLES, f"stage {name!r} has no example input in {__file__}: add one"
    inputs, params = EXAMPLES[name](chain)
    # every output pure: no stage may put a time, host or path in one (timings go
    # to ``ctx.timer``, which the engine keeps in the manifest)
    outputs = assert_stage_contract(name, inputs, params)
    assert set(outputs) == set(registered_stages()[name].outputs)


#: Stages whose first input is a file, and the files beside it they read too.
FILE_STAGES = {
    "ingest_c3d": lambda f: [],
    "ingest_bvh": lambda f: [],
    "ingest_amc": lambda f: [amc_skeleton_path(f)],
    "ingest_strokes": lambda f: [],
    "ingest_strokes_set": lambda f: [],
    "ingest_rom": lambda f: [],
}


def test_every_stage_reading_a_file_is_in_file_stages():
    readers = sorted(n for n in DOMAIN if registered_stages()[n].inputs
                     and "FilePath" in str(registered_stages()[n].func.__annotations__.get(
                         registered_stages()[n].inputs[0])))
    assert readers == sorted(FILE_STAGES)


@pytest.mark.parametrize("name", sorted(FILE_STAGES))
def test_outputs_do_not_depend_on_where_the_file_is(name, chain, tmp_path):
    """The same file in two folders gives the same output digests (no path in an output)."""
    inputs, params = EXAMPLES[name](chain)
    src = Path(inputs[0])
    digests = []
    for folder in (tmp_path / "a", tmp_path / "b" / "deeper"):
        folder.mkdir(parents=True)
        for f in [src, *FILE_STAGES[name](src)]:
            shutil.copy(f, folder / Path(f).name)
        out = assert_stage_contract(name, (str(folder / src.name), *inputs[1:]), params)
        digests.append({o: digest_encoded(encode(v)) for o, v in out.items()})
    assert digests[0] == digests[1]
