"""Configuration: ``config.yaml`` loaded into frozen dataclasses and validated at start.

Every tunable of every stage lives here, with its unit in the key name or its doc.
The dataclass defaults *are* the shipped configuration: ``config.yaml`` at the
repository root spells them out, and a test keeps the two identical.

Validation happens once, at load time, and stops the program with a message that
names the key, the value and the rule, e.g.::

    perception.recognition.area_px = -3: must be > 0
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar, get_type_hints

import yaml

from app.errors import ConfigError

T = TypeVar("T")


def param(
    default: Any,
    doc: str,
    *,
    gt: float | None = None,
    ge: float | None = None,
    lt: float | None = None,
    le: float | None = None,
    choices: tuple[Any, ...] | None = None,
    odd: bool = False,
) -> Any:
    """A configuration field with its documentation and validation rules."""
    meta = {"doc": doc, "gt": gt, "ge": ge, "lt": lt, "le": le, "choices": choices, "odd": odd}
    return field(default=default, metadata=meta)


# --------------------------------------------------------------------------- perception


@dataclass(frozen=True)
class DetectionConfig:
    """Stage 1 — camera-motion compensation and frame differencing (paper Alg. 1, §3-F)."""

    window_px: int = param(70, "side of each square border window for LK flow, px (paper: 70)", ge=16)
    window_count: int = param(
        6,
        "border windows: 4 = corners, 6 = + top/bottom middles (paper), 8 = + left/right middles",
        choices=(4, 6, 8),
    )
    min_points_per_window: int = param(
        12, "n of Alg. 1: re-seed a window when fewer tracked points remain", ge=1
    )
    max_points_per_window: int = param(25, "points seeded per window at most", ge=1)
    feature_quality: float = param(
        0.01, "goodFeaturesToTrack quality level, relative to the window's best", gt=0, lt=1
    )
    feature_min_distance_px: float = param(5.0, "min spacing of seeded points, px", gt=0)
    lk_window_px: int = param(21, "Lucas-Kanade search window side, px", ge=5, odd=True)
    lk_pyramid_levels: int = param(3, "Lucas-Kanade pyramid levels above the base", ge=0, le=6)
    lk_search_px: int = param(
        48, "how far beyond its window a point may move between frames, px", ge=8
    )
    lk_max_iterations: int = param(20, "Lucas-Kanade iterations per level", ge=1)
    lk_min_eigen: float = param(
        1e-3, "drop LK points whose gradient matrix is weaker (featureless sky)", gt=0
    )
    min_texture: float = param(
        1e-3,
        "a window whose strongest corner (min eigenvalue) is weaker is featureless sky: not seeded",
        gt=0,
    )
    ransac_reproj_px: float = param(2.0, "RANSAC inlier reprojection error, px", gt=0)
    min_inliers: int = param(
        10, "fewer RANSAC inliers than this: the frame is skipped (tracker coasts)", ge=4
    )
    combine: str = param(
        "mean",
        "how the two compensated differences are merged: mean (paper) or min (no ghosts)",
        choices=("mean", "min"),
    )
    median_ksize: int = param(5, "median filter aperture, px", ge=1, le=255, odd=True)
    dilate_ksize: int = param(5, "dilation kernel side, px (1 = none)", ge=1, odd=True)
    threshold: int = param(18, "binarisation threshold on the filtered difference, grey levels", ge=1, le=254)
    max_mask_frac: float = param(
        0.15,
        "a mask covering more of the frame than this means a bad warp: the frame is skipped (0-1)",
        gt=0, le=1,
    )
    border_px: int = param(
        4, "ignore this band along the frame edges, px", ge=0
    )
    object_margin_px: int = param(
        10, "grow tracked objects' boxes by this before masking border windows, px", ge=0
    )
    scene_cut_correlation: float = param(
        0.5,
        "grey histogram correlation of consecutive frames below this is a scene cut (-1 to 1)",
        ge=-1,
        le=1,
    )


@dataclass(frozen=True)
class RecognitionConfig:
    """Stage 2 — area-weighted DBSCAN over the blobs of the motion mask (paper Alg. 2, §4-A)."""

    min_blob_px: int = param(3, "blobs smaller than this are ignored outright, px²", ge=1)
    area_px: int = param(
        40, "a cluster must reach this summed blob area; a blob this big stands alone, px²", gt=0
    )
    dist_px: float = param(
        20.0, "blobs whose boxes are closer than this join one cluster (distThresh), px", gt=0
    )
    max_blobs: int = param(
        400, "keep only the largest blobs when a noisy mask has more than this", ge=1
    )
    max_cluster_frac: float = param(
        0.25, "a cluster covering more of the frame than this is not an object (0-1)", gt=0, le=1
    )


@dataclass(frozen=True)
class TrackingConfig:
    """Stage 3 — association, candidate/confirmed/lost life cycle, Kalman filter (Alg. 3, §4-B/C)."""

    dist_px: float = param(
        50.0, "a cluster farther than this from a track's prediction is not it (distThresh), px", gt=0
    )
    noise_frames: int = param(
        3, "a candidate seen in more than this many frames becomes confirmed (noiseThresh)", ge=0
    )
    candidate_max_misses: int = param(
        2, "a candidate missed this many frames in a row is dropped as noise", ge=1
    )
    lost_s: float = param(0.5, "a confirmed track unmatched this long is deleted, s", gt=0)
    measurement_std_px: float = param(3.0, "Kalman measurement noise (std), px", gt=0)
    process_accel_std_px: float = param(
        2.0, "Kalman process noise: white acceleration (std), px/frame²", gt=0
    )
    predict_with_homography: bool = param(
        True, "move track predictions through the frame's homography before association"
    )


@dataclass(frozen=True)
class PerceptionConfig:
    """Perception: stages 1-3 of the paper."""

    detection: DetectionConfig = field(default_factory=DetectionConfig)
    recognition: RecognitionConfig = field(default_factory=RecognitionConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)


@dataclass(frozen=True)
class Config:
    """midair configuration."""

    perception: PerceptionConfig = field(default_factory=PerceptionConfig)


# --------------------------------------------------------------------------- loading


def load_config(path: str | Path | None = None) -> Config:
    """Load and validate a YAML configuration; ``None`` gives the built-in defaults.

    Keys left out of the file keep their defaults. Raises :class:`ConfigError` naming
    the offending key for an unknown key, a wrong type or an out-of-range value.
    """
    if path is None:
        return Config()
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"config file {p} does not exist") from None
    except OSError as exc:
        raise ConfigError(f"config file {p} cannot be read: {exc.strerror}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        raise ConfigError(f"config file {p} is not valid YAML{where}") from None
    if data is None:
        data = {}
    return config_from_mapping(data, source=str(p))


def config_from_mapping(data: Any, source: str = "config") -> Config:
    """Build a validated :class:`Config` from plain data (as parsed from YAML)."""
    if not isinstance(data, Mapping):
        raise ConfigError(f"{source}: the top level must be a mapping of sections")
    cfg = _build(Config, data, prefix="")
    check_consistency(cfg)
    return cfg


def _build(cls: type[T], data: Mapping[str, Any], prefix: str) -> T:
    hints = get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    for key in data:
        if key not in fields:
            known = ", ".join(sorted(fields))
            raise ConfigError(f"{prefix}{key}: unknown key (known here: {known})")
    kwargs: dict[str, Any] = {}
    for name, f in fields.items():
        if name not in data:
            continue
        key = f"{prefix}{name}"
        value = data[name]
        typ = hints[name]
        if dataclasses.is_dataclass(typ):
            if not isinstance(value, Mapping):
                raise ConfigError(f"{key} = {value!r}: must be a section (a mapping)")
            kwargs[name] = _build(typ, value, prefix=f"{key}.")  # type: ignore[arg-type]
        else:
            kwargs[name] = _check(key, value, typ, f.metadata)
    return cls(**kwargs)


def _check(key: str, value: Any, typ: Any, meta: Mapping[str, Any]) -> Any:
    shown = f"{key} = {value!r}"
    if typ is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{shown}: must be true or false")
        return value
    if typ is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{shown}: must be a whole number")
    elif typ is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{shown}: must be a number")
        value = float(value)
        if not math.isfinite(value):
            raise ConfigError(f"{shown}: must be finite")
    elif typ is str:
        if not isinstance(value, str):
            raise ConfigError(f"{shown}: must be a string")
    rules = (("gt", ">", lambda v, b: v > b), ("ge", ">=", lambda v, b: v >= b),
             ("lt", "<", lambda v, b: v < b), ("le", "<=", lambda v, b: v <= b))
    for name, sym, ok in rules:
        bound = meta.get(name)
        if bound is not None and not ok(value, bound):
            raise ConfigError(f"{shown}: must be {sym} {bound:g}")
    choices = meta.get("choices")
    if choices is not None and value not in choices:
        raise ConfigError(f"{shown}: must be one of {', '.join(map(str, choices))}")
    if meta.get("odd") and value % 2 != 1:
        raise ConfigError(f"{shown}: must be odd")
    return value


def check_consistency(cfg: Config) -> None:
    """Rules that tie several keys together."""
    d = cfg.perception.detection
    if d.min_points_per_window > d.max_points_per_window:
        raise ConfigError(
            f"perception.detection.min_points_per_window = {d.min_points_per_window}: "
            f"must be <= max_points_per_window ({d.max_points_per_window})"
        )


def describe(cfg: Any = None, prefix: str = "") -> list[tuple[str, Any, str]]:
    """Flatten a config into ``(key, value, doc)`` rows, for ``midair config``."""
    cfg = Config() if cfg is None else cfg
    rows: list[tuple[str, Any, str]] = []
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if dataclasses.is_dataclass(value):
            rows.extend(describe(value, prefix=f"{prefix}{f.name}."))
        else:
            rows.append((f"{prefix}{f.name}", value, f.metadata.get("doc", "")))
    return rows


def to_yaml(cfg: Any = None) -> str:
    """The configuration as commented YAML that :func:`load_config` reads back."""
    cfg = Config() if cfg is None else cfg
    lines: list[str] = []

    def emit(obj: Any, indent: int) -> None:
        for f in dataclasses.fields(obj):
            value = getattr(obj, f.name)
            pad = "  " * indent
            if dataclasses.is_dataclass(value):
                doc = (type(value).__doc__ or "").strip().splitlines()
                if doc:
                    lines.append(f"{pad}# {doc[0]}")
                lines.append(f"{pad}{f.name}:")
                emit(value, indent + 1)
            else:
                text = yaml.safe_dump(value, default_flow_style=True).strip()
                text = text.removesuffix("...").strip()
                lines.append(f"{pad}{f.name}: {text}  # {f.metadata.get('doc', '')}")

    emit(cfg, 0)
    return "\n".join(lines) + "\n"

