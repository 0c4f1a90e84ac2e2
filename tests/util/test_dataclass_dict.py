"""Config dataclasses from dicts (JSON): every field is checked against its type, naming the key.

Issue 14, item 12: ``{"shard_rows": 1.5}`` made a map that crashed every later command;
``merge_both_ways: "no"`` and ``index_pca_dim: 1.5`` were taken silently. The check is driven by
the field types, so it covers every config dataclass (the map's, the HMM's, the server's, ...).
"""

from __future__ import annotations

import dataclasses
import json
import typing
from typing import Any

import pytest

from sprint_map.config import MapConfig
from sprint_map.errors import ConfigError
from sprint_map.frontend.groundtruth import GroundTruthSpec
from sprint_map.hmm.config import HMMConfig
from sprint_map.server.config import ServerConfig
from sprint_map.synth.city import CityConfig
from sprint_map.util import dataclass_dict

CONFIGS: list[tuple[type, dict[str, Any]]] = [
    (MapConfig, {"dim": 16}), (HMMConfig, {}), (ServerConfig, {}), (CityConfig, {}),
    (GroundTruthSpec, {"alignment": "frame"}),
]


def _wrong_values(hint: Any) -> list[Any]:
    """Values of another type than ``hint`` (as JSON could give them)."""
    origin = typing.get_origin(hint)
    if hint is bool:
        return ["no", 1, 0.0, None]
    if hint is int:
        return [1.5, "3", True, None, [1]]
    if hint is float:
        return ["0.5", True, None, {}]
    if hint is str:
        return [3, None, ["a"]]
    if origin is tuple:
        return ["abc", 3, [["x"]]]
    if origin is dict:
        return [[1], "x", {1: 2}]
    return []


@pytest.mark.parametrize("cls, base", CONFIGS, ids=[c.__name__ for c, _ in CONFIGS])
def test_every_field_refuses_values_of_another_type_naming_the_key(cls, base):
    hints = typing.get_type_hints(cls)
    tried = 0
    for field in dataclasses.fields(cls):
        for value in _wrong_values(hints[field.name]):
            with pytest.raises(ConfigError) as refused:
                dataclass_dict.from_dict(cls, {**base, field.name: value})
            message = str(refused.value)
            assert message.startswith(f"{cls.__name__}: {field.name} must be "), message
            assert "\n" not in message
            tried += 1
    assert tried >= len(dataclasses.fields(cls))


@pytest.mark.parametrize("cls, base", CONFIGS, ids=[c.__name__ for c, _ in CONFIGS])
def test_defaults_round_trip_through_json(cls, base):
    obj = dataclass_dict.from_dict(cls, base)
    again = dataclass_dict.from_dict(cls, json.loads(json.dumps(dataclass_dict.to_dict(obj))))
    assert again == obj


def test_the_issue_cases_and_what_stays_accepted():
    for key, value, says in (("shard_rows", 1.5, r"store: shard_rows must be an integer, got 1.5"),
                             ("merge_both_ways", "no", r"merge: both_ways must be true or false"),
                             ("index_pca_dim", 1.5, r"store: index_pca_dim must be an integer")):
        with pytest.raises(ConfigError, match=rf"^MapConfig\.{says}"):
            MapConfig.from_dict({"dim": 8, key: value})
    with pytest.raises(ConfigError, match=r"^MapConfig\.hmm: k must be an integer, got 2\.0$"):
        MapConfig.from_dict({"dim": 8, "hmm": {"k": 2.0}})
    with pytest.raises(ConfigError, match=r"^MapConfig\.hmm: dist_scale must be a number or "
                                          r"null, got 'auto'$"):
        MapConfig.from_dict({"dim": 8, "hmm": {"dist_scale": "auto"}})
    # Range checks stay the dataclasses' own.
    with pytest.raises(ConfigError, match="shard_rows must be >= 1"):
        MapConfig.from_dict({"dim": 8, "shard_rows": 0})
    # An integer is a number; a JSON list is a tuple; None where None is allowed.
    config = MapConfig.from_dict({"dim": 8, "merge_threshold": 1, "index_persist_growth": 2,
                                  "hmm": {"window": [1, 2], "dist_scale": None}})
    assert config.merge.threshold == 1.0 and isinstance(config.merge.threshold, float)
    assert config.hmm.window == (1.0, 2.0) and config.hmm.dist_scale is None
    # A nested config may also be given as such (dataclass_dict.replace).
    hmm = HMMConfig(k=3)
    assert dataclass_dict.replace(config, hmm=hmm).hmm is hmm
    with pytest.raises(ConfigError, match=r"^MapConfig\.hmm: expected a mapping, got int$"):
        MapConfig.from_dict({"dim": 8, "hmm": 3})


@pytest.mark.parametrize(("value", "ok"), [(0, True), (3, True), (-1, False), (True, False),
                                           (1.0, False), ("1", False)])
def test_check_int_takes_integers_at_least_the_bound(value, ok):
    if ok:
        dataclass_dict.check_int("n", value, 0)
    else:
        with pytest.raises(ValueError, match=r"^n must be an integer >= 0$"):
            dataclass_dict.check_int("n", value, 0)


@pytest.mark.parametrize(("value", "says"), [
    (float("nan"), "x must be a finite number"), (True, "x must be a finite number"),
    (0.0, r"x must be in \(0.0, 1.0\]"), (1.5, r"x must be in \(0.0, 1.0\]")])
def test_check_number_names_the_range(value, says):
    dataclass_dict.check_number("x", 0.5, 0.0, 1.0, lo_open=True)  # inside
    with pytest.raises(ValueError, match=f"^{says}$"):
        dataclass_dict.check_number("x", value, 0.0, 1.0, lo_open=True)
