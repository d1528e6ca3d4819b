"""Running ONNX models writes nothing under the user's home (issue 39: onnxruntime's telemetry database).

Each case runs in a fresh interpreter (the telemetry starts when the library loads, once per process)
with HOME and XDG_CACHE_HOME pointed into a temporary folder, then lists what appeared there. The
control case, a plain `import onnxruntime`, shows that the check sees the files when they are written.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("onnxruntime", reason="onnxruntime (a dependency of branchrange) is not installed")

#: The learned segmenter's shipped model in a session through `onnx_session`, one inference on a small input,
#: and the onnx stereo backend refusing a missing file (it imports onnxruntime before it opens the file).
OUR_SESSIONS = """
import numpy as np
from branchrange.core.segmentation.learned import SHIPPED_MODELS
from branchrange.core.segmentation.onnx_model import onnx_session
from stereo.backends.base import BackendConfigError
from stereo.backends.onnx import OnnxBackend

session = onnx_session(SHIPPED_MODELS["int8"], threads=1)
session.run(None, {session.get_inputs()[0].name: np.zeros((1, 5, 32, 32), np.float32)})
try:
    OnnxBackend("missing.onnx")
except BackendConfigError:
    pass
"""


#: Environment variables under which onnxruntime writes no telemetry files by itself.
QUIETING_VARIABLES = ("ORT_DISABLE_TELEMETRY", "CI", "GITHUB_ACTIONS", "TF_BUILD")


def _files_written_under_home(tmp_path: Path, code: str) -> list[str]:
    """Files that running `code` in a fresh interpreter leaves under its (temporary) home folder."""
    home = tmp_path / "home"
    home.mkdir()
    # onnxruntime also stays quiet on a CI machine (CI, GITHUB_ACTIONS, TF_BUILD): take those out too, so that
    # both cases run as on a user's computer, where the files would be written
    env = {k: v for k, v in os.environ.items() if k not in QUIETING_VARIABLES}
    env.update(HOME=str(home), XDG_CACHE_HOME=str(home / ".cache"))
    subprocess.run([sys.executable, "-c", code], env=env, cwd=tmp_path, check=True, timeout=120)
    return sorted(str(p.relative_to(home)) for p in home.rglob("*") if p.is_file())


def test_our_onnx_sessions_write_nothing_under_home(tmp_path):
    assert _files_written_under_home(tmp_path, OUR_SESSIONS) == []


def test_a_plain_import_of_onnxruntime_does_write_there_so_the_check_can_see_it(tmp_path):
    written = _files_written_under_home(tmp_path, "import onnxruntime")
    assert any("onnxruntime" in path for path in written), written
