"""The ``midair`` command line.

Exit codes: 0 success; 1 an unexpected error (a bug: traceback shown); 2 a bad command
line or configuration; 3 unusable input data; 4 the autopilot cannot be reached; 130
interrupted.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from app import __version__
from app.config import Config, explain, load_config, to_yaml
from app.errors import UsageError, UserError

if TYPE_CHECKING:
    from app.sim.simulate import Encounter, EncounterResult

log = logging.getLogger("midair")


def _seed(text: str) -> int:
    """A random seed as numpy takes it: a whole number >= 0."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"{value}: must be 0 or more")
    return value


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="midair",
        description="See a flying object coming with the forward camera and get out of its way.",
    )
    p.add_argument("--version", action="version", version=f"midair {__version__}")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def with_config(sp: argparse.ArgumentParser) -> None:
        sp.add_argument("--config", type=Path, help="YAML configuration (default: built-in, "
                        "identical to the repository's config.yaml)")

    d = sub.add_parser("demo", help="generate a synthetic flight, replay it, write the annotated video")
    d.add_argument("--out", type=Path, default=Path("out/demo"), help="output folder (default: out/demo)")
    d.add_argument("--frames", type=int, default=240, help="length of the synthetic flight, frames")
    d.add_argument("--seed", type=_seed, default=1, help="random seed, a whole number >= 0")
    d.add_argument("--ground-flights", type=int, metavar="N",
                   help="instead: write N synthetic flights over textured ground with truth (MP4 + "
                   "frame,id,x,y,w,h, 10 s each, app.sim.groundset) to --out and score perception "
                   "on them as `midair evaluate` does")
    d.add_argument("--depth", action="store_true", help="with --ground-flights: through the infrared "
                   "imager, each flight a recording folder with its depth (color.mp4, depth/, "
                   "intrinsics.json), so that perception runs with depth")
    d.add_argument("--workers", type=int, default=None, help="with --ground-flights: processes "
                   "that score the flights (default: one per core)")
    with_config(d)

    r = sub.add_parser("replay", help="run perception over a video, image folder or recording folder")
    r.add_argument("source", type=Path, help="video file, folder of images, or recording folder")
    r.add_argument("--out", type=Path, required=True, help="output folder")
    r.add_argument("--no-video", action="store_true", help="do not write annotated.mp4")
    r.add_argument("--fps", type=float, help="frame rate of an image folder (default 30)")
    r.add_argument("--altitude", type=float, metavar="M",
                   help="altitude above home assumed for the decision, m (default: unknown, "
                   "so no downward escape)")
    with_config(r)

    e = sub.add_parser("evaluate", help="score replay against ground truth (one clip or a data folder)")
    e.add_argument("path", type=Path, help="a clip (video or image folder) or a folder of clips, "
                   "e.g. ../shared/data")
    e.add_argument("--gt", type=Path, help="ground truth CSV (frame,id,x,y,w,h) for a single clip")
    e.add_argument("--out", type=Path, help="also write evaluation.md and evaluation.csv here")
    e.add_argument("--only", help="comma-separated substrings: keep clips whose name or group has one")
    e.add_argument("--workers", type=int, help="processes (default: all cores)")
    with_config(e)

    f = sub.add_parser("fit-confidence",
                       help="fit the track confidence's weights on clips with ground truth, "
                       "with a leave-one-clip-out estimate")
    f.add_argument("path", type=Path, help="a folder of clips, e.g. ../shared/data")
    f.add_argument("--train", default="halmstad",
                   help="comma-separated substrings: clips whose name or group has one are used "
                   "(default: halmstad; DAVIS labels only one object per sequence)")
    f.add_argument("--min-confidence", type=float, default=None, metavar="P",
                   help="threshold written with the weights (default: the config's, or 0.3 if 0)")
    f.add_argument("--features", metavar="NAMES",
                   help="comma-separated features to fit, the others' weights 0 (default: the "
                   "shipped nine, all but contrast and core)")
    f.add_argument("--score-on", type=Path, action="append", default=[], metavar="PATH",
                   help="also score, with the weights fitted on the training clips, every clip of "
                   "this folder that was not trained on (leave-one-dataset-out); repeatable")
    f.add_argument("--out", type=Path, help="write the perception.confidence section here (YAML)")
    f.add_argument("--workers", type=int, help="processes (default: all cores)")
    with_config(f)

    b = sub.add_parser("bench", help="time stages 1-3 on 640x480 frames, windows vs full-frame features")
    b.add_argument("--frames", type=int, default=300)
    b.add_argument("--repeats", type=int, default=5, help="interleaved runs of each variant")
    b.add_argument("--width", type=int, default=640, choices=(640, 848),
                   help="frame width at 480 rows: 640 (55 degrees) or 848 (the D435i's full 69)")
    b.add_argument("--warmup", type=float, default=3.0, metavar="S",
                   help="run both variants this long before timing, s")
    b.add_argument("--soak", type=int, default=0, metavar="N",
                   help="also replay N frames and report memory (e.g. 10000)")
    b.add_argument("--json", action="store_true", help="last line: one JSON object")
    b.add_argument("--link", action="store_true",
                   help="instead: the offboard path against the simulated PX4 over UDP "
                   "(setpoint rate, decision-to-wire latency)")
    b.add_argument("--fly", action="store_true",
                   help="instead: the whole flight process (capture, perception thread, offboard, "
                   "flight record) on a generated recording against the simulated PX4; "
                   "per-frame latency capture -> setpoint")
    b.add_argument("--fps", type=float, default=60.0, help="with --fly: the recording's frame rate")
    b.add_argument("--seconds", type=float, default=10.0, help="with --link or --fly: how long, s")
    with_config(b)

    f = sub.add_parser("fly", help="the flight process: camera -> perception -> PX4 offboard")
    f.add_argument("--camera", help="realsense (the D435i); synthetic (balls thrown at the "
                   "vehicle now and then, rendered live, until stopped); or a recording folder, "
                   "video or RealSense recording (.db3/.bag) played as the camera (default: "
                   "capture.camera)")
    f.add_argument("--seconds", type=float, metavar="S",
                   help="stop after S seconds (default: when stopped, or the recording ends)")
    f.add_argument("--connection", help="MAVSDK URL (default: flight.connection of the config)")
    f.add_argument("--mode", choices=("guard", "shadow", "test-flight"),
                   help="override flight.mode")
    f.add_argument("--record", type=Path, metavar="DIR",
                   help="write the flight record under DIR (default: record.dir)")
    f.add_argument("--no-record", action="store_true", help="write no flight record")
    with_config(f)

    m = sub.add_parser("simulate", help="closed-loop encounters: a rendered world as the camera, the "
                       "flight process, the simulated PX4; one encounter or a campaign")
    m.add_argument("--out", type=Path, default=Path("out/simulate"), help="output folder")
    m.add_argument("--seed", type=_seed, default=1, help="random seed, a whole number >= 0")
    m.add_argument("--campaign", type=int, metavar="N", help="run N randomised encounters")
    m.add_argument("--object-free", type=float, default=0.0, metavar="MIN",
                   help="also fly MIN simulated minutes with no object (false evasions per hour)")
    m.add_argument("--wide-passes", type=int, default=0, metavar="N",
                   help="also fly N encounters whose object misses by 2-4 m (unnecessary evasions)")
    m.add_argument("--crossing", type=int, default=0, metavar="N",
                   help="also fly N encounters crossing the view (approach 20-50 deg) that would "
                        "pass 0.15-0.55 m off: is the first evasion ever towards their passage?")
    m.add_argument("--workers", type=int, help="processes for a campaign (default: half the cores; "
                   "encounters run in real time)")
    m.add_argument("--trigger", choices=("distance", "ttc", "response"), help="override decision.trigger")
    m.add_argument("--connection", metavar="URL", help="single encounter against a PX4 SITL that "
                   "is already flying (e.g. udpin://0.0.0.0:14540): the camera renders from its "
                   "telemetry pose; default: the stand-in vehicle, started here")
    m.add_argument("--speed", type=float, default=6.0, help="single encounter: object speed, m/s")
    m.add_argument("--angle", type=float, default=10.0, help="single encounter: approach angle, "
                   "deg from head-on (+: from the right)")
    m.add_argument("--miss", type=float, default=0.0, help="single encounter: miss distance if "
                   "nobody moved, m (0: collision course)")
    m.add_argument("--size", type=float, default=0.3, help="single encounter: object diameter, m")
    m.add_argument("--fps", type=float, default=30.0, help="the simulated camera's frame rate (the "
                   "D435i's colour: 30 or 60), frames/s")
    m.add_argument("--vel-gain", type=float, default=1.8, metavar="P_ACC", help="the stand-in "
                   "vehicle's MPC_XY_VEL_P_ACC (PX4's default 1.8; hardware/px4-companion.params "
                   "recommends 2.5): how quickly it builds lateral speed")
    m.add_argument("--wander", type=float, default=0.0, metavar="K", help="the stand-in's hover "
                   "drifts as PX4 SITL's does (±0.5 m, up to 0.7 m/s: docs/sitl.md), times K (0-5; "
                   "default 0: still), and so does its flight on a leg")
    m.add_argument("--tilt", action="store_true", help="the camera is fixed to the body and banks "
                   "and pitches as the vehicle accelerates (default: held level); the decision runs "
                   "with decision.camera_mount: body, derotating by the autopilot's attitude")
    m.add_argument("--own-speed", type=float, default=0.0, help="single encounter: the vehicle's "
                   "forward speed (Mission leg), m/s; 0 hovers")
    m.add_argument("--resume", type=Path, metavar="DIR", help="campaign: continue the one in DIR "
                   "(same command line otherwise), running only the encounters its encounters.csv lacks")
    m.add_argument("--ray", nargs="?", const="local", metavar="ADDRESS", help="campaign: run the "
                   "encounters as Ray tasks, on a local Ray runtime or (ADDRESS: auto, HOST:6379) on "
                   "a running cluster; needs pip install '.[cluster]'")
    m.add_argument("--realtime-object-free", action="store_true", help="fly the object-free minutes "
                   "in real time through the full loop (default: faster than real time, re-flying "
                   "in real time any flight that would have commanded something)")
    m.add_argument("--open-loop", action="store_true", help="campaign sets flown open loop instead: "
                   "each encounter by its script, faster than real time, stopped at the first command "
                   "and scored from the truth with the response model (a development screen, not the "
                   "closed loop; writes openloop.csv and openloop.md)")
    m.add_argument("--world", metavar="MODULE:FACTORY", default="", help="render encounters with "
                   "another world: FACTORY(seed, lens) returns an object with camera() and render() "
                   "(docs/commands.md, 'Your own world'); default: the built-in world")
    m.add_argument("compare", nargs="*", metavar="compare A B", help="instead: say whether two "
                   "campaign folders' success rates differ beyond chance (paired by encounter)")
    with_config(m)

    c = sub.add_parser("config", help="print the configuration as commented YAML "
                       "(midair config > my.yaml to start tuning)")
    c.add_argument("--explain", action="store_true",
                   help="show how the decision thresholds follow from each other (eq. 4.3)")
    with_config(c)
    return p


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    logging.basicConfig(
        level=logging.WARNING,  # libraries (motmetrics logs timings at INFO on the root logger)
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    for name in ("app", "hardware"):
        logging.getLogger(name).setLevel(logging.DEBUG if args.verbose else logging.INFO)
    try:
        cfg = load_config(args.config)
        return _COMMANDS[args.command](args, cfg)
    except UserError as exc:
        print(f"midair: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print("midair: interrupted", file=sys.stderr)
        return 130


def _cmd_replay(args: argparse.Namespace, cfg: Config) -> int:
    from app.runtime.sources import open_source
    from app.tools.replay import ProgressBar, run_replay

    source = open_source(args.source, fps=args.fps)
    bar = ProgressBar(f"replay {source.name}")
    try:
        stats = run_replay(source, cfg, args.out, video=not args.no_video, progress=bar,
                           altitude_m=args.altitude)
    finally:
        bar.close()
    summary = stats.summary(source)
    print(json.dumps(summary, indent=2))
    print(f"wrote {args.out / 'tracks.csv'}, {args.out / 'summary.json'}"
          + (f", {args.out / 'decisions.csv'}" if source.has_depth else "")
          + ("" if args.no_video else f", {args.out / 'annotated.mp4'}"))
    return 0


def _cmd_demo(args: argparse.Namespace, cfg: Config) -> int:
    from app.runtime.sources import open_source
    from app.sim.synthetic import SyntheticScene, write_recording
    from app.tools.evaluate import read_boxes, score
    from app.tools.replay import ProgressBar, run_replay

    if args.ground_flights is not None:
        return _demo_ground_flights(args, cfg)
    if args.depth:
        raise UsageError("--depth: only with --ground-flights (the synthetic flight has its depth already)")
    if args.frames < 10:
        raise UsageError(f"--frames {args.frames}: must be at least 10")
    rec = write_recording(SyntheticScene(frames=args.frames, seed=args.seed), args.out / "recording")
    source = open_source(rec)
    bar = ProgressBar("demo")
    try:
        stats = run_replay(source, cfg, args.out, video=True, progress=bar)
    finally:
        bar.close()
    s = score(read_boxes(rec / "gt.csv"), stats.track_rows, len(source))
    summary = stats.summary(source)
    total = summary["stages"]["total"]  # type: ignore[index]
    print(f"synthetic flight: {len(source)} frames at {source.fps:g} fps, recording in {rec}")
    print(f"perception: {summary['confirmed_ids']} confirmed objects, "
          f"median {total['median_ms']} ms/frame, {summary['processing_fps']} frames/s")
    print(f"against the truth: recall {s['recall']:.2f}, precision {s['precision']:.2f}, "
          f"MOTA {s['mota']:.2f}, IDF1 {s['idf1']:.2f}")
    print(f"annotated video: {args.out / 'annotated.mp4'}  tracks: {args.out / 'tracks.csv'}")
    return 0


def _demo_ground_flights(args: argparse.Namespace, cfg: Config) -> int:
    from app.sim.groundset import plan_flights, write_dataset
    from app.tools.evaluate import (
        approach_shares,
        evaluate_all,
        find_clips,
        format_tables,
        totals,
        write_reports,
    )

    plan_flights(args.ground_flights, args.seed)  # bad counts refused before anything is written
    cap = cfg.capture
    size = (cap.depth_width, cap.depth_height) if args.depth else (cap.color_width, cap.color_height)
    flights = write_dataset(args.out, args.ground_flights, args.seed, *size, depth=args.depth)
    what = "recording folders with depth" if args.depth else "*.mp4"
    print(f"wrote {len(flights)} flights over ground to {args.out} (clips.csv, {what}, *.gt.csv)")
    scores = evaluate_all(find_clips(args.out), cfg, args.workers)
    sums = totals(scores)
    print(format_tables(scores, sums))
    write_reports(args.out, scores, sums)
    shares = approach_shares(args.out, cfg, args.workers)
    seen = [s for s in shares if s.first_reported is not None]
    after = sum(s.frames_after for s in seen)
    print(f"objects coming at the vehicle: {len(seen)} of {len(shares)} ever reported; once reported, "
          f"reported in {sum(s.reported_after for s in seen)} of their {after} frames"
          + (f" ({sum(s.reported_after for s in seen) / after:.1%})" if after else ""))
    print(f"wrote {args.out / 'evaluation.md'}; score again with: midair evaluate {args.out}")
    return 0


def _cmd_evaluate(args: argparse.Namespace, cfg: Config) -> int:
    from app.tools.evaluate import evaluate_all, find_clips, format_tables, totals, write_reports

    clips = find_clips(args.path, args.gt)
    if args.only:
        keys = [k.strip() for k in args.only.split(",") if k.strip()]
        clips = [c for c in clips if any(k in c.name or k in c.group for k in keys)]
        if not clips:
            raise UsageError(f"--only {args.only}: no clip matches")
    scores = evaluate_all(clips, cfg, args.workers)
    sums = totals(scores)
    print(format_tables(scores, sums))
    if args.out:
        write_reports(args.out, scores, sums)
        print(f"wrote {args.out / 'evaluation.md'} and {args.out / 'evaluation.csv'}")
    return 0


def _cmd_fit_confidence(args: argparse.Namespace, cfg: Config) -> int:
    import numpy as np

    from app.tools.confidence_fit import (
        DEFAULT_FEATURES,
        ClipExamples,
        collect_all,
        confidence,
        feature_columns,
        fit_logistic,
        leave_one_clip_out,
        threshold_table,
        weights_yaml,
    )
    from app.tools.evaluate import TOTALS, Clip, find_clips

    keys = [k.strip() for k in args.train.split(",") if k.strip()]
    clips = [c for c in find_clips(args.path) if any(k in c.name or k in c.group for k in keys)]
    if len(clips) < 2:
        raise UsageError(f"--train {args.train}: {len(clips)} clip(s) match, need at least 2")
    threshold = args.min_confidence
    if threshold is None:
        threshold = cfg.perception.confidence.min_confidence or 0.3
    if not 0 < threshold < 1:
        raise UsageError(f"--min-confidence {threshold}: must be > 0 and < 1")
    names = DEFAULT_FEATURES if args.features is None else tuple(
        n.strip() for n in args.features.split(",") if n.strip())
    try:
        columns = feature_columns(names)
    except ValueError as exc:
        raise UsageError(f"--features {args.features}: {exc}") from None
    trained = {c.video.resolve() for c in clips}
    held: list[Clip] = []  # clips scored with the training clips' weights, never fitted on
    for folder in args.score_on:
        held += [c for c in find_clips(folder) if c.video.resolve() not in trained]
    examples = collect_all(clips, cfg, args.workers)
    rows = sum(len(e.y) for e in examples)
    print(f"{len(clips)} clips, {rows} track reports, {sum(int(e.y.sum()) for e in examples)} "
          "on a labelled object")
    print("features fitted: " + ", ".join(names))
    loo = leave_one_clip_out(examples, columns)
    scored = list(zip(examples, loo, strict=True))
    groups = [(name, [(e, c) for e, c in scored if e.clip.group in members]) for name, members in TOTALS
              if any(e.clip.group in members for e in examples)]
    print("\nLeave-one-clip-out (each clip scored with weights fitted on the others):")
    print(threshold_table(groups, [0.0, 0.2, 0.25, 0.3, 0.35, 0.4, 0.5, round(threshold, 3)]))
    bias, w = fit_logistic(np.vstack([e.x for e in examples]), np.concatenate([e.y for e in examples]),
                           columns=columns)
    if held:
        by_group: dict[str, list[tuple[ClipExamples, np.ndarray]]] = {}
        for ex in collect_all(held, cfg, args.workers):
            by_group.setdefault(ex.clip.group, []).append((ex, confidence(bias, w, ex.x)))
        print(f"\nHeld out ({len(held)} clips never trained on, scored with the weights fitted on all "
              "the training clips):")
        print(threshold_table(list(by_group.items()), [0.0, 0.3, 0.35, 0.4, 0.5, 0.6, round(threshold, 3)]))
    text = weights_yaml(bias, w, threshold)
    print("\nFitted on all of them:\n" + text, end="")
    if args.out:
        args.out.write_text(text)
        print(f"wrote {args.out}")
    return 0


def _cmd_bench(args: argparse.Namespace, cfg: Config) -> int:
    from app.tools.bench import format_bench, run_bench

    if args.fly or args.link:
        from app.tools.linkbench import run_fly_bench, run_link_bench
        from hardware.px4 import FlightLinkError

        try:
            r = (run_fly_bench(cfg, fps=args.fps, seconds=args.seconds) if args.fly
                 else run_link_bench(cfg, seconds=args.seconds))
        except FlightLinkError as exc:  # the simulated vehicle did not come up
            print(f"midair: error: {exc}", file=sys.stderr)
            return 4
        print(json.dumps(r, indent=None if args.json else 2))
        return 0
    if args.frames < 30:
        raise UsageError(f"--frames {args.frames}: must be at least 30")
    if args.repeats < 1:
        raise UsageError(f"--repeats {args.repeats}: must be at least 1")
    if not 0 <= args.warmup <= 600:  # also refuses nan, which would never end the warm-up
        raise UsageError(f"--warmup {args.warmup}: must be between 0 and 600 s")
    result = run_bench(cfg, frames=args.frames, repeats=args.repeats, soak_frames=args.soak, width=args.width,
                       warmup_s=args.warmup)
    print(format_bench(result))
    if args.json:
        print(json.dumps(result))
    return 0


def _cmd_fly(args: argparse.Namespace, cfg: Config) -> int:
    import asyncio
    from dataclasses import replace

    from app.perception.frames import FrameSource
    from app.runtime.notify import Notifier
    from app.runtime.process import fly
    from app.runtime.record import FlightRecord
    from app.runtime.sources import open_source
    from hardware.px4 import FlightLinkError, Px4Link

    if args.seconds is not None and not args.seconds > 0:
        raise UsageError(f"--seconds {args.seconds}: must be > 0")
    flight = cfg.flight
    if args.connection:
        flight = replace(flight, connection=args.connection)
    if args.mode:
        flight = replace(flight, mode=args.mode)
    record_cfg = cfg.record
    if args.record:
        record_cfg = replace(record_cfg, dir=str(args.record))
    if args.no_record:
        record_cfg = replace(record_cfg, enabled=False)
    camera = args.camera or cfg.capture.camera
    cfg = replace(cfg, flight=flight, record=record_cfg,
                  capture=replace(cfg.capture, camera=camera))
    notifier = Notifier()
    source: FrameSource
    if camera == "realsense":
        from hardware.realsense import RealSenseSource

        source = RealSenseSource(cfg.capture)
    elif camera == "synthetic":
        from app.sim.synthetic import ThrowsSource

        source = ThrowsSource()
    else:
        source = open_source(camera, capture=cfg.capture)
    record = None
    if record_cfg.enabled:
        from app.camera import camera_from_config

        record = FlightRecord(record_cfg, cfg, source.camera or camera_from_config(cfg.camera))
        try:
            record.start()
        except OSError as exc:  # a guard that will not fly without its logs protects no one
            log.error("flight record disabled: %s cannot be written: %s", record_cfg.dir, exc)
            record = None
    summary: dict[str, object] = {}

    async def run() -> None:
        link = Px4Link(flight.connection)
        notifier.status(f"connecting to {flight.connection}")
        await link.connect(timeout_s=flight.connect_timeout_s)
        try:
            stats = await fly(cfg, source, link, record=record, notifier=notifier,
                              seconds=args.seconds)
            summary.update(stats.summary())
        finally:
            await link.close()

    try:
        asyncio.run(run())
    except BaseException as exc:  # noqa: BLE001 - sorted out below, then re-raised or mapped
        error = _unwrap(exc)
        summary["ended_by"] = f"error: {type(error).__name__}: {error}"
        if isinstance(error, FlightLinkError):
            print(f"midair: error: {error}", file=sys.stderr)
            return 4
        if isinstance(error, UserError):
            print(f"midair: error: {error}", file=sys.stderr)
            return error.exit_code
        if isinstance(error, KeyboardInterrupt):
            raise
        log.critical("stopped by an unexpected error (control was stopped first)", exc_info=error)
        return 1
    finally:
        notifier.stopping()
        notifier.close()
        source.close()
        if record is not None:
            record.close(summary)
            print(f"flight record: {record.folder}", file=sys.stderr)
    print(json.dumps(summary, indent=2))
    return 0


def _unwrap(exc: BaseException) -> BaseException:
    """The first real error inside (nested) exception groups."""
    while isinstance(exc, BaseExceptionGroup) and exc.exceptions:
        exc = exc.exceptions[0]
    return exc


def _cmd_simulate(args: argparse.Namespace, cfg: Config) -> int:
    import time
    from dataclasses import replace

    try:
        from app.sim.campaign import (
            crossing_set,
            default_workers,
            object_free,
            run_campaign,
            sample_encounters,
            wide_passes,
            with_trigger,
            write_report,
        )
        from app.sim.simulate import Encounter
    except ImportError as exc:  # pymavlink (the simulated PX4) missing
        raise UsageError(f"simulate needs the simulated PX4's packages: {exc}") from None
    if args.compare:
        return _compare(args.compare)
    if args.trigger:
        cfg = with_trigger(cfg, args.trigger)
    from app.sim.px4 import WANDER_RANGE, XY_VEL_P_ACC_RANGE

    if not XY_VEL_P_ACC_RANGE[0] <= args.vel_gain <= XY_VEL_P_ACC_RANGE[1]:
        raise UsageError(f"--vel-gain {args.vel_gain:g}: PX4's MPC_XY_VEL_P_ACC takes "
                         f"{XY_VEL_P_ACC_RANGE[0]:g}-{XY_VEL_P_ACC_RANGE[1]:g}")
    if not WANDER_RANGE[0] <= args.wander <= WANDER_RANGE[1]:
        raise UsageError(f"--wander {args.wander:g}: a multiple of PX4 SITL's hover drift, "
                         f"{WANDER_RANGE[0]:g}-{WANDER_RANGE[1]:g}")
    if args.wander > 0 and (args.connection or args.open_loop
                            or (args.object_free and not args.realtime_object_free)):
        raise UsageError("--wander drifts the stand-in vehicle: not with --connection (the vehicle "
                         "there drifts as it does), --open-loop or the fast object-free run (their "
                         "flights follow the script exactly; --realtime-object-free flies them)")
    if args.world:
        from app.sim.simulate import world_for

        world_for(cfg, Encounter(seed=args.seed, world=args.world))  # fails here, not in every worker
    t0 = time.monotonic()
    sets_given = args.campaign is not None or args.object_free or args.wide_passes or args.crossing
    if args.open_loop and (not sets_given or args.resume or args.ray):
        raise UsageError("simulate --open-loop: give the sets to fly (--campaign, --wide-passes, "
                         "--crossing, --object-free); it neither resumes nor runs on Ray")
    if not sets_given and not args.resume:
        enc = Encounter(seed=args.seed, object_speed_mps=args.speed, approach_deg=args.angle,
                        miss_m=args.miss, size_m=args.size, own_speed_mps=args.own_speed, fps=args.fps,
                        world=args.world, xy_vel_p_acc=args.vel_gain, tilt=args.tilt,
                        wander=args.wander)
        if not 0 < args.speed <= 40 or not -60 <= args.angle <= 60 or args.miss < 0 or args.size <= 0:
            raise UsageError("simulate: --speed in (0, 40] m/s, --angle in [-60, 60] deg, "
                             "--miss >= 0, --size > 0")
        return _single_encounter(cfg, enc, args.out, args.connection)
    if args.campaign is not None and args.campaign < 1:
        raise UsageError(f"--campaign {args.campaign}: must be at least 1")
    if args.wide_passes < 0 or args.object_free < 0 or args.crossing < 0:
        raise UsageError("--wide-passes, --crossing and --object-free must not be negative")
    if args.fps not in (30.0, 60.0):
        raise UsageError(f"--fps {args.fps:g}: the D435i's colour stream runs at 30 or 60")
    from app.sim.results import ResultLog, config_digest

    out = args.resume or args.out
    workers = args.workers or default_workers()
    flown = {"fps": args.fps, "world": args.world, "xy_vel_p_acc": args.vel_gain, "tilt": args.tilt,
             "wander": args.wander}
    encounters = [replace(e, **flown) for e in sample_encounters(args.campaign or 0, args.seed)]
    wide = [replace(e, **flown) for e in wide_passes(args.wide_passes, args.seed)]
    cross = [replace(e, **flown) for e in crossing_set(args.crossing, args.seed)]
    free = [replace(e, **flown) for e in object_free(args.object_free, args.seed)] if args.object_free else []
    if args.open_loop:
        if args.tilt:
            raise UsageError("--tilt flies the closed loop only: the open loop's scripted flights "
                             "do not accelerate, so their camera stays level")
        return _open_loop(cfg, [("main", encounters), ("wide", wide), ("crossing", cross), ("free", free)],
                          workers, out)
    fast = not args.realtime_object_free
    plan = {"seed": args.seed, "campaign": args.campaign or 0, "wide_passes": args.wide_passes,
            "crossing": args.crossing,
            "object_free_min": args.object_free, "fps": args.fps, "world": args.world,
            "fast_object_free": fast, "trigger": cfg.decision.trigger, "config": config_digest(cfg)}
    if args.vel_gain != Encounter.xy_vel_p_acc:  # only then: older campaigns resume as before
        plan["vel_gain"] = args.vel_gain
    if args.tilt:
        plan["tilt"] = True
    if args.wander:
        plan["wander"] = args.wander
    log = ResultLog(out, plan, resume=args.resume is not None)
    everything = [*encounters, *wide, *cross, *free]
    bar = _CampaignBar(len(everything), len(log.done),
                       sum(r.success for r in log.done.values() if r.threat),
                       sum(r.threat for r in log.done.values()))
    try:
        results = run_campaign(cfg, everything, workers, bar, log=log, fast_object_free=fast,
                               backend="ray" if args.ray else "pool", ray_address=args.ray)
    except KeyboardInterrupt:
        print(f"\nmidair: interrupted; {len(log.done)} of {len(everything)} encounters are in "
              f"{log.path}: continue with the same command and --resume {out}", file=sys.stderr)
        return 130
    finally:
        bar.close()
        log.close()
    wall = time.monotonic() - t0
    n, k, c = len(encounters), len(wide), len(cross)
    report = write_report(out, results[:n], results[n + k + c:], cfg, wall,
                          title=f"Campaign of {n} encounters, seed {args.seed}", wide=results[n:n + k],
                          crossing=results[n + k:n + k + c])
    print(report.read_text())
    print(f"wrote {report}, {out / 'encounters.csv'} and the plots in {out}")
    return 0


def _open_loop(cfg: Config, sets: list[tuple[str, list[Encounter]]], workers: int, out: Path) -> int:
    """``simulate --open-loop``: the sets flown by their scripts (app.sim.openloop)."""
    from tqdm import tqdm

    from app.sim.openloop import run_open_loop, write_open_loop

    bar = tqdm(total=sum(len(g) for _, g in sets), unit="enc", desc="open loop", file=sys.stderr,
               mininterval=1.0)
    try:
        results = run_open_loop(cfg, sets, workers, lambda _r: bar.update(1))
    finally:
        bar.close()
    print(write_open_loop(out, results), end="")
    print(f"wrote {out / 'openloop.csv'} and {out / 'openloop.md'}")
    return 0


class _CampaignBar:
    """tqdm's bar over a campaign's encounters, with the running success rate of threats."""

    def __init__(self, total: int, done: int, ok: int, threats: int) -> None:
        from tqdm import tqdm

        self.ok, self.threats = ok, threats
        self.bar = tqdm(total=total, initial=done, unit="enc", desc="encounters", file=sys.stderr,
                        disable=None, dynamic_ncols=True)

    def __call__(self, r: EncounterResult) -> None:
        if r.threat:
            self.threats += 1
            self.ok += r.success
        if self.threats:
            self.bar.set_postfix_str(f"avoided {self.ok}/{self.threats} ({self.ok / self.threats:.0%})",
                                     refresh=False)
        self.bar.update(1)

    def close(self) -> None:
        self.bar.close()


def _compare(words: list[str]) -> int:
    from app.sim.results import compare, read_results

    if len(words) != 3 or words[0] != "compare":
        raise UsageError(f"simulate: unexpected {' '.join(words)!r}; to compare two campaigns: "
                         "midair simulate compare DIR_A DIR_B")
    a, b = Path(words[1]), Path(words[2])
    result = compare(read_results(a), read_results(b))
    print(result.text(str(a), str(b)))
    return 0


def _single_encounter(cfg: Config, enc: Encounter, out: Path, connection: str | None = None) -> int:
    from app.runtime.sources import open_source
    from app.sim.simulate import run_encounter
    from app.tools.replay import run_replay
    from hardware.px4 import FlightLinkError

    out.mkdir(parents=True, exist_ok=True)
    try:
        r = run_encounter(cfg, enc, out_dir=out, save_frames=True, connection=connection)
    except FlightLinkError as exc:
        print(f"midair: error: {exc}", file=sys.stderr)
        return 4
    assert r.record is not None
    # the annotated video: the record replayed (same frames, same tracks and decisions)
    run_replay(open_source(r.record), cfg, out, video=True)
    row = r.row()
    (out / "encounter.json").write_text(json.dumps(row, indent=2, default=str) + "\n")
    verdict = ("avoided" if r.success else "NOT avoided") if r.threat else "no threat"
    print(f"encounter: {enc.kind} {enc.size_m:g} m at {enc.object_speed_mps:g} m/s, "
          f"{enc.approach_deg:g} deg from head-on, miss {enc.miss_m:g} m, own speed "
          f"{enc.own_speed_mps:g} m/s, trigger {cfg.decision.trigger}")
    def when(seen: bool, range_m: float | None, before_s: float | None) -> str:
        return f"at {range_m or 0:.1f} m, {before_s or 0:.2f} s before closest approach" if seen else "no"

    print(f"detected: {when(r.detected, r.detect_range_m, r.detect_before_cpa_s)}")
    print(f"evaded: {when(r.evaded, r.evade_range_m, r.evade_before_cpa_s)}")
    print(f"closest approach: {r.min_separation_m:.2f} m ({verdict}); capture -> setpoint p99 "
          f"{r.capture_to_setpoint_p99_ms} ms")
    print(f"annotated video: {out / 'annotated.mp4'}  record: {r.record}  result: {out / 'encounter.json'}")
    return 0


def _cmd_config(args: argparse.Namespace, cfg: Config) -> int:
    if args.explain:
        print(explain(cfg))
    else:
        sys.stdout.write(to_yaml(cfg))
    return 0


_COMMANDS = {
    "replay": _cmd_replay,
    "demo": _cmd_demo,
    "evaluate": _cmd_evaluate,
    "fit-confidence": _cmd_fit_confidence,
    "bench": _cmd_bench,
    "config": _cmd_config,
    "fly": _cmd_fly,
    "simulate": _cmd_simulate,
}

if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
