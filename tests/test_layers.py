"""The layers of the code base: no module imports from a layer above its own, and no import cycle anywhere.

    command line   branchrange/cli.py, branchrange/commands/   (may import everything below)
    ─────────────────────────────────────────────────────────────────────────────────────────
    api/           onboard runtime            offline tools          (siblings: none imports another;
                   branchrange/onboard/       branchrange/offline/    offline may use learning's formats)
                                              learning workshop
                                              branchrange/learning/
    ─────────────────────────────────────────────────────────────────────────────────────────
    config         branchrange/config/: the file's sections gathered, loaded, checked, documented
    ─────────────────────────────────────────────────────────────────────────────────────────
    core           branchrange/core/: what runs on every frame — geometry, masks, segmenters as they run,
                   cut points, tracking, FrameResult, pipeline (each module owns its settings section)
    ─────────────────────────────────────────────────────────────────────────────────────────
    leaves         stereo/, camera/   (know nothing of each other or of the application)

Every import is read from the source with `ast` (function-level and TYPE_CHECKING imports included),
so a lazy import cannot hide a dependency on a higher layer, nor a cycle.
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
    "branchrange.config": "config",
    "branchrange.learning": "learning",
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
    "config": {"stereo", "camera", "core", "config"},
    "learning": {"stereo", "camera", "core", "config", "learning"},
    "onboard": {"stereo", "camera", "core", "config", "onboard"},
    "offline": {"stereo", "camera", "core", "config", "learning", "offline"},
    "api": {"stereo", "camera", "core", "config", "api"},
    "cli": {"stereo", "camera", "core", "config", "learning", "onboard", "offline", "api", "cli"},
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
    """`branchrange/core/masks.py` → `branchrange.core.masks`; a package's `__init__.py` → the package."""
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
        "from branchrange.config.loader import Config\nfrom . import newest_slot\nimport numpy\n"
        "from stereo.backends.base import validate_pair\nfrom camera.sources import StereoSource\n"
    )
    assert violations(ROOT / "branchrange/onboard/daemon.py", source) == []
    assert violations(ROOT / "branchrange/commands/daemon.py", "from api.metrics import Metrics\n") == []


def imported_modules(source: str, module: str, is_package: bool, known: set[str]) -> set[str]:
    """The project modules among `known` that `source` imports: `from a.b import c` is the module `a.b.c` when
    there is one (a submodule), else `a.b`."""
    found = set()
    for _, name in imported_names(source, module, is_package):
        while name and name not in known:
            name = name.rpartition(".")[0]
        if name and name != module:
            found.add(name)
    return found


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module of `graph` (module → modules it imports),
    each sorted: every such component is an import cycle (Tarjan's algorithm, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles = []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph.get(child, ())))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    cycles.append(sorted(component))
    return cycles


def project_graph() -> dict[str, set[str]]:
    """module → the project modules it imports, over `PACKAGES`."""
    paths = {module_name(p): p for p in project_modules()}
    known = set(paths)
    return {
        module: imported_modules(path.read_text(encoding="utf-8"), module, path.name == "__init__.py", known)
        for module, path in paths.items()
    }


def test_no_import_cycle_in_the_project():
    cycles = import_cycles(project_graph())
    assert cycles == [], "import cycles:\n" + "\n".join(" ↔ ".join(c) for c in cycles)


def test_a_cycle_through_a_lazy_import_is_found():
    known = {"pkg.a", "pkg.b", "pkg.c", "pkg.d"}
    sources = {
        "pkg.a": "from pkg.b import thing\n",
        "pkg.b": "def f():\n    from pkg import c\n",
        "pkg.c": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from .a import Other\n",
        "pkg.d": "import pkg.a\n",
    }
    graph = {m: imported_modules(src, m, False, known) for m, src in sources.items()}
    assert graph["pkg.b"] == {"pkg.c"} and graph["pkg.c"] == {"pkg.a"}
    assert import_cycles(graph) == [["pkg.a", "pkg.b", "pkg.c"]]
    del graph["pkg.c"]
    assert import_cycles(graph) == []


def test_the_per_frame_core_never_imports_the_workshop_or_the_layers_above():
    above = ("branchrange.learning", "branchrange.config", "branchrange.onboard", "branchrange.offline")
    found = [
        f"{module} imports {target}"
        for module, targets in project_graph().items()
        if module.startswith("branchrange.core")
        for target in targets
        if target.startswith((*above, "api", "branchrange.commands", "branchrange.cli"))
    ]
    assert found == []


def test_the_shipped_cpu_loop_runs_a_frame_without_torch(tmp_path):
    """The onboard loop as `deploy/onboard_cpu.toml` ships it (SGBM, the ONNX segmenter on onnxruntime) and the
    daemon never import torch: each stereo worker process starts in less time and memory on a small companion
    computer. The network's PyTorch side (`branchrange.learning.branchnet`) is for training and export only."""
    import subprocess
    import sys

    script = """
import sys
import numpy as np
from branchrange.config.loader import load_config, pipeline_for
import branchrange.onboard.daemon
from camera.calibration import from_rectified
cfg = load_config("deploy/onboard_cpu.toml")
pipeline = pipeline_for(cfg, from_rectified(700.0, 640.0, 360.0, 0.063, (1280, 720)))
rng = np.random.default_rng(0)
left = rng.integers(0, 255, (720, 1280, 3), dtype=np.uint8)
pipeline.process(left, np.roll(left, -8, axis=1))
print("torch" in sys.modules)
"""
    done = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "False", "the per-frame path imported torch"
