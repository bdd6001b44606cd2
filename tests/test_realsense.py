"""The RealSense source against recordings that pyrealsense2 itself wrote (software device +
recorder), played back through the SDK's real pipeline."""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

# installed but unloadable (no libusb-1.0 on a bare Debian) skips too, with the loader's reason
rs = pytest.importorskip("pyrealsense2", exc_type=ImportError)

from app.camera import CameraModel, Intrinsics  # noqa: E402
from app.cli import main  # noqa: E402
from app.config import CaptureConfig, load_config  # noqa: E402
from app.errors import ConfigError, SourceError  # noqa: E402
from app.perception.frames import Frame  # noqa: E402
from app.runtime.sources import open_source  # noqa: E402
from app.sim.synthetic import approach_scene, render  # noqa: E402
from hardware.realsense import (  # noqa: E402
    CameraLost,
    RealSenseSource,
    configure_depth_sensor,
    write_realsense_recording,
)

# a D435i-like calibration: depth and colour lenses differ, 15 mm baseline, a slight rotation
ANGLE = np.deg2rad(0.5)
CAMERA = CameraModel(
    Intrinsics(640, 480, 615.0, 615.5, 321.0, 242.0),
    Intrinsics(640, 480, 385.0, 385.0, 318.0, 238.5),
    np.array([[np.cos(ANGLE), 0, np.sin(ANGLE)], [0, 1, 0], [-np.sin(ANGLE), 0, np.cos(ANGLE)]]),
    np.array([0.0148, 0.0001, 0.0003]),
    0.001,
)


def frames(n: int, seed: int = 3) -> list[Frame]:
    rng = np.random.default_rng(seed)
    return [Frame(k + 1, k / 30.0, rng.integers(0, 256, (480, 640, 3), dtype=np.uint8),
                  rng.integers(0, 9000, (480, 640), dtype=np.uint16)) for k in range(n)]


@pytest.fixture(scope="module")
def noise_recording(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[Frame]]:
    fs = frames(30)
    return write_realsense_recording(fs, CAMERA, 30.0, tmp_path_factory.mktemp("rs") / "noise.db3"), fs


def test_a_recording_plays_back_bit_exact_with_its_calibration(
        noise_recording: tuple[Path, list[Frame]]) -> None:
    path, written = noise_recording
    src = open_source(path)
    assert isinstance(src, RealSenseSource) and not src.live and src.has_depth
    got = list(src)
    assert len(got) == len(written)
    for a, b in zip(written, got, strict=True):
        assert b.color.flags.owndata and b.depth is not None and b.depth.flags.owndata
        assert a.depth is not None and np.array_equal(a.color, b.color) and np.array_equal(a.depth, b.depth)
    assert [f.index for f in got] == list(range(1, 31))
    assert np.allclose([f.t_s for f in got], [k / 30.0 for k in range(30)], atol=1e-6)
    cam = src.camera
    assert cam is not None
    assert cam.color == CAMERA.color and cam.depth == CAMERA.depth
    assert np.allclose(cam.rotation, CAMERA.rotation, atol=1e-6)  # column-major handled
    assert np.allclose(cam.translation_m, CAMERA.translation_m, atol=1e-6)
    assert cam.depth_scale_m == pytest.approx(0.001)
    assert src.fps == pytest.approx(30.0)
    assert len(list(src)) == 30  # a second pass starts the recording again


def test_an_infrared_recording_plays_its_grey_imager_registered_to_depth(tmp_path: Path) -> None:
    # the left infrared imager: the depth pair's lens, so depth -> image is the identity
    ir_lens = Intrinsics(848, 480, 447.0, 447.0, 423.5, 239.5)
    camera = CameraModel(ir_lens, ir_lens, np.eye(3), np.zeros(3), 0.001)
    rng = np.random.default_rng(5)
    written = [Frame(k + 1, k / 60.0, rng.integers(0, 256, (480, 848), dtype=np.uint8),
                     rng.integers(0, 9000, (480, 848), dtype=np.uint16)) for k in range(12)]
    path = write_realsense_recording(written, camera, 60.0, tmp_path / "ir.db3", stream="infrared")
    for cfg in (replace(CaptureConfig(), stream="infrared"), CaptureConfig()):
        # configured for colour, a recording that holds only the infrared imager plays that
        src = RealSenseSource(cfg, path)
        assert src.image_stream == "infrared"
        got = list(src)
        assert len(got) == 12
        for a, b in zip(written, got, strict=True):
            assert b.color.ndim == 2 and np.array_equal(a.color, b.color)
            assert a.depth is not None and b.depth is not None and np.array_equal(a.depth, b.depth)
        assert src.camera is not None and src.camera.color == ir_lens and src.camera.depth == ir_lens
        assert np.allclose(src.camera.rotation, np.eye(3)) and src.fps == pytest.approx(60.0)


def test_a_colour_recording_configured_for_infrared_plays_its_colour(
        noise_recording: tuple[Path, list[Frame]]) -> None:
    path, written = noise_recording
    src = RealSenseSource(replace(CaptureConfig(), stream="infrared"), path)
    assert src.image_stream == "color"
    first = next(iter(src))
    assert np.array_equal(first.color, written[0].color)
    src.close()


def test_writing_colour_frames_as_infrared_is_refused_by_name(tmp_path: Path) -> None:
    with pytest.raises(SourceError, match=r"frame 1 is \(480, 640, 3\), not a grey \(H x W\) infrared image"):
        write_realsense_recording(frames(2), CAMERA, 30.0, tmp_path / "bad.db3", stream="infrared")
    assert not (tmp_path / "bad.db3").exists()  # nothing half-written left behind
    with pytest.raises(ValueError, match="stream 'thermal'"):
        write_realsense_recording(frames(2), CAMERA, 30.0, tmp_path / "bad2.db3", stream="thermal")


def depth_sensor_with(*options: Any) -> Any:
    """A pyrealsense2 software sensor with the depth pair's writable ``options`` (ranges as
    a D435i reports them: presets 0-6, default 1; the projector 0-1, on)."""
    sensor = rs.software_device().add_sensor("Stereo Module")
    for option in options:
        r = rs.option_range()
        r.min, r.max, r.step, r.default = (0, 6, 1, 1) if option == rs.option.visual_preset else (0, 1, 1, 1)
        sensor.add_option(option, r, True)
    return sensor


def test_the_depth_preset_is_set_and_the_projector_left_off_for_the_infrared_image(
        caplog: pytest.LogCaptureFixture) -> None:
    sensor = depth_sensor_with(rs.option.visual_preset, rs.option.emitter_enabled)
    configure_depth_sensor(rs, sensor, "infrared", "high_accuracy")
    assert sensor.get_option(rs.option.visual_preset) == float(rs.rs400_visual_preset.high_accuracy)
    assert sensor.get_option(rs.option.emitter_enabled) == 0.0
    # colour: the projector stays as the preset left it; "keep" touches no preset
    sensor = depth_sensor_with(rs.option.visual_preset, rs.option.emitter_enabled)
    configure_depth_sensor(rs, sensor, "color", "keep")
    assert sensor.get_option(rs.option.visual_preset) == 1.0
    assert sensor.get_option(rs.option.emitter_enabled) == 1.0
    # a firmware without presets is said in the log, and the projector is still switched off
    sensor = depth_sensor_with(rs.option.emitter_enabled)
    with caplog.at_level("WARNING", logger="hardware.realsense"):
        configure_depth_sensor(rs, sensor, "infrared", "high_density")
    assert "no visual presets; capture.depth_preset high_density is not applied" in caplog.text
    assert sensor.get_option(rs.option.emitter_enabled) == 0.0


def test_an_unknown_depth_preset_is_refused_by_name(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("capture:\n  depth_preset: hight_accuracy\n")
    with pytest.raises(ConfigError, match="depth_preset"):
        load_config(bad)


def test_a_stall_restarts_the_pipeline_and_frames_come_again(
        noise_recording: tuple[Path, list[Frame]]) -> None:
    path, written = noise_recording
    cfg = replace(CaptureConfig(), frame_timeout_ms=200.0, backoff_initial_s=0.1, give_up_s=5.0)
    src = RealSenseSource(cfg, path)
    got: list[Frame] = []
    t_paused = 0.0
    for f in src:
        got.append(f)
        if len(got) == 10:
            src.playback.pause()  # the stream stops, as when the USB link drops frames
            t_paused = time.monotonic()
        if len(got) == 25:
            break
    assert src.restarts == 1 and src.resets == 0  # a recording is never hardware-reset
    # after the restart the recording plays from its start again: frame 11 of the source
    # is the recording's first frame, and the indices keep counting
    assert [f.index for f in got] == list(range(1, 26))
    assert np.array_equal(got[10].color, written[0].color)
    assert time.monotonic() - t_paused >= 0.2


def test_a_camera_that_never_comes_back_is_given_up_with_a_clear_error(
        tmp_path: Path, noise_recording: tuple[Path, list[Frame]]) -> None:
    path, _ = noise_recording
    copy = tmp_path / "gone.db3"
    copy.write_bytes(path.read_bytes())
    cfg = replace(CaptureConfig(), frame_timeout_ms=200.0, backoff_initial_s=0.1, backoff_max_s=0.2,
                  give_up_s=1.5)
    src = RealSenseSource(cfg, copy)
    it = iter(src)
    next(it)
    src.playback.pause()
    copy.unlink()  # every restart now fails: the device is gone
    t0 = time.monotonic()
    with pytest.raises(CameraLost, match=r"camera gone: no frame for 1\.[5-9] s after \d+ restarts"):
        for _ in it:
            pass
    assert 1.2 <= time.monotonic() - t0 <= 4.0
    assert src.restarts >= 2
    assert isinstance(CameraLost("x"), SourceError)  # the CLI prints it without a traceback


def test_bad_recording_paths_are_named(tmp_path: Path) -> None:
    with pytest.raises(SourceError, match="no such RealSense recording"):
        RealSenseSource(CaptureConfig(), tmp_path / "missing.db3")
    junk = tmp_path / "junk.db3"
    junk.write_bytes(b"not a recording")
    with pytest.raises(SourceError, match=r"junk\.db3: cannot be started"):
        RealSenseSource(CaptureConfig(), junk)
    wrong = tmp_path / "clip.avi"
    wrong.write_bytes(b"x")
    with pytest.raises(SourceError, match=r"ends in \.db3 or \.bag"):
        RealSenseSource(CaptureConfig(), wrong)


def test_no_camera_plugged_in_is_a_clear_error() -> None:
    if len(rs.context().query_devices()) > 0:
        pytest.skip("a RealSense camera is connected")
    with pytest.raises(SourceError, match="no RealSense camera found"):
        RealSenseSource(CaptureConfig())


def test_replay_reads_a_realsense_recording_and_decides(tmp_path: Path,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    scene = approach_scene((-0.4, -0.3, 8.0), frames=75)
    path = write_realsense_recording((f for f, _ in render(scene)), scene.camera(), scene.fps,
                                     tmp_path / "ball.db3")
    assert main(["replay", str(path), "--out", str(tmp_path / "out"), "--no-video",
                 "--altitude", "10"]) == 0
    rows = (tmp_path / "out" / "decisions.csv").read_text().splitlines()
    evades = [r for r in rows[1:] if ",evade," in r]
    assert evades, "the ball thrown from the upper left was never dodged"
    # away from where it passes (upper left): right and/or down, never up or left (with the
    # descent capped at PX4's 1.5 m/s, straight right gets farther in time than down-right)
    vel = [(float(r.split(",")[3]), float(r.split(",")[4])) for r in evades]
    assert all(right >= 0 and down >= 0 and right + down > 0 for right, down in vel)
