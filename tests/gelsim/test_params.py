"""Tests of gelsim.params: building validated frozen dataclasses from TOML tables."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal

import pytest

from gelsim.errors import GelsimError
from gelsim.params import build, dump_toml, load_toml, param, to_dict


@dataclass(frozen=True)
class Inner:
    size_mm: float = param(lo=0.0, hi=10.0, lo_open=True)
    count: int = param(3, lo=1, hi=9)


@dataclass(frozen=True)
class Outer:
    name: str
    inner: Inner
    items: tuple[Inner, ...] = ()
    rgb: tuple[float, float, float] = param((0.5, 0.5, 0.5), lo=0.0, hi=1.0)
    mode: Literal["fast", "slow"] = "fast"
    enabled: bool = True
    note: str | None = None

    def validate(self, where: str) -> None:
        if self.name == "forbidden":
            raise GelsimError(f"{where}.name: 'forbidden' is reserved; choose another name")


GOOD = {"name": "x", "inner": {"size_mm": 2.5}, "items": [{"size_mm": 1.0, "count": 2}]}


def test_build_good_table_with_defaults():
    o = build(Outer, GOOD, where="f.toml")
    assert o.inner == Inner(2.5, 3)
    assert o.items == (Inner(1.0, 2),)
    assert o.rgb == (0.5, 0.5, 0.5) and o.mode == "fast" and o.enabled is True and o.note is None
    assert isinstance(o.inner.size_mm, float)
    with pytest.raises(dataclasses.FrozenInstanceError):
        o.name = "y"  # type: ignore[misc]


def test_int_given_for_float_is_converted():
    o = build(Outer, {**GOOD, "inner": {"size_mm": 2}})
    assert o.inner.size_mm == 2.0 and isinstance(o.inner.size_mm, float)


@pytest.mark.parametrize("data, pattern", [
    ({**GOOD, "colour": 1}, r"^f\.toml: unknown key 'colour'; known keys are enabled, inner, items"),
    ({**GOOD, "inner": {"size_mm": 1.0, "sise": 2}}, r"^f\.toml\.inner: unknown key 'sise'"),
    ({"inner": {"size_mm": 1.0}}, r"^f\.toml\.name: missing; add it to the file$"),
    ({**GOOD, "inner": {}}, r"^f\.toml\.inner\.size_mm: missing"),
    ({**GOOD, "inner": {"size_mm": "big"}}, r"inner\.size_mm: expected a number, got 'big'"),
    ({**GOOD, "inner": {"size_mm": True}}, r"inner\.size_mm: expected a number, got True"),
    ({**GOOD, "inner": {"size_mm": 1.0, "count": 2.5}}, r"inner\.count: expected an integer, got 2\.5"),
    ({**GOOD, "name": 3}, r"\.name: expected a string, got 3"),
    ({**GOOD, "enabled": 1}, r"\.enabled: expected true or false, got 1"),
    ({**GOOD, "mode": "medium"}, r"\.mode: 'medium' is not one of 'fast', 'slow'"),
    ({**GOOD, "inner": 5}, r"\.inner: expected a table, got int"),
    ({**GOOD, "items": {"size_mm": 1.0}}, r"\.items: expected a list, got dict"),
    ({**GOOD, "rgb": [0.1, 0.2]}, r"\.rgb: expected 3 values, got 2"),
    ({**GOOD, "inner": {"size_mm": 0.0}}, r"inner\.size_mm: 0\.0 is out of range; it must be > 0\.0 and <= 10\.0"),
    ({**GOOD, "inner": {"size_mm": 11.0}}, r"inner\.size_mm: 11\.0 is out of range; it must be <= 10\.0"),
    ({**GOOD, "inner": {"size_mm": 1.0, "count": 0}}, r"inner\.count: 0 is out of range; it must be >= 1"),
    ({**GOOD, "rgb": [0.1, 1.2, 0.3]}, r"\.rgb\[1\]: 1\.2 is out of range"),
    ({**GOOD, "items": [{"size_mm": 1.0}, {"size_mm": -1.0}]}, r"\.items\[1\]\.size_mm: -1\.0 is out of range"),
    ({**GOOD, "inner": {"size_mm": float("nan")}}, r"inner\.size_mm: nan is not a finite number"),
    ({**GOOD, "inner": {"size_mm": float("inf")}}, r"inner\.size_mm: inf is not a finite number"),
    ({**GOOD, "name": "forbidden"}, r"f\.toml\.name: 'forbidden' is reserved"),
])
def test_build_rejects_bad_tables(data, pattern):
    with pytest.raises(GelsimError, match=pattern):
        build(Outer, data, where="f.toml")


def test_gelsim_error_is_a_value_error():
    with pytest.raises(ValueError):
        build(Outer, {}, where="f.toml")


def test_param_rejects_mutable_default():
    with pytest.raises(TypeError, match="immutable"):
        param([1, 2])


def test_load_toml_good_missing_and_malformed(tmp_path):
    good = tmp_path / "good.toml"
    good.write_text('name = "x"\n[inner]\nsize_mm = 1.5\n')
    assert load_toml(good) == {"name": "x", "inner": {"size_mm": 1.5}}
    with pytest.raises(GelsimError, match=r"nope\.toml: file not found; check the path"):
        load_toml(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text('name = "x\n')
    with pytest.raises(GelsimError, match=r"bad\.toml: malformed TOML \(.*\); fix the file's syntax"):
        load_toml(bad)
    nonfinite = tmp_path / "nan.toml"
    nonfinite.write_text('name = "x"\n[inner]\nsize_mm = nan\n')
    with pytest.raises(GelsimError, match="not a finite number"):
        build(Outer, load_toml(nonfinite), where="nan.toml")


def test_round_trip_through_toml(tmp_path):
    o = build(Outer, {**GOOD, "rgb": [0.1, 0.2, 0.3], "mode": "slow", "enabled": False})
    d = to_dict(o)
    d.pop("note")                       # None has no TOML form
    text = dump_toml(d, header="round trip")
    assert text.startswith("# round trip\n")
    p = tmp_path / "rt.toml"
    p.write_text(text)
    assert build(Outer, load_toml(p)) == o


def test_toml_entries_keep_each_keys_comment_with_its_continuation(tmp_path):
    from gelsim.params import toml_comments, toml_entries

    (tmp_path / "s.toml").write_text(
        '# header\n'
        'name = "x"  # a label # with a hash\n'
        'title = "a # b"\n'
        '[gel]\n'
        'thickness_mm = 2.0   # assumed: as vitac\n'
        '                     # (continued)\n'
        '# a section comment, not a continuation\n'
        'modulus = 0.2\n'
        '[[lights]]\n'
        'azimuth_deg = 4.8  # measured\n'
        '[[lights]]\n'
        'azimuth_deg = -118.3\n')
    got = toml_entries(tmp_path / "s.toml")
    assert got == [("name", '"x"', "a label # with a hash"), ("title", '"a # b"', None),
                   ("gel.thickness_mm", "2.0", "assumed: as vitac (continued)"), ("gel.modulus", "0.2", None),
                   ("lights[0].azimuth_deg", "4.8", "measured"), ("lights[1].azimuth_deg", "-118.3", None)]
    # what calibrate carries: plain values outside arrays of tables
    assert toml_comments(tmp_path / "s.toml") == {"gel.thickness_mm": "assumed: as vitac (continued)"}
