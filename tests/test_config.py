from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from app.config import Config, config_from_mapping, load_config, to_yaml
from app.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]


def test_repository_config_equals_built_in_defaults() -> None:
    assert load_config(ROOT / "config.yaml") == Config()


def test_yaml_dump_round_trips() -> None:
    cfg = config_from_mapping({"perception": {"detection": {"threshold": 30}}})
    p = ROOT / "tests" / "_tmp_roundtrip.yaml"
    try:
        p.write_text(to_yaml(cfg))
        assert load_config(p) == cfg
        assert load_config(p).perception.detection.threshold == 30
    finally:
        p.unlink(missing_ok=True)


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"perception": {"recognition": {"area_px": -3}}},
         "perception.recognition.area_px = -3: must be > 0"),
        ({"perception": {"detection": {"ransac_reproj_px": -1}}},
         "perception.detection.ransac_reproj_px = -1: must be > 0"),
        ({"perception": {"detection": {"median_ksize": 4}}},
         "perception.detection.median_ksize = 4: must be odd"),
        ({"perception": {"detection": {"window_count": 5}}},
         "perception.detection.window_count = 5: must be one of 4, 6, 8"),
        ({"perception": {"detection": {"combine": "max"}}},
         "perception.detection.combine = 'max': must be one of mean, min"),
        ({"perception": {"tracking": {"noise_frames": 2.5}}},
         "perception.tracking.noise_frames = 2.5: must be a whole number"),
        ({"perception": {"tracking": {"noise_frames": True}}},
         "perception.tracking.noise_frames = True: must be a whole number"),
        ({"perception": {"tracking": {"predict_with_homography": "yes"}}},
         "perception.tracking.predict_with_homography = 'yes': must be true or false"),
        ({"perception": {"tracking": {"lost_s": ".5"}}},
         "perception.tracking.lost_s = '.5': must be a number"),
        ({"perception": {"detection": "fast"}},
         "perception.detection = 'fast': must be a section (a mapping)"),
        ({"flight": {"takeover_modes": ["position", "acro"]}},
         "flight.takeover_modes = ['position', 'acro']: 'acro' is not one of position, hold, "
         "mission, altitude, manual, offboard, return, land, takeoff, other"),
        ({"flight": {"takeover_modes": "position"}},
         "flight.takeover_modes = 'position': must be a list of strings"),
        ({"flight": {"mode": "test"}}, "flight.mode = 'test': must be one of guard, shadow, test-flight"),
        ({"capture": {"stream": "thermal"}}, "capture.stream = 'thermal': must be one of color, infrared"),
        ({"capture": {"stream": "infrared"}, "perception": {"detection": {"chroma_gain": 0.5}}},
         "perception.detection.chroma_gain = 0.5: the infrared imager (capture.stream: infrared) is "
         "monochrome; set it to 0"),
        ({"perception": {"detection": {"near_noise_per_m": 0.005}}},
         "perception.detection.near_noise_per_m = 0.005: must equal decision.depth_rms_per_m2 (0.0036), "
         "the same stereo error"),
        ({"perception": {"detection": {"near_sigmas": -1}}},
         "perception.detection.near_sigmas = -1: must be >= 0"),
        ({"perception": {"detection": {"near_min_size_m": 0.3}}},
         "perception.detection.near_min_size_m = 0.3: must be <= decision.object_diameter_min_m (0.15): "
         "the depth path would drop objects the decision takes as plausible"),
        ({"decision": {"min_depth_cover": 1.5}}, "decision.min_depth_cover = 1.5: must be <= 1"),
        ({"decision": {"response_speed_mps": 4.0, "evade_speed_mps": 3.5}},
         "decision.response_speed_mps = 4: must be <= evade_speed_mps (3.5): the trigger would count "
         "on a speed the evasion is not flown at"),
        ({"perception": {"detection": {"min_points_per_window": 30}}},
         "perception.detection.min_points_per_window = 30: must be <= max_points_per_window (15)"),
        ({"perception": {"detection": {"lk_pyramid_levels": 3}}},
         "perception.detection.lk_pyramid_levels = 3: a 118 px crop (window_px + lk_search_px) holds "
         "at most 2 levels larger than the 21 px LK window; lower it, or raise lk_search_px to 99"),
    ],
)
def test_bad_values_name_key_value_and_rule(data: dict, message: str) -> None:
    with pytest.raises(ConfigError) as exc:
        config_from_mapping(data)
    assert str(exc.value) == message


def test_unknown_key_is_named_with_the_known_ones() -> None:
    with pytest.raises(ConfigError) as exc:
        config_from_mapping({"perception": {"tracking": {"dist_pix": 5}}})
    msg = str(exc.value)
    assert msg.startswith("perception.tracking.dist_pix: unknown key (known here: ")
    assert "dist_px" in msg


def test_a_renamed_key_says_what_replaced_it() -> None:
    with pytest.raises(ConfigError) as exc:
        config_from_mapping({"decision": {"image_confirm_frames": 3}})
    assert str(exc.value).startswith("decision.image_confirm_frames: no longer a setting: use "
                                     "decision.image_confirm_s")


def test_integers_are_accepted_for_floats() -> None:
    cfg = config_from_mapping({"perception": {"tracking": {"lost_s": 2}}})
    assert cfg.perception.tracking.lost_s == 2.0
    assert isinstance(cfg.perception.tracking.lost_s, float)


def test_missing_and_malformed_files(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="does not exist"):
        load_config(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("perception:\n  detection: [1, 2\n")
    with pytest.raises(ConfigError, match="is not valid YAML at line"):
        load_config(bad)
    empty = tmp_path / "empty.yaml"
    empty.write_text("")
    assert load_config(empty) == Config()


def test_cli_stops_with_exit_2_and_no_traceback(tmp_path: Path) -> None:
    bad = tmp_path / "c.yaml"
    bad.write_text("perception:\n  recognition:\n    area_px: -3\n")
    proc = subprocess.run(
        [sys.executable, "-m", "app.cli", "config", "--config", str(bad)],
        capture_output=True, text=True, timeout=60,
    )
    assert proc.returncode == 2
    assert "perception.recognition.area_px = -3: must be > 0" in proc.stderr
    assert "Traceback" not in proc.stderr
