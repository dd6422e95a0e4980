"""Line-aware YAML loading: configs are data only (no Python tags)."""

from __future__ import annotations

import re

import pytest

from mocapflow.pipeline.config import ConfigError, load_config
from mocapflow.pipeline.testing import write_config


def _load(tmp_path, text, **kw):
    return load_config(write_config(tmp_path / "g.yaml", text), **kw)


def test_configs_are_data_only(tmp_path):
    with pytest.raises(ConfigError) as e:
        _load(tmp_path, "nodes:\n  a: !!python/object/apply:os.system [echo hi]\n")
    assert re.match(r".*g\.yaml:2: yaml: malformed YAML", str(e.value))
