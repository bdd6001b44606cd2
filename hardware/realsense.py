"""The Intel RealSense D435i (colour + depth) through pyrealsense2, live or from a recording.

The only module that imports ``pyrealsense2``, and only when a RealSense source is opened:
everything else works without the SDK (it has no aarch64 wheel for Python >= 3.11; on the
Pi it is built from librealsense's source, see docs/pi-install.md).

What it does, per the runtime issue:

- colour (BGR8) and depth (Z16) at the configured resolutions and rates, IMU off unless
  asked for; frames are copied out of the SDK's buffers before they leave this module;
- or, with ``capture.stream: infrared``, the left infrared imager (Y8, grey) in place of
  colour: the depth pair's own lens (87° across against colour's 69°, global shutter),
  streamed with depth at its resolution and rate, the IR projector switched off (its dot
  pattern is fixed in the image, so it would move against a registered background);
- the calibration the device reports (both intrinsics, depth→image extrinsics, depth
  scale) as :class:`app.camera.CameraModel`, so depth pixels are projected per pixel
  (no ``rs.align``, which costs a full-frame remap per frame);
- capture times on the monotonic clock, corrected for the time the frame spent between the
  sensor and us when the device stamps in host time (``global_time`` domain);
- recovery of a live camera: a stall longer than ``frame_timeout_ms`` restarts the
  pipeline; after ``restarts_before_reset`` failed restarts the device gets a USB hardware
  reset; waits double from ``backoff_initial_s`` to ``backoff_max_s``; no frame for
  ``give_up_s`` raises :class:`CameraLost` (the service exits and systemd restarts it).
  Meanwhile the flight side sees no new decisions and acts by its dead-man rule.

A RealSense recording (``.db3`` from SDK 2.59's recorder, ``.bag`` from older ones) plays
through the same pipeline, frame by frame (not in real time: the caller paces it).

Facts used (librealsense 2.59 headers and docs): ``rs2_extrinsics.rotation`` is a
column-major 3x3 matrix; depth units come from the depth sensor's ``depth_units`` option
(``get_depth_scale``); ``try_wait_for_frames`` returns ``(False, …)`` on timeout instead of
raising; a playback device reports ``playback_status.stopped`` at its end.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from app.camera import CameraModel, Intrinsics
from app.config import CaptureConfig
from app.errors import SourceError
from app.perception.frames import Frame, FrameSource

log = logging.getLogger(__name__)

RECORDING_EXTS = {".bag", ".db3"}
_MAX_TRANSPORT_S = 0.5  # a host-time stamp further back than this is not believed


class CameraLost(SourceError):
    """The camera delivered no frame for ``give_up_s`` despite restarts and resets."""


def _rs() -> Any:
    try:
        import pyrealsense2 as rs
    except ModuleNotFoundError:
        raise SourceError(
            "the RealSense camera needs pyrealsense2: pip install 'midair[realsense]' "
            "(on a Pi 4, build it from librealsense's source, see docs/pi-install.md)"
        ) from None
    except ImportError as exc:
        # installed, but something it links against is missing (a fresh Debian has no
        # libusb-1.0.so.0): say what the loader said, not "install pyrealsense2"
        hint = " (on Debian/Ubuntu: apt-get install libusb-1.0-0)" if "libusb" in str(exc) else ""
        raise SourceError(f"pyrealsense2 is installed but cannot load: {exc}{hint}") from None
    return rs


def _intrinsics(profile: Any) -> Intrinsics:
    i = profile.as_video_stream_profile().get_intrinsics()
    return Intrinsics(int(i.width), int(i.height), float(i.fx), float(i.fy), float(i.ppx), float(i.ppy))


def camera_model(color: Any, depth: Any, depth_scale_m: float) -> CameraModel:
    """The calibration from the colour and depth stream profiles and the depth scale."""
    ext = depth.get_extrinsics_to(color)
    rotation = np.asarray(ext.rotation, float).reshape(3, 3).T  # column-major in the SDK
    return CameraModel(_intrinsics(color), _intrinsics(depth), rotation,
                       np.asarray(ext.translation, float), float(depth_scale_m))


def _image_kind(rs: Any, stream: str) -> Any:
    """The SDK's stream type of ``capture.stream``."""
    return rs.stream.infrared if stream == "infrared" else rs.stream.color


def configure_depth_sensor(rs: Any, sensor: Any, stream: str, preset: str) -> None:
    """The depth pair's settings: the visual preset ``preset`` (``capture.depth_preset``;
    "keep" leaves the camera's), then, for ``stream`` "infrared", the IR projector off. In
    that order: a preset carries its own laser settings and would switch the projector back
    on. A camera without the option (an older firmware) is logged, not refused."""
    if preset != "keep":
        if sensor.supports(rs.option.visual_preset):
            sensor.set_option(rs.option.visual_preset, float(getattr(rs.rs400_visual_preset, preset)))
            log.info("camera: depth preset %s", preset)
        else:
            log.warning("camera: this depth sensor has no visual presets; capture.depth_preset "
                        "%s is not applied", preset)
    if stream == "infrared" and sensor.supports(rs.option.emitter_enabled):
        sensor.set_option(rs.option.emitter_enabled, 0.0)
        log.info("camera: IR projector off (perception sees the infrared imager)")


class _Live:
    """The D435i through ``rs.pipeline`` (its frame syncer and queue)."""

    def __init__(self, rs: Any, config: Any, stream: str, preset: str) -> None:
        self.pipeline = rs.pipeline()
        profile = self.pipeline.start(config)
        self.device = profile.get_device()
        for sensor in self.device.query_sensors():
            # hardware timestamps mapped to the host clock: capture times net of USB delay
            if sensor.supports(rs.option.global_time_enabled):
                sensor.set_option(rs.option.global_time_enabled, 1.0)
        depth_sensor = self.device.first_depth_sensor()
        configure_depth_sensor(rs, depth_sensor, stream, preset)
        self.color = (profile.get_stream(rs.stream.infrared, 1) if stream == "infrared"
                      else profile.get_stream(rs.stream.color))
        self.depth = profile.get_stream(rs.stream.depth)
        self.depth_scale = depth_sensor.get_depth_scale()

    def wait(self, timeout_ms: int) -> tuple[bool, Any]:
        return self.pipeline.try_wait_for_frames(timeout_ms)

    def ended(self) -> bool:
        return False

    def stop(self) -> None:
        self.pipeline.stop()


class _Playback:
    """A recording through its playback device's sensors and a syncer, not ``rs.pipeline``:
    the pipeline starts the playback in real time before ``set_real_time(False)`` can be
    called, so its first frames can be dropped (seen here, 1 run in 5); sensor callbacks
    lose nothing (librealsense maintainers, issue #1180), and a non-real-time playback
    waits for the syncer's queue."""

    def __init__(self, rs: Any, path: Path, stream: str) -> None:
        self.rs = rs
        self.path = path
        self.ctx = rs.context()
        self.device = self.ctx.load_device(str(path))
        self.playback = self.device.as_playback()
        self.playback.set_real_time(False)  # before any sensor starts: every frame, in order
        self.syncer = rs.syncer(4)
        self.sensors = []
        self.color: Any = None  # the image stream perception sees: colour or infrared
        self.depth: Any = None
        # the configured image stream when the recording has it, else the other one: a
        # recording plays whatever its flight saw
        found: dict[Any, Any] = {}
        for sensor in self.device.query_sensors():
            for prof in sensor.get_stream_profiles():
                kind = prof.stream_type()
                if kind == rs.stream.infrared and prof.stream_index() != 1:
                    continue  # the right imager: depth is registered to the left one
                if kind in (rs.stream.color, rs.stream.infrared, rs.stream.depth) and kind not in found:
                    found[kind] = (sensor, prof)
        wanted = _image_kind(rs, stream)
        other = rs.stream.color if wanted == rs.stream.infrared else rs.stream.infrared
        image = found.get(wanted) or found.get(other)
        if image is None or rs.stream.depth not in found:
            self.ctx.unload_device(str(path))
            raise RuntimeError("the recording needs a colour or infrared stream and a depth stream")
        self.color, self.depth = image[1], found[rs.stream.depth][1]
        by_sensor: dict[int, tuple[Any, list[Any]]] = {}
        # depth's sensor started first, as the recorder wrote it first: its frame reaches the
        # syncer before the image's (a depth that comes alone waits for its image)
        for sensor, prof in (found[rs.stream.depth], image):
            by_sensor.setdefault(id(sensor), (sensor, []))[1].append(prof)
        self.sensors = list(by_sensor.values())
        self.depth_scale = self.device.first_depth_sensor().get_depth_scale()
        for sensor, profiles in self.sensors:
            sensor.open(profiles)
            sensor.start(self.syncer)

    def wait(self, timeout_ms: int) -> tuple[bool, Any]:
        # in slices, so the end of the file is noticed at once instead of after a timeout
        deadline = time.monotonic() + timeout_ms / 1000.0
        while True:
            ok, frames = self.syncer.try_wait_for_frames(min(timeout_ms, 50))
            if ok or self.ended() or time.monotonic() >= deadline:
                return ok, frames

    def ended(self) -> bool:
        return bool(self.playback.current_status() == self.rs.playback_status.stopped)

    def stop(self) -> None:
        for sensor, _ in self.sensors:
            for call in (sensor.stop, sensor.close):
                try:
                    call()
                except RuntimeError as exc:  # already stopped at the end of the file
                    log.debug("playback sensor: %s", exc)
        self.ctx.unload_device(str(self.path))


class RealSenseSource(FrameSource):
    """The D435i (``path=None``) or a RealSense recording file, as a :class:`FrameSource`.

    ``Frame.t_s`` is the monotonic capture time for the live camera (``live`` is True:
    the runtime neither paces nor re-stamps it) and seconds since the first frame for a
    recording. Frames without both colour and depth are passed with ``depth=None``.
    """

    def __init__(self, cfg: CaptureConfig, path: Path | None = None) -> None:
        self.cfg = cfg
        self.path = path
        self.live = path is None
        self.carried = path is None  # the D435i on the vehicle, not a recording of one
        self.has_depth = True
        self.name = "d435i" if path is None else path.stem
        self.fps = float(cfg.depth_fps if cfg.stream == "infrared" else cfg.color_fps)
        self.restarts = 0  # pipeline restarts after a stall
        self.resets = 0  # USB hardware resets
        self.last_gyro: tuple[float, float, float] | None = None  # rad/s, with enable_imu
        self._rs = _rs()
        self._backend: _Live | _Playback | None = None
        self._pending_depth: tuple[float, np.ndarray] | None = None  # depth that came alone
        self._t0_hw: float | None = None
        if path is not None:
            if not path.is_file():
                raise SourceError(f"{path}: no such RealSense recording")
            if path.suffix.lower() not in RECORDING_EXTS:
                raise SourceError(f"{path}: a RealSense recording ends in .db3 or .bag")
        self._start(first=True)

    # ------------------------------------------------------------------ pipeline

    def _config(self) -> Any:
        rs, c = self._rs, self.cfg
        config = rs.config()
        if c.serial:
            config.enable_device(c.serial)
        if c.stream == "infrared":  # the stereo module streams it with depth: same size and rate
            config.enable_stream(rs.stream.infrared, 1, c.depth_width, c.depth_height, rs.format.y8,
                                 c.depth_fps)
        else:
            config.enable_stream(rs.stream.color, c.color_width, c.color_height, rs.format.bgr8, c.color_fps)
        config.enable_stream(rs.stream.depth, c.depth_width, c.depth_height, rs.format.z16, c.depth_fps)
        if c.enable_imu:
            config.enable_stream(rs.stream.accel)
            config.enable_stream(rs.stream.gyro)
        return config

    def _start(self, first: bool = False) -> None:
        rs = self._rs
        if self.live and first and len(rs.context().query_devices()) == 0:
            raise SourceError("no RealSense camera found: is the D435i on a USB 3 port "
                              "(lsusb lists 8086:0b3a) and the udev rule installed?")
        try:
            backend: _Live | _Playback = (
                _Live(rs, self._config(), self.cfg.stream, self.cfg.depth_preset) if self.path is None
                else _Playback(rs, self.path, self.cfg.stream))
        except RuntimeError as exc:
            if first:
                what = str(self.path) if self.path else f"RealSense camera {self.cfg.serial}".strip()
                raise SourceError(f"{what}: cannot be started: {exc}") from None
            raise
        self._backend = backend
        self._pending_depth = None
        if self.path is not None:
            self.fps = float(backend.color.fps()) or self.fps
        self.camera = camera_model(backend.color, backend.depth, backend.depth_scale)
        # what the source delivers: the configured stream, or what a recording holds
        self.image_stream = "infrared" if backend.color.stream_type() == rs.stream.infrared else "color"
        if first:
            log.info("camera %s: %s %dx%d, depth %dx%d, depth scale %.4g m",
                     self.name, self.image_stream, self.camera.color.width, self.camera.color.height,
                     self.camera.depth.width, self.camera.depth.height, self.camera.depth_scale_m)

    def _stop(self) -> None:
        if self._backend is not None:
            try:
                self._backend.stop()
            except RuntimeError as exc:  # already stopped, or the device vanished
                log.debug("camera stop: %s", exc)
            self._backend = None

    def close(self) -> None:
        self._stop()

    @property
    def playback(self) -> Any:
        """The SDK's playback device of a recording (None for the live camera): its
        ``pause()``/``resume()`` stall the stream the way a flaky USB link does."""
        return self._backend.playback if isinstance(self._backend, _Playback) else None

    def _ended(self) -> bool:
        """A recording played to its end."""
        return self._backend is not None and self._backend.ended()

    # ------------------------------------------------------------------ frames

    def __len__(self) -> int:
        return 0  # unknown: a recording's duration is the recorder's wall time, not its frames

    def __iter__(self) -> Iterator[Frame]:
        index = 0
        stalled_since: float | None = None
        failures = 0
        backoff = self.cfg.backoff_initial_s
        timeout_ms = int(self.cfg.frame_timeout_ms)
        if self._backend is None:
            self._start()  # a second pass over a recording starts it again
            self._t0_hw = None
        try:
            while True:
                if self._backend is None:
                    ok, frames = False, None
                else:
                    try:
                        ok, frames = self._backend.wait(timeout_ms)
                    except RuntimeError as exc:  # device gone mid-wait
                        log.warning("camera: %s", exc)
                        ok, frames = False, None
                if ok:
                    frame = self._to_frame(frames, index + 1)
                    if frame is None:
                        continue  # an IMU-only frameset
                    if stalled_since is not None:
                        log.warning("camera: frames again after %.1f s", time.monotonic() - stalled_since)
                    stalled_since, failures, backoff = None, 0, self.cfg.backoff_initial_s
                    index += 1
                    yield frame
                    continue
                if self._ended():
                    return
                now = time.monotonic()
                if stalled_since is None:
                    stalled_since = now - timeout_ms / 1000.0
                    log.warning("camera: no frame for %d ms", timeout_ms)
                if now - stalled_since >= self.cfg.give_up_s:
                    raise CameraLost(f"camera {self.name}: no frame for {now - stalled_since:.1f} s "
                                     f"after {self.restarts} restarts and {self.resets} resets")
                self._recover(failures)
                failures += 1
                time.sleep(min(backoff, max(0.0, stalled_since + self.cfg.give_up_s - time.monotonic())))
                backoff = min(backoff * 2.0, self.cfg.backoff_max_s)
        finally:
            self._stop()

    def _recover(self, failures: int) -> None:
        """Restart the pipeline; after ``restarts_before_reset`` failures, reset the device."""
        self._stop()
        if self.live and failures >= self.cfg.restarts_before_reset:
            self.resets += 1
            log.warning("camera: USB hardware reset (attempt %d)", self.resets)
            try:
                for dev in self._rs.context().query_devices():
                    serial = dev.get_info(self._rs.camera_info.serial_number)
                    if not self.cfg.serial or serial == self.cfg.serial:
                        dev.hardware_reset()
            except RuntimeError as exc:
                log.warning("camera: hardware reset failed: %s", exc)
            return  # the device re-enumerates; the next attempt starts the pipeline
        self.restarts += 1
        log.warning("camera: restarting the pipeline (attempt %d)", self.restarts)
        try:
            self._start()
        except RuntimeError as exc:
            log.warning("camera: restart failed: %s", exc)

    def _to_frame(self, frames: Any, index: int) -> Frame | None:
        rs = self._rs
        if self.cfg.enable_imu:
            gyro = frames.first_or_default(rs.stream.gyro)
            if gyro:
                g = gyro.as_motion_frame().get_motion_data()
                self.last_gyro = (float(g.x), float(g.y), float(g.z))
        if frames.is_frameset():
            frames = frames.as_frameset()
        color = frames.first_or_default(_image_kind(rs, self.image_stream))
        depth = frames.first_or_default(rs.stream.depth)
        if not color:
            if depth:  # the syncer let it go alone: keep it for the colour frame that follows
                self._pending_depth = (float(depth.get_timestamp()),
                                       np.asanyarray(depth.get_data()).copy())
            return None
        arrived = time.monotonic()
        image = np.asanyarray(color.get_data()).copy()  # our own memory, not the SDK's
        if image.ndim == 3 and image.shape[2] == 3 and color.get_profile().format() == rs.format.rgb8:
            image = image[:, :, ::-1].copy()
        stamp_ms = float(color.get_timestamp())
        depth_mm = np.asanyarray(depth.get_data()).copy() if depth else None
        if depth_mm is None and self._pending_depth is not None:
            t_depth, pending = self._pending_depth
            if abs(t_depth - stamp_ms) <= 500.0 / self.fps:  # the same exposure, half a frame
                depth_mm = pending
        self._pending_depth = None
        if self.live:
            t = arrived
            if color.get_frame_timestamp_domain() == rs.timestamp_domain.global_time:
                transport = time.time() - stamp_ms / 1000.0  # host clock, so comparable
                if 0.0 <= transport <= _MAX_TRANSPORT_S:
                    t = arrived - transport
        else:
            if self._t0_hw is None:
                self._t0_hw = stamp_ms
            t = (stamp_ms - self._t0_hw) / 1000.0
        return Frame(index, t, image, depth_mm)


# --------------------------------------------------------------------------- writing


def write_realsense_recording(frames: Iterable[Frame], camera: CameraModel, fps: float,
                              path: Path, stream: str = "color") -> Path:
    """Write frames (colour BGR8, depth uint16) as a RealSense recording with pyrealsense2's
    own recorder and a software device carrying ``camera``'s calibration. With ``stream``
    "infrared" the images are grey (H x W) and go in as the left infrared imager (Y8,
    index 1), as a D435i streaming ``capture.stream: infrared`` records them.

    SDK 2.59 writes a ROS 2 ``.db3`` file whatever the name; give ``path`` that suffix.
    """
    if stream not in ("color", "infrared"):
        raise ValueError(f"stream {stream!r}: color or infrared")
    infrared = stream == "infrared"
    rs = _rs()
    path.parent.mkdir(parents=True, exist_ok=True)
    device = rs.software_device()
    depth_sensor = device.add_sensor("Depth")
    color_sensor = device.add_sensor("Infrared" if infrared else "Color")

    def video(kind: Any, uid: int, intr: Intrinsics, fmt: Any, bpp: int, index: int = 0) -> Any:
        vs = rs.video_stream()
        vs.type, vs.index, vs.uid = kind, index, uid
        vs.width, vs.height, vs.fps, vs.bpp, vs.fmt = intr.width, intr.height, int(round(fps)), bpp, fmt
        ri = rs.intrinsics()
        ri.width, ri.height, ri.fx, ri.fy, ri.ppx, ri.ppy = (
            intr.width, intr.height, intr.fx, intr.fy, intr.ppx, intr.ppy)
        ri.model, ri.coeffs = rs.distortion.none, [0.0] * 5
        vs.intrinsics = ri
        return vs

    d_profile = depth_sensor.add_video_stream(video(rs.stream.depth, 0, camera.depth, rs.format.z16, 2))
    c_bpp = 1 if infrared else 3
    c_profile = color_sensor.add_video_stream(
        video(rs.stream.infrared, 1, camera.color, rs.format.y8, 1, index=1) if infrared
        else video(rs.stream.color, 1, camera.color, rs.format.bgr8, 3))
    depth_sensor.add_read_only_option(rs.option.depth_units, camera.depth_scale_m)
    ext = rs.extrinsics()
    ext.rotation = np.asarray(camera.rotation, float).T.flatten().tolist()  # column-major
    ext.translation = np.asarray(camera.translation_m, float).tolist()
    d_profile.register_extrinsics_to(c_profile, ext)
    recorder = rs.recorder(str(path), device)
    sink = rs.frame_queue(64)
    for sensor, profile in ((depth_sensor, d_profile), (color_sensor, c_profile)):
        sensor.open(profile)
        sensor.start(sink)
    written = False
    try:
        for k, frame in enumerate(frames):
            stamp_ms = k * 1000.0 / fps
            color = np.ascontiguousarray(frame.color, np.uint8)
            if color.ndim != (2 if infrared else 3):
                raise SourceError(f"{path}: frame {frame.index} is {color.shape}, not a "
                                  f"{'grey (H x W)' if infrared else 'BGR (H x W x 3)'} {stream} image")
            if frame.depth is not None:
                depth = np.ascontiguousarray(frame.depth, np.uint16)
                _push(rs, depth_sensor, d_profile, depth, 2, stamp_ms, k)
            _push(rs, color_sensor, c_profile, color, c_bpp, stamp_ms, k)
            while sink.poll_for_frame():
                pass  # the recorder has them; keep the queue from filling
        written = True
    finally:
        for sensor in (depth_sensor, color_sensor):
            sensor.stop()
            sensor.close()
        del recorder  # closes the file
        if not written:
            path.unlink(missing_ok=True)  # no half-written recording left behind
    if not path.is_file() or path.stat().st_size == 0:
        raise SourceError(f"{path}: the RealSense recorder wrote nothing")
    return path


def _push(rs: Any, sensor: Any, profile: Any, pixels: np.ndarray, bpp: int, stamp_ms: float,
          number: int) -> None:
    f = rs.software_video_frame()
    f.pixels = pixels
    f.stride = pixels.shape[1] * bpp
    f.bpp = bpp
    f.timestamp = stamp_ms
    f.domain = rs.timestamp_domain.hardware_clock
    f.frame_number = number
    f.profile = profile.as_video_stream_profile()
    sensor.on_video_frame(f)


def is_realsense_recording(path: Path) -> bool:
    return path.suffix.lower() in RECORDING_EXTS

