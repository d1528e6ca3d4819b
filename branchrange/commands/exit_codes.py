"""Exit codes shared by `branchrange record`, `replay`, `export-frames` and `preflight`, and the `--help` epilog
of the first three."""

from __future__ import annotations

#: Every frame the source gave was handled (corrupt frames skipped and counted).
DONE = 0
#: Stopped on an error after it started (camera lost, disk full, video not writable); what was written is usable.
STOPPED_ON_ERROR = 1
#: Bad input, nothing done: an option out of range, a missing, deleted, truncated or unreadable
#: recording, a source that cannot be opened, or a source none of whose frames could be read.
BAD_INPUT = 2
#: `branchrange preflight`: it ran, and at least one check failed (not ready to arm).
CHECK_FAILED = 3

EPILOG = f"""exit codes (the same for record, replay and export-frames):
  {DONE}  done: every frame was handled (corrupt frames skipped and counted)
  {STOPPED_ON_ERROR}  stopped on an error after it started (camera lost, disk full, video not
     writable); what was written is usable
  {BAD_INPUT}  bad input, nothing usable written: an option out of range, a missing,
     deleted or truncated recording, a source that cannot be opened or none
     of whose frames could be read"""
