"""`run_preflight`: the ground test before arming (`branchrange preflight`), each check with its fix.

The checks, in order: the camera (opens, frames at the configured rate) and its calibration
(`camera_checks`), the models and the pipeline's latency on the camera's frames (`pipeline_checks`),
then the MAVLink link: heartbeat, autopilot type, signing and the autopilot's parameters
(`autopilot_checks`, tables in `autopilot_parameters`). A check that needs what an earlier one failed
to give is skipped, not failed again: each failure is reported once, with its own fix.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from branchrange.onboard.preflight.autopilot_checks import check_autopilot
from branchrange.onboard.preflight.camera_checks import check_camera
from branchrange.onboard.preflight.pipeline_checks import LATENCY, check_latency, check_models
from branchrange.onboard.preflight.report import PASS, CheckResult, PreflightReport

if TYPE_CHECKING:
    from branchrange.config.loader import Config

__all__ = ["CheckResult", "PreflightReport", "run_preflight"]


def run_preflight(cfg: Config, camera_serial: str | None = None) -> PreflightReport:
    """Every check for the configuration `cfg`; `camera_serial`: the serial on the camera's label, if given."""
    camera_results, sample = check_camera(cfg.camera, camera_serial)
    models_result, models = check_models(cfg)
    if sample is None or models is None or camera_results[1].status != PASS:
        latency = CheckResult.skipped(LATENCY, "needs the camera's frames, its calibration and the models")
    else:
        latency = check_latency(cfg, sample, models)
    return PreflightReport((*camera_results, models_result, latency, *check_autopilot(cfg.mavlink)))
