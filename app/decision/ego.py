"""The vehicle's own motion, and whether an object seen in the image only is static structure.

A multirotor flying forward sees the ground, trees and the horizon move and grow in its
image. A blob of that structure, tracked for a second, can read as an object on its way in
(time to contact from its growth; the passage in object sizes), and without a range its
passage in metres spans the plausible sizes: the worst case hits (docs/measurements.md,
"Ten object-free hours": every false evasion was such a blob, in forward flight).

The autopilot knows what the image cannot: the camera's velocity. A static point at
(X, Y, Z) (colour-camera axes: X right, Y down, Z forward) moves, relative to a camera
flying at v = (v_x, v_y, v_z), at -v; its bearing b = (X/Z, Y/Z) and angular size then
change as

    db/dt = s · (b · v_z - (v_x, v_y)),      d ln θ / dt = s · v_z,      s = 1 / Z

(the focus of expansion's flow field; Longuet-Higgins and Prazdny 1980, "The interpretation
of a moving retinal image"). Three measured rates, one unknown s: a weighted least-squares fit
gives s (so the range, with no size), and its chi-square says whether the blob moves as
static structure does. If it does, its passage follows in metres: the static point at b / s
passes the camera's line of flight at its distance from that line.

Where the test can mislead: an object that flies along the camera's line of travel has the
same flow field (its relative velocity is parallel to -v). Coming at the camera, it closes
faster than v_z, so the fit's range is short of the truth and the passage nearer than it is
(conservative); flying ahead of the camera in the same direction, slower (being overtaken),
the range and the passage are overstated by v_z over the closing speed. The decision uses
the test only to *clear* an object, only when the bearing moves clearly (a constant bearing,
the collision course, is never cleared) and only when the passage clears with room to spare.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from app.decision.looming import ImageEstimate

# A blob's three rates fit static structure when their chi-square (2 degrees of freedom) is
# below this: the 99th percentile of a chi-square with 2 dof
STATIC_CHI2 = 9.21
# ... and the bearing must move by this many of its standard errors: a bearing that holds
# (a collision course) is never explained away as structure
STATIC_BEARING_SIGMAS = 3.0


@dataclass(frozen=True)
class EgoMotion:
    """The camera's motion relative to the world, from the autopilot, in colour-camera axes
    (X right, Y down, Z forward; the camera looks along the body's forward axis)."""

    velocity_mps: tuple[float, float, float]  # m/s
    velocity_std_mps: float = 0.2  # its error per axis (PX4's EKF in GPS flight: ~0.1-0.3), m/s

    @property
    def speed_mps(self) -> float:
        return math.sqrt(sum(v * v for v in self.velocity_mps))


def camera_velocity(velocity_ned_mps: tuple[float, float, float], roll_rad: float, pitch_rad: float,
                    yaw_rad: float) -> tuple[float, float, float]:
    """The vehicle's NED velocity in colour-camera axes (X right, Y down, Z forward) for a
    camera on the body's forward axis, from the attitude's Euler angles (ZYX, as PX4 and
    MAVLink's ATTITUDE give them)."""
    n, e, d = velocity_ned_mps
    cr, sr = math.cos(roll_rad), math.sin(roll_rad)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
    # body FRD = R^T · NED, with R = Rz(yaw) · Ry(pitch) · Rx(roll) (body to NED)
    forward = cp * cy * n + cp * sy * e - sp * d
    right = (sr * sp * cy - cr * sy) * n + (sr * sp * sy + cr * cy) * e + sr * cp * d
    down = (cr * sp * cy + sr * sy) * n + (cr * sp * sy - sr * cy) * e + cr * cp * d
    return right, down, forward


# colour-camera axes (X right, Y down, Z forward) from the body's FRD axes
_BODY_TO_CAMERA = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])


def mounted(attitude_rad: tuple[float, float, float], mount: str) -> tuple[float, float, float]:
    """The camera's own attitude (roll, pitch, yaw): the body's for a camera fixed to it
    (``body``), yaw alone for one a gimbal holds level (``gimbal``)."""
    if mount == "body":
        return attitude_rad
    if mount == "gimbal":
        return 0.0, 0.0, attitude_rad[2]
    raise ValueError(f"camera mount {mount!r}: expected 'body' or 'gimbal'")


def _body_to_ned(roll: float, pitch: float, yaw: float) -> np.ndarray:
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    return rz @ ry @ rx  # ZYX Euler, as PX4 and MAVLink's ATTITUDE give them


def camera_rotation(before_rad: tuple[float, float, float], after_rad: tuple[float, float, float]
                    ) -> np.ndarray:
    """R (3 x 3): a direction fixed in the world, in the camera's axes at attitude
    ``before_rad``, into its axes at ``after_rad`` (roll, pitch, yaw rad each)."""
    r_b = _body_to_ned(*before_rad)
    r_a = _body_to_ned(*after_rad)
    return np.asarray(_BODY_TO_CAMERA @ r_a.T @ r_b @ _BODY_TO_CAMERA.T, dtype=np.float64)


def derotation(before_rad: tuple[float, float, float], after_rad: tuple[float, float, float],
               k: np.ndarray) -> np.ndarray:
    """K·R·K⁻¹: where a direction fixed in the world, seen at pixel p with the camera at
    attitude ``before_rad``, is seen with it at ``after_rad`` (homogeneous px -> px). Carries
    the image history through the camera's *rotation* only: a bank of 20° to accelerate
    sideways (4 m/s² needs tan⁻¹(4 / 9.81) = 22°) would otherwise read as a bearing rate
    tens of times an object's."""
    return np.asarray(k @ camera_rotation(before_rad, after_rad) @ np.linalg.inv(k), dtype=np.float64)


@dataclass(frozen=True)
class StaticFit:
    """An image estimate read as static structure seen from the moving camera."""

    inverse_range: float  # s = 1 / Z, 1/m
    inverse_range_std: float
    chi2: float  # of the three rates against the static flow field (2 dof)
    bearing_sigmas: float  # how far the bearing moves, in its standard errors
    miss_m: float  # the static point's distance from the camera's line of flight, m
    miss_std_m: float

    @property
    def fits(self) -> bool:
        """The blob moves as static structure does, and not as a collision course."""
        return (self.chi2 <= STATIC_CHI2 and self.bearing_sigmas >= STATIC_BEARING_SIGMAS
                and self.inverse_range > 2.0 * self.inverse_range_std)


def static_fit(e: ImageEstimate, ego: EgoMotion, rate_noise_rad_s: float) -> StaticFit | None:
    """Fit ``e``'s bearing rate and expansion to the flow field of static structure seen
    from a camera moving as ``ego``; None when the camera does not move forward (no flow
    field to grow in) or the fit puts the point behind it. ``rate_noise_rad_s`` is added to
    the bearing rate's error: the camera's rotation that is not taken out (attitude jitter)."""
    vx, vy, vz = ego.velocity_mps
    if vz <= 0:
        return None
    bx, by = e.bearing
    g = (bx * vz - vx, by * vz - vy, vz)
    y = (e.bearing_rate[0], e.bearing_rate[1], e.expansion_per_s)
    sb = math.hypot(e.bearing_rate_std, rate_noise_rad_s)
    base = (sb, sb, max(e.expansion_std, 1e-6))
    s = 0.0
    sig = base
    for _ in range(2):  # the velocity's error scales with s: once more with the first s
        w = [1.0 / si**2 for si in sig]
        info = sum(gi * gi * wi for gi, wi in zip(g, w, strict=True))
        if info <= 0:
            return None
        s = sum(gi * yi * wi for gi, yi, wi in zip(g, y, w, strict=True)) / info
        sv = abs(s) * ego.velocity_std_mps
        sig = (math.hypot(base[0], sv * math.hypot(1.0, bx)), math.hypot(base[1], sv * math.hypot(1.0, by)),
               math.hypot(base[2], sv))
    w = [1.0 / si**2 for si in sig]
    info = sum(gi * gi * wi for gi, wi in zip(g, w, strict=True))
    s_std = 1.0 / math.sqrt(info)
    chi2 = sum(((yi - s * gi) / si) ** 2 for gi, yi, si in zip(g, y, sig, strict=True))
    if s <= 0:
        return None
    bearing_sigmas = math.hypot(*e.bearing_rate) / sb
    # the static point P = (b_x, b_y, 1) / s passes the camera, which flies along v, at
    # |P - (P·v̂) v̂|: proportional to 1 / s, so its error is the range's
    p = (bx / s, by / s, 1.0 / s)
    speed = ego.speed_mps
    u = tuple(v / speed for v in ego.velocity_mps)
    along = sum(pi * ui for pi, ui in zip(p, u, strict=True))
    miss = math.sqrt(max(0.0, sum(pi * pi for pi in p) - along * along))
    return StaticFit(s, s_std, chi2, bearing_sigmas, miss, miss * s_std / s)
