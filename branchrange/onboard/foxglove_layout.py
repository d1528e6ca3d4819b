"""The Foxglove layout of `deploy/foxglove_layout.json`: every topic of branchrange.onboard.foxglove_sink in one view.

Left column: the overlay image (with the 3D cut points projected through /branchrange/camera_info)
above the colourised disparity. Right column: the 3D scene (cut-point spheres, branch axes, labels,
the target pose; display frame `camera`, switch to `local_ned` when the vehicle pose is known),
then the per-stage timing plot beside the raw result. The file uses Foxglove's layout export format
(`configById` + the mosaic `layout` tree), which `Layouts → Import from file…` reads.
Regenerate after changing topics: `python -m branchrange.onboard.foxglove_layout deploy/foxglove_layout.json`.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

from branchrange.onboard.foxglove_sink import CAMERA_FRAME, TOPICS

#: Stages plotted in the timing panel (the `timing_ms` keys of branchrange/v1).
PLOTTED_STAGES = ("rectify", "stereo", "masks", "cutpoints", "tracking", "total")


def _image_panel(topic: str, title: str, *, with_scene: bool) -> dict[str, Any]:
    """An Image panel showing `topic`, calibrated by the camera info so 3D entities project onto it."""
    config: dict[str, Any] = {
        "foxglovePanelTitle": title,
        "imageMode": {"imageTopic": topic, "calibrationTopic": TOPICS["camera_info"]},
    }
    if with_scene:
        config["topics"] = {TOPICS["cut_points"]: {"visible": True}, TOPICS["target"]: {"visible": True}}
    return config


def layout() -> dict[str, Any]:
    """The layout as Foxglove exports it (a JSON-ready dict)."""
    config_by_id = {
        "Image!overlay": _image_panel(TOPICS["overlay"], "Left view: masks, cut points, target", with_scene=True),
        "Image!disparity": _image_panel(TOPICS["disparity"], "Disparity (turbo, near = red)", with_scene=False),
        "3D!cutpoints": {
            "foxglovePanelTitle": "Cut points (camera frame; local_ned with vehicle pose)",
            "followTf": CAMERA_FRAME,
            "followMode": "follow-pose",
            "topics": {
                TOPICS["cut_points"]: {"visible": True},
                TOPICS["target"]: {"visible": True, "type": "axis", "axisScale": 0.2},
            },
            "cameraState": {
                "perspective": True,
                "distance": 3.0,
                "phi": 60.0,
                "thetaOffset": 180.0,
                "target": [0, 0, 0],
                "targetOffset": [0, 0, 1.0],
                "targetOrientation": [0, 0, 0, 1],
                "fovy": 45,
                "near": 0.01,
                "far": 100,
            },
        },
        "Plot!timing": {
            "foxglovePanelTitle": "Per-stage timing (ms)",
            "paths": [
                {
                    "value": f"{TOPICS['timing']}.{stage}",
                    "enabled": True,
                    "timestampMethod": "receiveTime",
                    "label": stage,
                }
                for stage in PLOTTED_STAGES
            ],
            "showLegend": True,
            "legendDisplay": "floating",
            "xAxisVal": "timestamp",
            "isSynced": True,
        },
        "RawMessages!result": {
            "foxglovePanelTitle": "branchrange/v1 result",
            "topicPath": TOPICS["result"],
            "expansion": "all",
        },
    }
    mosaic = {
        "direction": "row",
        "splitPercentage": 50,
        "first": {"direction": "column", "first": "Image!overlay", "second": "Image!disparity", "splitPercentage": 55},
        "second": {
            "direction": "column",
            "first": "3D!cutpoints",
            "splitPercentage": 55,
            "second": {
                "direction": "row",
                "first": "Plot!timing",
                "second": "RawMessages!result",
                "splitPercentage": 55,
            },
        },
    }
    return {
        "configById": config_by_id,
        "globalVariables": {},
        "userNodes": {},
        "playbackConfig": {"speed": 1},
        "layout": mosaic,
    }


def layout_text() -> str:
    """The layout file's text: indented JSON, one trailing newline."""
    return json.dumps(layout(), indent=2) + "\n"


def main(argv: list[str] | None = None) -> int:
    """Write the layout to the path given (default deploy/foxglove_layout.json)."""
    args = sys.argv[1:] if argv is None else argv
    out = Path(args[0] if args else "deploy/foxglove_layout.json")
    out.write_text(layout_text(), encoding="utf-8")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
