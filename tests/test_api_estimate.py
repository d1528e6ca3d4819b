"""POST /estimate and /disparity through the test client: real pipeline (SGBM) on an exact scene."""

from __future__ import annotations

import asyncio
import io
import json

import cv2
import jsonschema
import numpy as np
import pytest
from api_scene import BAR_DEPTH_M, BAR_DISPARITY, BASELINE_M, FOCAL_PX, bar_scene
from fastapi.testclient import TestClient

from api import create_app
from api.estimator import PipelineEstimator
from branchrange.config.sections import ApiConfig
from branchrange.core.frame_result import SCHEMA_PATH

FB = {"focal_px": str(FOCAL_PX), "baseline_m": str(BASELINE_M), "max_disp": "64"}
RESULT_SCHEMA = json.loads(SCHEMA_PATH.read_text())


@pytest.fixture(scope="module")
def scene():
    return bar_scene()


@pytest.fixture(scope="module")
def estimator():
    return PipelineEstimator()


@pytest.fixture
def client(estimator):
    with TestClient(create_app(ApiConfig(max_pixels=400 * 300, max_upload_mb=1.0), estimator)) as c:
        yield c


def pair_files(scene, mask=True):
    files = {"left": ("l.png", scene.png("left"), "image/png"), "right": ("r.png", scene.png("right"), "image/png")}
    if mask:
        files["mask"] = ("m.png", scene.png("mask"), "image/png")
    return files


def test_estimate_returns_the_bar_cut_point_in_metres(client, scene):
    r = client.post("/estimate", files=pair_files(scene), data=FB)
    assert r.status_code == 200, r.text
    body = r.json()
    jsonschema.validate(body, RESULT_SCHEMA)  # no nulls for keys the pipeline left out
    assert body["schema"] == "branchrange/v1" and body["frame"]["width"] == 320
    (branch,) = body["branches"]
    assert body["target_id"] == branch["id"]
    x, y, z = branch["cut_point_m"]
    assert z == pytest.approx(BAR_DEPTH_M, abs=0.06) and abs(y) < 0.01  # bar centre row is the image centre
    assert branch["distance_m"] == pytest.approx(np.linalg.norm([x, y, z]), abs=1e-3)
    assert branch["diameter_m"] == pytest.approx(21 * BAR_DEPTH_M / FOCAL_PX, abs=0.012)  # 21 px tall bar
    assert abs(branch["axis"][0]) > 0.99  # horizontal bar


def test_estimate_accepts_jpeg_and_no_mask(client, scene):
    def jpg(im):
        return cv2.imencode(".jpg", cv2.cvtColor(im, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()

    files = {"left": ("l.jpg", jpg(scene.left), "image/jpeg"), "right": ("r.jpg", jpg(scene.right), "image/jpeg")}
    r = client.post("/estimate", files=files, data=FB)
    assert r.status_code == 200, r.text
    assert r.json()["masks"]["source"] != "array"  # the segmenter ran


def test_estimate_with_a_calibration_file(client, scene, tmp_path):
    k = (
        "!!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
        f"   data: [{FOCAL_PX}, 0., 159.5, 0., {FOCAL_PX}, 127.5, 0., 0., 1.]"
    )
    yaml = (
        "%YAML:1.0\n---\n"
        f"K1: {k}\n"
        "D1: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n   data: [0., 0., 0., 0., 0.]\n"
        f"K2: {k}\n"
        "D2: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n   data: [0., 0., 0., 0., 0.]\n"
        "R: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [1., 0., 0., 0., 1., 0., 0., 0., 1.]\n"
        f"T: !!opencv-matrix\n   rows: 3\n   cols: 1\n   dt: d\n   data: [{-BASELINE_M}, 0., 0.]\n"
    )
    files = {**pair_files(scene), "calibration": ("rig.yml", yaml.encode(), "application/x-yaml")}
    r = client.post("/estimate", files=files, data={"max_disp": "64"})
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["camera"]["baseline_m"] == pytest.approx(BASELINE_M, rel=1e-3)
    assert body["branches"][0]["cut_point_m"][2] == pytest.approx(BAR_DEPTH_M, abs=0.08)


def test_disparity_as_kitti_png_and_npy(client, scene):
    r = client.post("/disparity", files=pair_files(scene, mask=False), data=FB)
    assert r.status_code == 200 and r.headers["content-type"] == "image/png"
    raw = cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16 and raw.shape == (256, 320)
    assert np.median(raw[scene.mask > 0]) / 256.0 == pytest.approx(BAR_DISPARITY, abs=0.5)
    r = client.post("/disparity", files=pair_files(scene, mask=False), data={**FB, "format": "npy"})
    disp = np.load(io.BytesIO(r.content))
    assert disp.dtype == np.float32 and np.median(disp[scene.mask > 0]) == pytest.approx(BAR_DISPARITY, abs=0.5)


PNG_1x1 = cv2.imencode(".png", np.zeros((1, 1, 3), np.uint8))[1].tobytes()


@pytest.mark.parametrize(
    "change, code, message",
    [
        (
            lambda f, d: f.update(left=("l.png", b"not an image at all", "image/png")),
            415,
            "left: expected a PNG or JPEG",
        ),
        (
            lambda f, d: f.update(right=("r.png", f["right"][1][:200], "image/png")),
            422,
            "right: the image could not be decoded",
        ),
        (lambda f, d: f.pop("right"), 422, "right"),
        (lambda f, d: (d.pop("focal_px"), d.pop("baseline_m")), 422, "missing camera"),
        (lambda f, d: d.update(focal_px="-3"), 422, "focal_px"),
        (lambda f, d: d.update(backend="raft"), 422, "backend"),
        (
            lambda f, d: f.update(
                mask=("m.png", cv2.imencode(".png", np.zeros((10, 10), np.uint8))[1].tobytes(), "image/png")
            ),
            422,
            "mask",
        ),
        (
            lambda f, d: (
                f.update(calibration=("x.conf", b"hello", "text/plain")),
                d.pop("focal_px"),
                d.pop("baseline_m"),
            ),
            422,
            "calibration: x.conf",
        ),
        (lambda f, d: f.update(calibration=("x.conf", b"hello", "text/plain")), 422, "not both"),
        (
            lambda f, d: f.update(
                left=("big.png", cv2.imencode(".png", np.zeros((400, 400, 3), np.uint8))[1].tobytes(), "image/png")
            ),
            413,
            "pixels exceeds the limit",
        ),
        (
            lambda f, d: f.update(left=("l.png", f["left"][1][:100], "image/png")),
            422,
            "left: the image could not be decoded",
        ),
        (
            lambda f, d: f.update(left=("l.png", PNG_1x1, "image/png"), right=("r.png", PNG_1x1, "image/png")),
            422,
            "left image",
        ),
        (
            lambda f, d: f.update(
                mask=("m.png", cv2.imencode(".png", np.zeros((100, 120), np.uint8))[1].tobytes(), "image/png")
            ),
            422,
            "mask is 120×100 px but the images are 320×256 px",
        ),
        (
            lambda f, d: (
                f.update(calibration=("rig.xml", b"<?xml version='1.0'?><opencv_storage><K1>", "text/xml")),
                d.pop("focal_px"),
                d.pop("baseline_m"),
            ),
            422,
            "calibration: rig.xml: <file>: is not a valid FileStorage file",
        ),
        (lambda f, d: d.update(focal_px="inf"), 422, "focal_px"),
        (lambda f, d: d.update(baseline_m="nan"), 422, "baseline_m"),
        (lambda f, d: d.update(backend="emcstereo"), 422, "backend 'emcstereo' has no weights on this server"),
        (lambda f, d: d.update(max_disp="1000"), 422, "max_disp"),
    ],
)
def test_bad_requests_get_4xx_with_a_message(client, scene, change, code, message):
    files, data = pair_files(scene), dict(FB)
    change(files, data)
    r = client.post("/estimate", files=files, data=data)
    assert r.status_code == code, r.text
    assert message in r.text


def test_mismatched_sizes_are_refused(client, scene):
    small = cv2.imencode(".png", scene.right[:200, :300])[1].tobytes()
    files = {**pair_files(scene), "right": ("r.png", small, "image/png")}
    r = client.post("/estimate", files=files, data=FB)
    assert r.status_code == 422 and "320×256" in r.json()["detail"] and "300×200" in r.json()["detail"]


def test_oversized_body_is_refused_before_parsing(client, scene):
    files = {**pair_files(scene), "mask": ("m.png", b"\0" * (1024 * 1024 + 10), "image/png")}
    r = client.post("/estimate", files=files, data=FB)
    assert r.status_code == 413 and "api.max_upload_mb" in r.json()["detail"]


def test_saturated_service_answers_503_with_retry_after(client, scene):
    slots = client.app.state.slots
    taken = asyncio.run(slots._semaphore.acquire())  # the one slot is busy with another inference
    try:
        r = client.post("/estimate", files=pair_files(scene), data=FB)
    finally:
        slots._semaphore.release()
    assert taken and r.status_code == 503 and r.headers["retry-after"] == "1"
    assert client.post("/estimate", files=pair_files(scene), data=FB).status_code == 200


def _resolve(spec: dict, schema: dict) -> dict:
    """An OpenAPI schema with its `$ref` (or `anyOf: [$ref, null]`) followed."""
    for option in schema.get("anyOf", [schema]):
        if "$ref" in option:
            return spec["components"]["schemas"][option["$ref"].rsplit("/", 1)[1]]
    return schema


def _missing_properties(spec: dict, openapi: dict, json_schema: dict, where: str) -> list[str]:
    """Property paths of the branchrange/v1 JSON schema that the OpenAPI model lacks, recursively."""
    if "$ref" in json_schema:
        json_schema = RESULT_SCHEMA["$defs"][json_schema["$ref"].rsplit("/", 1)[1]]
    if json_schema.get("type") == "array" and "items" in json_schema:
        openapi = _resolve(spec, openapi)
        items = next(o for o in openapi.get("anyOf", [openapi]) if o.get("type") == "array")["items"]
        return _missing_properties(spec, _resolve(spec, items), json_schema["items"], where + "[]")
    missing = []
    openapi = _resolve(spec, openapi)
    for name, sub in json_schema.get("properties", {}).items():
        if name not in openapi.get("properties", {}):
            missing.append(f"{where}.{name}")
        else:
            missing += _missing_properties(spec, openapi["properties"][name], sub, f"{where}.{name}")
    return missing


def test_openapi_documents_every_route_the_result_schema_and_the_bearer_scheme(client):
    spec = client.get("/openapi.json").json()
    schemas = spec["components"]["schemas"]
    assert {"/estimate", "/disparity", "/health", "/version", "/metrics", "/latest"} <= set(spec["paths"])
    assert all(op.get("summary") and op.get("description") for ops in spec["paths"].values() for op in ops.values())
    # the result model carries every key of branchrange/v1, with units
    assert _missing_properties(spec, schemas["EstimateResult"], RESULT_SCHEMA, "result") == []
    assert set(schemas["EstimateResult"]["required"]) == set(RESULT_SCHEMA["required"]) - {"schema"}
    assert "metres" in schemas["Branch"]["properties"]["cut_point_m"]["description"]
    assert spec["paths"]["/latest"]["get"]["responses"]["200"]["content"]["application/json"]["schema"][
        "$ref"
    ].endswith("/EstimateResult")
    # both POST routes describe their shared fields alike, and name the errors they answer with
    forms = [
        _resolve(spec, spec["paths"][p]["post"]["requestBody"]["content"]["multipart/form-data"]["schema"])
        for p in ("/estimate", "/disparity")
    ]
    for field in ("left", "right", "calibration", "resolution", "focal_px", "baseline_m", "backend", "max_disp"):
        assert forms[0]["properties"][field].get("description"), field
        assert forms[0]["properties"][field] == forms[1]["properties"][field], field
    assert {"413", "415", "422", "503"} <= set(spec["paths"]["/estimate"]["post"]["responses"])
    # bearer auth is declared where the token is checked, and only there
    assert spec["components"]["securitySchemes"]["HTTPBearer"] == {
        "type": "http",
        "scheme": "bearer",
        "description": spec["components"]["securitySchemes"]["HTTPBearer"]["description"],
    }
    secured = {path for path, ops in spec["paths"].items() for op in ops.values() if op.get("security")}
    assert secured == {"/estimate", "/disparity", "/metrics", "/latest"}
