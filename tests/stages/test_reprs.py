"""Stage output types print one short line (issue 18: reprs printed whole arrays).

Each type is made by its stage on small synthetic inputs; its repr must name the
type and its key sizes, stay under 300 characters and show no array contents.
"""

from __future__ import annotations

import functools
import inspect

import pytest

from mocapflow.pipeline import Context, codecs
from mocapflow.stages.motion.simulate.motion import simulate_walk
from mocapflow.stages.skin.segment import segment
from mocapflow.stages.texture.pyramid import pyramid
from mocapflow.stages.texture.stickfigure import stickfigure
from mocapflow.stages.variation.inputs import clips
from mocapflow.stages.variation.learn import learn
from mocapflow.stages.variation.plots import variation_plots
from mocapflow.stages.variation.sample import sample
from tests.stages.skin.conftest import limb_capture

LEARN = {"k": 8, "max_parents": 3, "candidates": 6, "restarts": 1, "score": "one_step"}


class Made:
    """The stage outputs under test, each made once, on demand."""

    @functools.cached_property
    def walk(self):
        return simulate_walk(n_frames=150, rate=30.0, ctx=Context(part="reprs"))["motion"]

    @functools.cached_property
    def clips(self):
        return clips([self.walk], ctx=Context())["clips"]

    @functools.cached_property
    def model(self):
        return learn(self.clips, **LEARN, ctx=Context())["model"]

    @functools.cached_property
    def variants(self):
        return sample(self.model, length=40, ctx=Context(part="seed=0"))["variants"]


@pytest.fixture(scope="module")
def made() -> Made:
    return Made()


def _pyramid(m):
    p = pyramid(m.walk, levels=3, ctx=Context())["pyramid"]
    return p, [f"{p.n_frames}/", f"× {p.levels[0].rotations.shape[1]} joints", "30 Hz"]


def _strip(m):
    s = stickfigure(m.walk, n_panels=3, video=True, video_step=10, ctx=Context())["strip"]
    (H, W), (N, h, w) = s.image.shape[:2], s.video.shape[:3]
    return s, [f"{W}×{H} px", f"{N} frames of {w}×{h} px", f"@ {s.rate:.4g} Hz"]


def _segmentation(m):
    limb = limb_capture(n_frames=60)
    s = segment(limb["markers"], limb["surface"], ctx=Context())["segmentation"]
    return s, [f"{len(s.labels)} markers", f"{s.n_parts} parts", f"{s.faces.shape[0]} triangles"]


def _clips(m):
    c = m.clips
    frames = sum(t.shape[0] for t in c.trajectories)
    return c, [f"{c.n_clips} motion clips", f"{frames} frames",
               f"{c.n_dofs} of {len(c.dof_names)} DOFs", "30 Hz"]


def _model(m):
    v = m.model
    return v, [f"{v.n_dofs} DOFs", f"{v.edges()['prior']} prior", "Clips("]


def _figures(m):
    f = variation_plots([m.clips], m.variants, ctx=Context())["figures"]
    name, img = next(iter(f.images.items()))
    return f, [f"{len(f.images)} images", f"{name!r} {img.shape[1]}×{img.shape[0]}"]


MAKERS = {
    "Pyramid": _pyramid,
    "StickStrip": _strip,
    "Segmentation": _segmentation,
    "Clips": _clips,
    "VariationModel": _model,
    "Figures": _figures,
}


@pytest.mark.parametrize("name", sorted(MAKERS))
def test_stage_output_repr_is_one_short_line_with_its_sizes(name, made):
    obj, sizes = MAKERS[name](made)
    text = repr(obj)
    assert type(obj).__name__ == name and text.startswith(f"{name}("), text
    assert len(text) < 300 and "\n" not in text and "array(" not in text, text
    for size in sizes:
        assert size in text, (size, text)


def test_every_stored_domain_type_has_its_own_repr():
    # the codec registry lists every type a stage may return (anything else is refused)
    types = [t for t in codecs._BY_CLASS if t.__module__.startswith("mocapflow.stages")]
    assert {t.__name__ for t in types} >= set(MAKERS)
    generated = [t.__name__ for t in types
                 if inspect.unwrap(t.__repr__).__code__.co_filename != inspect.getsourcefile(t)]
    assert generated == []  # a dataclass's generated repr prints whole arrays
