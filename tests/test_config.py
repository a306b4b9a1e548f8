"""config: nested Options, one source of defaults, and what the runner fingerprints."""
from __future__ import annotations

from dataclasses import dataclass

import pytest

from ibr_pipeline.cli import _parse_overrides
from ibr_pipeline.config import (Options, StageConfig, build_config, describe_fields, diff_configs,
                                 param)
from ibr_pipeline.errors import ConfigError


@dataclass(frozen=True)
class Inner(Options):
    weight: float = param(0.5, "a weight", min=0.0, max=1.0)
    grid: tuple[int, int] = param((4, 3), "cells", min=1)
    threads: int = param(1, "threads", min=1, affects_output=False)


@dataclass(frozen=True)
class Outer(StageConfig):
    scale: float = param(1.0, "a scale", min=0.1)
    inner: Inner = param(Inner(), "the algorithm's own options")


def test_nested_defaults_are_the_library_defaults_and_layers_override():
    assert build_config(Outer, "s").inner == Inner()
    cfg = build_config(Outer, "s", {"inner": {"weight": 0.25}}, {"inner": {"grid": "8 6"}, "scale": "2"})
    assert cfg.inner == Inner(weight=0.25, grid=(8, 6)) and cfg.scale == 2.0
    assert cfg.to_dict() == {"scale": 2.0, "inner": {"weight": 0.25, "grid": [8, 6], "threads": 1}}


def test_errors_name_the_nested_field():
    with pytest.raises(ConfigError, match=r"s\.inner\.weight: must be <= 1.0"):
        build_config(Outer, "s", {"inner": {"weight": 2}})
    with pytest.raises(ConfigError, match=r"s\.inner\.grid: expected 2 values"):
        build_config(Outer, "s", {"inner": {"grid": [4]}})
    with pytest.raises(ConfigError, match=r"did you mean s\.inner\.weight"):
        build_config(Outer, "s", {"weight": 0.1})
    with pytest.raises(ConfigError, match=r"s\.inner: is a table"):
        build_config(Outer, "s", {"inner": 3})


def test_fingerprint_leaves_out_what_does_not_affect_outputs():
    a, b = Outer(), Outer(inner=Inner(threads=8))
    assert a.fingerprint() == b.fingerprint() and a.digest() == b.digest() and a != b
    assert Outer(inner=Inner(weight=0.1)).digest() != a.digest()
    assert "threads" not in a.fingerprint()["inner"]


def test_flags_overrides_and_diffs_use_dotted_names():
    names = [n for n, *_ in describe_fields(Outer)]
    assert names == ["scale", "inner.weight", "inner.grid", "inner.threads"]
    assert _parse_overrides(["s.inner.weight=0.3", "s.scale=2"]) == {
        "s": {"inner": {"weight": "0.3"}, "scale": "2"}}
    old, new = Outer().fingerprint(), Outer(inner=Inner(weight=0.3)).fingerprint()
    assert diff_configs("s", old, new) == ["s.inner.weight 0.5 → 0.3"]
