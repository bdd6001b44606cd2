"""The MOT-challenge form of tracks (``frame,id,x,y,w,h,conf,-1,-1,-1``), as replay and the
flight record write them, so that the two compare line by line."""

from __future__ import annotations

MOT_HEADER = ("frame", "id", "x", "y", "w", "h", "conf", "wx", "wy", "wz")


def mot_row(frame: int, tid: int, x: float, y: float, w: float, h: float,
            conf: float = 1.0) -> list[object]:
    """One MOT-challenge line: ``frame,id,x,y,w,h,conf,-1,-1,-1`` (box as given, px)."""
    return [frame, tid, f"{x:.1f}", f"{y:.1f}", f"{w:.1f}", f"{h:.1f}", f"{conf:.3g}", -1, -1, -1]
