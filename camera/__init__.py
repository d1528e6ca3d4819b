"""camera/: calibration formats, rectification and stereo frame sources (a leaf: numpy, OpenCV, depthai).

Main names: `StereoCalibration` and its loaders (`from_zed_conf`, `from_opencv_file`,
`from_depthai_json`, `from_kitti`, `from_rectified`, `load_calibration`), `write_opencv_file`,
`Rectifier`, `CalibrationError`/`FrameSizeError`; frame sources live in `camera.sources`.
"""

from __future__ import annotations

from camera.calibration import CalibrationError, FrameSizeError, StereoCalibration, from_rectified
from camera.depthai_json import from_depthai_json
from camera.kitti import from_kitti
from camera.load import detect_format, load_calibration
from camera.opencv_file import from_opencv_file, write_opencv_file
from camera.rectify import Rectifier
from camera.sources import StereoFrame, open_source
from camera.zed_conf import from_zed_conf

__all__ = [
    "CalibrationError",
    "FrameSizeError",
    "Rectifier",
    "StereoCalibration",
    "StereoFrame",
    "detect_format",
    "from_depthai_json",
    "from_kitti",
    "from_opencv_file",
    "from_rectified",
    "from_zed_conf",
    "load_calibration",
    "open_source",
    "write_opencv_file",
]
