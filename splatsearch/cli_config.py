"""Every field of a config dataclass as a command-line flag: ``--PREFIX.FIELD VALUE``.

:func:`add_config_flags` adds one flag per field of :class:`~splatsearch.mapper.MapperConfig`,
:class:`~splatsearch.slam.TrackerConfig`,
:class:`~splatsearch.agent.AgentConfig` (and nested ones, e.g. ``--agent.local_map.stride``), with
the field's type, its default and the sentence of the class docstring that documents it as help.
Only the flags a user gives are applied (:func:`config_overrides`), so the dataclass defaults stay
the single source of truth. The config classes live in modules that import JAX, so the CLI adds
these flags only when the chosen sub-command needs them (``splatsearch --help`` stays light).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import re
from typing import Any

_TRUE = {"1", "true", "yes", "on"}
_FALSE = {"0", "false", "no", "off"}


def _bool(text: str) -> bool:
    t = text.strip().lower()
    if t in _TRUE:
        return True
    if t in _FALSE:
        return False
    raise argparse.ArgumentTypeError(f"expected true/false, got {text!r}")


def _optional(conv):
    def parse(text: str):
        return None if text.strip().lower() == "none" else conv(text)

    parse.__name__ = getattr(conv, "__name__", "value")
    return parse


def _sequence(text: str) -> tuple:
    """A comma-separated tuple of numbers, e.g. ``20,45`` or ``600,600``."""
    try:
        return tuple(int(v) if re.fullmatch(r"[+-]?\d+", v.strip()) else float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None


def _mapping(text: str) -> dict:
    try:
        value = json.loads(text)
    except json.JSONDecodeError as e:
        raise argparse.ArgumentTypeError(f"expected a JSON object, got {text!r} ({e.msg})") from None
    if not isinstance(value, dict):
        raise argparse.ArgumentTypeError(f"expected a JSON object, got {text!r}")
    return value


_PARSERS = {"bool": (_bool, "BOOL"), "int": (int, "INT"), "float": (float, "FLOAT"), "str": (str, "TEXT"),
            "tuple": (_sequence, "A,B,..."), "dict": (_mapping, "JSON")}


def field_help(cls: type, name: str) -> str:
    """The clause of ``cls``'s docstring that documents field ``name`` (``name`` in double back-quotes
    or as a Google-style ``name:`` attribute entry), in one line; "" if the docstring is silent."""
    doc = " ".join((cls.__doc__ or "").split())
    m = re.search(rf"(?:^|[.;:]\s)([^.;]*?``{re.escape(name)}``[^;]*?)(?:[.;](?:\s|$)|$)", doc)
    if m is None:
        m = re.search(rf"(?:^|\s){re.escape(name)}:\s(.*?)(?=\s[a-z_]+:\s|$)", doc)
    if m is None:
        return ""
    text = m.group(1).strip().replace("``", "")
    return text if text.startswith(name) else text[:1].upper() + text[1:]


def _resolve(type_text: Any, cls: type) -> tuple[str, bool]:
    """(base type name, optional) of a field's annotation (a string under postponed annotations)."""
    if not isinstance(type_text, str):
        type_text = getattr(type_text, "__name__", str(type_text))
    parts = [p.strip() for p in type_text.replace("Optional[", "").rstrip("]").split("|")]
    optional = "None" in parts
    parts = [p for p in parts if p != "None"]
    base = parts[0] if parts else "str"
    base = base.split("[")[0]
    return base, optional


def add_config_flags(parser: argparse.ArgumentParser, cls: type, prefix: str, *, skip: tuple[str, ...] = (),
                     title: str | None = None, helps: dict[str, str] | None = None) -> list[str]:
    """Add ``--{prefix}.{field}`` for every field of dataclass ``cls`` (recursing into nested
    dataclasses) to ``parser`` in their own help group. ``helps`` (field name -> text) replaces
    :func:`field_help` for the top-level fields it names. Returns the flag names added."""
    group = parser.add_argument_group(
        title or f"{cls.__name__} (--{prefix}.FIELD; applied after the flags above)",
        f"every field of {cls.__module__}.{cls.__name__}; only the ones given change the defaults")
    return _add(group, cls, prefix, skip, helps or {})


def _add(group, cls: type, prefix: str, skip: tuple[str, ...], helps: dict[str, str] | None = None) -> list[str]:
    helps = helps or {}
    added = []
    for f in dataclasses.fields(cls):
        if f.name in skip or not f.init:
            continue
        default = f.default if f.default is not dataclasses.MISSING else (
            f.default_factory() if f.default_factory is not dataclasses.MISSING else None)
        if dataclasses.is_dataclass(default):
            added += _add(group, type(default), f"{prefix}.{f.name}", ())
            continue
        base, optional = _resolve(f.type, cls)
        if base not in _PARSERS:
            base = type(default).__name__ if type(default).__name__ in _PARSERS else "str"
        conv, metavar = _PARSERS[base]
        if optional:
            conv, metavar = _optional(conv), metavar + "|none"
        doc = helps.get(f.name) or field_help(cls, f.name)
        shown = json.dumps(default) if isinstance(default, dict) else (
            ",".join(map(str, default)) if isinstance(default, tuple) else default)
        help_ = f"{doc + '; ' if doc else ''}{base}{' or none' if optional else ''} (default: {shown})"
        flag = f"--{prefix}.{f.name}"
        group.add_argument(flag, dest=f"{prefix}.{f.name}", type=conv, metavar=metavar, default=argparse.SUPPRESS,
                           help=help_.replace("%", "%%"))
        added.append(flag)
    return added


def config_overrides(args: argparse.Namespace, prefix: str) -> dict[str, Any]:
    """The ``--{prefix}.*`` values the user gave, as a nested dict of field overrides."""
    out: dict[str, Any] = {}
    for key, value in vars(args).items():
        if not key.startswith(prefix + "."):
            continue
        node = out
        *path, leaf = key[len(prefix) + 1:].split(".")
        for p in path:
            node = node.setdefault(p, {})
        node[leaf] = value
    return out


def apply_overrides(config, overrides: dict[str, Any]):
    """``config`` with ``overrides`` (from :func:`config_overrides`) applied, nested dataclasses
    included; the dataclass' own checks (``__post_init__``, ``validate``) run on the result."""
    changes = {}
    for name, value in overrides.items():
        current = getattr(config, name)
        changes[name] = apply_overrides(current, value) if dataclasses.is_dataclass(current) else value
    new = dataclasses.replace(config, **changes)
    if hasattr(new, "validate"):
        new.validate()
    return new
