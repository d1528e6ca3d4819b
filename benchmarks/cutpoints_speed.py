"""Cut-point geometry per frame: the cropped geometry against the per-frame code it replaced, same run.

Cases (truth disparity and instance mask of `stereo.synth.render_scene(7)` at
`SynthCamera.zed_mini(1280, 720)`, which holds 10 branches, a trunk, twigs and leaves):
- `hd720_3`, `hd720_5`, `hd720_10`: the branches with ids 1..k kept (the others become
  background), trunk, twigs and leaves as rendered;
- `canvas_1440p_10`: the 10-branch frame pasted into a 2560×1440 frame that is empty (disparity 0,
  label 0) elsewhere — what a full-resolution disparity holding only regions of interest costs;
- `ids_65000`: a 640×512 mask with 65,000 instance ids (5-pixel runs), disparity 20 px: refused
  by `cutpoints.max_instances` (time to the `MaskError`), and with the cap lifted (the cost of
  estimating every instance). The baseline has no cap; it runs the first 1 % of the ids in the same
  640×512 frame and its time is scaled ×100 (each of its instances costs O(frame), so the scaling
  is linear; marked "extrapolated").

The baseline is the package at `--baseline` (a git revision, default 930314a: before the crops),
exported with `git archive` into a temporary folder and run in a subprocess with that folder first
on `PYTHONPATH`; the current tree runs in an identical subprocess. Baseline and current alternate,
`--repeats` timed runs each after one warm-up, and the table shows wall-clock medians and minima
(ms per frame) with the process's CPU time (median), the speed-up (median over median, of the wall
clock and of the CPU time: on a loaded machine the CPU time is the steadier) and the largest
cut-point difference (m)
between the two on the same frame. Prints the CPU (model, AVX2 / AVX-512, cores; `machine.py`) and the
load average: the machine may be shared, so read the same-run ratios, not the absolute times.

    .venv/bin/python benchmarks/cutpoints_speed.py --repeats 7 --json cutpoints_speed.json
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from machine import cpu_description, cpu_name  # a script's own folder is on its import path

ROOT = Path(__file__).resolve().parents[1]
CASES = ("hd720_3", "hd720_5", "hd720_10", "canvas_1440p_10", "ids_65000", "ids_65000_capped")
#: The share of the 65,000 ids the baseline runs (its time is scaled by the inverse).
BASELINE_ID_SHARE = 0.01


def write_frames(folder: Path) -> None:
    """Render the scene once and write every case's (disparity, labels, geometry) as .npz files."""
    import numpy as np

    from stereo.synth import SynthCamera, is_branch_id, render_scene

    camera = SynthCamera.zed_mini(1280, 720)
    scene = render_scene(7, camera, supersample=1)
    geometry = [camera.focal_px, camera.baseline_m, camera.cx, camera.cy]
    labels, disparity = scene.instance_mask.astype(np.int32), scene.disparity.astype(np.float32)
    for k in (3, 5, 10):
        kept = np.where(is_branch_id(labels) & (labels > k), 0, labels)
        np.savez(folder / f"hd720_{k}.npz", labels=kept, disparity=disparity, geometry=geometry)
    canvas_labels = np.zeros((1440, 2560), np.int32)
    canvas_disparity = np.zeros((1440, 2560), np.float32)
    top, left = 300, 700
    canvas_labels[top : top + 720, left : left + 1280] = labels
    canvas_disparity[top : top + 720, left : left + 1280] = disparity
    np.savez(
        folder / "canvas_1440p_10.npz",
        labels=canvas_labels,
        disparity=canvas_disparity,
        geometry=[camera.focal_px, camera.baseline_m, camera.cx + left, camera.cy + top],
    )
    many = np.minimum(np.arange(512 * 640) // 5 + 1, 65000).reshape(512, 640).astype(np.int32)
    flat = np.full((512, 640), 20.0, np.float32)
    np.savez(folder / "ids_65000.npz", labels=many, disparity=flat, geometry=[320.0, 0.063, 319.5, 255.5])
    share = np.where(many <= int(65000 * BASELINE_ID_SHARE), many, 0)
    np.savez(folder / "ids_65000_share.npz", labels=share, disparity=flat, geometry=[320.0, 0.063, 319.5, 255.5])


def time_cases(folder: Path, repeats: int, baseline: bool) -> dict:
    """Worker: time `estimate_cut_points` on every case (ms per frame) and keep the cut points."""
    import numpy as np

    from branchrange.core.cutpoints import CutPointConfig, estimate_cut_points
    from branchrange.core.geometry import StereoGeometry
    from branchrange.core.masks import masks_from_array

    out: dict = {}
    for case in CASES:
        if baseline and case == "ids_65000_capped":
            continue  # the baseline has no cap
        source = ("ids_65000_share" if baseline else "ids_65000") if case.startswith("ids_65000") else case
        with np.load(folder / f"{source}.npz") as stored:
            frame = dict(stored)
        geometry = StereoGeometry(*[float(v) for v in frame["geometry"]])
        config = CutPointConfig() if case == "ids_65000_capped" or baseline else CutPointConfig(max_instances=70000)
        times, cpu_times, result, error = [], [], None, None
        slow = case == "ids_65000" or (baseline and case.startswith("ids_65000"))
        for run in range(2 if slow else repeats + 1):  # the slow cases once after a warm-up
            start, cpu_start = time.perf_counter(), time.process_time()
            try:  # masks are read inside the timed span: indexing them is part of the cost
                masks = masks_from_array(frame["labels"], kind="instance")
                result = estimate_cut_points(masks, frame["disparity"], geometry, config)
            except ValueError as exc:
                error = f"{type(exc).__name__}: {exc}"
            if run:
                times.append((time.perf_counter() - start) * 1000.0)
                cpu_times.append((time.process_time() - cpu_start) * 1000.0)
        points = {} if result is None else {b.mask_id: b.cut_point_m.tolist() for b in result.branches}
        out[case] = {
            "ms": times,
            "cpu_ms": cpu_times,
            "cut_points": points,
            "error": error,
            "branches": len(masks_from_array(frame["labels"], kind="instance").branch_ids()),
        }
    return out


def run_worker(folder: Path, repeats: int, pythonpath: str, baseline: bool) -> dict:
    """Run `time_cases` in a fresh interpreter with `pythonpath` first on the path."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([pythonpath, str(ROOT)])}
    command = [sys.executable, str(Path(__file__).resolve()), "--worker", str(folder), "--repeats", str(repeats)]
    if baseline:
        command.append("--as-baseline")
    done = subprocess.run(command, env=env, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise SystemExit(f"benchmark worker failed:\n{done.stderr}")
    return json.loads(done.stdout)


def export_baseline(revision: str, folder: Path) -> None:
    """The `branchrange` package at `revision`, exported into `folder`."""
    archive = subprocess.run(
        ["git", "-C", str(ROOT), "archive", revision, "branchrange"], capture_output=True, check=False
    )
    if archive.returncode != 0:
        raise SystemExit(f"cannot export branchrange at {revision!r}: {archive.stderr.decode().strip()}")
    subprocess.run(["tar", "-x", "-C", str(folder)], input=archive.stdout, check=True)


def summarise(current: list[dict], baseline: list[dict]) -> dict:
    """Per case: median/min ms of both, the speed-up and the largest cut-point difference (m)."""
    rows = {}
    for case in CASES:
        new = [t for run in current for t in run[case]["ms"]]
        new_cpu = [t for run in current for t in run[case]["cpu_ms"]]
        row = {
            "branches": current[0][case]["branches"],
            "new_ms": {"median": statistics.median(new), "min": min(new)},
            "new_cpu_ms": statistics.median(new_cpu),
            "new_error": current[0][case]["error"],
        }
        if case in baseline[0]:
            scale = 1.0 / BASELINE_ID_SHARE if case.startswith("ids_65000") else 1.0
            old = [t * scale for run in baseline for t in run[case]["ms"]]
            old_cpu = [t * scale for run in baseline for t in run[case]["cpu_ms"]]
            row["old_ms"] = {"median": statistics.median(old), "min": min(old)}
            row["old_cpu_ms"] = statistics.median(old_cpu)
            row["old_extrapolated"] = scale != 1.0
            row["speedup"] = row["old_ms"]["median"] / row["new_ms"]["median"]
            row["speedup_cpu"] = row["old_cpu_ms"] / row["new_cpu_ms"]
            a, b = current[0][case]["cut_points"], baseline[0][case]["cut_points"]
            if not case.startswith("ids_65000"):
                row["same_branches"] = sorted(a) == sorted(b)
                row["max_cut_point_diff_m"] = max(
                    (max(abs(x - y) for x, y in zip(a[k], b[k])) for k in a if k in b), default=0.0
                )
        rows[case] = row
    return rows


def print_table(rows: dict, cpu: dict, baseline: str) -> None:
    """The table: one line per case."""
    print(f"CPU: {cpu_name()}; load average {cpu['load_average_1min']} at the start")
    print(f"baseline: branchrange at {baseline}; ms per frame: wall clock median (min) | CPU median\n")
    print(f"{'case':<17}{'branches':>9}{'baseline ms':>34}{'current ms':>28}{'speed-up':>14}{'max Δ cut m':>13}  note")
    for case, row in rows.items():
        old = (
            f"{row['old_ms']['median']:.1f} ({row['old_ms']['min']:.1f}) | {row['old_cpu_ms']:.1f}"
            + ("*" if row.get("old_extrapolated") else "")
            if "old_ms" in row
            else "—"
        )
        new = f"{row['new_ms']['median']:.1f} ({row['new_ms']['min']:.1f}) | {row['new_cpu_ms']:.1f}"
        speedup = f"{row['speedup']:.1f}× | {row['speedup_cpu']:.1f}×" if "speedup" in row else "—"
        diff = f"{row['max_cut_point_diff_m']:.1e}" if "max_cut_point_diff_m" in row else "—"
        note = row["new_error"][:100] if row["new_error"] else ("cap lifted" if case == "ids_65000" else "")
        print(f"{case:<17}{row['branches']:>9}{old:>34}{new:>28}{speedup:>14}{diff:>13}  {note}")
    print(
        f"\n* extrapolated: the baseline ran {BASELINE_ID_SHARE:.0%} of the ids in the same frame, time ×"
        f"{1 / BASELINE_ID_SHARE:.0f}"
    )


def main(argv: list[str] | None = None) -> int:
    """Parse options; either be a worker or run the whole comparison."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5, help="timed runs per case and round (after one warm-up)")
    parser.add_argument("--rounds", type=int, default=2, help="baseline/current alternations")
    parser.add_argument("--baseline", default="930314a", help="git revision of the per-frame geometry")
    parser.add_argument("--json", type=Path, help="write the results here")
    parser.add_argument("--worker", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--as-baseline", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.repeats < 1 or args.rounds < 1:
        parser.error(f"--repeats and --rounds must be ≥ 1, got {args.repeats} and {args.rounds}")
    if args.worker is not None:
        print(json.dumps(time_cases(args.worker, args.repeats, args.as_baseline)))
        return 0
    cpu = cpu_description()
    with tempfile.TemporaryDirectory() as tmp:
        frames, old_tree = Path(tmp) / "frames", Path(tmp) / "baseline"
        frames.mkdir()
        old_tree.mkdir()
        sys.path.insert(0, str(ROOT))
        write_frames(frames)
        export_baseline(args.baseline, old_tree)
        baseline, current = [], []
        for _ in range(args.rounds):
            baseline.append(run_worker(frames, args.repeats, str(old_tree), baseline=True))
            current.append(run_worker(frames, args.repeats, str(ROOT), baseline=False))
    rows = summarise(current, baseline)
    print_table(rows, cpu, args.baseline)
    if args.json is not None:
        args.json.write_text(
            json.dumps(
                {"cpu": cpu, "baseline": args.baseline, "repeats": args.repeats, "rounds": args.rounds, "cases": rows},
                indent=2,
            ),
            encoding="utf-8",
        )
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
