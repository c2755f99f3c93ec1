"""drivers.strict_input: no bool or string read as a number, no key given twice, YAML 1.2 floats."""

from __future__ import annotations

import pytest
import yaml
from pydantic import Field, ValidationError

from drivers.strict_input import DuplicateKeyError, StrictModel, error_location, load_yaml_unique, loads_json_unique


class _Model(StrictModel):
    count: int = 0
    gain: float | None = None
    limits: tuple[float, ...] = ()
    name: str = ""
    flag: bool = False
    bounded: float = Field(1.0, le=10.0)


@pytest.mark.parametrize(
    ("data", "field"),
    [
        ({"count": True}, "count"),
        ({"count": "3"}, "count"),
        ({"gain": False}, "gain"),
        ({"gain": "0.5"}, "gain"),
        ({"limits": [1.0, True]}, "limits"),
    ],
)
def test_a_bool_or_a_string_is_not_a_number(data: dict[str, object], field: str) -> None:
    with pytest.raises(ValidationError) as info:
        _Model.model_validate(data)
    first = info.value.errors()[0]
    assert error_location(first)[-1] == field and "expected a number" in first["msg"]


def test_numbers_strings_and_flags_where_they_belong_are_read() -> None:
    model = _Model.model_validate({"count": 3, "gain": 1, "limits": [1, 2.5], "name": "12", "flag": True})
    assert model.count == 3 and model.gain == 1.0 and model.limits == (1.0, 2.5) and model.flag is True


@pytest.mark.parametrize("value", [float("inf"), float("nan"), 1e300])
def test_non_finite_and_out_of_range_values_are_refused(value: float) -> None:
    with pytest.raises(ValidationError):
        _Model.model_validate({"bounded": value})


def test_a_yaml_key_given_twice_is_refused_at_its_line() -> None:
    with pytest.raises(yaml.YAMLError) as info:
        load_yaml_unique("a: 1\nb:\n  c: 2\n  c: 3\n")
    assert "duplicate key 'c'" in str(info.value) and "line 4" in str(info.value)
    assert load_yaml_unique("base: &b {x: 1}\nderived:\n  <<: *b\n  y: 2\n")["derived"] == {"x": 1, "y": 2}


def test_yaml_exponent_floats_are_numbers() -> None:
    data = load_yaml_unique("a: 1e300\nb: 1.5e3\nc: 12\nd: '1e3'\ne: 2.0e-5\n")
    assert data == {"a": 1e300, "b": 1500.0, "c": 12, "d": "1e3", "e": 2e-5}


def test_a_json_key_given_twice_and_nan_are_refused() -> None:
    with pytest.raises(DuplicateKeyError, match="duplicate key 'a'"):
        loads_json_unique('{"a": 1, "b": {"a": 2}, "a": 3}')
    with pytest.raises(ValueError, match="NaN is not JSON"):
        loads_json_unique('{"a": NaN}')
    assert loads_json_unique('{"a": {"a": 1}}') == {"a": {"a": 1}}
