"""Stage settings as JSON and back, and a --set value checked against its declared type (workbench.stages.settings)."""

from __future__ import annotations

import dataclasses
import typing
from pathlib import Path

import pytest

from workbench.stages.register import RegisterSettings
from workbench.stages.settings import setting_value, settings_dict, settings_from_json


@dataclasses.dataclass(frozen=True)
class _Settings:
    name: str = "a"
    size: int = 3
    scale: float | None = None
    on: bool = True
    levels: tuple | None = (3, 5)
    where: Path = Path("out") / "x.json"
    pairs: tuple = ()


def test_settings_dict_is_plain_json():
    d = settings_dict(_Settings(pairs=(("shrink", (4, 2)),)))
    assert d == {
        "name": "a",
        "size": 3,
        "scale": None,
        "on": True,
        "levels": [3, 5],
        "where": "out/x.json",
        "pairs": [["shrink", [4, 2]]],
    }
    assert type(d["levels"]) is list and type(d["pairs"][0][1]) is list


def test_settings_dict_refuses_what_json_cannot_hold():
    with pytest.raises(ValueError, match=r"\$\.scale is nan"):
        settings_dict(_Settings(scale=float("nan")))


def test_a_flat_settings_object_round_trips_exactly():
    s = _Settings(name="b", size=7, scale=0.1 + 0.2, on=False, levels=(1, 2, 4))
    args = settings_from_json(_Settings, settings_dict(s))
    assert args["levels"] == (1, 2, 4) and type(args["levels"]) is tuple  # a JSON list back to a tuple
    assert _Settings(**{**args, "where": Path(args["where"])}) == s


def test_nested_lists_stay_lists_but_the_json_is_a_fixed_point():
    # only a setting's own list becomes a tuple; lists inside it stay lists (RegisterSettings makes its pairs
    # tuples itself)
    s = RegisterSettings(
        levels=(2, 3), dense_settings=(("elastic_mm", 1.5), ("iterations", (20, 10)), ("shrink", (4, 2)))
    )
    recorded = settings_dict(s)
    args = settings_from_json(RegisterSettings, recorded)
    assert args["dense_settings"] == (["elastic_mm", 1.5], ["iterations", [20, 10]], ["shrink", [4, 2]])
    assert args["levels"] == (2, 3)
    assert RegisterSettings(**args) == s
    # what the digests hash: the recorded JSON, which the round trip reproduces exactly
    assert settings_dict(RegisterSettings(**args)) == recorded


def test_missing_keys_are_left_to_the_defaults_and_unknown_keys_are_dropped():
    # a study recorded by another version: absent settings take their defaults, settings this version does not
    # have are not passed on (the constructor would refuse them)
    args = settings_from_json(_Settings, {"size": 9, "retired_setting": 1})
    assert args == {"size": 9}
    assert _Settings(**args) == _Settings(size=9)


def test_settings_from_json_of_nothing_is_the_defaults():
    assert settings_from_json(_Settings, {}) == {}


_HINTS = typing.get_type_hints(_Settings)


@pytest.mark.parametrize(
    "field, value, expected",
    [
        ("size", 4, 4),
        ("size", 4.0, 4),  # a whole-number float is taken for an int
        ("scale", 2, 2.0),  # and a whole number for a float
        ("scale", 0.25, 0.25),
        ("scale", None, None),  # null: the default of an optional setting
        ("on", False, False),
        ("name", "b", "b"),
        ("levels", [3, 5], [3, 5]),
    ],
)
def test_setting_value_takes_the_declared_type(field, value, expected):
    got = setting_value(field, value, _HINTS[field])
    assert got == expected and type(got) is type(expected)


def test_setting_value_reads_optional_and_union_spellings_alike():
    assert setting_value("x", None, typing.Optional[int]) is None  # noqa: UP045 (the spelling under test)
    assert setting_value("x", 3, typing.Union[int, None]) == 3  # noqa: UP007
    assert setting_value("x", 3, int | None) == 3


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("size", 2.5, "--set size: the setting is a whole number (int), got 2.5; nothing was changed."),
        ("size", True, "--set size: the setting is a whole number (int), got true; nothing was changed."),
        ("size", "four", "--set size: the setting is a whole number (int), got the text 'four'; nothing was changed."),
        ("size", None, "--set size: the setting is a whole number (int), got null; nothing was changed."),
        ("on", 1, "--set on: the setting is true or false (bool), got 1; nothing was changed."),
        ("name", 5, "--set name: the setting is text (str), got 5; nothing was changed."),
        (
            "scale",
            "big",
            "--set scale: the setting is a number (float) (null for the default), got the text 'big'; nothing was "
            "changed.",
        ),
        (
            "levels",
            3,
            "--set levels: the setting is a JSON list (tuple), e.g. [3, 5] (null for the default), got 3; nothing was "
            "changed.",
        ),
        (
            "levels",
            {"a": 1},
            '--set levels: the setting is a JSON list (tuple), e.g. [3, 5] (null for the default), got {"a": 1}; '
            "nothing was changed.",
        ),
    ],
)
def test_a_wrong_value_is_one_line_naming_the_setting_the_type_and_the_value(field, value, message):
    with pytest.raises(ValueError) as e:
        setting_value(field, value, _HINTS[field])
    assert str(e.value) == message
    assert "\n" not in str(e.value)


def test_the_error_names_the_option_given():
    with pytest.raises(ValueError, match=r"^--dense shrink: the setting is a JSON list"):
        setting_value("shrink", 4, tuple, option="--dense")
