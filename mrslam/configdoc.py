"""The configuration reference, generated from the config models themselves.

Each process's config is a pydantic model whose fields carry their meaning in
``Field(description=...)``. This module walks such a model (nested models become sections,
every other field a row: key path, type, default, description) and renders Markdown, and
prints a component's defaults as YAML (``mrslam config server``). ``docs/config.md`` is its
output; ``tests/test_configdoc.py`` fails when the two differ, so the page cannot go stale:

    python -m mrslam.configdoc > docs/config.md
"""

from __future__ import annotations

import importlib
import json
import types
import typing
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import annotated_types
import yaml
from pydantic import BaseModel

#: component -> (model as ``module:Class``, the command that reads it)
COMPONENTS: dict[str, tuple[str, str]] = {
    "server": ("server.config:ServerConfig", "`mrslam server -c server.yaml`: the central "
               "server (Zenoh router, SLAM, merging, exploration)"),
    "agent": ("robot_agent.config:AgentConfig", "`mrslam agent -c agent.yaml`: the agent on "
              "each robot (drivers or the simulator backend)"),
    "sim": ("sim.config:SimConfig", "`mrslam sim -c sim.yaml`: the 2D simulator"),
    "demo": ("mrslam.demo:DemoConfig", "`mrslam demo`: one demo run, set by its command-line "
             "options and saved as `demo_config.yaml` in the run folder"),
}
#: where the packages are installed: defaults under it are shown relative to it
_INSTALL_ROOT = Path(__file__).resolve().parents[1]
COMMAND = "python -m mrslam.configdoc > docs/config.md"


class ConfigDocError(ValueError):
    """An unknown component was asked for."""

    user_error = True


@dataclass(frozen=True)
class Row:
    key: str            # dotted path from the top of the file, e.g. ``teams.min_sightings``
    type: str
    default: str
    description: str


@dataclass(frozen=True)
class Section:
    path: str           # dotted path of the nested model ('' for the top level)
    doc: str            # first paragraph of the model's docstring ('' without one)
    rows: tuple[Row, ...]


def model_of(component: str) -> type[BaseModel]:
    """The config model of ``component`` (imported only now: the server's pulls in gtsam)."""
    if component not in COMPONENTS:
        raise ConfigDocError(f"unknown component {component!r}: give one of "
                             f"{', '.join(COMPONENTS)}")
    module, name = COMPONENTS[component][0].split(":")
    model = getattr(importlib.import_module(module), name)
    assert isinstance(model, type) and issubclass(model, BaseModel)
    return model


def default_yaml(component: str) -> str:
    """The component's default configuration as YAML, every key spelled out."""
    model = model_of(component)
    head = (f"# mrslam {component}: the default configuration "
            f"(`mrslam config {component} --markdown` says what each key means)\n")
    return head + yaml.safe_dump(model().model_dump(mode="json"), sort_keys=False,
                                 allow_unicode=True)


# -- walking a model ---------------------------------------------------------------------------
def _nested_model(annotation: Any) -> type[BaseModel] | None:
    return annotation if isinstance(annotation, type) and issubclass(annotation, BaseModel) \
        else None


def sections(model: type[BaseModel], instance: BaseModel | None = None,
             path: str = "") -> Iterator[Section]:
    """The model's own fields as one section, then each nested model's, depth first; defaults
    are read from ``instance`` (a parent may give a nested model other defaults than its
    class has)."""
    inst = instance if instance is not None else model()
    dumped = inst.model_dump(mode="json")
    rows, nested = [], []
    for name, field in model.model_fields.items():
        key = f"{path}.{name}" if path else name
        sub = _nested_model(field.annotation)
        if sub is not None:
            nested.append((sub, getattr(inst, name), key))
            continue
        rows.append(Row(key, _type_text(field.annotation, field.metadata),
                        _value_text(dumped[name]), _one_line(field.description or "")))
    yield Section(path, _doc(model), tuple(rows))
    for sub, sub_inst, key in nested:
        yield from sections(sub, sub_inst, key)


def _doc(model: type[BaseModel]) -> str:
    doc = model.__dict__.get("__doc__") or ""   # a model's own docstring, never its base's
    return _one_line(doc.strip().split("\n\n")[0])


def _one_line(text: str) -> str:
    return " ".join(text.replace("``", "`").split())


def _type_text(annotation: Any, metadata: list[Any] | None = None) -> str:
    args = typing.get_args(annotation)
    if typing.get_origin(annotation) in (typing.Union, types.UnionType) and type(None) in args:
        rest = [a for a in args if a is not type(None)]   # bounds bind to the value, not null
        value = (_type_text(rest[0], metadata) if len(rest) == 1
                 else " or ".join(_type_name(a) for a in rest))
        return f"{value} or null"
    text = _type_name(annotation)
    bounds = _bounds(metadata or [])
    return f"{text} {bounds}" if bounds else text


def _type_name(t: Any) -> str:
    origin, args = typing.get_origin(t), typing.get_args(t)
    if origin is typing.Annotated:
        return _type_name(args[0])
    if t is type(None):
        return "null"
    if origin is typing.Literal:
        return " or ".join(json.dumps(a) for a in args)
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_type_name(a) for a in args)
    if origin is list:
        return f"list of {_type_name(args[0])}"
    if origin is dict:
        return f"map of {_type_name(args[0])} to {_type_name(args[1])}"
    if origin is tuple:
        return "[" + ", ".join(_type_name(a) for a in args) + "]"
    return getattr(t, "__name__", str(t))


def _bounds(metadata: list[Any]) -> str:
    lo: tuple[str, Any] | None = None
    hi: tuple[str, Any] | None = None
    for m in metadata:
        if isinstance(m, annotated_types.Gt):
            lo = ("(", m.gt)
        elif isinstance(m, annotated_types.Ge):
            lo = ("[", m.ge)
        elif isinstance(m, annotated_types.Lt):
            hi = (")", m.lt)
        elif isinstance(m, annotated_types.Le):
            hi = ("]", m.le)
    if lo and hi:
        return f"in {lo[0]}{_number(lo[1])}, {_number(hi[1])}{hi[0]}"
    if lo:
        return f"{'>' if lo[0] == '(' else '≥'} {_number(lo[1])}"
    if hi:
        return f"{'<' if hi[0] == ')' else '≤'} {_number(hi[1])}"
    return ""


def _number(v: Any) -> str:
    return f"{v:g}" if isinstance(v, float) else str(v)


def _value_text(v: Any) -> str:
    if isinstance(v, str):
        p = Path(v)
        if p.is_absolute() and p.is_relative_to(_INSTALL_ROOT):
            return f"`{p.relative_to(_INSTALL_ROOT).as_posix()}` (shipped with mrslam)"
        return f"`{v}`" if v else '`""`'
    return f"`{json.dumps(v, ensure_ascii=False)}`"


# -- Markdown ----------------------------------------------------------------------------------
def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def render_component(component: str) -> str:
    """One component's reference: a heading, then a table per (nested) section."""
    model = model_of(component)
    return render_model(component, COMPONENTS[component][1] + ".", model)


def render_model(title: str, intro: str, model: type[BaseModel]) -> str:
    out = [f"## {title}", "", intro, ""]
    for s in sections(model):
        if not s.rows:
            continue
        out += [f"### {title}: `{s.path}`" if s.path else f"### {title}: top level", ""]
        if s.doc:
            out += [s.doc, ""]
        out += ["| key | type | default | description |", "|---|---|---|---|"]
        out += [f"| `{r.key}` | {_cell(r.type)} | {_cell(r.default)} | {_cell(r.description)} |"
                for r in s.rows]
        out.append("")
    return "\n".join(out)


def render_reference() -> str:
    """The whole reference: what ``docs/config.md`` holds."""
    links = ", ".join(f"[{c}](#{c})" for c in COMPONENTS)
    head = f"""# Configuration reference

<!-- Generated from the config models by `{COMMAND}`; do not edit by hand.
     tests/test_configdoc.py fails when this page and the models differ. -->

Every process reads one YAML file (`-c FILE`); only the keys that differ from the defaults
need to be in it. A key path such as `teams.min_sightings` is written nested:

```yaml
teams:
  min_sightings: 3
```

Environment variables `MRSLAM_<KEY>__<SUBKEY>` override the file, e.g.
`MRSLAM_TEAMS__MIN_SIGHTINGS=4` or `MRSLAM_BUS__CONNECT='["tcp/10.0.0.2:7447"]'` (values are
read as YAML). An unknown key or a value out of range stops the process with one line naming
the key (exit code 2). The resolved configuration is written next to a run's outputs.
`mrslam config COMPONENT` prints a component's defaults as YAML, a starting point for a file.

Units are in the names: `_m` metres, `_s` seconds, `_ns` nanoseconds, `_deg` degrees, `_rad`
radians, `_mps` m/s, `_rps` rad/s, `_hz` per second, `_px` pixels, `_m2` square metres.
Sections: {links}.
"""
    return head + "\n" + "\n".join(render_component(c) for c in COMPONENTS)


def main() -> None:
    print(render_reference(), end="")


if __name__ == "__main__":
    main()
