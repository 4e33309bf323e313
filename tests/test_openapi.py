"""The committed OpenAPI spec (openapi/openapi.json) is exactly what the app serves."""

from __future__ import annotations

import json

from service.openapi import SPEC_PATH, current_spec, render


def test_committed_spec_matches_the_app() -> None:
    spec = current_spec()
    committed = SPEC_PATH.read_text()
    assert committed == render(spec), "the API changed: run `python -m service.openapi` and commit openapi/openapi.json"
    paths = json.loads(committed)["paths"]
    assert "/v1/scenes/{scene_id}/render" in paths and "post" in paths["/v1/scenes/{scene_id}/render"]
    upload = paths["/v1/scenes"]["post"]
    assert "multipart/form-data" in upload["requestBody"]["content"]
    assert {"202", "413", "415", "422"} <= set(upload["responses"])
    assert spec["components"]["securitySchemes"]["HTTPBearer"]["scheme"] == "bearer"
    # the routes limited per API key list their 429, with Retry-After and the RateLimit fields
    fields = {"Retry-After", "RateLimit-Limit", "RateLimit-Remaining", "RateLimit-Reset"}
    for path in ("/v1/scenes", "/v1/scenes/{scene_id}/render", "/v1/scenes/{scene_id}/depth"):
        too_many = paths[path]["post"]["responses"]["429"]
        assert too_many["content"]["application/json"]["schema"] == {"$ref": "#/components/schemas/ErrorBody"}
        assert set(too_many["headers"]) == fields, path
    assert "429" not in paths["/v1/scenes/{scene_id}"]["get"]["responses"]  # status polls are not limited


def test_error_codes_are_one_enum_listed_in_the_spec() -> None:
    """Every code a client sees is an ErrorCode, spelled once, and the spec lists them all, for API
    errors and failed jobs alike; the worker maps exceptions to codes through one table."""
    from cmc.errors import CameraError, PoseEstimationError, SceneError
    from service.errors import ErrorCode
    from worker.pipeline import failure_code

    schemas = current_spec()["components"]["schemas"]
    listed = set(schemas["ErrorCode"]["enum"])
    assert listed == {c.value for c in ErrorCode}
    for model in ("ErrorDetail", "JobError"):
        assert schemas[model]["properties"]["code"]["$ref"] == "#/components/schemas/ErrorCode"
    assert {"invalid_images", "invalid_cameras"} <= listed  # one spelling: not invalid_image / invalid_camera
    assert not {"invalid_image", "invalid_camera"} & listed
    assert failure_code(PoseEstimationError("x")) == ErrorCode.pose_estimation_failed
    assert failure_code(CameraError("x")) == ErrorCode.invalid_cameras
    assert failure_code(SceneError("x")) == ErrorCode.invalid_images
    assert failure_code(FloatingPointError("x")) == ErrorCode.training_failed
    assert failure_code(KeyError("x")) is None  # a bug: internal_error, logged
