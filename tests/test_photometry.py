"""The contrast flux (app.perception.photometry) on real pixels: discs drawn by OpenCV into a
noisy sky, and the looming estimator fed with it where the boxes step by whole pixels."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.camera import Intrinsics
from app.decision.looming import LoomingEstimator
from app.perception.photometry import contrast_flux, core_area
from app.sim.world import draw_object

SKY, OBJECT, NOISE = 180.0, 60.0, 1.5


def frame(u: float, v: float, r: float, seed: int = 0, size: tuple[int, int] = (120, 160)) -> np.ndarray:
    """A grey sky with sensor noise and one dark disc of radius ``r`` px at (u, v)."""
    cover = np.zeros(size, np.uint8)
    draw_object(cover, "disc", u, v, r, 0.0)
    a = cover.astype(np.float32) / 255.0
    rng = np.random.default_rng(seed)
    g = SKY * (1 - a) + OBJECT * a + rng.normal(0, NOISE, size)
    return np.clip(g, 0, 255).astype(np.uint8)


def box(u: float, v: float, r: float, pad: int = 2) -> tuple[int, int, int, int]:
    """The box a motion mask gives: whole pixels, grown by its dilation."""
    x0, y0 = int(math.floor(u - r)) - pad, int(math.floor(v - r)) - pad
    x1, y1 = int(math.ceil(u + r)) + pad, int(math.ceil(v + r)) + pad
    return x0, y0, x1 - x0, y1 - y0


@pytest.mark.parametrize("r", [1.5, 2.3, 4.0, 9.0])
def test_the_flux_is_the_area_times_the_contrast(r: float) -> None:
    """Against the area the disc covers as drawn (anti-aliased edges count their fraction)."""
    f = contrast_flux(frame(80.3, 60.6, r), box(80.3, 60.6, r))
    assert f is not None
    cover = np.zeros((120, 160), np.uint8)
    draw_object(cover, "disc", 80.3, 60.6, r, 0.0)
    drawn = float(cover.sum()) / 255.0
    assert f[0] / (SKY - OBJECT) == pytest.approx(drawn, rel=0.10)
    assert drawn == pytest.approx(math.pi * r * r, rel=0.15)
    assert abs(f[0] - (SKY - OBJECT) * drawn) < 3 * f[1]  # its error says how far off it is


def test_its_square_root_grows_smoothly_with_the_size_where_the_box_steps() -> None:
    """Radii 2.0-3.0 px in tenths: the boxes take three sizes (steps of 10 %), sqrt(flux) is a
    line in r (each within 4 % of the fit through all of them, 1.5 grey levels of noise)."""
    rs = np.arange(2.0, 3.01, 0.1)
    roots = []
    for i, r in enumerate(rs):
        f = contrast_flux(frame(80.3, 60.6, float(r), seed=i), box(80.3, 60.6, float(r)))
        assert f is not None
        roots.append(math.sqrt(f[0]))
    assert len({box(80.3, 60.6, float(r))[2] for r in rs}) <= 3
    a, b = np.polyfit(rs, roots, 1)
    assert np.max(np.abs(np.array(roots) - (a * rs + b)) / roots) < 0.04
    assert a > 0


def test_no_flux_at_the_frame_edge_and_none_in_empty_sky_beyond_its_noise() -> None:
    assert contrast_flux(frame(3.0, 60.0, 4.0), box(3.0, 60.0, 4.0)) is None
    empty = contrast_flux(frame(-50.0, -50.0, 1.0, seed=3), (70, 50, 12, 12))
    assert empty is not None and empty[0] < 3 * empty[1]


def test_looming_from_the_flux_is_exact_where_whole_pixel_boxes_are_not() -> None:
    """A 0.3 m ball from 40 m at 10 m/s (2.3 -> 3.1 px radius in 1 s): with the flux the time
    to contact is within 10 % of the truth; the boxes' whole-pixel steps alone give none, or
    one further off."""
    k = Intrinsics(160, 120, 615.0, 615.0, 79.5, 59.5)
    d, z0, vz = 0.3, 40.0, -10.0
    with_flux = LoomingEstimator(k, window_s=1.0, min_samples=6, size_bias_px=4.0)
    boxes_only = LoomingEstimator(k, window_s=1.0, min_samples=6, size_bias_px=4.0)
    n = 30
    for i in range(n + 1):
        t = i / 30.0
        z = z0 + vz * t
        u, v, r = 80.3 + 0.5 * t, 60.2, k.fx * d / 2 / z
        b = box(u, v, r)
        f = contrast_flux(frame(u, v, r, seed=i), b)
        with_flux.add(t, tuple(float(x) for x in b), f)  # type: ignore[arg-type]
        boxes_only.add(t, tuple(float(x) for x in b))  # type: ignore[arg-type]
    true_tau = (z0 + vz * n / 30.0) / -vz
    e = with_flux.estimate(n / 30.0)
    assert e is not None and e.tau_s is not None
    assert e.tau_s == pytest.approx(true_tau, rel=0.10)
    eb = boxes_only.estimate(n / 30.0)
    assert eb is None or eb.tau_s is None or abs(eb.tau_s - true_tau) > abs(e.tau_s - true_tau)


def test_a_flux_that_jumps_is_not_trusted_and_the_boxes_decide() -> None:
    """A flux doubling every few frames (a blob merging with a cloud's edge) fits no course:
    the estimate is the boxes' one, exactly as without a flux."""
    k = Intrinsics(160, 120, 615.0, 615.0, 79.5, 59.5)
    a = LoomingEstimator(k, window_s=1.0, min_samples=6)
    b = LoomingEstimator(k, window_s=1.0, min_samples=6)
    for i in range(31):
        t = i / 30.0
        z = 12.0 - 6.0 * t
        s = k.fx * 0.3 / z
        bx = (80.0 - s / 2, 60.0 - s / 2, s, s)
        jumpy = (1000.0 * (2.0 if (i // 4) % 2 else 1.0), 20.0)
        a.add(t, bx, jumpy)
        b.add(t, bx)
    ea, eb = a.estimate(1.0), b.estimate(1.0)
    assert ea is not None and eb is not None and ea.tau_s is not None
    assert ea.tau_s == pytest.approx(eb.tau_s) and ea.size_chi2 == pytest.approx(eb.size_chi2)


def test_samples_without_a_flux_are_left_out_of_the_flux_fit_not_the_flux_given_up() -> None:
    """The ball of the test above, its first samples too faint for a flux (below five of its
    standard errors) and one patch cut by the edge (no flux): the fit is still the flux's,
    within 10 % of the true time to contact, and the same as with every sample's flux. With
    fewer than ``min_samples`` fluxes, or none in the newest sample, it is the boxes'."""
    k = Intrinsics(160, 120, 615.0, 615.0, 79.5, 59.5)
    d, z0, vz = 0.3, 40.0, -10.0
    n = 30
    every, some, stale = (LoomingEstimator(k, window_s=1.0, min_samples=6, size_bias_px=4.0)
                          for _ in range(3))
    boxes_only = LoomingEstimator(k, window_s=1.0, min_samples=6, size_bias_px=4.0)
    for i in range(n + 1):
        t = i / 30.0
        z = z0 + vz * t
        u, v, r = 80.3 + 0.5 * t, 60.2, k.fx * d / 2 / z
        b = tuple(float(x) for x in box(u, v, r))
        f = contrast_flux(frame(u, v, r, seed=i), box(u, v, r))
        assert f is not None
        faint = (f[0], f[0] / 4.0) if i < 8 else None if i == 15 else f
        every.add(t, b, f)  # type: ignore[arg-type]
        some.add(t, b, faint)  # type: ignore[arg-type]
        stale.add(t, b, f if i < n else None)  # type: ignore[arg-type]
        boxes_only.add(t, b)  # type: ignore[arg-type]
    true_tau = (z0 + vz * n / 30.0) / -vz
    e_every, e_some = every.estimate(n / 30.0), some.estimate(n / 30.0)
    assert e_every is not None and e_some is not None and e_some.tau_s is not None
    assert e_some.tau_s == pytest.approx(true_tau, rel=0.10)
    assert e_some.tau_s == pytest.approx(e_every.tau_s, rel=0.05)
    e_stale, e_boxes = stale.estimate(n / 30.0), boxes_only.estimate(n / 30.0)
    assert e_stale is not None and e_boxes is not None
    assert e_stale.tau_s == e_boxes.tau_s and e_stale.size_chi2 == e_boxes.size_chi2


def test_the_core_area_ignores_the_texture_around_the_object_that_the_flux_sums_in() -> None:
    """A dark disc on ground-like bands (+-6 grey over 6 px) drifting under it: the flux's
    square root over the radius wanders with the bands inside the patch, the core area's
    stays at sqrt(pi) within 8 %; with the contrast within the texture there is none."""
    rows = np.arange(120, dtype=np.float32)[:, None]
    bands = 6.0 * np.sin(rows / 6.0) + np.zeros((120, 160), np.float32)
    core_ratios, flux_ratios = [], []
    for i in range(12):
        v = 50.0 + 1.3 * i
        base = frame(80.3, v, 5.0, seed=i).astype(np.float32)
        g = np.clip(base + bands, 0, 255).astype(np.uint8)
        a = core_area(g, box(80.3, v, 5.0))
        f = contrast_flux(g, box(80.3, v, 5.0))
        assert a is not None and f is not None
        core_ratios.append(math.sqrt(a[0]) / 5.0)
        flux_ratios.append(math.sqrt(f[0]) / 5.0)
    assert np.allclose(core_ratios, math.sqrt(math.pi), rtol=0.08)
    assert np.ptp(core_ratios) / np.mean(core_ratios) < np.ptp(flux_ratios) / np.mean(flux_ratios)
    faint = np.clip(np.full((120, 160), 100.0) + bands * 3 + (frame(80.3, 60.0, 5.0) < 120) * -10.0, 0, 255)
    assert core_area(faint.astype(np.uint8), box(80.3, 60.0, 5.0)) is None


def test_a_photometric_size_noisier_than_it_says_fails_its_goodness_of_fit_and_the_boxes_decide() -> None:
    """A photometric size states its error, so its fit is a goodness-of-fit test. Sizes that
    keep to a course but scatter 2.5 times their stated error (reduced chi-square ~6: within
    the boxes' max_chi2 of 9, beyond what a course gives once in a thousand fits) are left to
    the boxes; the same sizes within their stated error are the fit's."""
    k = Intrinsics(160, 120, 615.0, 615.0, 79.5, 59.5)
    rng = np.random.default_rng(4)
    honest, noisy, boxes_only = (LoomingEstimator(k, window_s=1.0, min_samples=6, max_chi2=9.0)
                                 for _ in range(3))
    for i in range(31):
        t = i / 30.0
        z = 12.0 - 6.0 * t
        s = k.fx * 0.3 / z
        bx = (80.0 - s / 2, 60.0 - s / 2, s, s)
        area, std = math.pi * s * s / 4, 0.02 * math.pi * s * s / 4
        honest.add(t, bx, None, (area + rng.normal(0, std), std))
        noisy.add(t, bx, None, (area + rng.normal(0, 2.5 * std), std))
        boxes_only.add(t, bx)
    eh, en, eb = honest.estimate(1.0), noisy.estimate(1.0), boxes_only.estimate(1.0)
    assert eh is not None and en is not None and eb is not None
    assert eh.size_chi2 < 2.0 and eh.size_chi2 != eb.size_chi2
    assert en.size_chi2 == pytest.approx(eb.size_chi2) and en.tau_s == pytest.approx(eb.tau_s)
