"""Synthetic flight sequences: per-frame truth vs the renderer, the approach, flight.json, the recording,
the command."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from branchrange.core.frame_results import read_results
from branchrange.offline.flight import FLIGHT_NAME, FlightCutPoint, FlightFormatError, FlightPose, FlightTruth
from camera.sources import ReplaySource
from stereo.cli import build_parser
from stereo.synth import LEAF_ID, SynthOptions, render_scene
from stereo.synth.camera import SynthCamera
from stereo.synth.flight import FlightRenderer
from stereo.synth.flight_path import YAW_BOUND_DEG, ApproachPath, FlightOptions
from stereo.synth.motion_blur import blur_along_motion, image_motion
from stereo.synth.render import auto_gain, develop, render_views
from stereo.synth.viewpoint import scene_in_camera

#: A small, fast flight with every disturbance on (sway, jitter, exposure wobble, motion blur).
WOBBLY = [
    "--frames",
    "6",
    "--resolution",
    "320x180",
    "--sway-m",
    "0.05",
    "--sway-hz",
    "1.5",
    "--jitter-deg",
    "1.5",
    "--exposure",
    "0.2",
    "--motion-blur",
    "--seed",
    "4",
]
WOBBLY_OPTIONS = FlightOptions(
    frames=6, width=320, height=180, sway_m=0.05, sway_hz=1.5, jitter_deg=1.5, exposure=0.2, motion_blur=True, seed=4
)


def _run(argv: list[str]) -> int:
    """Run `branchrange ARGV` with only the synth-flight subcommand registered."""
    args = build_parser("branchrange", "test", ["branchrange.commands.synth_flight"]).parse_args(argv)
    return args.func(args)


@pytest.fixture(scope="module")
def wobbly_renderer() -> FlightRenderer:
    return FlightRenderer(WOBBLY_OPTIONS)


@pytest.fixture(scope="module")
def wobbly_frames(wobbly_renderer: FlightRenderer) -> list:
    return list(wobbly_renderer)


@pytest.fixture(scope="module")
def wobbly_recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The same flight written by the command."""
    out = tmp_path_factory.mktemp("flight") / "rec"
    assert _run(["synth-flight", "--out", str(out), *WOBBLY]) == 0
    return out


def _project(points_cam: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Pixels `(N, 2)` of camera-frame points `(N, 3)` through intrinsics `k` (3×3)."""
    uvw = points_cam @ k.T
    return uvw[:, :2] / uvw[:, 2:]


def test_truth_pixel_is_the_renderers_cut_pixel_and_lies_on_its_branch(wobbly_recording: Path, wobbly_frames: list):
    truth = FlightTruth.load(wobbly_recording)
    k = ReplaySource(wobbly_recording, pace="fast").calibration.K1
    assert len(truth.poses) == len(wobbly_frames) == 6
    checked = 0
    for position, frame in enumerate(wobbly_frames):
        in_camera = truth.cut_points_in_camera(position)
        for branch in frame.branches:
            point = in_camera[branch.id]
            np.testing.assert_allclose(point, branch.cut_point_m, atol=1e-9)
            pixel = _project(point[None, :], k)[0]
            np.testing.assert_allclose(pixel, branch.cut_pixel, atol=1e-6)
            x, y = (int(round(c)) for c in pixel)
            inside = 0 <= x < 320 and 0 <= y < 180 and point[2] > 0
            on_branch = inside and frame.mask[y, x] == branch.id
            assert (branch.id in truth.poses[position].visible_cut_ids) == on_branch == branch.cut_visible
            if on_branch:  # the surface point seen at that pixel lies on the branch's tapered surface
                surface = np.linalg.inv(k) @ [x, y, 1.0] * float(frame.depth_m[y, x])
                along = (surface - branch.base_m) @ np.asarray(branch.direction)
                off_axis = np.linalg.norm(surface - branch.base_m - along * np.asarray(branch.direction))
                assert off_axis == pytest.approx(branch.radius_at(along), abs=1e-4)
                checked += 1
    assert checked >= 6


def test_flight_approaches_the_target_from_start_to_end_distance():
    options = FlightOptions(frames=5, width=160, height=90, seed=2)
    renderer = FlightRenderer(options)
    truth = FlightTruth(
        [FlightPose(i, options.timestamp_ns(i), *renderer.world_pose(options.time_s(i))) for i in range(5)],
        [FlightCutPoint(c.id, c.world_m, c.radius_m) for c in renderer.cut_points],
    )
    expected = np.linspace(3.0, 0.8, 5)
    for position, distance in enumerate(expected):
        target = truth.cut_points_in_camera(position)[renderer.target_id]
        np.testing.assert_allclose(target, [0.0, 0.0, distance], atol=1e-9)  # straight ahead, on the optical axis
        assert truth.poses[position].timestamp_ns - truth.poses[0].timestamp_ns == round(position * 1e9 / 15)
    np.testing.assert_allclose(truth.poses[0].R_world_cam, np.eye(3), atol=0)
    np.testing.assert_allclose(truth.poses[0].t_world_cam, 0.0, atol=0)


def test_sway_and_jitter_keep_the_distance_along_the_approach(wobbly_renderer: FlightRenderer):
    target = next(c.world_m for c in wobbly_renderer.cut_points if c.id == wobbly_renderer.target_id)
    approach = target / np.linalg.norm(target)  # frame 0 is on the approach line (sway starts at 0)
    sideways, tilted = [], []
    for index in range(6):
        rotation, position = wobbly_renderer.world_pose(WOBBLY_OPTIONS.time_s(index))
        along = (target - position) @ approach
        assert along == pytest.approx(WOBBLY_OPTIONS.distance_m(WOBBLY_OPTIONS.time_s(index)), abs=1e-9)
        sideways.append(np.linalg.norm(target - position - along * approach))
        tilted.append(math.degrees(math.acos(np.clip(rotation[:, 2] @ approach, -1, 1))))
    assert max(sideways) <= 0.05 + 1e-9 and max(sideways) > 0.01
    assert 0.05 < max(tilted) <= 1.5 * math.sqrt(3)


def test_speed_sets_the_frame_count_without_overshooting_the_end():
    options = FlightOptions(speed_mps=0.5, fps=15.0)
    assert options.frame_count == 67  # 2.2 m at 0.5 m/s = 4.4 s → frames at 0 … 4.4 s
    last = options.distance_m(options.time_s(options.frame_count - 1))
    assert 0.8 - 1e-9 <= last < 0.8 + 0.5 / 15
    assert FlightOptions().frame_count == 83 and FlightOptions().speed == pytest.approx(0.4)
    assert FlightOptions(frames=12).speed == pytest.approx(2.2 * 15 / 11)
    with pytest.raises(ValueError, match="speed_mps"):
        FlightOptions(frames=12, speed_mps=0.5)


def test_yaw_sweep_turns_about_gravity_at_its_rate_and_back_at_the_bound():
    target, down = np.array([0.3, -0.2, 2.5]), np.array([0.0, 1.0, 0.0])
    still = ApproachPath(target, down, FlightOptions(frames=40), np.random.default_rng(0))
    options = FlightOptions(frames=40, yaw_rate_dps=40.0)
    turning = ApproachPath(target, down, options, np.random.default_rng(0))
    assert YAW_BOUND_DEG == 15.0  # the angles below: 40 °/s reaches 15° at 0.375 s and turns back
    expected = [(0.0, 0.0), (0.25, 10.0), (0.5, 10.0), (0.75, 0.0), (1.0, -10.0), (1.125, -15.0), (1.5, 0.0)]
    for time_s, expected_deg in expected:
        rotation, position = turning.pose(time_s)
        still_rotation, still_position = still.pose(time_s)
        np.testing.assert_allclose(position, still_position, atol=1e-12)  # the view turns, the camera stays put
        turn = rotation @ still_rotation.T
        np.testing.assert_allclose(turn @ down, down, atol=1e-12)  # about the vertical axis
        angle = math.degrees(math.atan2(turn[0, 2], turn[0, 0]))  # about +y: z turns toward x
        assert angle == pytest.approx(expected_deg, abs=1e-9)
    for time_s in np.arange(0.0, options.time_s(39), 1 / 15):  # the target stays within the bound of the axis
        rotation, position = turning.pose(time_s)
        toward = rotation.T @ (target - position)
        assert math.degrees(math.acos(toward[2] / np.linalg.norm(toward))) <= YAW_BOUND_DEG + 1e-9


def test_flight_renderer_at_the_scene_pose_reproduces_render_scene():
    camera = SynthCamera.zed_mini(320, 180)
    reference = render_scene(6, camera, supersample=1, foliage="bare", noise_std=0.0, view_gain_jitter=0.0)
    renderer = FlightRenderer(FlightOptions(frames=2, width=320, height=180, seed=6, noise_std=0.0))
    view = renderer.view(np.eye(3), np.zeros(3))
    assert np.array_equal(view.views.ids, reference.instance_mask)
    assert np.array_equal(view.views.depth.astype(np.float32), reference.depth_m)
    assert [b.to_dict() for b in view.branches] == [b.to_dict() for b in reference.branches]
    still = SynthOptions(supersample=1, noise_std=0.0, view_gain_jitter=0.0)
    left, right = develop(
        [view.views.left, view.views.right],
        auto_gain(view.views.left, renderer.scene.exposure_target),
        still,
        np.random.default_rng(0),
    )
    assert np.array_equal(left, reference.left) and np.array_equal(right, reference.right)


def test_moving_the_camera_moves_the_rendered_depth_rigidly():
    """A camera 0.2 m further forward sees the same surfaces, each 0.2 m nearer."""
    renderer = FlightRenderer(FlightOptions(frames=2, width=160, height=90, seed=1))
    step = np.array([0.0, 0.0, 0.2])
    here = render_views(scene_in_camera(renderer.scene, np.eye(3), np.zeros(3), renderer.camera), renderer.camera, 1, 1)
    ahead = render_views(scene_in_camera(renderer.scene, np.eye(3), step, renderer.camera), renderer.camera, 1, 1)
    cam = renderer.camera
    v, u = np.mgrid[0 : cam.height, 0 : cam.width]
    ok = np.isfinite(ahead.depth) & (ahead.ids > 0)
    z, u, v = ahead.depth[ok], u[ok], v[ok]
    # the point behind pixel (u, v) of the forward camera, as seen from the first camera
    x, y, z0 = (u - cam.cx) * z / cam.focal_px, (v - cam.cy) * z / cam.focal_px, z + 0.2
    uu = np.clip(np.rint(cam.focal_px * x / z0 + cam.cx).astype(int), 0, cam.width - 1)
    vv = np.clip(np.rint(cam.focal_px * y / z0 + cam.cy).astype(int), 0, cam.height - 1)
    same = here.ids[vv, uu] == ahead.ids[ok]
    depth_then = here.depth[vv, uu]
    assert same.mean() > 0.8 and ok.sum() > 500
    # where the same surface is hit, it lies 0.2 m further from the first camera (within a pixel's depth spread)
    assert np.median(np.abs(depth_then[same] - z0[same])) < 0.01


def test_image_motion_of_a_sideways_step_and_a_yaw():
    camera = SynthCamera.zed_mini(64, 36)
    depth = np.full((36, 64), 2.0)
    still = (np.eye(3), np.zeros(3))
    moved = (np.eye(3), np.array([0.1, 0.0, 0.0]))  # now 0.1 m to the right of where it was
    flow = image_motion(depth, camera, "left", moved, still)
    np.testing.assert_allclose(flow[..., 0], camera.focal_px * 0.1 / 2.0, atol=1e-4)  # it was seen further right
    np.testing.assert_allclose(flow[..., 1], 0.0, atol=1e-4)
    sky = image_motion(np.full((36, 64), np.inf), camera, "right", moved, still)
    np.testing.assert_allclose(sky, 0.0, atol=1e-6)  # translation does not move the sky
    angle = math.radians(1.0)
    yawed = (
        np.array([[math.cos(angle), 0, math.sin(angle)], [0, 1, 0], [-math.sin(angle), 0, math.cos(angle)]]),
        np.zeros(3),
    )
    centre = image_motion(np.full((36, 64), np.inf), camera, "left", yawed, still)[18, 32]
    assert centre[0] == pytest.approx(camera.focal_px * math.tan(angle), rel=0.02)


def test_blur_smears_an_edge_along_the_motion_only():
    image = np.zeros((20, 40, 3), dtype=np.float32)
    image[:, 20:] = 1.0
    motion = np.zeros((20, 40, 2), dtype=np.float32)
    assert blur_along_motion(image, motion, 0.5) is image
    motion[..., 0] = 8.0
    blurred = blur_along_motion(image, motion, 1.0)
    row = blurred[10, :, 0]
    assert np.allclose(blurred, blurred[:1])  # rows unchanged relative to each other
    # content moved +8 px during the exposure: pixels 20..27 gathered both sides of the edge
    assert row[19] == pytest.approx(0.0) and row[28] == pytest.approx(1.0)
    assert 0.3 < row[24] < 0.7 and np.all(np.diff(row) >= -1e-6)


def test_exposure_wobble_is_smooth_and_bounded(wobbly_renderer: FlightRenderer):
    gains = [wobbly_renderer.path.gain_factor(t) for t in np.arange(0, 20, 1 / 15)]
    assert min(gains) >= 0.8 - 1e-9 and max(gains) <= 1.2 + 1e-9 and max(gains) - min(gains) > 0.1
    assert max(abs(b - a) for a, b in zip(gains, gains[1:])) < 0.03


def test_recording_replays_with_masks_and_timestamps(wobbly_recording: Path, wobbly_frames: list):
    truth = FlightTruth.load(wobbly_recording)
    source = ReplaySource(wobbly_recording, pace="fast")
    replayed = list(source)
    assert source.calibration.K1[0, 0] == pytest.approx(160.0) and source.calibration.baseline_m == pytest.approx(0.063)
    assert [f.timestamp_ns for f in replayed] == [p.timestamp_ns for p in truth.poses]
    assert [f.timestamp_ns - replayed[0].timestamp_ns for f in replayed] == [round(i * 1e9 / 15) for i in range(6)]
    for back, frame in zip(replayed, wobbly_frames):
        assert back.mask.dtype == np.uint16 and np.array_equal(back.mask, frame.mask)
        assert np.array_equal(back.left, frame.left) and np.array_equal(back.right, frame.right)
    assert not np.array_equal(replayed[0].left, replayed[1].left)


def test_branchrange_replay_reads_the_recording(wobbly_recording: Path, tmp_path: Path):
    args = build_parser("branchrange", "test", ["branchrange.commands.replay"]).parse_args(
        ["replay", str(wobbly_recording), "--out", str(tmp_path / "results.jsonl")]
    )
    assert args.func(args) == 0
    lines = [r.to_json_dict() for r in read_results(tmp_path / "results.jsonl")]  # the run header skipped
    truth = FlightTruth.load(wobbly_recording)
    assert [line["frame"]["timestamp_ns"] for line in lines] == [pose.timestamp_ns for pose in truth.poses]
    assert sum(bool(line["branches"]) for line in lines) >= 5


def test_flight_json_round_trips_exactly(wobbly_recording: Path, tmp_path: Path):
    truth = FlightTruth.load(wobbly_recording)
    truth.write(tmp_path)
    back = FlightTruth.load(tmp_path)
    for a, b in zip(truth.poses, back.poses):
        assert (a.index, a.timestamp_ns, a.visible_cut_ids) == (b.index, b.timestamp_ns, b.visible_cut_ids)
        assert np.array_equal(a.R_world_cam, b.R_world_cam) and np.array_equal(a.t_world_cam, b.t_world_cam)
    assert [(c.id, c.world_m.tolist(), c.radius_m) for c in truth.cut_points] == [
        (c.id, c.world_m.tolist(), c.radius_m) for c in back.cut_points
    ]


def test_pose_at_interpolates_rotation_by_slerp_and_translation_linearly():
    def yaw(degrees: float) -> np.ndarray:
        a = math.radians(degrees)
        return np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])

    truth = FlightTruth(
        [FlightPose(0, 1000, yaw(0), np.zeros(3)), FlightPose(1, 2000, yaw(30), np.array([0, 0, 1.0]))],
        [FlightCutPoint(1, np.array([0, 0, 2.0]), 0.01)],
    )
    rotation, translation = truth.pose_at(1250)
    np.testing.assert_allclose(rotation, yaw(7.5), atol=1e-12)
    np.testing.assert_allclose(translation, [0, 0, 0.25], atol=1e-12)
    np.testing.assert_allclose(truth.pose_at(2000)[0], yaw(30), atol=0)
    with pytest.raises(ValueError, match="outside the flight"):
        truth.pose_at(2001)
    assert truth.poses[0].visible_cut_ids is None


def _good_document() -> dict:
    return {
        "format": "branchrange-flight",
        "version": 1,
        "poses": [
            {
                "index": 0,
                "timestamp_ns": 10,
                "R_world_cam": np.eye(3).tolist(),
                "t_world_cam": [0, 0, 0],
                "visible_cut_ids": [1],
            },
            {"index": 1, "timestamp_ns": 20, "R_world_cam": np.eye(3).tolist(), "t_world_cam": [0, 0, 0.1]},
        ],
        "cut_points": [{"id": 1, "world_m": [0, 0, 2], "radius_m": 0.01}],
    }


@pytest.mark.parametrize(
    "change, key",
    [
        (lambda d: d.update(format="branchrange-recording"), "format"),
        (lambda d: d.update(version=2), "version"),
        (lambda d: d.pop("poses"), "poses"),
        (lambda d: d["poses"][1].pop("t_world_cam"), "t_world_cam"),
        (lambda d: d["poses"][0].update(R_world_cam=[[1, 0], [0, 1]]), r"poses\[0\].R_world_cam"),
        (lambda d: d["poses"][0].update(R_world_cam=(2 * np.eye(3)).tolist()), "rotation matrix"),
        (lambda d: d["poses"][0].update(R_world_cam=np.diag([1.0, 1.0, -1.0]).tolist()), "rotation matrix"),
        (lambda d: d["poses"][1].update(t_world_cam=[0, "x", 0]), r"poses\[1\].t_world_cam"),
        (lambda d: d["poses"][1].update(timestamp_ns=5), "increasing"),
        (lambda d: d["poses"][0].update(index=-1), r"poses\[0\].index"),
        (lambda d: d["poses"][0].update(visible_cut_ids=[7]), "visible_cut_ids"),
        (lambda d: d["cut_points"][0].update(radius_m=-0.01), "radius_m"),
        (lambda d: d["cut_points"].append(dict(d["cut_points"][0])), "distinct"),
    ],
)
def test_bad_flight_files_name_the_key(tmp_path: Path, change, key: str):
    document = _good_document()
    (tmp_path / FLIGHT_NAME).write_text(json.dumps(document))
    assert len(FlightTruth.load(tmp_path).poses) == 2
    change(document)
    (tmp_path / FLIGHT_NAME).write_text(json.dumps(document))
    with pytest.raises(FlightFormatError, match=key) as caught:
        FlightTruth.load(tmp_path)
    assert str(tmp_path / FLIGHT_NAME) in str(caught.value)


def test_missing_or_garbled_flight_file(tmp_path: Path):
    with pytest.raises(FlightFormatError, match="cannot be read"):
        FlightTruth.load(tmp_path)
    (tmp_path / FLIGHT_NAME).write_text("{not json")
    with pytest.raises(FlightFormatError, match="not JSON"):
        FlightTruth.load(tmp_path)


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--start-m", "0.8", "--end-m", "0.8"], "start_m"),
        (["--end-m", "3.5"], "start_m"),
        (["--fps", "-15"], "fps"),
        (["--resolution", "720p"], "--resolution"),
        (["--resolution", "1280x"], "--resolution"),
        (["--frames", "6", "--speed", "0.4"], "speed_mps"),
        (["--frames", "1"], "frames"),
        (["--speed", "0"], "speed_mps"),
        (["--jitter-deg", "-1"], "jitter_deg"),
        (["--yaw-rate", "-5"], "yaw_rate_dps"),
        (["--supersample", "9"], "supersample"),
    ],
)
def test_bad_options_exit_2_with_a_message(tmp_path: Path, capsys: pytest.CaptureFixture[str], argv, message):
    assert _run(["synth-flight", "--out", str(tmp_path / "rec"), *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and "expected" in err
    assert not (tmp_path / "rec").exists()


def test_a_non_empty_out_directory_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]):
    (tmp_path / "keep.txt").write_text("x")
    assert _run(["synth-flight", "--out", str(tmp_path), "--frames", "2", "--resolution", "64x36"]) == 2
    assert "not empty" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.txt"]


def test_progress_lines_when_stderr_is_not_a_terminal(tmp_path: Path, capsys: pytest.CaptureFixture[str]):
    assert (
        _run(
            [
                "synth-flight",
                "--out",
                str(tmp_path / "rec"),
                "--frames",
                "20",
                "--resolution",
                "64x36",
                "--start-m",
                "1.2",
            ]
        )
        == 0
    )
    captured = capsys.readouterr()
    progress = [line for line in captured.err.splitlines() if line.startswith("synth-flight:")]
    assert len(progress) == 10 and progress[-1].startswith("synth-flight: 20/20 frames")
    assert "wrote 20 frames" in captured.out
    assert len(FlightTruth.load(tmp_path / "rec").poses) == 20


def test_foliage_switches_the_leaves_on():
    def leaves(foliage: bool) -> int:
        scene = FlightRenderer(FlightOptions(frames=2, width=64, height=36, seed=3, foliage=foliage)).scene
        return sum(leaf.instance_id == LEAF_ID for leaf in scene.leaves)

    assert leaves(False) == 0 and leaves(True) > 50
