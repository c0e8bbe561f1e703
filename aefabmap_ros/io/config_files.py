"""YAML config files for the CLIs: sections of flat keys that map onto the core's config dataclasses.

The same dataclasses are the nodes' ROS parameters, so a key means the same thing everywhere. A key
that no dataclass has is an error naming it (a typo must not silently fall back to a default).
"""

from __future__ import annotations

import dataclasses
import importlib.resources
from pathlib import Path
from typing import Any, TypeVar

import yaml

from aefabmap_ros.errors import ConfigError

ConfigT = TypeVar("ConfigT")


def coerce_like(value: Any, default: Any) -> Any:
    """``value`` made the type of ``default`` where that is lossless: an int where a float is expected
    becomes a float (YAML, ROS parameters and the command line write 1 for 1.0). Everything else,
    bool included, is returned unchanged for the caller's type check. The one coercion of the package:
    config files, node parameters and the synthetic town's config all use it."""
    if isinstance(default, float) and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    return value


def shipped_config(name: str) -> Path:
    """A YAML file shipped in the package (``aefabmap_ros/config/``): found the same way from a source
    checkout, a pip install or a colcon install, never by counting parent folders."""
    path = Path(str(importlib.resources.files("aefabmap_ros") / "config" / name))
    if not path.is_file():
        raise ConfigError(f"no shipped config {name!r} in {path.parent}")
    return path


def read_sections(path: Path | None, allowed: set[str]) -> dict[str, dict[str, Any]]:
    """``{section: {key: value}}`` from a YAML file (empty when ``path`` is None)."""
    if path is None:
        return {}
    try:
        data = yaml.safe_load(Path(path).read_text()) or {}
    except OSError as exc:
        raise ConfigError(f"cannot read config file {path}: {exc.strerror}") from exc
    except yaml.YAMLError as exc:
        raise ConfigError(f"config file {path} is not valid YAML: {exc}") from exc
    if not isinstance(data, dict) or any(not isinstance(v, dict) for v in data.values()):
        raise ConfigError(f"config file {path} must map section names to key/value mappings")
    unknown = set(data) - allowed
    if unknown:
        raise ConfigError(f"config file {path}: unknown section(s) {sorted(unknown)}; known: {sorted(allowed)}")
    return data


def build_config(config_type: type[ConfigT], values: dict[str, Any], origin: str) -> ConfigT:
    """``config_type(**values)`` with unknown keys reported by name and ints accepted for floats."""
    if not dataclasses.is_dataclass(config_type):
        raise TypeError(f"{config_type!r} is not a dataclass")
    fields = {f.name: f for f in dataclasses.fields(config_type)}
    unknown = set(values) - set(fields)
    if unknown:
        raise ConfigError(f"{origin}: unknown key(s) {sorted(unknown)}; known: {sorted(fields)}")
    defaults: Any = config_type()
    coerced = {}
    for key, value in values.items():
        default = getattr(defaults, key)
        value = coerce_like(value, default)
        if type(value) is not type(default):
            raise ConfigError(f"{origin}: {key}={value!r} must be a {type(default).__name__}")
        coerced[key] = value
    return config_type(**coerced)
