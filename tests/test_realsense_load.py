"""What the RealSense source says when the SDK is missing or cannot load (no SDK needed)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

_OPEN = ("from app.errors import SourceError\n"
         "from hardware.realsense import RealSenseSource\n"
         "from app.config import CaptureConfig\n"
         "try:\n    RealSenseSource(CaptureConfig())\nexcept SourceError as e:\n    print(e)\n")


def _run(code: str, path: Path | None = None) -> subprocess.CompletedProcess[str]:
    env = None
    if path is not None:
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(path), *sys.path])}
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=60, env=env)


def test_the_sdk_is_only_needed_for_realsense_sources() -> None:
    code = ("import sys; sys.modules['pyrealsense2'] = None\n"
            "from app.runtime.sources import open_source\n"
            "import app.runtime.process, app.cli\n" + _OPEN)
    out = _run(code)
    assert out.returncode == 0, out.stderr
    assert "needs pyrealsense2" in out.stdout


def _fake_sdk(root: Path, message: str) -> Path:
    """A pyrealsense2 under ``root`` whose import fails with ``message``, as an installed SDK
    does when the loader cannot find what it links against."""
    (root / "pyrealsense2").mkdir()
    (root / "pyrealsense2" / "__init__.py").write_text(f"raise ImportError({message!r})\n")
    return root


def test_an_sdk_that_cannot_load_names_the_missing_library(tmp_path: Path) -> None:
    out = _run(_OPEN, _fake_sdk(tmp_path, "libusb-1.0.so.0: cannot open shared object file: "
                                          "No such file or directory"))
    assert out.returncode == 0, out.stderr
    assert "pyrealsense2 is installed but cannot load: libusb-1.0.so.0" in out.stdout
    assert "apt-get install libusb-1.0-0" in out.stdout
    assert "needs pyrealsense2" not in out.stdout


def test_an_sdk_that_cannot_load_for_another_reason_gets_no_libusb_advice(tmp_path: Path) -> None:
    out = _run(_OPEN, _fake_sdk(tmp_path, "numpy.core.multiarray failed to import"))
    assert out.returncode == 0, out.stderr
    assert "pyrealsense2 is installed but cannot load: numpy.core.multiarray failed to import" in out.stdout
    assert "libusb" not in out.stdout
