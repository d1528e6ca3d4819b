"""The service over real HTTP (uvicorn on 127.0.0.1, ephemeral port): auth, health, metrics, latest, serve."""

from __future__ import annotations

import json
import socket
import threading
import time

import httpx
import pytest
import uvicorn
from api_scene import BASELINE_M, FOCAL_PX, bar_scene
from openapi_check import check_response

from api import create_app
from api.estimator import PipelineEstimator
from branchrange.cli import main as branchrange_main
from branchrange.config.sections import ApiConfig
from branchrange.core.frame_results import result_line
from branchrange.core.pipeline import Pipeline, PipelineConfig, StereoConfig

TOKEN = "s3cret-token"
UPLOAD_LIMIT_MB = 1.0


class LiveState:
    """A daemon's view as the API sees it: the newest result and the camera/link state."""

    def __init__(self):
        self.result = None
        self.camera_lost = False

    def latest_result(self):
        return self.result

    def health(self):
        return {
            "camera": {"lost": self.camera_lost, "source": "replay:test"},
            "mavlink": {"connected": True, "url": "udpout:127.0.0.1:14550"},
        }


@pytest.fixture(scope="module")
def live():
    return LiveState()


@pytest.fixture(scope="module")
def server(live):
    """A real uvicorn server in a thread; yields its base URL."""
    app = create_app(ApiConfig(token=TOKEN, max_upload_mb=UPLOAD_LIMIT_MB), PipelineEstimator(), state=live)
    srv = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=0, log_level="warning"))
    thread = threading.Thread(target=srv.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 10
    while not srv.started and time.monotonic() < deadline:
        time.sleep(0.02)
    assert srv.started, "uvicorn did not start within 10 s"
    port = srv.servers[0].sockets[0].getsockname()[1]
    yield f"http://127.0.0.1:{port}"
    srv.should_exit = True
    thread.join(timeout=5)


def auth(token=TOKEN):
    return {"Authorization": f"Bearer {token}"}


def test_requests_without_the_right_token_get_401(server):
    scene = bar_scene()
    files = {"left": ("l.png", scene.png("left")), "right": ("r.png", scene.png("right"))}
    # bars, not a tree: the weight-free structure segmenter finds them, the learned one looks for trees
    data = {"focal_px": str(FOCAL_PX), "baseline_m": str(BASELINE_M), "max_disp": "64", "segmenter": "structure"}
    with httpx.Client(base_url=server, timeout=20) as c:
        assert c.post("/estimate", files=files, data=data).status_code == 401
        r = c.post("/estimate", files=files, data=data, headers=auth("wrong"))
        assert r.status_code == 401 and r.headers["www-authenticate"] == "Bearer"
        assert c.get("/metrics").status_code == 401 and c.get("/latest").status_code == 401
        r = c.post("/estimate", files=files, data=data, headers=auth())
    assert r.status_code == 200 and r.json()["branches"], r.text


def test_health_reports_model_camera_and_link_and_degrades_when_camera_lost(server, live):
    with httpx.Client(base_url=server, timeout=10) as c:
        ok = c.get("/health").json()
        live.camera_lost = True
        lost = c.get("/health").json()
        live.camera_lost = False
        version = c.get("/version").json()
    assert ok["status"] == "ok" and ok["model"]["backend"] == "sgbm" and ok["mavlink"]["connected"] is True
    assert lost["status"] == "degraded" and lost["camera"]["lost"] is True
    assert version["schema"] == "branchrange/v1" and version["name"] == "branchrange"


def test_latest_returns_the_daemons_newest_result_unchanged(server, live):
    scene = bar_scene()
    pipeline = Pipeline(
        PipelineConfig(stereo=StereoConfig(mode="full", max_disp=64)), focal_px=FOCAL_PX, baseline_m=BASELINE_M
    )
    result = pipeline.process(scene.left, scene.right, scene.mask, index=7, timestamp_ns=5)
    with httpx.Client(base_url=server, timeout=10, headers=auth()) as c:
        assert c.get("/latest").status_code == 404
        live.result = result
        r = c.get("/latest")
    assert r.status_code == 200 and r.json()["frame"]["index"] == 7 and r.json()["branches"]
    assert r.json() == json.loads(result_line(result))  # the daemon's log line, key for key (no nulls added)


def test_metrics_count_requests_latencies_frames_and_errors(server):
    scene = bar_scene()
    with httpx.Client(base_url=server, timeout=20, headers=auth()) as c:
        c.post(
            "/estimate",
            files={"left": ("l.png", scene.png("left")), "right": ("r.png", scene.png("right"))},
            data={"focal_px": str(FOCAL_PX), "baseline_m": str(BASELINE_M), "max_disp": "64"},
        )
        c.post(
            "/estimate",
            files={"left": ("l.png", b"nope"), "right": ("r.png", b"nope")},
            data={"focal_px": "1", "baseline_m": "1"},
        )
        text = c.get("/metrics").text
    values = {
        line.rsplit(" ", 1)[0]: float(line.rsplit(" ", 1)[1]) for line in text.splitlines() if not line.startswith("#")
    }
    ok = values['branchrange_http_requests_total{route="/estimate",method="POST",status="200"}']
    assert values['branchrange_http_requests_total{route="/estimate",method="POST",status="415"}'] == 1
    assert ok >= 1 and values["branchrange_frames_total"] == ok  # every successful estimate is one frame
    assert values['branchrange_frame_duration_seconds_count{source="api"}'] == ok
    assert values['branchrange_http_request_duration_seconds_count{route="/estimate"}'] >= ok + 1
    assert values['branchrange_http_request_duration_seconds_bucket{route="/estimate",le="+Inf"}'] >= ok + 1


def test_declared_oversized_body_gets_413_before_the_server_reads_it(server):
    host, port = server.removeprefix("http://").split(":")
    with socket.create_connection((host, int(port)), timeout=5) as sock:
        # headers only: a server that waited for the 50 MB body would time out here
        sock.sendall(
            b"POST /estimate HTTP/1.1\r\nHost: x\r\nContent-Type: multipart/form-data; boundary=b\r\n"
            b"Content-Length: 50000000\r\n\r\n"
        )
        answer = b""
        while chunk := sock.recv(4096):  # the server closes the connection after its answer
            answer += chunk
    answer = answer.decode("latin-1")
    assert answer.startswith("HTTP/1.1 413") and "exceeds the limit of 1048576 bytes (api.max_upload_mb)" in answer


def test_streamed_body_without_length_is_cut_off_at_the_limit(server):
    def chunks():  # a 2 MiB file part in 64 KiB pieces, chunked transfer encoding (no Content-Length)
        yield b'--b\r\nContent-Disposition: form-data; name="left"; filename="l.png"\r\nContent-Type: image/png\r\n\r\n'
        for _ in range(32):
            yield b"x" * 65536

    with httpx.Client(base_url=server, timeout=20, headers=auth()) as c:
        r = c.post("/estimate", content=chunks(), headers={"Content-Type": "multipart/form-data; boundary=b"})
    # counted as it streamed in: the limit names no declared size
    assert r.status_code == 413 and r.json()["detail"].startswith("request body of more than 1048576 bytes exceeds")


def test_serve_refuses_a_public_address_without_a_token(capsys, monkeypatch):
    monkeypatch.delenv("BRANCHRANGE_API_TOKEN", raising=False)
    assert branchrange_main(["serve", "--host", "0.0.0.0", "--port", "0"]) == 2
    assert "refusing to serve on 0.0.0.0 without a token" in capsys.readouterr().err


def test_serve_fails_at_start_when_the_stereo_backend_cannot_be_built(tmp_path, capsys):
    config = tmp_path / "serve.toml"
    config.write_text(f'[stereo]\nbackend = "emcstereo"\nweights = "{tmp_path / "missing.pth"}"\n')
    assert branchrange_main(["serve", "--config", str(config), "--port", "0"]) == 2
    assert f"stereo.weights = '{tmp_path / 'missing.pth'}': no such file" in capsys.readouterr().err


def test_every_route_answers_as_the_served_openapi_document_says(server, live):
    """Issue 15 item 8: success and error answers of every route validated against /openapi.json."""
    scene = bar_scene()
    pair = {"left": ("l.png", scene.png("left"), "image/png"), "right": ("r.png", scene.png("right"), "image/png")}
    fb = {"focal_px": str(FOCAL_PX), "baseline_m": str(BASELINE_M), "max_disp": "64"}
    pipeline = Pipeline(
        PipelineConfig(stereo=StereoConfig(mode="full", max_disp=64)), focal_px=FOCAL_PX, baseline_m=BASELINE_M
    )
    live.result = None  # before the daemon's first frame: /latest is 404
    calls = [  # (method, path, keyword arguments of httpx, expected status)
        ("GET", "/health", {}, 200),
        ("GET", "/version", {}, 200),
        ("GET", "/metrics", {"headers": auth()}, 200),
        ("GET", "/metrics", {}, 401),
        ("GET", "/latest", {}, 401),
        ("GET", "/latest", {"headers": auth()}, 404),
        ("POST", "/estimate", {"files": pair, "data": fb, "headers": auth()}, 200),
        ("POST", "/estimate", {"files": pair, "data": fb}, 401),
        ("POST", "/estimate", {"files": pair, "data": {**fb, "max_disp": "abc"}, "headers": auth()}, 422),
        ("POST", "/estimate", {"files": {"left": pair["left"]}, "data": fb, "headers": auth()}, 422),
        ("POST", "/estimate", {"files": pair, "data": {**fb, "baseline_m": "1e300"}, "headers": auth()}, 422),
        (
            "POST",
            "/estimate",
            {"files": {**pair, "left": ("l.png", b"GIF89a", "image/gif")}, "data": fb, "headers": auth()},
            415,
        ),
        (
            "POST",
            "/estimate",
            {"content": b"x" * 2_000_000, "headers": {**auth(), "Content-Type": "multipart/form-data; boundary=b"}},
            413,
        ),
        (
            "POST",
            "/estimate",
            {"content": b"--nope", "headers": {**auth(), "Content-Type": "multipart/form-data"}},
            400,
        ),
        ("POST", "/disparity", {"files": pair, "data": fb, "headers": auth()}, 200),
        ("POST", "/disparity", {"files": pair, "data": {**fb, "format": "npy"}, "headers": auth()}, 200),
        ("POST", "/disparity", {"files": pair, "data": {**fb, "format": "tiff"}, "headers": auth()}, 422),
    ]
    with httpx.Client(base_url=server, timeout=30) as c:
        spec = c.get("/openapi.json").json()
        for method, path, kwargs, expected in calls:
            r = c.request(method, path, **kwargs)
            assert r.status_code == expected, (method, path, expected, r.text[:300])
            check_response(spec, method, path, r)
            if r.status_code >= 400:
                assert isinstance(r.json()["detail"], str) and r.json()["detail"], r.text  # one ErrorBody shape
        live.result = pipeline.process(scene.left, scene.right, scene.mask, index=3, timestamp_ns=1)
        try:
            check_response(spec, "GET", "/latest", c.get("/latest", headers=auth()))
        finally:
            live.result = None
        assert c.get("/health").status_code == 200
    assert "HTTPValidationError" not in spec["components"]["schemas"]  # FastAPI's list shape is never sent
