"""Typed reading of ONNX ``metadata_props`` strings: each function returns the value of one
key as the type the contract needs, or raises :class:`ModelContractError` naming the key and
what it held (the first 60 characters)."""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from typing import Any

from tactile.errors import ModelContractError


def isnum(x: object) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def json_value(meta: Mapping[str, str], key: str) -> Any:
    try:
        return json.loads(meta[key])
    except (TypeError, ValueError) as e:
        raise ModelContractError(f"metadata key {key!r} is not valid JSON ({e})") from None


def names(meta: Mapping[str, str], key: str) -> tuple[str, ...]:
    v = strings(meta, key)
    if len(set(v)) != len(v) or not all(v):
        raise ModelContractError(f"metadata key {key!r}: names must be unique and non-empty, "
                                 f"got {list(v)}")
    return v


def strings(meta: Mapping[str, str], key: str) -> tuple[str, ...]:
    v = json_value(meta, key)
    if not (isinstance(v, list) and all(isinstance(x, str) for x in v)):
        raise ModelContractError(f"metadata key {key!r} must be a JSON list of strings, "
                                 f"got {meta[key][:60]!r}")
    return tuple(v)


def json_object(meta: Mapping[str, str], key: str) -> dict:
    v = json_value(meta, key)
    if not isinstance(v, dict):
        raise ModelContractError(f"metadata key {key!r} must be a JSON object, "
                                 f"got {meta[key][:60]!r}")
    return v


def integer(meta: Mapping[str, str], key: str) -> int:
    try:
        return int(meta[key])
    except ValueError:
        raise ModelContractError(f"metadata key {key!r} must be an integer, "
                                 f"got {meta[key][:60]!r}") from None


def number(meta: Mapping[str, str], key: str) -> float:
    try:
        return float(meta[key])
    except ValueError:
        raise ModelContractError(f"metadata key {key!r} must be a number, "
                                 f"got {meta[key][:60]!r}") from None


def text(meta: Mapping[str, str], key: str) -> str:
    return str(meta[key])


def choice(meta: Mapping[str, str], key: str, allowed: tuple[str, ...]) -> str:
    v = meta[key]
    if v not in allowed:
        raise ModelContractError(f"metadata key {key!r} is {v[:60]!r}, allowed: "
                                 f"{', '.join(allowed)}")
    return v


def list_of_objects(meta: Mapping[str, str], key: str) -> list[dict]:
    if key not in meta:
        return []
    v = json_value(meta, key)
    if not (isinstance(v, list) and v and all(isinstance(x, dict) for x in v)):
        raise ModelContractError(f"metadata key {key!r} must be a non-empty JSON list of "
                                 f"objects, got {meta[key][:60]!r}")
    return v


def entry_field(key: str, i: int, obj: dict, name: str, kind: str):
    """``obj[name]`` of entry ``i`` of list ``key``, checked to be a ``kind``."""
    v = obj.get(name)
    ok = {
        "name": isinstance(v, str) and bool(v),
        "names": isinstance(v, list) and bool(v) and all(isinstance(x, str) for x in v)
        and len(set(v)) == len(v),
        "bool": isinstance(v, bool),
        "int": isinstance(v, int) and not isinstance(v, bool),
        "rate": isnum(v) and v > 0,
    }[kind]
    if not ok:
        what = {"name": "a non-empty string", "names": "a non-empty list of distinct names",
                "bool": "true or false", "int": "an integer", "rate": "a number > 0"}[kind]
        raise ModelContractError(f"metadata key {key!r}: entry {i} {name!r} must be {what}, "
                                 f"got {json.dumps(v)[:60]}")
    return tuple(v) if kind == "names" else (float(v) if kind == "rate" else v)


__all__ = ["isnum", "json_value", "names", "strings", "json_object", "integer", "number", "text",
           "choice", "list_of_objects", "entry_field"]
