"""Load a run's configuration once: pydantic model <- YAML file <- environment overrides.

Every process loads its config with this module (it needs only pydantic and PyYAML, which all
of them have); the models themselves derive from ``schemas.config.ConfigModel``.

Environment variables ``MRSLAM_<FIELD>[__<SUBFIELD>...]`` override the file, e.g.
``MRSLAM_BUS__CONNECT='["tcp/10.0.0.2:7447"]'`` or ``MRSLAM_ROBOT_ID=r2``; values are parsed
as YAML scalars or lists. The resolved configuration is written next to a run's outputs.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

import pydantic
import yaml

from schemas.textfile import UnreadableFile, read_yaml

T = TypeVar("T", bound=pydantic.BaseModel)
ENV_PREFIX = "MRSLAM_"


class ConfigError(ValueError):
    """The configuration file or an override is missing, unreadable or invalid."""


def _set_path(tree: dict[str, Any], path: list[str], value: Any) -> None:
    node = tree
    for part in path[:-1]:
        child = node.get(part)
        if not isinstance(child, dict):
            child = node[part] = {}
        node = child
    node[path[-1]] = value


def env_overrides(model: type[pydantic.BaseModel], environ: Mapping[str, str],
                  prefix: str = ENV_PREFIX) -> dict[str, Any]:
    """Nested overrides from ``PREFIX`` variables whose first part is a field of ``model``."""
    out: dict[str, Any] = {}
    for name, raw in environ.items():
        if not name.startswith(prefix):
            continue
        path = [p.lower() for p in name[len(prefix):].split("__") if p]
        if not path or path[0] not in model.model_fields:
            continue
        try:
            value = yaml.safe_load(raw) if raw.strip() else raw
        except yaml.YAMLError as e:
            raise ConfigError(f"{name}: not a YAML value ({e})") from None
        _set_path(out, path, value)
    return out


def _merge(base: dict[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), dict):
            out[k] = _merge(out[k], v)
        else:
            out[k] = v
    return out


def load_config(model: type[T], path: str | Path | None = None,
                overrides: Mapping[str, Any] | None = None,
                environ: Mapping[str, str] | None = None) -> T:
    """Validate ``model`` from the YAML at ``path``, then env, then explicit ``overrides``."""
    data: dict[str, Any] = {}
    if path is not None:
        data = read_yaml_mapping(Path(path))
    data = _merge(data, env_overrides(model, os.environ if environ is None else environ))
    data = _merge(data, overrides or {})
    return validate(model, data, path)


def read_yaml_mapping(path: Path) -> dict[str, Any]:
    """The mapping in a YAML file; ``ConfigError`` when it cannot be read, is not text, is not
    YAML or holds something else."""
    try:
        loaded = read_yaml(path, "a config is YAML text")
    except UnreadableFile as e:
        raise ConfigError(f"{path}: {e.problem.replace('cannot read', 'cannot read config')}"
                          ) from None
    if loaded is not None and not isinstance(loaded, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level")
    return loaded or {}


def validate(model: type[T], data: Mapping[str, Any], path: str | Path | None = None,
             root: str = "") -> T:
    """``model`` from ``data``; ``ConfigError`` naming each bad field on one line (under
    ``root`` when ``model`` is one part of a larger config, e.g. ``bus``)."""
    try:
        return model.model_validate(data)
    except pydantic.ValidationError as e:
        where = f" in {path}" if path else ""
        raise ConfigError(f"config error{where}: {describe(e, root)}") from None


def describe(err: pydantic.ValidationError, root: str = "") -> str:
    """A validation error as ``field.path: what is wrong`` items on one line."""
    items = []
    for e in err.errors(include_url=False):
        loc = ".".join([root] * bool(root) + [str(p) for p in e["loc"]]) or "(top level)"
        msg = e["msg"].removeprefix("Value error, ")
        items.append(f"{loc}: {' '.join(msg.split())}")
    return "; ".join(items)


def write_resolved(cfg: pydantic.BaseModel, out_dir: str | Path,
                   name: str = "config.yaml") -> Path:
    """Write the validated configuration, defaults filled in, into ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    target = out / name
    target.write_text(yaml.safe_dump(cfg.model_dump(mode="json"), sort_keys=False))
    return target


def changed_keys(old: pydantic.BaseModel, new: pydantic.BaseModel,
                 under: tuple[str, ...] = ()) -> list[tuple[str, Any, Any]]:
    """The settings that differ between two configs of one model, as ``(dotted.key, old
    value, new value)`` in the model's order; ``under``: only keys under these top-level
    ones (all when empty). Lists are values of their own (``robots``, ``bus.listen``)."""
    a, b = _flat(old.model_dump(mode="json")), _flat(new.model_dump(mode="json"))
    keys = list(a) + [k for k in b if k not in a]
    return [(k, a.get(k), b.get(k)) for k in keys
            if a.get(k) != b.get(k) and (not under or k.split(".", 1)[0] in under)]


def describe_changes(changes: list[tuple[str, Any, Any]], shown: int = 4) -> str:
    """``key (old → new), …`` on one line: the first ``shown``, then "and N more"."""
    items = [f"{k} ({_short(a)} → {_short(b)})" for k, a, b in changes[:shown]]
    if len(changes) > shown:
        items.append(f"and {len(changes) - shown} more")
    return ", ".join(items)


def _flat(data: Any, prefix: str = "") -> dict[str, Any]:
    if not isinstance(data, dict):
        return {prefix: data}
    out: dict[str, Any] = {}
    for k, v in data.items():
        out.update(_flat(v, f"{prefix}.{k}" if prefix else str(k)))
    return out


def _short(value: Any, width: int = 40) -> str:
    text = " ".join(str(value).split())
    return text if len(text) <= width else text[:width - 1] + "…"
