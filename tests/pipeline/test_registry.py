"""The @stage registry, param validation and output codecs."""

from typing import Literal

import numpy as np
import pytest

from mocapflow.pipeline.codecs import decode, digest_encoded, encode
from mocapflow.pipeline.context import Context, part_seed
from mocapflow.pipeline.registry import (
    FilePath,
    ParamError,
    get_stage,
    stage,
    validate_params,
)


@stage("_test_registry_example", outputs=("out",))
def _example(
    path: FilePath,
    other,
    *,
    alpha: float = 0.5,
    n: int = 3,
    mode: Literal["a", "b"] = "a",
    names: list[str] | None = None,
    required: bool,
    ctx: Context,
):
    return {"out": alpha}


def test_spec_splits_inputs_params_and_ctx():
    spec = get_stage("_test_registry_example")
    assert spec.inputs == ("path", "other")
    assert spec.file_inputs() == ("path",)
    assert list(spec.params) == ["alpha", "n", "mode", "names", "required"]
    assert spec.wants_ctx and spec.outputs == ("out",)


def test_validate_params_fills_defaults_and_coerces_int_to_float():
    spec = get_stage("_test_registry_example")
    p = validate_params(spec, {"alpha": 1, "required": True})
    assert p == {"alpha": 1.0, "n": 3, "mode": "a", "names": None, "required": True}
    assert isinstance(p["alpha"], float)


@pytest.mark.parametrize(
    "given, message",
    [
        ({"required": True, "alpah": 1.0}, "did you mean 'alpha'"),
        ({}, "missing required param 'required'"),
        ({"required": True, "n": 1.5}, "expected an integer"),
        ({"required": True, "n": True}, "expected an integer"),
        ({"required": "yes"}, "expected a boolean"),
        ({"required": True, "mode": "c"}, "not one of"),
        ({"required": True, "names": [1]}, r"names\[0\]: expected a string, got 1$"),
        ({"required": True, "names": "x"}, "'x' does not fit list"),
    ],
)
def test_validate_params_rejects_bad_values(given, message):
    with pytest.raises(ParamError, match=message):
        validate_params(get_stage("_test_registry_example"), given)


def test_unknown_stage_suggests_close_match():
    with pytest.raises(KeyError, match="did you mean _test_registry_example"):
        get_stage("_test_registry_exampel")


def test_duplicate_stage_name_from_another_function_is_an_error():
    with pytest.raises(ValueError, match="registered twice"):

        @stage("_test_registry_example", outputs=("x",))
        def other_function():
            return {}


def test_context_rng_depends_on_seed_and_part_only():
    a = Context(part="p1", seed=3).rng.random(4)
    b = Context(part="p1", seed=3).rng.random(4)
    c = Context(part="p2", seed=3).rng.random(4)
    d = Context(part="p1", seed=4).rng.random(4)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c) and not np.allclose(a, d)
    assert part_seed(3, "p1") == part_seed(3, "p1")
    assert Context().map(abs, [-1, 2, -3]) == [1, 2, 3]


@pytest.mark.parametrize(
    "value",
    [
        np.arange(12.0).reshape(3, 4),
        {"a": 1, "b": [1.5, "x", None], "c": {"d": True}},
        {"arr": np.array([np.nan, 1.0]), "meta": {"k": 1}},
        [1, 2, 3],
    ],
)
def test_builtin_codecs_round_trip(value):
    enc = encode(value)
    back = decode(enc)
    if isinstance(value, np.ndarray):
        np.testing.assert_array_equal(back, value)
    elif isinstance(value, dict) and "arr" in value:
        np.testing.assert_array_equal(back["arr"], value["arr"])
        assert back["meta"] == value["meta"]
    else:
        assert back == value
    assert digest_encoded(encode(back)) == digest_encoded(enc)


def test_digest_distinguishes_dtype_shape_and_attrs():
    a = np.zeros((2, 3))
    digests = {
        digest_encoded(encode(a)),
        digest_encoded(encode(a.astype(np.float32))),
        digest_encoded(encode(a.reshape(3, 2))),
        digest_encoded(encode({"x": 1})),
        digest_encoded(encode({"x": 1.0})),
    }
    assert len(digests) == 5


def test_unstorable_output_names_the_type():
    with pytest.raises(TypeError, match="cannot store a object"):
        encode(object())


@stage("_test_registry_numbers", outputs=("out",))
def _numbers(*, rate: float | None = None, counts: list[int] | None = None, seed: int = 0):
    return {"out": rate}


@pytest.mark.parametrize("given, message", [
    ({"rate": float("inf")}, r"param _test_registry_numbers\.rate: expected a finite number, "
                             r"got inf$"),
    ({"rate": float("nan")}, "expected a finite number, got nan"),
    ({"rate": 10**400}, r"rate: 1000000000000\.\.\.0+ is out of range \(at most "
                        r"1e12 in magnitude\)$"),
    ({"rate": 2e12}, "2000000000000.0 is out of range"),
    ({"counts": [1, 10**13]}, r"counts\[1\]: 10000000000000 is out of range"),
    ({"counts": list(range(10_000)) + ["x"]}, r"counts\[10000\]: expected an integer, got 'x'"),
    ({"rate": "x" * 10_000}, r"rate: 'x+\.\.\.x+' does not fit float \| None$"),
    ({"seed": 2**32}, r"seed: a seed must be in \[0, 2\*\*32\), got 4294967296"),
])
def test_numbers_finite_in_range_messages_short(given, message):
    # a union keeps the range message of the member that fits the kind
    with pytest.raises(ParamError, match=message) as e:
        validate_params(get_stage("_test_registry_numbers"), given)
    assert len(str(e.value)) < 160


def test_stages_called_from_python_validate_numbers_too():
    assert _numbers(rate=3) == {"out": 3.0}
    with pytest.raises(ParamError, match="expected a finite number"):
        _numbers(rate=float("-inf"))
