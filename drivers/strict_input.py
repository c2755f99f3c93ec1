"""Strict reading of config files: what YAML and pydantic's lax mode would otherwise let through.

- :class:`StrictModel`: a pydantic base that refuses a YAML boolean or a string where a number is
  expected (``node_id: true`` would otherwise be node 1, ``period_s: "0.001"`` a float) and any
  non-finite float (``.inf``, ``.nan``). Lists, tuples and paths are still read from YAML's
  plain types (pydantic's ``strict`` mode would refuse a YAML list for a tuple).
- :func:`load_yaml_unique`: ``yaml.safe_load`` that refuses a mapping with a key twice (PyYAML
  keeps the last one silently: an operator who overrides a limit further down a long file and
  forgets the first line gets whichever came last).
- :func:`loads_json_unique`: ``json.loads`` with the same refusal (the policy-bundle manifest).

Only pydantic, PyYAML and the standard library: the daemon, the driver and the target share it.
"""

from __future__ import annotations

import json
import os
import re
import types
import typing
from pathlib import Path
from typing import Annotated, Any, Union, get_args, get_origin

import yaml
from pydantic import BaseModel, ConfigDict, ValidationInfo, model_validator
from pydantic_core import PydanticCustomError


def _refused(annotation: Any, value: Any) -> bool:
    """True when ``value`` is a bool or a string given where ``annotation`` takes only numbers."""
    origin, args = get_origin(annotation), get_args(annotation)
    if annotation is type(None):
        return value is not None
    if origin is Annotated:
        return _refused(args[0], value)
    if origin in (Union, types.UnionType):  # refused only when no alternative takes it
        return all(_refused(arg, value) for arg in args)
    if origin in (tuple, list) and isinstance(value, (list, tuple)):
        items = [arg for arg in args if arg is not Ellipsis]
        if not items:
            return False
        if len(items) == 1 or len(items) != len(value):
            return any(_refused(items[0], item) for item in value)
        return any(_refused(kind, item) for kind, item in zip(items, value, strict=True))
    if annotation in (int, float):
        return isinstance(value, (bool, str))
    return False


class StrictModel(BaseModel):
    """Frozen, no unknown fields, no non-finite floats, no bool or string read as a number."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    @model_validator(mode="before")
    @classmethod
    def _no_coercion(cls, data: Any) -> Any:
        # A model validator, not a field one: pydantic forbids 'before' validators on the
        # discriminator of a tagged union ('kind'), which a "*" field validator would include.
        if isinstance(data, dict):
            for name, field in cls.model_fields.items():
                key = field.alias or name
                if key in data and _refused(field.annotation, data[key]):
                    raise PydanticCustomError(
                        "strict_number",
                        "expected a number, got {value}",
                        {"field": key, "value": _short(data[key])},
                    )
        return data


def config_relative_path(value: Path, info: ValidationInfo) -> Path:
    """A path field of a config file: relative to the file's folder (the validation context's
    ``base_dir``), not to whatever directory the daemon was started from."""
    base = info.context.get("base_dir") if isinstance(info.context, dict) else None
    value = value.expanduser()
    return Path(os.path.normpath(Path(base) / value)) if base is not None and not value.is_absolute() else value


def error_location(error: Any) -> tuple[Any, ...]:
    """The location of one pydantic error, with the field a :class:`StrictModel` refused appended
    (a model validator's error is located at the model, its ``field`` in the context)."""
    loc = tuple(error["loc"])
    if error.get("type") == "strict_number":
        loc += (error.get("ctx", {}).get("field", ""),)
    return loc


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


class DuplicateKeyError(ValueError):
    """A JSON object with one key twice."""


class _UniqueKeyLoader(yaml.SafeLoader):
    """SafeLoader whose mappings refuse a repeated key (at the repeated key's line), and which reads
    ``1e300`` or ``1.5e3`` as the number YAML 1.2 says it is (PyYAML's 1.1 rules want a dot and a
    signed exponent, else it is a string)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: set[Any] = set()
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":  # '<<: *anchor' merges, it is no key
                continue
            key = self.construct_object(key_node, deep=deep)
            try:
                repeated = key in seen
            except TypeError:  # an unhashable key: SafeLoader's own error follows
                continue
            if repeated:
                raise yaml.constructor.ConstructorError(
                    "while constructing a mapping", node.start_mark, f"duplicate key {key!r}", key_node.start_mark
                )
            seen.add(key)
        return super().construct_mapping(node, deep)


_UniqueKeyLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$"),  # 1e300, 1.5e3, .5e3
    list("-+0123456789."),
)


def load_yaml_unique(text: str) -> Any:
    """``yaml.safe_load`` refusing duplicate keys (``yaml.YAMLError`` with the line)."""
    return yaml.load(text, Loader=_UniqueKeyLoader)


def _unique_pairs(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise DuplicateKeyError(f"duplicate key {key!r}")
        out[key] = value
    return out


def loads_json_unique(text: str | bytes) -> Any:
    """``json.loads`` refusing duplicate keys (:class:`DuplicateKeyError`) and NaN/Infinity."""

    def constant(name: str) -> typing.NoReturn:
        raise ValueError(f"{name} is not JSON")

    return json.loads(text, object_pairs_hook=_unique_pairs, parse_constant=constant)
