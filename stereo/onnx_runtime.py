"""onnxruntime, imported with its telemetry off: every module of this project that runs ONNX models gets it here.

onnxruntime on Linux (measured with 1.31.1) starts Microsoft's 1DS telemetry as the library loads: a
plain `import onnxruntime` writes a device id and an event database under
`~/.cache/Microsoft/DeveloperTools/.onnxruntime/` and queues events for upload. A drone's companion
computer must write nothing under the user's home and send nothing. `onnxruntime.disable_telemetry_events()`
comes too late (the files exist once the import returns); the runtime's own switch, the
`ORT_DISABLE_TELEMETRY` environment variable that its telemetry reads when the library loads, is set
before the first import. It is set, not defaulted: nothing in this project wants the telemetry on.
"""

from __future__ import annotations

import os
from types import ModuleType

#: The environment switch onnxruntime's 1DS telemetry reads when the library loads.
TELEMETRY_SWITCH = "ORT_DISABLE_TELEMETRY"


def import_onnxruntime() -> ModuleType:
    """The onnxruntime module with its telemetry off (see the module docstring); ImportError when not installed."""
    os.environ[TELEMETRY_SWITCH] = "1"
    import onnxruntime

    module: ModuleType = onnxruntime  # (untyped package)
    module.disable_telemetry_events()  # the events of sessions, should the library have been loaded already
    return module
