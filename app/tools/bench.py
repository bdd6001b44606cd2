"""``midair bench``: time stages 1–3 on 640×480 frames with one OpenCV thread.

Runs the border-window detector and, in the same run on the same frames, the full-frame
variant (corners tracked over the whole frame), the two taking turns every 30 frames, and
prints per-stage median/p95 and the ratio. ``--soak N`` also replays N frames and reports
resident memory along the way.
"""

from __future__ import annotations

import math
import os
import resource
import time
from typing import cast

import cv2
import numpy as np

from app.camera import Intrinsics
from app.config import Config
from app.perception import near
from app.perception.frames import Frame
from app.perception.pipeline import Perception, PerceptionResult
from app.sim.synthetic import SyntheticScene, render

STAGES = ("detection_ms", "recognition_ms", "tracking_ms", "total_ms")
# The variants take turns every this many frames (about 0.1 + 0.3 s here): the development VM's
# speed wanders by up to 25 % within seconds, and turns this short put both variants under the
# same speed. Measured: with whole-clip turns (300 frames) the ratio of six runs spread over
# 2.75-3.10x.
CHUNK_FRAMES = 30


def _frames(n: int, seed: int, width: int = 640) -> list[Frame]:
    scene = SyntheticScene(width=width, height=480, frames=n, seed=seed)
    return [f for f, _ in render(scene)]


def time_interleaved(frames: list[Frame], cfg: Config, chunk: int = CHUNK_FRAMES
                     ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], list[float]]:
    """Both variants over the clip, taking turns every ``chunk`` frames (each keeps its own
    state across the turns); their stage times, and the full-frame / windows ratio of the
    median total in each turn."""
    win = Perception(cfg.perception)
    full = Perception(cfg.perception, full_frame_features=True)
    out_w: dict[str, list[float]] = {k: [] for k in STAGES}
    out_f: dict[str, list[float]] = {k: [] for k in STAGES}
    ratios: list[float] = []
    for start in range(0, len(frames), chunk):
        part = frames[start:start + chunk]
        n_w, n_f = len(out_w["total_ms"]), len(out_f["total_ms"])
        for f in part:
            _record(win.push(f), out_w)
        for f in part:
            _record(full.push(f), out_f)
        tw, tf = out_w["total_ms"][n_w:], out_f["total_ms"][n_f:]
        if tw and tf:
            ratios.append(float(np.median(tf) / np.median(tw)))
    return ({k: np.asarray(v) for k, v in out_w.items()}, {k: np.asarray(v) for k, v in out_f.items()},
            ratios)


def _record(r: PerceptionResult | None, out: dict[str, list[float]]) -> None:
    if r is None or r.status in ("warmup", "scene_cut"):
        return
    for k in STAGES:
        out[k].append(r.timings_ms[k])


def _pin_to_one_core() -> None:
    """Run on one core (the last): fewer migrations, steadier timings."""
    try:
        cores = sorted(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {cores[-1]})
    except (AttributeError, OSError):  # not Linux: time as is
        pass


def rss_mib() -> float:
    """Current resident set size, MiB (Linux /proc; falls back to the peak)."""
    try:
        with open("/proc/self/statm") as fh:
            pages = int(fh.read().split()[1])
        return pages * resource.getpagesize() / 2**20
    except OSError:
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def soak(frames: list[Frame], cfg: Config, total: int) -> list[tuple[int, float]]:
    """Replay ``total`` frames (the clip looped, timestamps continuing); RSS at 10 points."""
    p = Perception(cfg.perception)
    marks: list[tuple[int, float]] = []
    step = max(1, total // 10)
    dt = frames[1].t_s - frames[0].t_s
    for i in range(total):
        src = frames[i % len(frames)]
        p.push(Frame(i + 1, i * dt, src.color, src.depth))
        if (i + 1) % step == 0:
            marks.append((i + 1, rss_mib()))
    return marks


def warm_up(clip: list[Frame], cfg: Config, seconds: float) -> None:
    """Run both variants over the clip (at least once) until ``seconds`` have passed.

    On the development VM the first seconds of a run are up to 50 % slower than the rest
    (measured: per-repeat medians 4.2, 4.3, 3.6, then 2.8-3.0 ms for the same code), so a
    short warm-up made the first timed repeat an outlier.
    """
    t_end = time.perf_counter() + seconds
    while True:
        time_interleaved(clip, cfg)
        if time.perf_counter() >= t_end:
            return


def run_bench(cfg: Config, frames: int = 300, repeats: int = 5, seed: int = 1,
              soak_frames: int = 0, warmup_s: float = 3.0, width: int = 640) -> dict[str, object]:
    cv2.setNumThreads(1)
    _pin_to_one_core()
    clip = _frames(frames, seed, width)
    # warm-up: first calls allocate, caches fill, and the machine settles (see warm_up)
    warm_up(clip, cfg, warmup_s)
    # Interleaved in short turns, so that both variants run at the same speed of a shared machine.
    runs_w: list[dict[str, np.ndarray]] = []
    runs_f: list[dict[str, np.ndarray]] = []
    turn_ratios: list[float] = []
    for _ in range(repeats):
        w, f, ratios = time_interleaved(clip, cfg)
        runs_w.append(w)
        runs_f.append(f)
        turn_ratios += ratios
    win = {k: np.concatenate([r[k] for r in runs_w]) for k in STAGES}
    full = {k: np.concatenate([r[k] for r in runs_f]) for k in STAGES}
    result: dict[str, object] = {
        "frame_size": f"{width}x480",
        "opencv_threads": cv2.getNumThreads(),
        "frames_timed": int(len(win["total_ms"])),
        "windows": {k.removesuffix("_ms"): _stats(v) for k, v in win.items()},
        "full_frame": {k.removesuffix("_ms"): _stats(v) for k, v in full.items()},
        "median_ms_per_frame": round(float(np.median(win["total_ms"])), 3),
        "p95_ms_per_frame": round(float(np.percentile(win["total_ms"], 95)), 3),
        "baseline_median_ms_per_frame": round(float(np.median(full["total_ms"])), 3),
        # the spread between repeats shows how much the machine itself varied during the run
        "repeat_medians_ms": [round(float(np.median(r["total_ms"])), 3) for r in runs_w],
        "baseline_repeat_medians_ms": [round(float(np.median(r["total_ms"])), 3) for r in runs_f],
        "warmup_s": warmup_s,
        "turn_frames": CHUNK_FRAMES,
        # full-frame / windows ratio of the median total within each turn: its spread
        "turn_speedup_p10_p50_p90": [round(float(np.percentile(turn_ratios, q)), 2) for q in (10, 50, 90)],
    }
    lens = SyntheticScene(width=width, height=480).camera().depth  # the lens the clip's depth was drawn in
    result["depth_path"] = _stats(time_near(clip, cfg, lens))
    result["speedup_vs_full_frame"] = round(
        float(result["baseline_median_ms_per_frame"]) / float(result["median_ms_per_frame"]), 2  # type: ignore[arg-type]
    )
    if soak_frames:
        marks = soak(clip, cfg, soak_frames)
        first = marks[0][1]
        result["soak"] = {
            "frames": soak_frames,
            "rss_mib": [[n, round(m, 1)] for n, m in marks],
            "growth_mib_after_first_tenth": round(marks[-1][1] - first, 1),
        }
    return result


def time_near(frames: list[Frame], cfg: Config, lens: Intrinsics, repeats: int = 3) -> np.ndarray:
    """The depth path's time per frame (app.perception.near, ms) on the clip's depth: it runs
    only where depth is registered to the image (the infrared imager), so it is not in the
    stages' figures; timed at ``near_sigmas`` 5 when the configuration has it off, with the
    patch floor of the clip's depth ``lens``."""
    d = cfg.perception.detection
    sigmas = d.near_sigmas or 5.0
    floor = near.patch_floor_px(lens.fx, lens.fy, d.near_min_size_m)
    times = []
    for _ in range(repeats):
        before: near.Patches | None = None
        for f in frames:
            if f.depth is None:
                continue
            t0 = time.perf_counter()
            marks = near.near_mask(f.depth, 0.001, sigmas, d.near_noise_per_m, d.near_window_px,
                                   near.MIN_M, near.MAX_M, floor)
            _, before = near.grow_persistent(marks, f.depth, 0.001, before, near.REACH_PX, d.dilate_ksize)
            times.append((time.perf_counter() - t0) * 1e3)
    return np.array(times) if times else np.array([math.nan])


def _stats(v: np.ndarray) -> dict[str, float]:
    return {"median_ms": round(float(np.median(v)), 3), "p95_ms": round(float(np.percentile(v, 95)), 3)}


def format_bench(r: dict[str, object]) -> str:
    win = cast(dict[str, dict[str, float]], r["windows"])
    full = cast(dict[str, dict[str, float]], r["full_frame"])
    lines = [
        f"stages 1-3 on {r['frame_size']} synthetic frames, {r['opencv_threads']} OpenCV thread, "
        f"{r['frames_timed']} frames per variant",
        f"{'stage':<12} {'windows median/p95 ms':>24} {'full-frame median/p95 ms':>28}",
    ]
    for k in ("detection", "recognition", "tracking", "total"):
        a, b = win[k], full[k]
        lines.append(f"{k:<12} {a['median_ms']:>11.3f} / {a['p95_ms']:<10.3f} "
                     f"{b['median_ms']:>13.3f} / {b['p95_ms']:<10.3f}")
    near_r = cast(dict[str, float], r["depth_path"])
    lines.append(f"{'depth path':<12} {near_r['median_ms']:>11.3f} / {near_r['p95_ms']:<10.3f} "
                 "(app.perception.near: only where depth is registered to the image; not in the total)")
    lines.append(f"full-frame / windows (median total): {r['speedup_vs_full_frame']}x")
    lines.append(f"median total per repeat, ms: windows {r['repeat_medians_ms']}, "
                 f"full-frame {r['baseline_repeat_medians_ms']}")
    lines.append(f"ratio within each turn of {r['turn_frames']} frames, p10/p50/p90: "
                 f"{r['turn_speedup_p10_p50_p90']}")
    soak_r = r.get("soak")
    if isinstance(soak_r, dict):
        lines.append(f"soak {soak_r['frames']} frames: RSS MiB at checkpoints "
                     f"{[m for _, m in soak_r['rss_mib']]}; growth after the first tenth "
                     f"{soak_r['growth_mib_after_first_tenth']} MiB")
    return "\n".join(lines)
