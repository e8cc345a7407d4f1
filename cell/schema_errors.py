"""What to tell a person whose YAML a schema refused: the key they probably meant, and whether they gave a
file of another kind altogether.

A misspelled key is an unknown key to pydantic (``extra_forbidden``); :func:`unknown_key_message` finds the
schema at the key's place (walking the field annotations along the error's location) and offers the closest
known key (difflib). :func:`wrong_kind_message` recognises a whole file of another kind by its top-level keys
(:data:`cell.file_kinds.FILE_KINDS`): a recipe given where a cell config belongs is one mistake, not a list of
typos.
"""

from __future__ import annotations

import difflib
import types
from collections.abc import Mapping, Sequence
from typing import Annotated, Any, Union, get_args, get_origin

from pydantic import BaseModel

from cell.file_kinds import explained_keys, identify, kind_of_schema

MAX_LISTED = 12  # with no close match, the known keys are listed when there are at most this many


def _members(tp: Any) -> list[Any]:
    """The types an annotation may hold: Annotated and unions unwrapped, None dropped."""
    origin = get_origin(tp)
    if origin is Annotated:
        return _members(get_args(tp)[0])
    if origin is Union or origin is types.UnionType:
        return [m for a in get_args(tp) for m in _members(a)]
    return [] if tp is type(None) else [tp]


def _is_model(tp: Any) -> bool:
    return isinstance(tp, type) and issubclass(tp, BaseModel)


def _step(tp: Any, part: str | int) -> Any:
    """The annotation one location step below ``tp`` (a field, a list item, a mapping value, a union member
    named by pydantic's tag), or None when the walk cannot follow."""
    for member in _members(tp):
        if _is_model(member):
            if isinstance(part, str) and part in member.model_fields:
                return member.model_fields[part].annotation
            if part == member.__name__:  # pydantic names the union member it tried
                return member
            continue
        origin, args = get_origin(member), get_args(member)
        if isinstance(part, int) and origin in (list, set, frozenset, Sequence) and args:
            return args[0]
        if isinstance(part, int) and origin is tuple and args:
            variadic = len(args) == 2 and args[1] is Ellipsis
            return args[0] if variadic else args[part] if part < len(args) else None
        if isinstance(part, str) and origin in (dict, Mapping) and len(args) == 2:
            return args[1]
    return None


def known_keys(model: type[BaseModel], where: Sequence[str | int]) -> list[str]:
    """The keys the schema ``model`` allows at location ``where`` (a mapping's place in the file), or []."""
    tp: Any = model
    for part in where:
        tp = _step(tp, part)
        if tp is None:
            return []
    models = [m for m in _members(tp) if _is_model(m)]
    return sorted({k for m in models for k in m.model_fields})


def meant_key(model: type[BaseModel], loc: Sequence[str | int]) -> str | None:
    """The known key closest to the unknown key at ``loc`` when one is close (difflib), else None."""
    key = str(loc[-1]) if loc else ""
    close = difflib.get_close_matches(key, known_keys(model, loc[:-1]), n=1, cutoff=0.6)
    return close[0] if close else None


def unknown_key_message(model: type[BaseModel], loc: Sequence[str | int]) -> str:
    """The message for the unknown key at ``loc``: the closest known key when one is close, else the known
    keys when they are few."""
    close = meant_key(model, loc)
    if close:
        return f"unknown key (typo?); did you mean '{close}'?"
    known = known_keys(model, loc[:-1])
    if known and len(known) <= MAX_LISTED:
        return f"unknown key (typo?); the keys here are: {', '.join(known)}"
    return "unknown key (typo?); remove it or check the schema in docs/"


def wrong_kind_message(model: type[BaseModel], data: Mapping[str, Any]) -> str | None:
    """'this is a <kind> file, not a <expected> file' when ``data``'s top-level keys say it is a file of
    another known kind than ``model``'s (and explain more of it than ``model`` does); else None."""
    expected = kind_of_schema(f"{model.__module__}:{model.__qualname__}")
    if expected is None:
        return None
    keys = {str(k) for k in data}
    found = identify(keys)
    if found is None or found is expected or explained_keys(found, keys) <= explained_keys(expected, keys):
        return None
    return f"this is {_a(found.name)} file, not {_a(expected.name)} file; {found.use}"


def _a(noun: str) -> str:
    return f"{'an' if noun[0] in 'aeiou' else 'a'} {noun}"
