"""Weights download against a loopback HTTP server: verified, refused, or dropped mid-way."""

from __future__ import annotations

import hashlib
import http.server
import threading
from pathlib import Path

import pytest

from stereo.cli import main
from stereo.weights import REGISTRY, WeightsError, WeightsInfo, fetch_weights

PAYLOAD = bytes(range(256)) * 4096  # 1 MiB


class _Handler(http.server.BaseHTTPRequestHandler):
    def do_GET(self) -> None:  # noqa: N802 (http.server's naming)
        body = PAYLOAD
        self.send_response(200)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        if self.path == "/drop":
            self.wfile.write(body[: len(body) // 3])
            self.wfile.flush()
            self.connection.shutdown(2)
            return
        self.wfile.write(body)

    def log_message(self, *args) -> None:
        pass


@pytest.fixture()
def server():
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _Handler)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{httpd.server_address[1]}"
    httpd.shutdown()
    httpd.server_close()


def info_for(payload: bytes, *, sha: str | None = None) -> WeightsInfo:
    return WeightsInfo(
        name="test",
        filename="test.pth",
        sha256=sha or hashlib.sha256(payload).hexdigest(),
        layout="ours",
        url="http://127.0.0.1:9/unused",
        size_bytes=len(payload),
    )


def test_download_with_right_checksum_lands_verified(server, tmp_path):
    seen = []
    path = fetch_weights(info_for(PAYLOAD), tmp_path, url=f"{server}/w", progress=lambda n, t: seen.append((n, t)))
    assert path == tmp_path / "test.pth" and path.read_bytes() == PAYLOAD
    assert seen[-1] == (len(PAYLOAD), len(PAYLOAD))
    assert [p.name for p in tmp_path.iterdir()] == ["test.pth"]


def test_wrong_checksum_leaves_nothing_behind(server, tmp_path):
    with pytest.raises(WeightsError, match="does not match"):
        fetch_weights(info_for(PAYLOAD, sha="0" * 64), tmp_path, url=f"{server}/w")
    assert list(tmp_path.iterdir()) == []


def test_connection_dropped_midway_leaves_nothing_behind(server, tmp_path):
    with pytest.raises(WeightsError, match="bytes"):
        fetch_weights(info_for(PAYLOAD), tmp_path, url=f"{server}/drop")
    assert list(tmp_path.iterdir()) == []


def test_unreachable_server_is_a_clear_error(tmp_path):
    with pytest.raises(WeightsError, match="download failed"):
        fetch_weights(info_for(PAYLOAD), tmp_path, url="http://127.0.0.1:9/none", timeout_s=2)


def test_cli_fetch_refuses_file_that_is_not_the_release(server, tmp_path, capsys):
    code = main(
        ["weights", "fetch", "emcstereo-virtualtree", "--url", f"{server}/w", "--dest", str(tmp_path), "--quiet"]
    )
    assert code == 1
    assert "expected 61866765" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_registry_describes_the_authors_release():
    info = REGISTRY["emcstereo-virtualtree"]
    assert info.sha256 == "bc2e591d9138ab09af2023fbf313c1b54bac0dcd955fe2264fd6290a93d68747"
    assert info.layout == "authors" and info.metrics["virtualtree/test"]["epe"] == pytest.approx(1.30774)


def test_cli_verify_names_a_registered_file(tmp_path, capsys):
    path = Path(tmp_path / "x.pth")
    path.write_bytes(b"not weights")
    assert main(["weights", "verify", str(path)]) == 1
    assert "matches no registered weights" in capsys.readouterr().err
