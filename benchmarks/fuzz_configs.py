"""Hostile graph configs for the fuzz suite: alias bombs, deep nesting, huge numbers,
wrong types, unknown tags, reference bombs, fan-out bombs.

``cases()`` returns ``[(name, yaml_text), ...]``, generated (nothing stored).
Every case must be *rejected* by config loading, quickly and within little
memory, with one ``ConfigError`` line ``FILE:LINE: key: problem``;
``expected()`` gives, per case, the key the message must name and a fragment
of its problem (``benchmarks/fuzz.py`` runs them under a memory limit;
``tests/pipeline/test_fuzz_configs.py`` runs all of them on the toy stages).

The configs use one source stage (no inputs, an ``int`` and a ``float``
param, a ``seed``) and one stage reading its output: the shipped
``simulate_walk`` → ``pyramid`` by default (:data:`SHIPPED`), or the engine's toy
stages (:data:`TOY`, with ``MOCAPFLOW_STAGE_MODULES=mocapflow.pipeline.testing``).

Run ``python benchmarks/fuzz_configs.py`` to print the cases and their sizes.
"""

from __future__ import annotations

from collections.abc import Mapping

from mocapflow.pipeline.config_yaml import MAX_NODES

__all__ = ["SHIPPED", "TOY", "cases", "expected"]

#: Stage names and params the cases use (the shipped stage families).
SHIPPED = {"source": "simulate_walk", "output": "motion", "int": "n_frames", "float": "rate",
           "sink": "pyramid", "sink_input": "motion"}
#: The same with the engine's toy stages.
TOY = {"source": "toy_source", "output": "values", "int": "n", "float": "value",
       "sink": "toy_add", "sink_input": "values"}


def _src(s: Mapping[str, str], params: str = "{}", extra: str = "") -> str:
    """A config with one source node ``src`` (``params`` as a flow mapping)."""
    return f"nodes:\n  src:\n    stage: {s['source']}\n    params: {params}\n{extra}"


def _chain(s: Mapping[str, str], src_extra: str = "", sink_extra: str = "") -> str:
    return (f"nodes:\n  src:\n    stage: {s['source']}\n{src_extra}"
            f"  sink:\n    stage: {s['sink']}\n"
            f"    inputs: {{{s['sink_input']}: src.{s['output']}}}\n{sink_extra}")


def _laughs(levels: int, width: int = 10) -> str:
    """``l0: &l0 [x, x, ...]``, ``l1: &l1 [*l0, *l0, ...]``, ... (``width ** levels`` nodes)."""
    lines = ["l0: &l0 [" + ", ".join(["lol"] * width) + "]"]
    for i in range(1, levels):
        lines.append(f"l{i}: &l{i} [" + ", ".join([f"*l{i - 1}"] * width) + "]")
    return "\n".join(lines) + "\n"


def _merge_bomb(levels: int) -> str:
    """Each mapping merges the previous one twice (``2 ** levels`` merged pairs)."""
    lines = ["m0: &m0 {k: 1}"]
    for i in range(1, levels):
        lines.append(f"m{i}: &m{i} {{<<: [*m{i - 1}, *m{i - 1}], k{i}: {i}}}")
    return "\n".join(lines) + "\n"


def cases(stages: Mapping[str, str] = SHIPPED) -> list[tuple[str, str]]:
    """The hostile configs, ``[(name, yaml_text), ...]`` (see the module docstring)."""
    s = stages
    i, f = s["int"], s["float"]
    out: list[tuple[str, str]] = []

    def add(name: str, text: str) -> None:
        out.append((name, text))

    # ---- alias and reference bombs
    add("billion_laughs", "params:\n" + "".join("  " + ln + "\n" for ln in
                                                _laughs(9).splitlines()) + _src(s))
    add("billion_laughs_unknown_key", _laughs(9) + _src(s))
    add("merge_key_bomb", "params:\n" + "".join("  " + ln + "\n" for ln in
                                                _merge_bomb(40).splitlines()) + _src(s))
    add("merge_key_bomb_unknown_key", _merge_bomb(40) + _src(s))
    add("alias_quadratic", "big: &big [" + ", ".join(["0"] * 2000) + "]\n"
        + "uses: [" + ", ".join(["*big"] * 2000) + "]\n" + _src(s))
    add("recursive_alias", "params:\n  a: &a [1, *a]\n" + _src(s))
    add("recursive_merge", "params:\n  a: &a {x: 1, y: {<<: *a}}\n" + _src(s))
    add("alias_depth", "params:\n" + "".join(
        f"  a{k}: &a{k} [{'*a' + str(k - 1) if k else 1}]\n" for k in range(80)) + _src(s))
    add("ref_bomb_lists", "params:\n" + "".join(
        f"  p{k}: [${{params.p{k + 1}}}, ${{params.p{k + 1}}}]\n" for k in range(30))
        + "  p30: x\n" + _src(s, f"{{{i}: '${{params.p0}}'}}"))
    add("ref_bomb_strings", "params:\n" + "".join(
        f"  p{k}: \"${{params.p{k + 1}}}${{params.p{k + 1}}}\"\n" for k in range(12))
        + "  p12: " + "x" * 100_000 + "\n" + _src(s))
    add("ref_chain", "params:\n" + "".join(
        f"  p{k}: ${{params.p{k + 1}}}\n" for k in range(2000)) + "  p2000: 1\n"
        + _src(s, f"{{{i}: '${{params.p0}}'}}"))
    add("ref_cycle", "params:\n  a: ${params.b}\n  b: [${params.a}]\n" + _src(s))
    add("unclosed_refs", f"nodes:\n  src:\n    stage: {s['source']}\n    params:\n"
        f"      {i}: \"" + "${" * 1_000_000 + "\"\n")
    # ---- deep nesting
    add("deep_flow_list", _src(s, f"{{{i}: " + "[" * 20_000 + "]" * 20_000 + "}"))
    add("deep_flow_map", _src(s, f"{{{i}: " + "{a: " * 20_000 + "1" + "}" * 20_000 + "}"))
    add("deep_block_map", "params:\n" + "".join("  " * (k + 1) + f"k{k}:\n"
                                                for k in range(2_000)) + _src(s))
    add("deep_block_list", "params:\n  deep:\n" + "".join("    " + "  " * k + "-\n"
                                                         for k in range(2_000)) + _src(s))
    add("deep_set_of_keys", "x: " + "[" * 500 + "]" * 500 + "\n" + _src(s))
    # ---- sizes
    add("many_nodes", "params:\n  big: [" + ",".join(["0"] * (MAX_NODES + 10)) + "]\n" + _src(s))
    add("long_unknown_key", "? " + "k" * 1_000_000 + "\n: 1\n" + _src(s))
    add("oversized", "# " + "x" * (17 << 20) + "\n" + _src(s))
    add("glob_whole_filesystem", "parts: ['/**/*.mocapflow-no-such-file']\n"
        + _src(s).replace("    params: {}\n", f"    params: {{{i}: 1}}\n"))
    # ---- numbers
    add("float_400_digits", _src(s, f"{{{f}: {'9' * 400}.0}}"))
    add("int_400_digits_for_float", _src(s, f"{{{f}: {'9' * 400}}}"))
    add("int_5000_digits", _src(s, f"{{{i}: {'9' * 5000}}}"))
    add("inf_param", _src(s, f"{{{f}: .inf}}"))
    add("minus_inf_param", _src(s, f"{{{f}: -.inf}}"))
    add("nan_param", _src(s, f"{{{f}: .nan}}"))
    add("int_1e14", _src(s, f"{{{i}: 100000000000000}}"))
    add("float_1e14", _src(s, f"{{{f}: 1.0e+14}}"))
    add("exponent_without_dot", _src(s, f"{{{f}: 1e14}}"))  # YAML 1.1: a string
    add("seed_count_1e8", _src(s, extra="    seeds: {count: 100000000}\n"))
    add("seed_fan_out", _chain(s, "    seeds: {count: 1000}\n", "    seeds: {count: 1001}\n"))
    add("seed_too_big", _src(s, extra="    seeds: [4294967296]\n"))
    add("seed_negative", _src(s, extra="    seeds: [-1]\n"))
    add("seed_param_negative", _src(s, "{seed: -1}"))
    # ---- wrong types
    add("nodes_is_a_list", "nodes: [a, b]\n")
    add("node_is_a_string", "nodes:\n  src: hello\n")
    add("stage_is_a_mapping", "nodes:\n  src:\n    stage: {a: 1}\n")
    add("int_param_is_a_list", _src(s, f"{{{i}: [1, 2]}}"))
    add("int_param_is_a_bool", _src(s, f"{{{i}: true}}"))
    add("int_param_is_a_float", _src(s, f"{{{i}: 3.5}}"))
    add("float_param_is_text", _src(s, f"{{{f}: fast}}"))
    add("int_param_is_a_date", _src(s, f"{{{i}: 2024-01-01}}"))
    add("params_is_a_list", _src(s, "[1, 2]"))
    add("seeds_is_text", _src(s, extra="    seeds: many\n"))
    add("gather_is_text", _src(s, extra="    gather: yes please\n"))
    add("inputs_is_a_list", _chain(s).replace(f"inputs: {{{s['sink_input']}: src.{s['output']}}}",
                                              "inputs: [src]"))
    add("key_is_a_list", "[a, b]: 1\n" + _src(s))
    add("top_is_a_scalar", "42\n")
    add("top_is_empty", "")
    add("control_characters", "nodes:\n  src: \x00\x07\n")
    # ---- tags
    add("python_object_tag", "nodes:\n  src: !!python/object/apply:os.system [echo pwned]\n")
    add("custom_tag", _src(s, f"{{{i}: !grow 3}}"))
    add("set_tag", _src(s, f"{{{i}: !!set {{a, b}}}}"))
    add("binary_tag", _src(s, f"{{{f}: !!binary aGVsbG8=}}"))
    add("omap_tag", "params: !!omap [{a: 1}, {b: 2}]\n" + _src(s))
    return out


def expected(stages: Mapping[str, str] = SHIPPED) -> dict[str, tuple[str, str]]:
    """``name -> (key the message names, fragment of its problem)`` for every case."""
    i, f = stages["int"], stages["float"]
    pi, pf = f"nodes.src.params.{i}", f"nodes.src.params.{f}"
    expands = f"expands to more than {MAX_NODES:,}"
    return {
        "billion_laughs": ("params.l4[7]", expands),
        "billion_laughs_unknown_key": ("l4[7]", expands),
        "merge_key_bomb": ("params.m", expands),
        "merge_key_bomb_unknown_key": ("m", expands),
        "alias_quadratic": ("uses[", expands),
        "recursive_alias": ("params.a[1]", "recursive aliases are not allowed"),
        "recursive_merge": ("params.a.y", "recursive aliases are not allowed"),
        "alias_depth": ("params.a", "nesting deeper than 64 levels"),
        "ref_bomb_lists": ("params.p0", f"references expand to more than {MAX_NODES:,} values"),
        "ref_bomb_strings": ("params.p0", "MiB of text"),
        "ref_chain": ("params.p0", "more than 32 ${params.NAME} references in a chain"),
        "ref_cycle": ("params.a", "circular reference"),
        "unclosed_refs": (pi, "expected an integer, got '${${${"),
        "deep_flow_list": (pi, "nesting deeper than 64 levels"),
        "deep_flow_map": (pi, "nesting deeper than 64 levels"),
        "deep_block_map": ("params.k0.k1", "nesting deeper than 64 levels"),
        "deep_block_list": ("params.deep[0][0]", "nesting deeper than 64 levels"),
        "deep_set_of_keys": ("x", "nesting deeper than 64 levels"),
        "many_nodes": ("params.big[", f"expands to more than {MAX_NODES:,} YAML nodes"),
        "long_unknown_key": ("kkkk", "unknown top-level key"),
        "oversized": ("", "config is larger than 16 MiB"),
        # a full walk is refused (or, on a small filesystem, finds nothing): bounded either way
        "glob_whole_filesystem": ("parts[0]", "'/**/*.mocapflow-no-such-file'"),
        "float_400_digits": (pf, "expected a finite number, got inf"),
        "int_400_digits_for_float": (pf, "an integer of 400 characters is out of range"),
        "int_5000_digits": (pi, "an integer of 5,000 characters is out of range"),
        "inf_param": (pf, "expected a finite number, got inf"),
        "minus_inf_param": (pf, "expected a finite number, got -inf"),
        "nan_param": (pf, "expected a finite number, got nan"),
        "int_1e14": (pi, "out of range (at most 1e12 in magnitude)"),
        "float_1e14": (pf, "out of range (at most 1e12 in magnitude)"),
        "exponent_without_dot": (pf, "expected a number, got '1e14'"),
        "seed_count_1e8": ("nodes.src.seeds.count", "more than the 1,000,000 tasks"),
        "seed_fan_out": ("nodes.sink.seeds", "fans out to 1,001,000 tasks"),
        "seed_too_big": ("nodes.src.seeds[0]", "a seed must be in [0, 2**32)"),
        "seed_negative": ("nodes.src.seeds[0]", "a seed must be in [0, 2**32)"),
        "seed_param_negative": ("nodes.src.params.seed", "a seed must be in [0, 2**32)"),
        "nodes_is_a_list": ("nodes", "must be a non-empty mapping"),
        "node_is_a_string": ("nodes.src", "a node must be a mapping"),
        "stage_is_a_mapping": ("nodes.src.stage", "must be a stage name"),
        "int_param_is_a_list": (pi, "expected an integer, got [1, 2]"),
        "int_param_is_a_bool": (pi, "expected an integer, got True"),
        "int_param_is_a_float": (pi, "expected an integer, got 3.5"),
        "float_param_is_text": (pf, "expected a number, got 'fast'"),
        "int_param_is_a_date": (pi, "expected an integer, got '2024-01-01'"),
        "params_is_a_list": ("nodes.src.params", "must be a mapping"),
        "seeds_is_text": ("nodes.src.seeds", "expected a non-empty list of seeds"),
        "gather_is_text": ("nodes.src.gather", "must be true or false"),
        "inputs_is_a_list": ("nodes.sink.inputs", "must be a mapping"),
        "key_is_a_list": ("yaml", "a key must be a scalar"),
        "top_is_a_scalar": ("", "must be a YAML mapping"),
        "top_is_empty": ("", "must be a YAML mapping"),
        "control_characters": ("yaml", "unacceptable character #x0000"),
        "python_object_tag": ("nodes.src", "unknown tag '!!python/object/apply:os.system'"),
        "custom_tag": (pi, "unknown tag '!grow'"),
        "set_tag": (pi, "tag !!set is not allowed"),
        "binary_tag": (pf, "tag !!binary is not allowed"),
        "omap_tag": ("params", "tag !!omap is not allowed"),
    }


if __name__ == "__main__":  # pragma: no cover
    exp = expected()
    for name, text in cases():
        key, fragment = exp[name]
        print(f"{name:<28} {len(text):>10,} chars   {key or '-'}: {fragment}")
