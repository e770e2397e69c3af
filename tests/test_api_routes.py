"""The API's layout: one router per resource, a response model on every JSON route, and the
OpenAPI at /docs describes them (the answers themselves: tests/test_service.py)."""

from __future__ import annotations

from pathlib import Path

import pytest
from fastapi.routing import APIRoute
from rangefuse.service.api.models import JobOut, SceneDetail, SceneOut
from rangefuse.service.api.routes import ROUTERS
from rangefuse.service.app import create_app
from rangefuse.service.settings import Settings


@pytest.fixture(scope="module")
def app(tmp_path_factory: pytest.TempPathFactory):
    return create_app(Settings(data_dir=Path(tmp_path_factory.mktemp("store"))))


def test_every_json_route_has_a_response_model() -> None:
    routes = [
        r for router in ROUTERS for r in router.routes
        if isinstance(r, APIRoute) and r.include_in_schema
    ]  # fmt: skip
    assert len(routes) == 18
    binary = {
        "/metrics",
        "/v1/scenes/{scene_id}/mesh",
        "/v1/scenes/{scene_id}/slice",
        "/v1/scenes/{scene_id}/preview",
    }
    for route in routes:
        if route.path in binary or route.status_code == 204:
            continue
        assert route.response_model is not None, (route.path, route.methods)


def test_openapi_shows_the_models(app) -> None:
    spec = app.openapi()

    def answer(path: str, method: str, status: str) -> dict:
        content = spec["paths"][path][method]["responses"][status]["content"]
        return content["application/json"]["schema"]

    assert answer("/v1/scenes", "post", "201") == {"$ref": "#/components/schemas/SceneOut"}
    assert answer("/v1/scenes", "get", "200")["items"] == {"$ref": "#/components/schemas/SceneOut"}
    assert answer("/v1/scenes/{scene_id}", "get", "200")["$ref"].endswith("/SceneDetail")
    assert answer("/v1/scenes/{scene_id}/scans", "post", "202")["$ref"].endswith("/Upload")
    assert answer("/v1/scenes/{scene_id}/scans", "get", "200")["items"]["$ref"].endswith("/ScanOut")
    assert answer("/v1/scenes/{scene_id}/reconstructions", "post", "202")["$ref"].endswith(
        "/Accepted"
    )
    assert answer("/v1/jobs/{job_id}", "get", "200")["$ref"].endswith("/JobOut")
    assert answer("/v1/jobs/{job_id}", "get", "404")["$ref"].endswith("/Problem")
    assert answer("/healthz", "get", "200")["$ref"].endswith("/Health")
    # every error is {"detail": "..."} (the handlers' shape), never FastAPI's default list
    assert "HTTPValidationError" not in spec["components"]["schemas"]
    upload = spec["paths"]["/v1/scenes/{scene_id}/scans"]["post"]["requestBody"]
    assert set(upload["content"]["multipart/form-data"]["schema"]["required"]) == {
        "range",
        "meta",
    }
    tags = {op["tags"][0] for ops in spec["paths"].values() for op in ops.values()}
    assert tags == {"scenes", "scans", "reconstructions", "slices", "jobs", "service", "viewer"}


def test_response_models_keep_the_answers_fields() -> None:
    """The JSON the service answered before the models existed (tests/test_service.py)."""
    assert list(SceneOut.model_fields) == [
        "id", "name", "voxel_size", "tile_size", "mode", "bounds", "noise", "filter",
        "max_discontinuity", "no_return", "sensor", "created_at",
    ]  # fmt: skip
    assert list(SceneDetail.model_fields)[-2:] == ["scans", "tiles"]
    job = JobOut(id="j", kind="integrate", scene_id="s", state="queued", progress=0.0,
                 created_at=1.0)  # fmt: skip
    assert job.model_dump(exclude_unset=True) == {
        "id": "j", "kind": "integrate", "scene_id": "s", "state": "queued", "progress": 0.0,
        "created_at": 1.0,
    }  # fmt: skip


@pytest.mark.parametrize(("eps_per_m", "falloff", "expected"), [
    (0.0, None, 0.04), (0.01, None, None), (0.01, 0.03, 0.03),
])  # fmt: skip
def test_a_scene_reports_the_falloff_it_uses(eps_per_m, falloff, expected) -> None:
    """Without a fall-off of its own, the fall-off is eps + eps_per_m * r: eps only when the
    half-width does not grow with range."""
    from rangefuse.engine import FusionParams, GridSpec, NoiseModel
    from rangefuse.storage.catalog import SceneRow

    noise = NoiseModel(eps=0.04, eps_per_m=eps_per_m, rho=0.05, falloff=falloff)
    row = SceneRow("s", "s", "t", GridSpec(0.02).to_dict(), FusionParams(noise).to_dict(), 1.0)
    assert SceneOut.from_row(row).noise.falloff == expected
