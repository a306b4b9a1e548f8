"""Stage configs: frozen dataclasses with a documented default, range and help per field.

Each stage declares one `StageConfig` subclass whose fields are made with `param(...)`:

    @dataclass(frozen=True)
    class ViewMeshConfig(StageConfig):
        target_triangles: int = param(40000, "triangles per view after simplification", min=100)

`validate()` checks every declared range/choice and then calls the subclass's `check()` for
relations between fields. Values come from the defaults, then the workspace's ibr.toml (one table
per stage), then command-line flags; `build_config` coerces and validates them and names the
offending `stage.field` on any error.
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
          choices: tuple | None = None) -> Any:
    """A config field with its documentation and allowed range (inclusive bounds)."""
    return dataclasses.field(default=default,
                             metadata={"help": help, "min": min, "max": max, "choices": choices})


@dataclass(frozen=True)
class StageConfig:
    """Base class of every stage's config. Subclasses add `param` fields and may override check()."""

    def validate(self, stage: str = "") -> None:
        prefix = f"{stage}." if stage else ""
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            meta = f.metadata
            name = prefix + f.name
            if isinstance(v, float) and not math.isfinite(v):
                raise ConfigError(name, f"must be a finite number, got {v}")
            if meta.get("choices") is not None and v not in meta["choices"]:
                raise ConfigError(name, f"must be one of {list(meta['choices'])}, got {v!r}")
            if meta.get("min") is not None and v < meta["min"]:
                raise ConfigError(name, f"must be >= {meta['min']}, got {v}")
            if meta.get("max") is not None and v > meta["max"]:
                raise ConfigError(name, f"must be <= {meta['max']}, got {v}")
        self.check(prefix)

    def check(self, prefix: str) -> None:
        """Relations between fields; raise ConfigError(prefix + field, why)."""

    def to_dict(self) -> dict:
        return {f.name: _jsonable(getattr(self, f.name)) for f in dataclasses.fields(self)}

    def digest(self) -> str:
        return hashlib.sha256(json.dumps(self.to_dict(), sort_keys=True).encode()).hexdigest()[:16]


def _jsonable(v: Any) -> Any:
    return list(v) if isinstance(v, tuple) else v


def field_types(cls: type[StageConfig]) -> dict[str, type]:
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls)}


def describe_fields(cls: type[StageConfig]) -> list[tuple[str, str, Any, str]]:
    """(name, type name, default, help) for every field: used by --help and `ibr stages`."""
    types = field_types(cls)
    out = []
    for f in dataclasses.fields(cls):
        t = types[f.name]
        out.append((f.name, getattr(t, "__name__", str(t)), f.default, f.metadata.get("help", "")))
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
        return tuple(coerce(v, item_t, name) for v in value)
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


def build_config(cls: type[StageConfig], stage: str, *layers: dict) -> StageConfig:
    """Defaults, overridden by each layer in turn ({field: raw value}); coerced and validated."""
    types = field_types(cls)
    values: dict[str, Any] = {}
    for layer in layers:
        for key, raw in layer.items():
            name = f"{stage}.{key}"
            if key not in types:
                known = ", ".join(types) or "none"
                raise ConfigError(name, f"unknown field (known fields: {known})")
            values[key] = coerce(raw, types[key], name)
    cfg = cls(**values)
    cfg.validate(stage)
    return cfg


def diff_configs(stage: str, old: dict, new: dict) -> list[str]:
    """Human-readable differences: 'view_mesh.target_triangles 40000 → 20000'."""
    out = []
    for key in sorted(set(old) | set(new)):
        a, b = old.get(key, "<unset>"), new.get(key, "<unset>")
        if a != b:
            out.append(f"{stage}.{key} {a} → {b}")
    return out
