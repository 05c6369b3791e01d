"""Every configuration key with its type, default and description, read from the section models.

docs/configuration.md is generated from here (`siteloc config docs`; a test checks it is current), and
`siteloc config show --explain KEY` prints one key, so neither can drift from the code.
"""

from __future__ import annotations

import difflib
import types
import typing
from dataclasses import dataclass

from pydantic import BaseModel

from pipeline.errors import ConfigError

# Which stage reads each top-level section (docs/pipeline.md names the stages).
OWNERS = {
    "preset": "every stage", "seed": "every stage", "synth": "synth", "ingest": "ingest", "ingest_log": "ingest-log",
    "filter": "the runtime (bundle's filter.yaml), localize, evaluate", "detector": "train-detector, evaluate-detector",
    "retrieval": "extract, build-index, query, evaluate-retrieval, export", "place": "train-place",
    "export": "export", "update": "update", "check": "check", "sequence": "frame-features, train-sequence",
    "prior": "prior features, prior build, prior evaluate", "evaluate": "evaluate, localize",
}


@dataclass(frozen=True)
class Key:
    key: str  # dotted
    type: str
    default: object  # the model's default (a section: None)
    description: str
    section: bool


def _type_name(annotation) -> str:
    origin = typing.get_origin(annotation)
    if origin is typing.Literal:
        return " | ".join(repr(a) for a in typing.get_args(annotation))
    if origin in (typing.Union, types.UnionType):
        return " | ".join("null" if a is type(None) else _type_name(a) for a in typing.get_args(annotation))
    if origin is tuple:
        args = [a for a in typing.get_args(annotation) if a is not Ellipsis]
        return f"list of {_type_name(args[0])}" if args else "list"
    if origin is dict:
        return "mapping"
    if isinstance(annotation, type):
        if issubclass(annotation, BaseModel):
            return "section"
        return {"int": "integer", "float": "number", "str": "string", "bool": "true | false"}.get(
            annotation.__name__, annotation.__name__)
    return str(annotation)


def _section_model(annotation) -> type[BaseModel] | None:
    return annotation if isinstance(annotation, type) and issubclass(annotation, BaseModel) else None


def _doc(text: str | None) -> str:
    return " ".join((text or "").split())


def keys(model: type[BaseModel] | None = None, prefix: str = "") -> list[Key]:
    """Every key under `model` (default: the whole config), depth first, sections before their keys."""
    from pipeline.config import SitelocConfig

    model = model or SitelocConfig
    out = []
    for name, field in model.model_fields.items():
        dotted = f"{prefix}{name}"
        sub = _section_model(field.annotation)
        if sub is not None:
            out.append(Key(dotted, "section", None, _doc(field.description or sub.__doc__), True))
            out.extend(keys(sub, dotted + "."))
        else:
            default = field.get_default(call_default_factory=True)
            if isinstance(default, BaseModel):
                default = default.model_dump(mode="json")
            out.append(Key(dotted, _type_name(field.annotation), default, _doc(field.description), False))
    return out


def _value(v) -> str:
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, tuple | list):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    return str(v)


def explain(dotted: str, cfg: BaseModel | None = None) -> str:
    """A key's (or a section's) type, default, value in `cfg` (when given) and description, as plain text."""
    found = {k.key: k for k in keys()}
    if dotted not in found:
        close = difflib.get_close_matches(dotted, list(found), n=3, cutoff=0.6)
        hint = f"; did you mean {', '.join(close)}?" if close else "; `siteloc config docs` lists every key"
        raise ConfigError(f"unknown config key '{dotted}'{hint}")
    k = found[dotted]
    top = dotted.split(".")[0]
    lines = [f"{k.key}  ({k.type}; read by {OWNERS.get(top, top)})"]
    if k.section:
        if k.description:
            lines.append(f"  {k.description}")
        lines += [f"  {c.key}: {_value(c.default)}" for c in found.values()
                  if c.key.startswith(dotted + ".") and c.key.count(".") == dotted.count(".") + 1]
        return "\n".join(lines)
    lines.append(f"  default: {_value(k.default)}")
    if cfg is not None:
        lines.append(f"  in this config: {_value(_value_at(cfg, dotted))}")
    if k.description:
        lines.append(f"  {k.description}")
    return "\n".join(lines)


def _value_at(cfg: BaseModel, dotted: str):
    node = cfg
    for part in dotted.split("."):
        node = getattr(node, part)
    return node.model_dump(mode="json") if isinstance(node, BaseModel) else node


def markdown() -> str:
    """docs/configuration.md: one table per top-level section."""
    from pipeline.config import SitelocConfig

    lines = ["# Configuration keys", "",
             "Generated from the models of `pipeline/config/` by `siteloc config docs --out docs/configuration.md`",
             "(a test fails when it is stale). `siteloc config show --explain KEY` prints one key;",
             "`siteloc config show --config PRESET` the effective values. Presets are in `configs/`;",
             "any key can be set with `--set KEY=VALUE`.", ""]
    top_level = [k for k in keys() if "." not in k.key]
    scalars = [k for k in top_level if not k.section]
    if scalars:
        lines += ["## Top level", "", "| key | type | default | description |", "| --- | --- | --- | --- |"]
        lines += [_row(k) for k in scalars] + [""]
    for sec in (k for k in top_level if k.section):
        model = SitelocConfig.model_fields[sec.key].annotation
        lines += [f"## `{sec.key}`", "", f"Read by {OWNERS.get(sec.key, sec.key)}. {_doc(model.__doc__)}".rstrip(),
                  "", "| key | type | default | description |", "| --- | --- | --- | --- |"]
        lines += [_row(k) for k in keys(model, sec.key + ".") if not k.section] + [""]
    return "\n".join(lines)


def _row(k: Key) -> str:
    esc = lambda s: s.replace("|", "\\|")  # noqa: E731
    return f"| `{k.key}` | {esc(k.type)} | `{esc(_value(k.default))}` | {esc(k.description)} |"
