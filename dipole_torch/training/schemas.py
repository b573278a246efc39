"""The structured configs (Hydra schemas) of ``train.py``, generated from the code they build.

Each default is stated once, where the object is defined: a task's in its constructor's
signature, DIPOLE's in ``DipoleOptions``, PoWER's in
``Power``'s signature. ``builds`` turns a signature (or a dataclass)
into a dataclass with the same names, defaults and OmegaConf-checkable types, and the help
of each field from the docstring's ``Args:`` / ``Attributes:`` section (or a gymnasium-style
``## Arguments`` list), as hydra-zen's ``builds`` does, plus the help. The YAML files of
``configs/`` then hold only the experiment's own settings (a task's name, budget and initial
samples; an algorithm's name) and extend these schemas, so OmegaConf checks every value's
type when a config is composed and names the key in its error.

The schemas are stored in Hydra's ConfigStore under top-level names (``dipole_torch/...``,
not in the ``task`` or ``algo`` groups), so they are never offered as choices. They are
registered by ``train.py`` and by importing ``dipole_torch.configs`` (which
``hydra.initialize_config_module("dipole_torch.configs")`` does), never by merely installing
the package: no Hydra plugin.
"""

from __future__ import annotations

import dataclasses
import inspect
import re
import types
import typing
from collections.abc import Callable, Mapping, Sequence
from dataclasses import MISSING as DATACLASS_MISSING
from dataclasses import field
from pathlib import Path
from typing import Any

from omegaconf import MISSING

__all__ = ["builds", "docstring_help", "field_help"]

_SCALARS = (bool, int, float, str)


def builds(
    target: Callable | type,
    *,
    target_path: str,
    exclude: Sequence[str] = (),
    values: Mapping[str, Any] | None = None,
    also: tuple[Callable | type, Sequence[str]] | None = None,
    name: str | None = None,
) -> type:
    """A dataclass of ``target``'s arguments: ``_target_ = target_path`` and one field per
    parameter of its signature (or field of a dataclass ``target``), with its default, an
    OmegaConf type and ``metadata={"help": ...}`` from its docstring.

    Args:
        target: a class (its ``__init__``), a function or a dataclass.
        target_path: the dotted path ``hydra.utils.instantiate`` calls.
        exclude: parameters the caller supplies (``theta0``, ``generator``, …) or that are
            no config's business (``dtype``).
        values: fields whose schema default differs from the signature's (e.g. a device
            that interpolates the run's ``${device}``).
        also: ``(callable, names)``: more fields, the parameters ``names`` of another
            signature (e.g. a constructor's ``bounds`` beside its options dataclass).
        name: the dataclass's name (default: the target's, plus ``Config``).
    """
    values = dict(values or {})
    parameters, hints, doc = _parameters(target)
    help_of = docstring_help(doc)
    if also is not None:
        more, more_hints, more_doc = _parameters(also[0])
        parameters += [(n, d) for n, d in more if n in also[1]]
        hints = {**more_hints, **hints}
        help_of = {**docstring_help(more_doc), **help_of}
    fields = [("_target_", str, field(default=target_path, metadata={"help": "what is built"}))]
    for parameter, default in parameters:
        if parameter in exclude:
            continue
        annotation = _config_type(hints.get(parameter, Any))
        value = values.pop(parameter, default)
        fields.append((parameter, annotation, _field(_plain(value), help_of.get(parameter, ""))))
    if values:
        raise ValueError(f"{target_path} has no argument(s) {sorted(values)}")
    title = name or f"{getattr(target, '__name__', 'Target')}Config"
    return dataclasses.make_dataclass(title, fields)


def field_help(schema: type) -> dict[str, str]:
    """``{field: help}`` of a schema made by ``builds`` or written with ``_field``."""
    return {f.name: f.metadata.get("help", "") for f in dataclasses.fields(schema)}


def docstring_help(doc: str | None) -> dict[str, str]:
    """``{name: one-line help}`` from a docstring's Google-style ``Args:`` or ``Attributes:``
    section (``name: text``, continued on indented lines) or a gymnasium-style
    ``## Arguments`` list (``* ``name``[, ``other``]: text``). The help is the entry's first
    sentence."""
    if not doc:
        return {}
    text = inspect.cleandoc(doc)
    entries: dict[str, str] = {}
    google = re.search(r"^(Args|Arguments|Attributes):\n((?:[ \t]+.*\n?|\n)+)", text, re.M)
    if google:
        block = google.group(2)
        indent = min(len(line) - len(line.lstrip()) for line in block.splitlines() if line.strip())
        current = None
        for line in block.splitlines():
            if not line.strip():
                continue
            depth = len(line) - len(line.lstrip())
            match = re.match(r"\s*\**(\w+)(?: \(.*?\))?:\s*(.*)", line)
            if depth == indent and match:
                current = [match.group(1)]
                entries[current[0]] = match.group(2)
            elif current:
                for key in current:
                    entries[key] += " " + line.strip()
    bullets = re.search(r"^## Arguments\n((?:.*\n?)*?)(?=^## |\Z)", text, re.M)
    if bullets:
        current = []
        for line in bullets.group(1).splitlines():
            match = re.match(r"\* ((?:``\w+``(?:, )?)+):\s*(.*)", line)
            if match:
                current = re.findall(r"``(\w+)``", match.group(1))
                for key in current:
                    entries.setdefault(key, match.group(2))
            elif line.startswith(" ") and current:
                for key in current:
                    entries[key] += " " + line.strip()
            elif not line.strip():
                continue
            else:
                current = []
    return {key: _first_sentence(value) for key, value in entries.items()}


def _first_sentence(text: str) -> str:
    """The text up to its first ``.`` outside parentheses that ends a sentence (the next word
    starts with a capital: "eq. 9" and "e.g. a" go on), reST roles unwrapped."""
    text = re.sub(r"``([^`]*)``", r"\1", " ".join(text.split()))
    text = re.sub(r":\w+:`~?([^`]*)`", r"\1", text)
    depth = 0
    for i, char in enumerate(text):
        depth += {"(": 1, "[": 1, ")": -1, "]": -1}.get(char, 0)
        if char != "." or depth != 0:
            continue
        if i + 1 == len(text) or (
            text[i + 1] == " "
            and not text[i + 2 : i + 3].islower()
            and not text[i + 2 : i + 3].isdigit()
        ):
            return _without_references(text[:i])
    return _without_references(text.rstrip("."))


def _without_references(sentence: str) -> str:
    """``sentence`` without its pointers into the code's docs ("; see DPSampler.fit",
    "(see Description)"), which ``--help`` cannot follow."""
    sentence = re.sub(r";\s*see [^();]*\)", ")", sentence)  # "(the default; see below)"
    sentence = re.sub(r" \(see [^()]*\)", "", sentence)
    clauses = re.split(r"; (?![^()\[\]]*[)\]])", sentence)  # at "; " outside brackets
    return "; ".join(c for c in clauses if not re.search(r"\bsee\b", c)) or clauses[0]


def _parameters(target) -> tuple[list[tuple[str, Any]], dict[str, Any], str | None]:
    """``[(name, default)]``, the type hints and the docstring of ``target``."""
    if dataclasses.is_dataclass(target):
        fields = [
            (f.name, f.default if f.default is not DATACLASS_MISSING else MISSING)
            for f in dataclasses.fields(target)
        ]
        return fields, typing.get_type_hints(target), target.__doc__
    function = target.__init__ if inspect.isclass(target) else target
    signature = inspect.signature(function)
    parameters = [
        (p.name, MISSING if p.default is inspect.Parameter.empty else p.default)
        for p in signature.parameters.values()
        if p.name != "self" and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)
    ]
    doc = target.__doc__ if inspect.isclass(target) else function.__doc__
    return parameters, typing.get_type_hints(function), doc


def _config_type(annotation: Any) -> Any:
    """The OmegaConf type of a Python annotation: scalars and ``None`` unions of them,
    ``list[...]`` for sequences, ``str`` for paths, ``Any`` for the rest (checked by the
    constructor)."""
    if annotation in _SCALARS:
        return annotation
    if annotation is Path:
        return str
    if typing.is_typeddict(annotation):
        return _typed_dict_schema(annotation)
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin in (types.UnionType, typing.Union):
        inner = [_config_type(a) for a in args if a is not type(None)]
        inner = list(dict.fromkeys(str if a is Path else a for a in inner))
        optional = type(None) in args
        if len(inner) == 1 and inner[0] is not Any:
            return inner[0] | None if optional else inner[0]
        return Any
    if origin in (list, tuple, Sequence) or (
        isinstance(origin, type) and issubclass(origin, Sequence) and origin is not str
    ):
        items = [a for a in args if a is not Ellipsis]
        if len(set(items)) == 1:
            inner = _config_type(items[0])
            return list[inner] if inner is not Any else list
        return list
    return Any


def _typed_dict_schema(annotation) -> type:
    """A dataclass of a ``TypedDict``'s keys (each required, typed, its help from the
    docstring's ``Attributes:``), so that OmegaConf checks each entry of a list of them."""
    help_of = docstring_help(annotation.__doc__)
    fields = [
        (key, _config_type(hint), _field(MISSING, help_of.get(key, "")))
        for key, hint in typing.get_type_hints(annotation).items()
    ]
    return dataclasses.make_dataclass(annotation.__name__, fields)


def _plain(value: Any) -> Any:
    """A default as a config value: tuples as lists, paths as strings."""
    if isinstance(value, tuple | list):
        return [_plain(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    return value


def _field(default: Any, help: str) -> Any:  # noqa: A002 (the metadata key Hydra users know)
    """A dataclass field with a ``help`` string; a list default is copied per instance."""
    if isinstance(default, list):
        return field(default_factory=lambda: [*default], metadata={"help": help})
    return field(default=default, metadata={"help": help})
