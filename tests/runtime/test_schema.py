"""Registry checks against plain reference versions of the same rules."""

from __future__ import annotations

import enum
from typing import Any

import numpy as np
import pytest

from gsfix_online.runtime.schema import REGISTRY, MessageSpec, WireError, _meta_ok, check_meta

SCALARS = (type(None), bool, int, float, str)


def check_meta_reference(type_name: str, spec: MessageSpec, meta: Any) -> None:
    """check_meta as first written: every value through isinstance, lists element by element."""
    if not isinstance(meta, dict):
        raise WireError("meta", "not a map")
    for key, value in meta.items():
        if not isinstance(key, str):
            raise WireError("meta", "key")
        flat = value if isinstance(value, list) else [value]
        if not all(isinstance(v, SCALARS) for v in flat):
            raise WireError("meta", "value")
    for key, kind in spec.meta.items():
        if key not in meta or not _meta_ok(meta[key], kind):
            raise WireError("meta", "missing or wrong type")


class Level(enum.IntEnum):
    LOW = 1


class Name(str):
    pass


EXTRA_VALUES = [
    None,
    True,
    3,
    -(2**63),
    2.5,
    float("nan"),
    "x",
    Level.LOW,  # an int subclass
    Name("n"),  # a str subclass
    np.float64(1.0),  # a float subclass
    np.int64(1),  # not an int subclass
    np.bool_(True),
    b"\x00",
    [],
    [1, "a", None, 2.0, False],
    [Level.LOW, Name("n")],
    [[1]],
    [b"x"],
    (1, 2),
    {"a": 1},
    {1, 2},
]


def outcome(check: Any, meta: Any) -> str:
    try:
        check("heartbeat", REGISTRY["heartbeat"], meta)
    except WireError as exc:
        return exc.reason
    return "ok"


@pytest.mark.parametrize("value", EXTRA_VALUES, ids=repr)
def test_check_meta_matches_its_reference(value: object) -> None:
    base = {"node": "a", "pid": 1, "uptime_s": 0.5}
    for meta in ({**base, "extra": value}, {**base, "pid": value}, {"extra": value}):
        assert outcome(check_meta, meta) == outcome(check_meta_reference, meta)
    assert outcome(check_meta, {**base, 7: value}) == "meta"  # non-str key
    assert outcome(check_meta, [base]) == "meta"
