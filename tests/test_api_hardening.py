"""Issue 15, items 1–4, 7, 9, 11: hostile uploads and settings against a real `branchrange serve`.

The server is the real command in a subprocess on 127.0.0.1 (an ephemeral port), so an upload that
crashed OpenCV would kill that process, not pytest: each test ends by checking that `/health`
still answers. Every error answer is also checked against the served OpenAPI document.
"""

from __future__ import annotations

import os
import re
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import pytest
from api_scene import BASELINE_M, FOCAL_PX, bar_scene
from openapi_check import check_response

from branchrange.cli import main as branchrange_main
from branchrange.config.loader import config_from_dict
from branchrange.core.settings_check import ConfigError

ROOT = Path(__file__).resolve().parents[1]
FB = {"focal_px": str(FOCAL_PX), "baseline_m": str(BASELINE_M), "max_disp": "64"}


def _serve(args: list[str], env: dict[str, str] | None = None) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "branchrange.cli", "serve", *args],
        cwd=ROOT,
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        env={**os.environ, "PYTHONPATH": str(ROOT), **(env or {})},
    )


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """`branchrange serve` on 127.0.0.1:0 in a subprocess; yields (base URL, served OpenAPI document)."""
    config = tmp_path_factory.mktemp("serve") / "serve.toml"
    config.write_text('[api]\nmax_upload_mb = 8.0\nmax_concurrency = 1\nretry_after_s = 2\n[log]\nlevel = "INFO"\n')
    proc = _serve(["--config", str(config), "--host", "127.0.0.1", "--port", "0"])
    lines: list[str] = []
    threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True).start()  # keeps the pipe drained
    deadline = time.monotonic() + 60
    url = None
    while url is None and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.05)
        url = next((m.group(1) for line in list(lines) if (m := re.search(r"running on (http://\S+)", line))), None)
    assert url, f"branchrange serve did not start: {''.join(lines)[-2000:]}"
    spec = httpx.get(f"{url}/openapi.json", timeout=10).json()
    yield url, spec
    proc.terminate()
    proc.wait(timeout=10)


def assert_alive(url: str) -> None:
    """The server process still answers (an OpenCV abort would have killed it)."""
    r = httpx.get(f"{url}/health", timeout=10)
    assert r.status_code == 200 and r.json()["status"] == "ok"


def post(server, files: dict, data: dict, path: str = "/estimate") -> httpx.Response:
    url, spec = server
    r = httpx.post(f"{url}{path}", files=files, data=data, timeout=60)
    check_response(spec, "POST", path, r)
    return r


@pytest.fixture(scope="module")
def pair():
    scene = bar_scene()
    return {"left": ("l.png", scene.png("left"), "image/png"), "right": ("r.png", scene.png("right"), "image/png")}


def opencv_yaml(
    k1: str | None = None, width: int = 320, height: int = 256, t: str = f"[{-BASELINE_M}, 0., 0.]"
) -> bytes:
    """An OpenCV FileStorage YAML stereo calibration of the bar scene; `k1` replaces K1's node body."""
    k = (
        "!!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
        f"   data: [{FOCAL_PX}, 0., 159.5, 0., {FOCAL_PX}, 127.5, 0., 0., 1.]"
    )
    d = "!!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n   data: [0., 0., 0., 0., 0.]"
    return (
        "%YAML:1.0\n---\n"
        f"K1: {k1 or k}\nD1: {d}\nK2: {k}\nD2: {d}\nR: [1., 0., 0., 0., 1., 0., 0., 0., 1.]\nT: {t}\n"
        f"image_width: {width}\nimage_height: {height}\n"
    ).encode()


# ------------------------------------------------------------------ item 1: malformed !!opencv-matrix

MATRIX = '{"type_id": "opencv-matrix", %s}'
JSON_REST = (
    '"D1": [0, 0, 0, 0, 0], "K2": [[400, 0, 159.5], [0, 400, 127.5], [0, 0, 1]], "D2": [0, 0, 0, 0, 0], '
    '"R": [1, 0, 0, 0, 1, 0, 0, 0, 1], "T": [-0.1, 0, 0], "image_width": 320, "image_height": 256'
)


@pytest.mark.parametrize(
    "name, content, message",
    [
        # this one corrupted the heap inside FileNode.mat() and aborted the whole server (SIGABRT)
        (
            "rig.json",
            (
                '{"K1": '
                + MATRIX % '"rows": 3, "dt": "2d", "data": [1, 2, 3, 4, 5, 6, 7, 8, 9]'
                + ", "
                + JSON_REST
                + "}"
            ).encode(),
            "K1: is a matrix without cols",
        ),
        (
            "rig.yml",
            opencv_yaml("!!opencv-matrix\n   rows: 3\n   dt: d\n   data: [1., 2., 3., 4., 5., 6., 7., 8., 9.]"),
            "K1: is a matrix without cols",
        ),
        (
            "rig.yml",
            opencv_yaml("!!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [1., 2., 3., 4., 5.]"),
            "K1: has rows × cols = 3×3 but 5 data values",
        ),
        (
            "rig.yml",
            opencv_yaml(
                "!!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: 3d\n   data: [1., 2., 3., 4., 5., 6., 7., 8., 9.]"
            ),
            "<file>: is not a valid FileStorage file",
        ),  # OpenCV's YAML parser refuses it itself
        (
            "rig.json",
            (
                '{"K1": '
                + MATRIX % '"rows": 3, "cols": 3, "dt": "3d", "data": [1, 2, 3, 4, 5, 6, 7, 8, 9]'
                + ", "
                + JSON_REST
                + "}"
            ).encode(),
            "K1: has dt = '3d' (multi-channel or unknown)",
        ),
        (
            "rig.yml",
            opencv_yaml("!!opencv-matrix\n   rows: 100000\n   cols: 100000\n   dt: d\n   data: [1.]"),
            "K1: has rows = 100000",
        ),
        (
            "rig.yml",
            opencv_yaml("!!opencv-matrix\n   rows: x\n   cols: 3\n   dt: d\n   data: [1., 2., 3.]"),
            "K1: has rows = 'x'",
        ),
        ("rig.yml", opencv_yaml("[" + ", ".join(["1."] * 5000) + "]"), "K1: holds more than 64 numbers"),
        (
            "rig.xml",
            b'<?xml version="1.0"?>\n<opencv_storage><K1 type_id="opencv-matrix"><rows>3</rows><cols>3</cols>'
            b"<dt>d</dt><data>1 2 3 4</data></K1></opencv_storage>\n",
            "K1: has rows × cols = 3×3 but 4 data values",
        ),
    ],
)
def test_malformed_opencv_matrices_get_422_and_the_server_lives(server, pair, name, content, message):
    r = post(server, {**pair, "calibration": (name, content, "text/plain")}, {"max_disp": "64"})
    assert r.status_code == 422 and f"calibration: {name}: {message}" in r.json()["detail"], r.text
    assert_alive(server[0])


# ------------------------------------------------------------------ item 2: image size before maps


@pytest.mark.parametrize(
    "size, message",
    [
        (
            (8000, 8000),
            "calibration: rig.yml: image size: is 8000×8000 px (expected 320×256 px, the size of the images",
        ),
        (
            (100_000, 500),
            "image_size: is (100000, 500) (expected a positive (width, height) in pixels, each at most 8192)",
        ),
    ],
)
def test_calibration_image_size_is_checked_before_maps_are_built(server, pair, size, message):
    start = time.perf_counter()
    r = post(
        server,
        {**pair, "calibration": ("rig.yml", opencv_yaml(width=size[0], height=size[1]), "text/plain")},
        {"max_disp": "64"},
    )
    assert r.status_code == 422 and message in r.json()["detail"], r.text
    # 8000×8000 maps took seconds and 2.5 GB; the check answers before any is built
    assert time.perf_counter() - start < 10
    assert_alive(server[0])


def test_image_wider_than_the_maximum_is_refused_from_its_header(server, pair):
    import cv2
    import numpy as np

    wide = cv2.imencode(".png", np.zeros((1, 9000, 3), np.uint8))[1].tobytes()
    r = post(server, {"left": ("l.png", wide, "image/png"), "right": ("r.png", wide, "image/png")}, FB)
    assert r.status_code == 422 and "left image size = 9000×1: expected each side from 1 to 8192 px" in r.text
    assert_alive(server[0])


# ------------------------------------------------------------------ item 3: the client's file name is no path


@pytest.mark.parametrize(
    "filename, shown",
    [
        ("..", "calibration"),
        ("x" * 300, "x" * 63 + "…"),
        ("rig\0.yml", "rig.yml"),
        ("../../etc/passwd", "passwd"),
    ],
)
def test_hostile_calibration_file_names_are_never_paths(server, pair, filename, shown):
    url, spec = server
    boundary = "hardening-boundary"
    parts = []
    for field, (name, data, kind) in {**pair, "calibration": (filename, opencv_yaml(), "text/plain")}.items():
        parts.append(
            f'--{boundary}\r\nContent-Disposition: form-data; name="{field}"; filename="{name}"\r\n'
            f"Content-Type: {kind}\r\n\r\n".encode()
            + data
            + b"\r\n"
        )
    parts.append(
        f'--{boundary}\r\nContent-Disposition: form-data; name="max_disp"\r\n\r\n64\r\n--{boundary}--\r\n'.encode()
    )
    headers = {"Content-Type": f"multipart/form-data; boundary={boundary}"}
    r = httpx.post(f"{url}/estimate", content=b"".join(parts), headers=headers, timeout=60)
    check_response(spec, "POST", "/estimate", r)
    assert r.status_code == 200 and r.json()["camera"]["baseline_m"] == pytest.approx(BASELINE_M, rel=1e-3), r.text
    broken = b"".join(parts).replace(b"rows: 3\n   cols: 3", b"rows: 3\n   cols: 4", 1)
    r = httpx.post(f"{url}/estimate", content=broken, headers=headers, timeout=60)
    assert r.status_code == 422 and r.json()["detail"].startswith(f"calibration: {shown}: K1: "), r.text
    assert_alive(url)


# ------------------------------------------------------------------ item 4: physical ranges, once, at each entry


@pytest.mark.parametrize(
    "field, value, accepted",
    [
        ("baseline_m", "1e300", "a baseline in metres from 0.001 to 10 m"),
        ("baseline_m", "1e-320", "a baseline in metres from 0.001 to 10 m"),
        ("focal_px", "1e9", "a focal length in pixels from 1 to 100000 px"),
        ("focal_px", "0.5", "a focal length in pixels from 1 to 100000 px"),
    ],
)
def test_absurd_focal_or_baseline_gets_422_naming_value_and_range(server, pair, field, value, accepted):
    r = post(server, pair, {**FB, field: value})
    assert r.status_code == 422 and f"{field} = {float(value)!r}: expected {accepted}" in r.json()["detail"], r.text
    assert_alive(server[0])


def test_calibration_with_an_absurd_baseline_gets_422(server, pair):
    r = post(
        server, {**pair, "calibration": ("rig.yml", opencv_yaml(t="[-1e-9, 0., 0.]"), "text/plain")}, {"max_disp": "64"}
    )
    assert r.status_code == 422 and "rig.yml: baseline |T| = 1e-09: expected a baseline in metres" in r.text, r.text
    assert_alive(server[0])


def test_cli_and_config_refuse_the_same_ranges(tmp_path, capsys):
    scene = bar_scene()
    for name in ("left", "right"):
        (tmp_path / f"{name}.png").write_bytes(scene.png(name))
    base = [
        "estimate",
        "--left",
        str(tmp_path / "left.png"),
        "--right",
        str(tmp_path / "right.png"),
        "--max-disp",
        "64",
    ]
    assert branchrange_main([*base, "--focal-px", str(FOCAL_PX), "--baseline-m", "1e300"]) == 2
    assert "--baseline-m = 1e+300: expected a baseline in metres from 0.001 to 10 m" in capsys.readouterr().err
    assert branchrange_main([*base, "--focal-px", "1e9", "--baseline-m", "0.1"]) == 2
    assert "--focal-px = 1000000000.0: expected a focal length in pixels" in capsys.readouterr().err
    crash = tmp_path / "rig.json"  # the upload that aborted the server made the CLI exit 134 (SIGABRT) too
    crash.write_text(
        '{"K1": ' + MATRIX % '"rows": 3, "dt": "2d", "data": [1, 2, 3, 4, 5, 6, 7, 8, 9]' + ", " + JSON_REST + "}"
    )
    assert branchrange_main([*base, "--calib", str(crash)]) == 2
    assert "rig.json: K1: is a matrix without cols (expected an !!opencv-matrix" in capsys.readouterr().err
    with pytest.raises(
        ConfigError, match=r"mavlink\.max_distance_m = 1e\+300: expected a distance in metres from 0 to 655 m"
    ):
        config_from_dict({"mavlink": {"max_distance_m": 1e300}})
    with pytest.raises(ConfigError, match=r"cutpoints\.cut_offset_m = 1e\+300: expected an offset"):
        config_from_dict({"cutpoints": {"cut_offset_m": 1e300}})


# ------------------------------------------------------------------ item 7: 503 before the body is read


def test_busy_service_answers_503_before_reading_the_body(server):
    url, spec = server
    big = bar_scene(1280, 720)
    files = {"left": ("l.png", big.png("left"), "image/png"), "right": ("r.png", big.png("right"), "image/png")}
    answers: list[httpx.Response] = []
    slow = threading.Thread(
        target=lambda: answers.append(
            httpx.post(f"{url}/estimate", files=files, data={**FB, "max_disp": "256"}, timeout=120)
        )
    )
    slow.start()
    deadline = time.monotonic() + 60
    while httpx.get(f"{url}/health", timeout=10).json()["model"]["inference_in_use"] == 0:
        assert time.monotonic() < deadline and slow.is_alive(), "the first request never held the inference slot"
        time.sleep(0.005)
    host, port = url.removeprefix("http://").split(":")
    with socket.create_connection((host, int(port)), timeout=10) as sock:
        # headers only: a server that read (or waited for) the 5 MB body before refusing would time out here
        sock.sendall(
            b"POST /estimate HTTP/1.1\r\nHost: x\r\nContent-Type: multipart/form-data; boundary=b\r\n"
            b"Content-Length: 5000000\r\n\r\n"
        )
        answer = b""
        while chunk := sock.recv(4096):
            answer += chunk
    head = answer.decode("latin-1")
    slow.join(timeout=120)
    assert head.startswith("HTTP/1.1 503") and "retry-after: 2" in head.lower(), head
    assert '"detail":"all 1 inference slots are busy; retry in 2 s"' in head
    lines, body = head.split("\r\n\r\n", 1)
    headers = [tuple(line.split(": ", 1)) for line in lines.split("\r\n")[1:]]
    check_response(spec, "POST", "/estimate", httpx.Response(503, headers=headers, content=body.encode()))
    assert answers and answers[0].status_code == 200, answers
    assert_alive(url)


# ------------------------------------------------------------------ item 9: a whitespace token is no token


@pytest.mark.parametrize("env, config", [({"BRANCHRANGE_API_TOKEN": "   "}, ""), ({}, '[api]\ntoken = " \\t "\n')])
def test_whitespace_token_does_not_let_serve_bind_a_public_address(tmp_path, env, config):
    path = tmp_path / "serve.toml"
    path.write_text(config)
    proc = _serve(["--config", str(path), "--host", "0.0.0.0", "--port", "0"], env={"BRANCHRANGE_API_TOKEN": "", **env})
    try:
        output, _ = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 2, output
    assert "api.token is whitespace only (or BRANCHRANGE_API_TOKEN)" in output and "Uvicorn running" not in output


def test_a_token_with_stray_spaces_is_refused_without_echoing_it():
    # the bearer check strips what the client sends, so " s3cret" could never match: refused at load
    with pytest.raises(ConfigError, match="api.token has leading or trailing whitespace") as error:
        config_from_dict({"api": {"token": " s3cret"}})
    assert "s3cret" not in str(error.value)


# ------------------------------------------------------------------ item 11: /docs offline


@pytest.mark.parametrize("page", ["/docs", "/redoc"])
def test_docs_pages_load_every_asset_from_this_server(server, page):
    url, _ = server
    with httpx.Client(base_url=url, timeout=10) as client:
        html = client.get(page)
        assert html.status_code == 200 and html.headers["content-type"].startswith("text/html")
        assert "http://" not in html.text and "https://" not in html.text and "//cdn" not in html.text
        refs = re.findall(r"""(?:src|href|spec-url)=["']([^"']+)["']|url: ?'([^']+)'""", html.text)
        urls = {a or b for a, b in refs}
        assert {"/openapi.json"} < urls and len(urls) >= 3, urls  # the document, a script, the icon (+ css)
        for ref in urls:
            assert ref.startswith("/"), f"{page} loads {ref} from elsewhere"
            asset = client.get(ref)
            assert asset.status_code == 200 and len(asset.content) > 100, ref
        scripts = [u for u in urls if u.endswith(".js")]
        assert scripts and all(len(client.get(u).content) > 500_000 for u in scripts)  # the real bundles
    assert_alive(url)
