"""agvviz.sim.imaging: each error source changes the image the way physics says, each draws
from its own stream, and everything off renders exactly as render_frame does."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from agvviz.geometry import se3
from agvviz.geometry.camera import PinholeCamera
from agvviz.sim import imaging
from agvviz.sim.render import FloorCode, FloorScene, RenderError, render_frame, render_irradiance

WHITE_DN, BLACK_DN = 200.0, 40.0


def _camera(width_px=64, height_px=48, focal_px=100.0, dist=(0.0, 0.0)) -> PinholeCamera:
    K = np.array([[focal_px, 0.0, (width_px - 1) / 2.0], [0.0, focal_px, (height_px - 1) / 2.0], [0.0, 0.0, 1.0]])
    return PinholeCamera(K, np.array([*dist, 0.0, 0.0, 0.0]), width_px, height_px)


def _looking_down(x_m: float, y_m: float, height_m: float) -> np.ndarray:
    """Camera straight above (x, y): image u along world +x, v along world −y."""
    return se3.make(np.diag([1.0, -1.0, -1.0]), [x_m, y_m, height_m])


def _half_plane_scene() -> FloorScene:
    """A black label (1 module, no quiet zone) of 4 m covering world x < 0 near the origin, on
    a white floor: a straight vertical edge at world x = 0 in the image."""
    code = FloorCode("edge", "", se3.make(np.eye(3), [-2.0, 0.0, 0.0]), 4.0, np.ones((1, 1), bool),
                     np.zeros((4, 3)), quiet_zone_modules=0)
    return FloorScene(codes=(code,), floor_dn=WHITE_DN, black_dn=BLACK_DN, white_dn=WHITE_DN)


def _qr_like_scene(seed: int = 0) -> FloorScene:
    modules = np.random.default_rng(seed).uniform(size=(11, 11)) < 0.5
    code = FloorCode("q", "", np.eye(4), 0.2, modules, np.zeros((4, 3)), quiet_zone_modules=2)
    return FloorScene(codes=(code,), floor_dn=120.0, black_dn=BLACK_DN, white_dn=WHITE_DN)


def _edge_positions_px(image: np.ndarray) -> np.ndarray:
    """Per row, the u of the dark→light edge from the area under the profile: the dark area
    (in pixels) left of the edge, minus ½ for the pixel-centre convention."""
    darkness = (WHITE_DN - image.astype(float)) / (WHITE_DN - BLACK_DN)
    return darkness.sum(axis=1) - 0.5


# -- everything off: today's renderer ------------------------------------------------------------
def test_all_off_renders_exactly_as_render_frame():
    scene, camera = _qr_like_scene(), _camera()
    T = se3.make(np.diag([1.0, -1.0, -1.0]) @ se3.exp(np.array([0, 0, 0, 0.2, 0.1, 0.3]))[:3, :3], [0.01, 0.0, 0.35])
    expected = render_frame(scene, camera, T, np.random.default_rng(7))
    irradiance = imaging.render_exposure(scene, camera, lambda t_s: T, 0.0)
    frame = imaging.camera_frame(irradiance, camera, imaging.IDEAL_IMAGING, {"read_noise": np.random.default_rng(7)})
    assert np.array_equal(frame, expected)
    # The hooks at their defaults change nothing either.
    assert imaging.print_label(scene.codes[0], scene, imaging.IDEAL_IMAGING, {}) is scene.codes[0]
    full = render_irradiance(scene, camera, T, 4)
    assert np.array_equal(render_irradiance(scene, camera, T, 4, pixel_aperture=1.0), full)
    band = render_irradiance(scene, camera, T, 4, row_range=(10, 30))
    assert np.array_equal(band[10:30], full[10:30]) and np.all(band[:10] == scene.floor_dn)
    textured = dataclasses.replace(scene.codes[0], texture_dn=imaging.ideal_texture_dn(scene.codes[0], scene, 1))
    assert np.array_equal(render_irradiance(dataclasses.replace(scene, codes=(textured,)), camera, T, 4), full)


def test_finer_texture_of_the_same_print_renders_the_same():
    """r = 3 texels per module of the ideal print: the same edges, so the same image up to the
    float32 rounding of a texel lookup at the edges (a sub-sample within ~1e-6 texel of an edge
    may change sides: one sub-sample of 16 moves a pixel by (WHITE − BLACK)/16 = 10 DN)."""
    scene, camera = _qr_like_scene(), _camera()
    T = _looking_down(0.003, -0.002, 0.3)
    fine = dataclasses.replace(scene.codes[0], texture_dn=imaging.ideal_texture_dn(scene.codes[0], scene, 3))
    a = render_irradiance(scene, camera, T, 4)
    b = render_irradiance(dataclasses.replace(scene, codes=(fine,)), camera, T, 4)
    assert np.mean(a != b) < 0.01 and np.max(np.abs(a - b)) <= 10.0 + 1e-3


def test_bad_parameters_raise_one_clear_error():
    with pytest.raises(RenderError, match="defocus_radius_px"):
        imaging.ImagingErrors(defocus_radius_px=-1.0)
    with pytest.raises(RenderError, match="pixel_aperture"):
        imaging.ImagingErrors(pixel_aperture=0.0)
    with pytest.raises(RenderError, match="jpeg_quality"):
        imaging.ImagingErrors(jpeg_quality=101)
    with pytest.raises(RenderError, match="row_range"):
        render_irradiance(_qr_like_scene(), _camera(), _looking_down(0, 0, 0.3), row_range=(5, 5))
    bad = dataclasses.replace(_qr_like_scene().codes[0], texture_dn=np.zeros((16, 16)))
    with pytest.raises(RenderError, match="texture_dn"):
        render_irradiance(FloorScene(codes=(bad,)), _camera(), _looking_down(0, 0, 0.3))


# -- optics ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("radius_px", [0.7, 2.0, 3.5])
def test_disk_psf_conserves_energy_and_has_the_radius_asked(radius_px):
    kernel = imaging.disk_kernel(radius_px).astype(float)
    k = kernel.shape[0] // 2
    assert kernel.sum() == pytest.approx(1.0, abs=1e-6)
    x = np.arange(-k, k + 1, dtype=float)
    r2 = x[None, :] ** 2 + x[:, None] ** 2
    # No pixel whose nearest point lies beyond R carries light; every pixel wholly inside does.
    assert np.all(kernel[np.sqrt(r2) > radius_px + np.sqrt(0.5)] == 0)
    assert np.all(kernel[np.sqrt(r2) < radius_px - np.sqrt(0.5)] > 0)
    # Second moment of a uniform disk: E[x² + y²] = R²/2; integrating over the kernel's pixels
    # adds a pixel box's 1/12 per axis. Tolerance: the 16×16 sub-sampling of the disk edge
    # (≈1/16 px on the radius, ≈2·(1/16)/R relative on R²) with a margin.
    moment = float(np.sum(kernel * r2))
    assert moment == pytest.approx(radius_px**2 / 2.0 + 1.0 / 6.0, rel=0.15 / radius_px)


def test_vignetting_at_the_corner_follows_cos4():
    camera = _camera(64, 48, 50.0)
    gain = imaging.vignetting_gain(camera, 0.6)
    tan_theta = np.hypot(0 - camera.K[0, 2], 0 - camera.K[1, 2]) / 50.0
    cos4 = 1.0 / (1.0 + tan_theta**2) ** 2
    assert gain[0, 0] == pytest.approx(1.0 - 0.6 * (1.0 - cos4), rel=1e-6)
    assert gain.max() == pytest.approx(1.0, abs=1e-3)  # centre pixels (0.5 px off axis)


def test_illumination_field_is_smooth_with_the_asked_spread():
    gain = imaging.illumination_gain((48, 64), 0.1, 20.0, np.random.default_rng(3)).astype(float)
    assert gain.std() == pytest.approx(0.1, rel=1e-3) and gain.mean() == pytest.approx(1.0, abs=1e-6)
    # Smooth: a field correlated over 20 px changes by ≈σ/20 per pixel (10× that bounds the
    # largest step over the image); white noise would step by ≈σ·√2 = 0.14 per pixel.
    assert np.max(np.abs(np.diff(gain, axis=1))) < 0.1 * 10 / 20


# -- exposure ------------------------------------------------------------------------------------
SPEED_MPS, HEIGHT_M, FOCAL_PX = 0.5, 1.0, 100.0
IMAGE_SPEED_PX_S = FOCAL_PX * SPEED_MPS / HEIGHT_M  # 50 px/s


def _moving_pose(t_s: float) -> np.ndarray:
    """Camera 1 m above the floor moving along world −x: the edge moves along +u."""
    return _looking_down(-SPEED_MPS * t_s, 0.0, HEIGHT_M)


def test_motion_blur_spreads_an_edge_by_speed_times_exposure():
    """The edge's line-spread function (derivative of the row profile) widens by the motion:
    N samples spaced L/N over the path L = speed · exposure add the variance L²(N² − 1)/(12N²);
    its mean moves by L/2 (the exposure's middle).

    The LSF of one edge at fraction f into a pixel is (1 − f, f) on two pixels, variance
    f(1 − f). Static, the edge sits on a pixel boundary (f = 0); the 12 moving copies sit at
    0.25 + 0.5 j px (f = ¼ or ¾, variance 3/16 each) — positions the 8 × 8 sub-samples resolve
    exactly, so both variances are exact and the motion's must match to rounding."""
    camera = _camera(48, 8, FOCAL_PX)
    scene = _half_plane_scene()
    exposure_s, n = 0.12, 12  # L = 6 px
    static = imaging.render_exposure(scene, camera, _moving_pose, 0.0, supersample=8)
    moving = imaging.render_exposure(scene, camera, _moving_pose, 0.0, exposure_s=exposure_s, time_samples=n, supersample=8)

    def spread(row):
        lsf = np.diff(row.astype(float))
        lsf = lsf / lsf.sum()
        u = np.arange(lsf.size) + 0.5
        mean = np.sum(lsf * u)
        return mean, np.sum(lsf * (u - mean) ** 2)

    (mean0, var0), (mean1, var1) = spread(static[4]), spread(moving[4])
    path_px = IMAGE_SPEED_PX_S * exposure_s
    assert mean1 - mean0 == pytest.approx(path_px / 2.0, abs=0.01)
    assert var0 == pytest.approx(0.0, abs=1e-9)
    assert var1 == pytest.approx(path_px**2 * (n**2 - 1) / (12 * n**2) + 3.0 / 16.0, abs=1e-4)


def test_rolling_shutter_shears_rows_by_line_delay_times_row_times_speed():
    camera = _camera(48, 40, FOCAL_PX)
    line_delay_s = 0.004  # 0.2 px per row at 50 px/s
    image = imaging.render_exposure(
        _half_plane_scene(), camera, _moving_pose, 0.0, line_delay_s=line_delay_s, rows_per_band=1, supersample=8
    )
    edges = _edge_positions_px(image)
    slope = np.polyfit(np.arange(camera.height_px), edges, 1)[0]
    # Each row's edge position is exact to the area integration's 1/64-px steps.
    assert slope == pytest.approx(line_delay_s * IMAGE_SPEED_PX_S, rel=0.01)
    assert edges[0] == pytest.approx(camera.K[0, 2], abs=0.05)  # row 0 exposed at t = 0


def test_pixel_aperture_point_samples_the_pixel_centre():
    """Aperture → 0: a pixel is dark or light according to its centre alone."""
    camera = _camera(48, 8, FOCAL_PX)
    T = _looking_down(-0.0033, 0.0, HEIGHT_M)  # edge at u = cx + 0.33 px
    image = render_irradiance(_half_plane_scene(), camera, T, 4, pixel_aperture=1e-3)
    assert set(np.unique(image)) == {BLACK_DN, WHITE_DN}
    whole = render_irradiance(_half_plane_scene(), camera, T, 4)
    assert len(np.unique(whole)) > 2


# -- sensor ------------------------------------------------------------------------------------------
def test_noise_variance_is_signal_over_gain_plus_read_squared():
    """Flat 100 DN, 2 e⁻/DN, read noise 3 DN: var = 100/2 + 9 + 1/12 (quantisation) DN².
    The sample variance of n = 16 384 pixels has a relative std √(2/n) ≈ 1.1 %: ±5 % is > 4σ."""
    errors = imaging.ImagingErrors(shot_gain_e_per_dn=2.0, read_noise_dn=3.0)
    camera = _camera(128, 128)
    frame = imaging.camera_frame(np.full((128, 128), 100.0, np.float32), camera, errors, imaging.source_rngs(11, 0))
    assert frame.astype(float).var() == pytest.approx(100.0 / 2.0 + 9.0 + 1.0 / 12.0, rel=0.05)
    assert frame.astype(float).mean() == pytest.approx(100.0, abs=0.3)


def test_switching_one_source_off_leaves_every_other_draw_unchanged():
    camera = _camera()
    irradiance = render_irradiance(_qr_like_scene(), camera, _looking_down(0, 0, 0.3))
    on = dataclasses.replace(imaging.TYPICAL_IMAGING, jpeg_quality=0)
    for source, off in (("shot_noise", {"shot_gain_e_per_dn": 0.0}), ("illumination", {"illumination_sigma": 0.0})):
        rngs_on, rngs_off = imaging.source_rngs(5, 3), imaging.source_rngs(5, 3)
        imaging.camera_frame(irradiance, camera, on, rngs_on)
        imaging.camera_frame(irradiance, camera, dataclasses.replace(on, **off), rngs_off)
        for name in imaging.SOURCES:
            if name == "shot_noise" and source != name:
                continue  # Poisson draws consume a signal-dependent count of numbers (physics)
            same = rngs_on[name].bit_generator.state == rngs_off[name].bit_generator.state
            assert same == (name != source), (source, name)
    # Exactly: without shot noise the frame is the noiseless one plus the same read-noise draw.
    no_shot = dataclasses.replace(imaging.ImagingErrors(read_noise_dn=2.0, illumination_sigma=0.1))
    a = imaging.sensor_image(imaging.optical_image(irradiance, camera, no_shot, imaging.source_rngs(5, 3)), no_shot, imaging.source_rngs(5, 3))
    clean = imaging.optical_image(irradiance, camera, no_shot, imaging.source_rngs(5, 3))
    read = 2.0 * imaging.source_rngs(5, 3)["read_noise"].standard_normal(clean.shape, dtype=np.float32)
    assert np.array_equal(a, clean + read)


def test_print_effects_draw_from_their_own_streams():
    scene = _qr_like_scene()
    code = scene.codes[0]
    errors = dataclasses.replace(imaging.HARSH_IMAGING, occlusion_probability=1.0)
    with_glare = imaging.print_label(code, scene, errors, imaging.source_rngs(2, 9)).texture_dn
    without = imaging.print_label(code, scene, dataclasses.replace(errors, glare_peak_dn=0.0), imaging.source_rngs(2, 9)).texture_dn
    # Glare only adds light (before the occluder's floor disk, which it cannot change), so the
    # two prints differ only where the glare blob is, and there the glare print is brighter.
    assert np.all(with_glare >= without - 1e-9)
    occluded = np.isclose(without, scene.floor_dn) & np.isclose(with_glare, scene.floor_dn)
    assert occluded.any()  # the occluder is drawn identically in both


# -- print ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("spread_modules", [0.1, 0.3, -0.2])
def test_ink_spread_grows_dark_areas_by_the_asked_fraction(spread_modules):
    """An isolated dark 3×3-module block: the ink across the row through its centre is
    (3 + 2·spread) modules (straight edges along the texel grid: the coverage is exact)."""
    r = 8
    dark = np.zeros((9, 9), bool)
    dark[3:6, 3:6] = True
    coverage = imaging.ink_coverage(np.kron(dark, np.ones((r, r), bool)), spread_modules * r)
    assert coverage[4 * r + r // 2].sum() / r == pytest.approx(3 + 2 * spread_modules, abs=1e-9)


def test_paper_warp_moves_the_print_by_the_asked_rms():
    """A white label with one dark column of texels: its displacement along x per row has the
    asked RMS (the field is normalised to unit std over the label; per-row sampling of 48
    correlated rows leaves ≈±30 %)."""
    texture = np.full((48, 48), WHITE_DN)
    texture[:, 24] = BLACK_DN
    warped = imaging.warp_texture(texture, 0.5, 200.0, np.random.default_rng(4))
    darkness = (WHITE_DN - warped) / (WHITE_DN - BLACK_DN)
    centre = (darkness * np.arange(48)).sum(axis=1) / darkness.sum(axis=1)
    assert np.abs(centre - 24).max() > 0.05 and np.sqrt(np.mean((centre - 24) ** 2)) < 1.0
