"""Each fusion and grid parameter is declared once (engine/params.py) and reaches the value
objects, the command line and the REST API with the same name, default, help and range; each
invalid value is refused by all three with a message that names it."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from rangefuse.engine import FusionParams, GridSpec, InvalidInputError, NoiseModel
from rangefuse.engine.params import PARAMS, Param, params_of
from rangefuse.service.accounts import Accounts
from rangefuse.service.api.models import NoiseIn, NoiseOut, SceneIn, SceneOut
from rangefuse.service.app import create_app
from rangefuse.service.cli import build_parser
from rangefuse.service.settings import Settings
from rangefuse.storage import Store

DECLARED = list(PARAMS)
VALUE_OBJECT = {"grid": GridSpec, "noise": NoiseModel, "fusion": FusionParams}


def _invalid(param: Param) -> list[Any]:
    """Values just outside the declared range or choices, and values of the wrong kind."""
    if param.kind == "choice":
        return ["nope"]
    if param.kind == "bounds":
        return [[0.0, 0.0, 0.0, 1.0, 1.0], [0.0, 0.0, 0.0, math.inf, 1.0, 1.0]]
    out: list[Any] = []
    if param.low is not None:
        out.append(param.low if not param.low_inclusive else param.low - 1)
    if param.high is not None:
        out.append(param.high if not param.high_inclusive else param.high + 1)
    if param.kind == "float":
        out.append(math.nan)
    return [*out, "abc"]


def _cases() -> list[tuple[str, Any]]:
    return [(name, value) for name in DECLARED for value in _invalid(PARAMS[name])]


def _build(name: str, value: Any) -> object:
    group = PARAMS[name].group
    if group == "grid":
        return GridSpec(**{"voxel_size": 0.01, name: value})
    if group == "noise":
        return NoiseModel(**{"eps": 0.01, name: value})
    return FusionParams(NoiseModel(0.01), **{name: value})


def _fuse_options() -> dict[str, argparse.Action]:
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    fuse = sub.choices["fuse"]
    return {o: a for a in fuse._actions for o in a.option_strings}


# --- the declaration reaches every front end ---------------------------------------------------


def test_the_declared_groups_are_the_value_objects_fields() -> None:
    for group, cls in VALUE_OBJECT.items():
        fields = [f for f in cls.__dataclass_fields__ if f != "noise"]
        assert fields == [p.name for p in params_of(group)], group


@pytest.mark.parametrize("name", DECLARED)
def test_value_object_default(name: str) -> None:
    param = PARAMS[name]
    field = VALUE_OBJECT[param.group].__dataclass_fields__[name]
    if param.required or (param.default is None and not param.nullable):  # voxel_size, eps
        assert field.default is field.default_factory  # no default (both MISSING)
    else:
        assert field.default == param.default
    if param.default is not None:
        assert param.validate(param.default) == param.default


@pytest.mark.parametrize("name", DECLARED)
def test_command_line_option(name: str, capsys: pytest.CaptureFixture[str]) -> None:
    param = PARAMS[name]
    action = _fuse_options()[param.flag]
    assert action.dest == name
    assert action.default == param.default
    assert action.required == param.required
    assert action.help is not None and action.help.startswith(param.describe(param.metavar or None))
    assert param.default_words in action.help
    if param.kind == "choice":
        assert tuple(action.choices or ()) == param.choices
    with pytest.raises(SystemExit):
        build_parser().parse_args(["fuse", "--help"])
    assert param.flag in capsys.readouterr().out


@pytest.mark.parametrize("name", DECLARED)
def test_rest_request_and_response_fields(name: str) -> None:
    param = PARAMS[name]
    request, response = (NoiseIn, NoiseOut) if param.group == "noise" else (SceneIn, SceneOut)
    field = request.model_fields[name]
    assert field.is_required() == param.required
    if not param.required:
        assert field.default == param.default
    assert field.description is not None and field.description.startswith(param.describe())
    schema = request.model_json_schema()["properties"][name]
    assert param.json_schema().items() <= schema.items()
    assert schema["description"] == field.description
    answer = response.model_fields[name]
    assert answer.is_required() and answer.description.startswith(param.describe())


def test_rest_models_hold_only_declared_parameters() -> None:
    assert set(NoiseIn.model_fields) == {p.name for p in params_of("noise")}
    assert set(SceneIn.model_fields) - {"name", "noise", "sensor"} == {
        p.name for p in PARAMS.values() if p.group != "noise"
    }


# --- every invalid value is refused, naming the parameter --------------------------------------


@pytest.mark.parametrize(("name", "value"), _cases())
def test_value_object_refuses(name: str, value: Any) -> None:
    with pytest.raises(InvalidInputError) as info:
        _build(name, value)
    assert info.value.field == name
    assert str(info.value).startswith(f"{name}: ")


@pytest.mark.parametrize(("name", "value"), _cases())
def test_command_line_refuses(name: str, value: Any, capsys: pytest.CaptureFixture[str]) -> None:
    param = PARAMS[name]
    words = [str(v) for v in value] if isinstance(value, list) else [str(value)]
    argv = ["fuse", "data", "--voxel-size", "0.01", param.flag, *words]
    with pytest.raises(SystemExit) as info:
        build_parser().parse_args(argv)
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert f"argument {param.flag}: " in err, err
    if param.kind in ("float", "int") and not isinstance(value, str):
        with pytest.raises(InvalidInputError) as engine:
            param.validate(value)
        assert f"argument {param.flag}: {engine.value.problem}" in err  # the same words


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> TestClient:
    data_dir = Path(tmp_path_factory.mktemp("store"))
    app = create_app(Settings(data_dir=data_dir))  # no lifespan: no job runs here
    with Store.open(data_dir) as store, Accounts(store.catalog.path) as accounts:
        token = accounts.create_token("t")
    return TestClient(app, headers={"Authorization": f"Bearer {token}"})


@pytest.mark.parametrize(("name", "value"), _cases())
def test_rest_refuses(name: str, value: Any, client: TestClient) -> None:
    body: dict[str, Any] = {"name": "x", "voxel_size": 0.01}
    if PARAMS[name].group == "noise":
        body["noise"] = {name: value}
    else:
        body[name] = value
    text = json.dumps(body)  # NaN and Infinity as Python's json writes them
    r = client.post("/v1/scenes", content=text, headers={"content-type": "application/json"})
    assert r.status_code == 422, r.text
    assert f"{name}: " in r.json()["detail"]
    if not isinstance(value, str) and PARAMS[name].kind != "choice":
        with pytest.raises(InvalidInputError) as engine:
            _build(name, value)
        assert r.json()["detail"] == str(engine.value)  # the engine's words


def test_rest_fills_in_the_declared_defaults(client: TestClient) -> None:
    r = client.post("/v1/scenes", json={"name": "x", "voxel_size": 0.02})
    assert r.status_code == 201, r.text
    scene = r.json()
    for param in PARAMS.values():
        got = scene["noise"][param.name] if param.group == "noise" else scene[param.name]
        if param.name in ("eps", "falloff"):
            assert got == 2 * 0.02  # 2 voxels; falloff: eps
        elif not param.required:
            assert got == param.default, param.name
