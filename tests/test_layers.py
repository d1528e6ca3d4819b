"""The layers of the code base: no module imports from a layer above its own.

    command line   branchrange/cli.py, branchrange/commands/   (may import everything below)
    ─────────────────────────────────────────────────────────────────────────────────────────
    api/           onboard runtime            offline tools       (siblings: none imports another)
                   branchrange/onboard/       branchrange/offline/
    ─────────────────────────────────────────────────────────────────────────────────────────
    core           branchrange/core/: geometry, masks, segmentation, cut points, tracking,
                   FrameResult, pipeline, config
    ─────────────────────────────────────────────────────────────────────────────────────────
    leaves         stereo/, camera/   (know nothing of each other or of the application)

Every import is read from the source with `ast` (function-level and TYPE_CHECKING imports included),
so a lazy import cannot hide a dependency on a higher layer.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: Layer of each package prefix (the longest matching prefix wins) → the layers it may import.
LAYER_OF = {
    "stereo": "stereo",
    "camera": "camera",
    "branchrange": "package",
    "branchrange.core": "core",
    "branchrange.onboard": "onboard",
    "branchrange.offline": "offline",
    "api": "api",
    "branchrange.cli": "cli",
    "branchrange.commands": "cli",
}
MAY_IMPORT = {
    "stereo": {"stereo"},
    "camera": {"camera"},
    "package": set(),  # branchrange/__init__.py: a docstring, nothing that ties the layers together
    "core": {"stereo", "camera", "core"},
    "onboard": {"stereo", "camera", "core", "onboard"},
    "offline": {"stereo", "camera", "core", "offline"},
    "api": {"stereo", "camera", "core", "api"},
    "cli": {"stereo", "camera", "core", "onboard", "offline", "api", "cli"},
}
PACKAGES = ("stereo", "camera", "branchrange", "api")


def layer(dotted: str) -> str | None:
    """The layer of a module or imported name (`a.b.c`), None outside the project's packages."""
    parts = dotted.split(".")
    for n in range(len(parts), 0, -1):
        found = LAYER_OF.get(".".join(parts[:n]))
        if found is not None:
            return found
    return None


def module_name(path: Path) -> str:
    """`branchrange/core/config.py` → `branchrange.core.config`; a package's `__init__.py` → the package."""
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported_names(source: str, module: str, is_package: bool) -> list[tuple[int, str]]:
    """(line, dotted name) of everything `source` imports; `from a.b import c` gives `a.b.c`, relative
    imports are resolved against `module` (a package's own name when `is_package`)."""
    names = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = module.split(".")[: len(module.split(".")) - node.level + (1 if is_package else 0)]
                base = ".".join([*anchor, base] if base else anchor)
            names += [(node.lineno, f"{base}.{alias.name}") for alias in node.names]
    return names


def violations(path: Path, source: str) -> list[str]:
    """One line per import in `source` (the file at `path`) from a layer its own may not import."""
    module = module_name(path)
    own = layer(module)
    assert own is not None, f"{module} is in no layer: add its package to LAYER_OF"
    found = []
    for line, name in imported_names(source, module, path.name == "__init__.py"):
        target = layer(name)
        if target is not None and target not in MAY_IMPORT[own]:
            found.append(f"{path.relative_to(ROOT)}:{line}: {module} ({own}) imports {name} ({target})")
    return found


def project_modules() -> list[Path]:
    return sorted(p for package in PACKAGES for p in (ROOT / package).rglob("*.py"))


def test_no_module_imports_from_a_higher_layer():
    found = [v for path in project_modules() for v in violations(path, path.read_text(encoding="utf-8"))]
    assert found == [], "imports from a higher layer:\n" + "\n".join(found)


def test_every_branchrange_module_sits_in_a_named_layer():
    loose = [module_name(p) for p in (ROOT / "branchrange").glob("*.py") if p.name not in ("__init__.py", "cli.py")]
    assert loose == [], f"modules directly in branchrange/ belong in core/, onboard/ or offline/: {loose}"


@pytest.mark.parametrize(
    ("path", "source", "offending"),
    [
        (
            "branchrange/core/geometry.py",
            "from branchrange.onboard.daemon import Daemon\n",
            "branchrange.onboard.daemon.Daemon (onboard)",
        ),
        ("branchrange/core/masks.py", "def f():\n    from api.metrics import Metrics\n", "api.metrics.Metrics (api)"),
        (
            "branchrange/onboard/daemon.py",
            "import branchrange.offline.replay\n",
            "branchrange.offline.replay (offline)",
        ),
        (
            "branchrange/offline/replay.py",
            "from ..onboard import foxglove_sink\n",
            "branchrange.onboard.foxglove_sink (onboard)",
        ),
        (
            "api/app.py",
            "from branchrange.commands.serve import check_bind\n",
            "branchrange.commands.serve.check_bind (cli)",
        ),
        (
            "stereo/metrics.py",
            "from camera.calibration import Calibration\n",
            "camera.calibration.Calibration (camera)",
        ),
        ("branchrange/core/segmentation/__init__.py", "from ...cli import main\n", "branchrange.cli.main (cli)"),
    ],
)
def test_an_import_from_a_higher_layer_is_named(path, source, offending):
    found = violations(ROOT / path, source)
    assert len(found) == 1
    assert found[0].startswith(f"{path}:") and found[0].endswith(offending), found


def test_imports_from_the_same_or_a_lower_layer_pass():
    source = (
        "from branchrange.core.config import Config\nfrom . import newest_slot\nimport numpy\n"
        "from stereo.backends.base import validate_pair\nfrom camera.sources import StereoSource\n"
    )
    assert violations(ROOT / "branchrange/onboard/daemon.py", source) == []
    assert violations(ROOT / "branchrange/commands/daemon.py", "from api.metrics import Metrics\n") == []
