"""Options: frozen dataclasses with a documented default, range and help per field, nested.

Every algorithm that has settings declares them once, beside itself, as an `Options` subclass
whose fields are made with `param(...)` (COLMAP's `PatchMatchOptions` + `Check()` style):

    @dataclass(frozen=True)
    class DecomposeOptions(Options):
        lambda_s: float = param(0.04, "Eq. 7 smoothness weight", min=0.0)

A stage's config (`StageConfig`) holds its own fields and embeds the options of the algorithms it
calls as nested fields (nerfstudio's nested config dataclasses):

    decompose: DecomposeOptions = param(DecomposeOptions(), "the two-layer decomposition")

so the defaults exist once, the TOML table `[reflection.decompose]` and the override
`--set reflection.decompose.lambda_s=0.1` reach them, and a test that builds `DecomposeOptions()`
tests what the product ships. `validate()` checks every declared range/choice (nested options
included) and then the subclass's `check()` for relations between fields. Values come from the
defaults, then the workspace's ibr.toml, then command-line flags; `build_config` coerces and
validates them and names the offending `stage.field` (`stage.table.field`) on any error.

`param(..., affects_output=False)` marks a field that changes how a stage runs but not what it
writes (threads, progress bars, a device): the runner leaves such fields out of a stage's
fingerprint, so changing them neither reruns the stage nor invalidates a resumable run.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import typing
from dataclasses import dataclass
from typing import Any

from .errors import ConfigError


def param(default: Any, help: str, *, min: float | None = None, max: float | None = None,
          choices: tuple | None = None, affects_output: bool = True) -> Any:
    """A field with its documentation and allowed range (inclusive bounds). `default` may be an
    Options instance: a nested table of options."""
    return dataclasses.field(default=default,
                             metadata={"help": help, "min": min, "max": max, "choices": choices,
                                       "affects_output": affects_output})


@dataclass(frozen=True)
class Options:
    """Base class of every options / config dataclass. Subclasses add `param` fields and may
    override check()."""

    def validate(self, prefix: str = "") -> None:
        """Raise ConfigError naming `prefix + field` for the first value out of its range."""
        pre = f"{prefix}." if prefix and not prefix.endswith(".") else prefix
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            meta = f.metadata
            name = pre + f.name
            if isinstance(v, Options):
                v.validate(name)
                continue
            if isinstance(v, float) and not math.isfinite(v):
                raise ConfigError(name, f"must be a finite number, got {v}")
            if meta.get("choices") is not None and v not in meta["choices"]:
                raise ConfigError(name, f"must be one of {list(meta['choices'])}, got {v!r}")
            for item in (v if isinstance(v, tuple) else (v,)):
                if meta.get("min") is not None and item < meta["min"]:
                    raise ConfigError(name, f"must be >= {meta['min']}, got {v}")
                if meta.get("max") is not None and item > meta["max"]:
                    raise ConfigError(name, f"must be <= {meta['max']}, got {v}")
        self.check(pre)

    def check(self, prefix: str) -> None:
        """Relations between fields; raise ConfigError(prefix + field, why)."""

    def to_dict(self) -> dict:
        """Every field (nested options as nested dicts), JSON-ready."""
        return {f.name: _jsonable(getattr(self, f.name)) for f in dataclasses.fields(self)}

    def fingerprint(self) -> dict:
        """to_dict() without the fields marked affects_output=False: what decides the outputs."""
        out = {}
        for f in dataclasses.fields(self):
            if not f.metadata.get("affects_output", True):
                continue
            v = getattr(self, f.name)
            out[f.name] = v.fingerprint() if isinstance(v, Options) else _jsonable(v)
        return out

    def digest(self) -> str:
        return hashlib.sha256(json.dumps(self.fingerprint(), sort_keys=True).encode()).hexdigest()[:16]


@dataclass(frozen=True)
class StageConfig(Options):
    """Base class of every stage's config (one per stage, `ibr stages` lists its fields)."""


def _jsonable(v: Any) -> Any:
    if isinstance(v, Options):
        return v.to_dict()
    return list(v) if isinstance(v, tuple) else v


def field_types(cls: type[Options]) -> dict[str, type]:
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls)}


def _is_options(t: Any) -> bool:
    return isinstance(t, type) and issubclass(t, Options)


def describe_fields(cls: type[Options], prefix: str = "") -> list[tuple[str, str, Any, str]]:
    """(dotted name, type name, default, help) for every leaf field, nested options flattened
    ("decompose.lambda_s"): used by --help and `ibr stages`."""
    types = field_types(cls)
    out = []
    for f in dataclasses.fields(cls):
        t = types[f.name]
        if _is_options(t):
            out += describe_fields(t, f"{prefix}{f.name}.")
            continue
        default = list(f.default) if isinstance(f.default, tuple) else f.default
        out.append((prefix + f.name, getattr(t, "__name__", str(t)), default, f.metadata.get("help", "")))
    return out


def coerce(value: Any, typ: Any, name: str) -> Any:
    """Convert a TOML value or a command-line string to the field's declared type."""
    origin = typing.get_origin(typ)
    if origin is tuple:
        (item_t, *_rest) = typing.get_args(typ)
        if isinstance(value, str):
            value = [s for s in value.replace(",", " ").split() if s]
        if not isinstance(value, (list, tuple)):
            raise ConfigError(name, f"expected a list, got {value!r}")
        out = tuple(coerce(v, item_t, name) for v in value)
        args = typing.get_args(typ)
        if Ellipsis not in args and len(args) > 1 and len(out) != len(args):
            raise ConfigError(name, f"expected {len(args)} values, got {len(out)}")
        return out
    if typ is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("1", "true", "yes", "on"):
            return True
        if isinstance(value, str) and value.lower() in ("0", "false", "no", "off"):
            return False
        raise ConfigError(name, f"expected true/false, got {value!r}")
    if typ is int:
        if isinstance(value, bool):
            raise ConfigError(name, f"expected an integer, got {value!r}")
        if isinstance(value, int):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
        if isinstance(value, str):
            try:
                return int(value)
            except ValueError:
                pass
        raise ConfigError(name, f"expected an integer, got {value!r}")
    if typ is float:
        if isinstance(value, bool):
            raise ConfigError(name, f"expected a number, got {value!r}")
        try:
            return float(value)
        except (TypeError, ValueError):
            raise ConfigError(name, f"expected a number, got {value!r}") from None
    if typ is str:
        if not isinstance(value, str):
            raise ConfigError(name, f"expected a string, got {value!r}")
        return value
    raise TypeError(f"config field {name}: unsupported type {typ}")


def nest(flat: dict[str, Any]) -> dict[str, Any]:
    """{"decompose.lambda_s": v} -> {"decompose": {"lambda_s": v}} (command-line overrides)."""
    out: dict[str, Any] = {}
    for key, v in flat.items():
        *tables, leaf = key.split(".")
        d = out
        for t in tables:
            d = d.setdefault(t, {})
            if not isinstance(d, dict):
                raise ConfigError(key, f"{t} is a value, not a table")
        d[leaf] = v
    return out


def _merge(cls: type[Options], name: str, values: dict[str, Any], layer: dict) -> None:
    types = field_types(cls)
    if not isinstance(layer, dict):
        raise ConfigError(name, f"expected a table of fields, got {layer!r}")
    for key, raw in layer.items():
        full = f"{name}.{key}"
        if key not in types:
            nested = [f"{name}.{f}.{key}" for f, t in types.items()
                      if _is_options(t) and key in field_types(t)]
            if nested:
                raise ConfigError(full, f"unknown field; did you mean {' or '.join(nested)}?")
            known = ", ".join(types) or "none"
            raise ConfigError(full, f"unknown field (known fields: {known})")
        if _is_options(types[key]):
            if not isinstance(raw, dict):
                raise ConfigError(full, f"is a table of options ([{full}]), got {raw!r}")
            _merge(types[key], full, values.setdefault(key, {}), raw)
        else:
            values[key] = coerce(raw, types[key], full)


def _construct(cls: type[Options], values: dict[str, Any]) -> Options:
    types = field_types(cls)
    kw = {k: (_construct(types[k], v) if _is_options(types[k]) else v) for k, v in values.items()}
    return cls(**kw)


def build_config(cls: type[Options], stage: str, *layers: dict) -> Options:
    """Defaults, overridden by each layer in turn ({field: raw value}, nested tables as dicts);
    coerced and validated."""
    values: dict[str, Any] = {}
    for layer in layers:
        _merge(cls, stage, values, layer)
    cfg = _construct(cls, values)
    cfg.validate(stage)
    return cfg


def _flatten(d: dict, prefix: str = "") -> dict[str, Any]:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[prefix + k] = v
    return out


def diff_configs(stage: str, old: dict, new: dict) -> list[str]:
    """Human-readable differences: 'view_mesh.target_triangles 40000 → 20000'."""
    a, b = _flatten(old), _flatten(new)
    out = []
    for key in sorted(set(a) | set(b)):
        x, y = a.get(key, "<unset>"), b.get(key, "<unset>")
        if x != y:
            out.append(f"{stage}.{key} {x} → {y}")
    return out
