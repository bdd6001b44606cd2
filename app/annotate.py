"""Drawing of perception results on a copy of the colour frame (for people, not for stages)."""

from __future__ import annotations

import cv2
import numpy as np

from app.perception import PerceptionResult

MASK_COLOUR = (0, 0, 255)  # BGR: red outline of the motion mask
CLUSTER_COLOUR = (0, 220, 255)  # yellow: recognised clusters
TRACK_COLOUR = (60, 220, 60)  # green: confirmed tracks
LOST_COLOUR = (160, 160, 160)  # grey: confirmed but coasting
TEXT_COLOUR = (255, 255, 255)


def annotate(result: PerceptionResult, extra_lines: tuple[str, ...] = ()) -> np.ndarray:
    """The frame with the mask outline, clusters, tracks with IDs and Kalman trails."""
    img = result.frame.color
    out = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR) if img.ndim == 2 else img.copy()
    if result.mask is not None:
        contours, _ = cv2.findContours(result.mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        cv2.drawContours(out, contours, -1, MASK_COLOUR, 1)
    for c in result.clusters:
        x, y, w, h = c.box
        cv2.rectangle(out, (x, y), (x + w, y + h), CLUSTER_COLOUR, 1)
    for t in result.tracks:
        colour = TRACK_COLOUR if t.matched else LOST_COLOUR
        if len(t.trail) > 1:
            pts = np.round(np.array(t.trail)).astype(np.int32).reshape(-1, 1, 2)
            cv2.polylines(out, [pts], False, colour, 1, cv2.LINE_AA)
        x, y, w, h = (int(round(v)) for v in t.box)
        cv2.rectangle(out, (x, y), (x + w, y + h), colour, 2)
        cv2.putText(out, f"#{t.track_id}", (x, max(12, y - 4)), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                    colour, 1, cv2.LINE_AA)
    lines = (f"frame {result.frame.index}  {result.status}  tracks {len(result.tracks)}",
             *extra_lines)
    for i, line in enumerate(lines):
        org = (8, 20 + 18 * i)
        cv2.putText(out, line, org, cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(out, line, org, cv2.FONT_HERSHEY_SIMPLEX, 0.5, TEXT_COLOUR, 1, cv2.LINE_AA)
    return out
