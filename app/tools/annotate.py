"""Drawing of perception results on a copy of the colour frame (for people, not for stages)."""

from __future__ import annotations

import cv2
import numpy as np

from app.decision.policy import Command, DecisionMaker, ObjectState
from app.perception.pipeline import PerceptionResult

MASK_COLOUR = (0, 0, 255)  # BGR: red outline of the motion mask
CLUSTER_COLOUR = (0, 220, 255)  # yellow: recognised clusters
TRACK_COLOUR = (60, 220, 60)  # green: confirmed tracks
LOST_COLOUR = (160, 160, 160)  # grey: reported while coasting
CLUTTER_COLOUR = (0, 140, 255)  # orange, thin: confirmed, but its confidence says clutter
TEXT_COLOUR = (255, 255, 255)
WINDOW_COLOUR = (255, 160, 0)  # blue-ish: the safe window
ALERT_COLOUR = (0, 0, 255)  # red: the evasion arrow


def annotate(
    result: PerceptionResult,
    extra_lines: tuple[str, ...] = (),
    decision: tuple[Command | None, list[ObjectState] | None, DecisionMaker] | None = None,
) -> np.ndarray:
    """The frame with the mask outline, clusters, tracks with IDs and Kalman trails; with a
    decision, also the safe window, each object's distance and the command."""
    img = result.frame.color
    out = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR) if img.ndim == 2 else img.copy()
    if result.mask is not None:
        contours, _ = cv2.findContours(result.mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        cv2.drawContours(out, contours, -1, MASK_COLOUR, 1)
    for c in result.clusters:
        x, y, w, h = c.box
        cv2.rectangle(out, (x, y), (x + w, y + h), CLUSTER_COLOUR, 1)
    for t in result.tracks:
        if not (t.reported or t.matched):
            continue  # a coasting track not believed: nothing to show
        colour = (TRACK_COLOUR if t.matched else LOST_COLOUR) if t.reported else CLUTTER_COLOUR
        if len(t.trail) > 1:
            pts = np.round(np.array(t.trail)).astype(np.int32).reshape(-1, 1, 2)
            cv2.polylines(out, [pts], False, colour, 1, cv2.LINE_AA)
        x, y, w, h = (int(round(v)) for v in t.box)
        cv2.rectangle(out, (x, y), (x + w, y + h), colour, 2 if t.reported else 1)
        cv2.putText(out, f"#{t.track_id} {t.confidence:.2f}", (x, max(12, y - 4)),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.5, colour, 1, cv2.LINE_AA)
    reported = sum(t.reported for t in result.tracks)
    lines = [f"frame {result.frame.index}  {result.status}  objects {reported}  "
             f"tracks {len(result.tracks)}",
             *extra_lines]
    if decision is not None:
        lines.append(_draw_decision(out, result, *decision))
    for i, line in enumerate(lines):
        org = (8, 20 + 18 * i)
        (w, h), base = cv2.getTextSize(line, cv2.FONT_HERSHEY_SIMPLEX, 0.5, 1)
        # a dark band behind the text: readable over bright sky as over dark ground
        cv2.rectangle(out, (org[0] - 3, org[1] - h - 4), (org[0] + w + 3, org[1] + base + 1), (0, 0, 0), -1)
        cv2.putText(out, line, org, cv2.FONT_HERSHEY_SIMPLEX, 0.5, TEXT_COLOUR, 1, cv2.LINE_AA)
    return out


def _draw_decision(out: np.ndarray, result: PerceptionResult, command: Command | None,
                   objects: list[ObjectState] | None, decider: DecisionMaker) -> str:
    """Safe window (a circle of radius R_safe at the nearest object's distance, or at the
    avoidance distance), distances per track, and the command line."""
    cam = decider.camera.color
    objects = objects or []
    by_id = {o.track_id: o for o in objects}
    z_ref = min((o.z_m for o in objects if o.fresh), default=decider.avoid_m)
    z_ref = max(z_ref, 0.3)
    radius = int(round(cam.fx * decider.cfg.safe_window_m / z_ref))
    centre = (int(round(cam.ppx)), int(round(cam.ppy)))
    cv2.circle(out, centre, radius, WINDOW_COLOUR, 1, cv2.LINE_AA)
    cv2.putText(out, f"safe window @ {z_ref:.1f} m", (centre[0] - 60, max(12, centre[1] - radius - 6)),
                cv2.FONT_HERSHEY_SIMPLEX, 0.45, WINDOW_COLOUR, 1, cv2.LINE_AA)
    for t in result.tracks:
        o = by_id.get(t.track_id)
        if o is None:
            continue
        x, y, w, h = (int(round(v)) for v in t.box)
        if o.source == "image":  # no range yet: the image's time to contact
            label = "image"
        else:
            label = f"{o.z_m:.1f} m" + ("" if o.fresh else " (stale)")
        if o.tau_s is not None:
            label += f" tau {o.tau_s:.1f}s"
        cv2.putText(out, label, (x, y + h + 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, TRACK_COLOUR, 1,
                    cv2.LINE_AA)
        if o.miss_sizes is not None and o.tau_s is not None and o.tau_s > 0:
            # the predicted passage, drawn where it will cross (object sizes -> px at its range)
            d = o.diameter_m or decider.cfg.object_diameter_min_m
            z = max(o.z_m, 0.3) if o.source != "image" else d / max(1e-6, (w + h) / 2 / cam.fx)
            px = (int(round(cam.ppx + cam.fx * o.miss_sizes[0] * d / z)),
                  int(round(cam.ppy + cam.fy * o.miss_sizes[1] * d / z)))
            cv2.line(out, (x + w // 2, y + h // 2), px, ALERT_COLOUR, 1, cv2.LINE_AA)
            cv2.drawMarker(out, px, ALERT_COLOUR, cv2.MARKER_TILTED_CROSS, 10, 2)
    if command is None or command.action == "none":
        return "decision: none"
    if command.action == "evade":
        # arrow from the centre along the commanded (right, down) velocity
        k = 40 / max(command.speed_mps, 1e-6)
        tip = (int(centre[0] + k * command.right_mps), int(centre[1] + k * command.down_mps))
        cv2.arrowedLine(out, centre, tip, ALERT_COLOUR, 3, cv2.LINE_AA, tipLength=0.3)
    return f"decision: {command.action} - {command.reason}"
