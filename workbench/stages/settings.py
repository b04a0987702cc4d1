"""Stage settings as JSON and back: what ``study.json`` records and the digest hashes
(:func:`~workbench.stages.settings.settings_dict`, :func:`~workbench.stages.settings.settings_from_json`), and a
value given on the command line checked against the type its settings dataclass declares
(:func:`~workbench.stages.settings.setting_value`).
"""

from __future__ import annotations

import dataclasses

from workbench.io.jsonio import to_jsonable

__all__ = ["settings_dict", "settings_from_json", "setting_value"]


def settings_dict(settings) -> dict:
    """A settings dataclass as plain JSON (paths as strings, tuples as lists)."""
    return to_jsonable(dataclasses.asdict(settings))


def settings_from_json(cls, d: dict) -> dict:
    """Recorded settings back into constructor arguments (lists → tuples where the default is a tuple)."""
    out = {}
    for f in dataclasses.fields(cls):
        if f.name not in d:
            continue
        v = d[f.name]
        if isinstance(v, list):
            v = tuple(v)
        out[f.name] = v
    return out


_TYPE_WORDS = {
    int: "a whole number (int)",
    float: "a number (float)",
    bool: "true or false (bool)",
    str: "text (str)",
    tuple: "a JSON list (tuple), e.g. [3, 5]",
}


def setting_value(name: str, value, declared, option: str = "--set"):
    """``value`` as the type ``declared`` (``X`` or ``X | None``), else one clear :class:`ValueError`."""
    import json
    import types
    import typing

    args = (
        typing.get_args(declared)
        if isinstance(declared, types.UnionType) or typing.get_origin(declared) is typing.Union
        else (declared,)
    )
    optional = type(None) in args
    kinds = [a for a in args if a is not type(None)]
    if value is None and optional:
        return None
    for kind in kinds:
        if kind is bool and isinstance(value, bool):
            return value
        if kind is int and isinstance(value, int) and not isinstance(value, bool):
            return value
        if kind is int and isinstance(value, float) and value.is_integer():
            return int(value)
        if kind is float and isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        if kind is str and isinstance(value, str):
            return value
        if kind is tuple and isinstance(value, list):
            return value
    want = " or ".join(_TYPE_WORDS.get(k, getattr(k, "__name__", str(k))) for k in kinds)
    if optional:
        want += " (null for the default)"
    got = "null" if value is None else f"the text {value!r}" if isinstance(value, str) else json.dumps(value)
    raise ValueError(f"{option} {name}: the setting is {want}, got {got}; nothing was changed.")
