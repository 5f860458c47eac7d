"""The error sources of a real camera and a real print, each on its own (issue 14).

:func:`agvviz.sim.render.render_frame` draws a perfectly printed, evenly lit code through a
Gaussian blur and Gaussian noise. This module adds what a real frame has, every source a field
of :class:`ImagingErrors` whose zero default switches it off:

============================  ==================================================================
source                        model
============================  ==================================================================
print: ink spread             dark areas grow by ``ink_spread_modules`` on every edge (negative:
                              light areas grow); texels partly covered get the covered fraction
print: paper warp             the pattern displaced in the label plane by a smooth random field
                              of RMS ``paper_warp_m`` per axis, correlation length
                              ``paper_warp_scale_m`` (printer registration and banding, paper
                              cockle seen obliquely)
print: paper texture          reflectance × (1 + ``paper_texture_sigma`` · N(0, 1)) per texel
print: glare                  + ``glare_peak_dn`` · Gaussian blob (σ ``glare_sigma_m``) at a
                              uniform point of the label (a lamp's reflection in a glossy print)
print: dirt                   Poisson(``dirt_spots_per_label``) spots of radius ``dirt_radius_m``
                              removing up to ``dirt_darkening`` of the reflectance
print: occlusion              with probability ``occlusion_probability`` a disk of floor
                              (radius ``occlusion_radius_fraction`` · label side) centred on a
                              uniform point of the label's outline
exposure: motion blur         each row integrates ``exposure_s``: the average of renders at
                              ``time_samples`` poses from the caller's pose-at-time function
pixel aperture                each pixel integrates a square of side ``pixel_aperture`` · pitch
                              (1 — the default, no error — the whole pixel; small: point
                              sampling, aliased edges, as decimated read-out or downscaling)
exposure: rolling shutter     row v starts its exposure ``v · line_delay_s`` after row 0
                              (rendered in bands of ``rows_per_band`` rows, one time per band)
light: uneven illumination    gain 1 + ``illumination_sigma`` · z, z a smooth unit-variance
                              field with correlation length ≈ ``illumination_scale_px``
optics: vignetting            gain 1 − ``vignetting_strength`` · (1 − cos⁴ θ), θ the pixel's
                              angle off the optical axis (strength 1: the natural cos⁴ law)
optics: defocus               disk PSF of radius ``defocus_radius_px`` (area-integrated kernel)
optics: Gaussian blur         σ ``blur_sigma_px`` (:func:`render_frame`'s ``blur_sigma_px``)
sensor: shot noise            electrons = Poisson(DN · ``shot_gain_e_per_dn``), back to DN
sensor: read noise            + ``read_noise_dn`` · N(0, 1) (:func:`render_frame`'s noise)
encoding: JPEG                round trip at ``jpeg_quality`` (0: none)
============================  ==================================================================

Random draws: every source draws from its own ``numpy.random.Generator`` (:func:`source_rngs`
gives one per name of :data:`SOURCES` from a seed and a key, e.g. the frame index or the code
index), and a source that is off draws nothing, so switching one source off leaves every other
source's draws — and so its effect — unchanged: the counterfactual of issue 14's error budget
is exact. ``ImagingErrors(blur_sigma_px=b, read_noise_dn=n)`` with the read-noise stream
``rng`` renders exactly :func:`render_frame` (…, rng, blur_sigma_px=b, noise_sigma_dn=n).

Order of image formation: print (once per code, :func:`print_label`) → exposure (geometry,
:func:`render_exposure`) → illumination → vignetting → defocus → Gaussian blur → shot noise →
read noise → quantisation → JPEG (:func:`camera_frame`). Math only: no files, no printing.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import cv2
import numpy as np

from agvviz.geometry.camera import PinholeCamera
from agvviz.sim.render import (
    FloorCode,
    FloorScene,
    RenderError,
    codes_in_view,
    render_irradiance,
    undistorted_rays,
)

#: Names of the random streams, one per source that draws. The index of a name is part of its
#: stream's seed: append new names, never reorder.
SOURCES = ("illumination", "shot_noise", "read_noise", "paper_texture", "glare", "dirt", "occlusion", "paper_warp")
#: Sources that change the print (drawn once per code by :func:`print_label`).
PRINT_SOURCES = ("paper_warp", "paper_texture", "glare", "dirt", "occlusion")
#: Texels per module of a printed texture: ink spread is represented by partial coverage, so
#: any spread works at this resolution; paper texture has this grain.
DEFAULT_TEXELS_PER_MODULE = 4
#: Largest accepted disk PSF radius (the kernel is (2R + 3)² pixels).
MAX_DEFOCUS_RADIUS_PX = 50.0


@dataclass(frozen=True)
class ImagingErrors:
    """Image-formation and print error sources; every default is "off" (an ideal camera and
    print). See the module docstring for each model."""

    # print (per code, :func:`print_label`)
    ink_spread_modules: float = 0.0  # edge growth of dark areas, in modules (< 0: light grows)
    paper_texture_sigma: float = 0.0  # relative reflectance std per texel
    paper_warp_m: float = 0.0  # RMS in-plane displacement of the printed pattern, metres
    paper_warp_scale_m: float = 0.01  # correlation length of that displacement, metres
    glare_peak_dn: float = 0.0  # brightness added at the glare blob's centre, DN
    glare_sigma_m: float = 0.01  # glare blob σ on the label, metres
    dirt_spots_per_label: float = 0.0  # mean number of dirt spots per label (Poisson)
    dirt_radius_m: float = 0.003  # dirt spot radius (Gaussian σ), metres
    dirt_darkening: float = 0.5  # largest fraction of reflectance a spot removes, 0..1
    occlusion_probability: float = 0.0  # chance a label is partly covered, 0..1
    occlusion_radius_fraction: float = 0.15  # occluder radius / label side
    # exposure (per frame, :func:`render_exposure`)
    exposure_s: float = 0.0  # exposure time of each row, seconds
    line_delay_s: float = 0.0  # rolling shutter: row v starts v · line_delay_s after row 0
    pixel_aperture: float = 1.0  # side of each pixel's light-gathering square / pitch (1: whole)
    # light and optics (per frame, :func:`camera_frame`)
    illumination_sigma: float = 0.0  # relative std of the illumination gain field
    illumination_scale_px: float = 200.0  # correlation length of that field, pixels
    vignetting_strength: float = 0.0  # 0..1: 1 is the natural cos⁴ law
    defocus_radius_px: float = 0.0  # disk PSF radius, pixels
    blur_sigma_px: float = 0.0  # Gaussian optical blur σ, pixels
    # sensor and encoding
    shot_gain_e_per_dn: float = 0.0  # conversion gain, electrons per DN (0: no shot noise)
    read_noise_dn: float = 0.0  # Gaussian read noise σ, DN
    jpeg_quality: int = 0  # JPEG round trip quality 1..100 (0: none)

    def __post_init__(self):
        check_imaging_errors(self)

    @property
    def prints_ideally(self) -> bool:
        """True when no print effect is on (:func:`print_label` returns codes unchanged)."""
        return (
            self.ink_spread_modules == 0
            and self.paper_warp_m == 0
            and self.paper_texture_sigma == 0
            and self.glare_peak_dn == 0
            and self.dirt_spots_per_label == 0
            and self.occlusion_probability == 0
        )


def check_imaging_errors(errors: ImagingErrors) -> None:
    """RenderError naming the first field out of its physical range."""
    for field in dataclasses.fields(errors):
        value = getattr(errors, field.name)
        if not (isinstance(value, (int, float)) and math.isfinite(value)):
            raise RenderError(f"imaging error {field.name} must be a finite number, got {value!r}")
    non_negative = (
        "paper_texture_sigma", "paper_warp_m", "glare_peak_dn", "glare_sigma_m", "dirt_spots_per_label", "dirt_radius_m",
        "exposure_s", "line_delay_s", "illumination_sigma", "defocus_radius_px", "blur_sigma_px",
        "shot_gain_e_per_dn", "read_noise_dn",
    )
    for name in non_negative:
        if getattr(errors, name) < 0:
            raise RenderError(f"imaging error {name} must be ≥ 0, got {getattr(errors, name)}")
    for name in ("dirt_darkening", "occlusion_probability", "vignetting_strength"):
        if not 0 <= getattr(errors, name) <= 1:
            raise RenderError(f"imaging error {name} must lie in 0..1, got {getattr(errors, name)}")
    if not -0.5 < errors.ink_spread_modules < 0.5:
        raise RenderError(f"ink_spread_modules must lie in (-0.5, 0.5), got {errors.ink_spread_modules}")
    if not 0 < errors.pixel_aperture <= 1:
        raise RenderError(f"pixel_aperture must lie in (0, 1], got {errors.pixel_aperture}")
    if errors.paper_warp_scale_m <= 0:
        raise RenderError(f"paper_warp_scale_m must be > 0, got {errors.paper_warp_scale_m}")
    if errors.illumination_scale_px <= 0 or not 0 < errors.occlusion_radius_fraction <= 1:
        raise RenderError("illumination_scale_px must be > 0 and occlusion_radius_fraction in (0, 1]")
    if errors.defocus_radius_px > MAX_DEFOCUS_RADIUS_PX:
        raise RenderError(f"defocus_radius_px must be ≤ {MAX_DEFOCUS_RADIUS_PX}, got {errors.defocus_radius_px}")
    if errors.jpeg_quality != int(errors.jpeg_quality) or not 0 <= errors.jpeg_quality <= 100:
        raise RenderError(f"jpeg_quality must be an integer in 0..100 (0: no JPEG), got {errors.jpeg_quality}")


# -- profiles ------------------------------------------------------------------------------------
#: What :func:`render_frame`'s defaults render (Gaussian blur 0.8 px, read noise 2 DN): the
#: reference world of the solver studies.
IDEAL_IMAGING = ImagingErrors(blur_sigma_px=0.8, read_noise_dn=2.0)

#: Typical: calibrated on real photographs — bench/bench_render_vs_photos.py renders the
#: ChArUco board of ``../shared/data/opencv_contrib_aruco`` at each photo's pose and
#: calibration; the leave-one-marker-out corner residual of the renders matches the photos'
#: (median within ±30 %, ECC and OpenCV's plain corners). The three sources that set it:
TYPICAL_IMAGING = ImagingErrors(
    # (1) The print is not where the file says: 0.15 mm RMS smooth in-plane displacement over
    # ≈1 cm — laser-printer registration/banding (≈0.1 mm) plus a sheet that is not flat,
    # seen obliquely. Sets ECC's residual (0.05 px without, 0.29 px with; real 0.29 px).
    paper_warp_m=1.5e-4,
    paper_warp_scale_m=0.01,
    # (2) Light areas grow into dark ones by 0.1 module (0.25 mm on 2.5 mm modules): thin
    # toner plus the light a bright white scatters into dark areas in lens and sensor.
    # Sets the inward bias of contour corners (OpenCV plain: 0.75 → 0.98 px; real 0.98 px).
    ink_spread_modules=-0.1,
    # (3) Point-like pixels: the photos are phone images decimated to 640×480, edges alias
    # (pixel staircases, hardly any grey edge pixels). Sensors read out in a skipping mode
    # do the same; a native-resolution camera has ≈1.
    pixel_aperture=0.25,
    # The rest are ordinary values for a camera under room light and barely move the residual:
    paper_texture_sigma=0.03,  # office paper: a few % reflectance grain
    glare_peak_dn=20.0,  # a lamp's broad, faint reflection in matte paper
    glare_sigma_m=0.02,
    dirt_spots_per_label=1.0,
    dirt_radius_m=0.002,
    dirt_darkening=0.3,
    exposure_s=0.002,  # 2 ms: ≈1 px motion blur at 1 m/s, 1.8 m range, f = 1000 px
    line_delay_s=15e-6,  # rolling shutter: 15 ms readout of 1024 rows
    illumination_sigma=0.1,  # ±10 % lighting over a few hundred pixels
    illumination_scale_px=250.0,
    vignetting_strength=0.5,  # a lens at f/2–f/4: about half the natural cos⁴ law
    defocus_radius_px=0.5,  # fixed-focus lens slightly out of focus
    blur_sigma_px=0.4,  # the lens's own blur
    shot_gain_e_per_dn=40.0,  # ≈10 000 e⁻ full well over 255 DN
    read_noise_dn=2.0,
    jpeg_quality=90,
)

#: Harsh: a worn, dirty floor, a cheap soft lens, dim light (long exposure, low full well).
#: On the photos' board: ECC ≈2.4× the real residual, plain ≈0.8× (blur and ink growth move
#: contour corners outwards again), about half the markers lost.
HARSH_IMAGING = ImagingErrors(
    paper_warp_m=3e-4,
    paper_warp_scale_m=0.01,
    ink_spread_modules=0.06,
    pixel_aperture=0.25,
    paper_texture_sigma=0.06,
    glare_peak_dn=60.0,
    glare_sigma_m=0.03,
    dirt_spots_per_label=5.0,
    dirt_radius_m=0.004,
    dirt_darkening=0.6,
    occlusion_probability=0.2,
    occlusion_radius_fraction=0.15,
    exposure_s=0.008,
    line_delay_s=30e-6,
    illumination_sigma=0.25,
    illumination_scale_px=200.0,
    vignetting_strength=1.0,
    defocus_radius_px=1.5,
    blur_sigma_px=1.0,
    shot_gain_e_per_dn=10.0,
    read_noise_dn=4.0,
    jpeg_quality=75,
)


# -- random streams ------------------------------------------------------------------------------
def source_rngs(seed: int, *key: int) -> dict[str, np.random.Generator]:
    """One independent generator per name of :data:`SOURCES`, from ``seed`` and a key of
    non-negative integers (e.g. ``(frame_index,)`` or ``(code_index,)``): the stream of a
    source depends only on the seed, the key and the source's name."""
    if any(int(k) != k or k < 0 for k in key) or int(seed) != seed or seed < 0:
        raise RenderError(f"seed and key must be non-negative integers, got {seed}, {key}")
    return {
        name: np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(*map(int, key), index)))
        for index, name in enumerate(SOURCES)
    }


def _stream(rngs: Mapping[str, np.random.Generator], name: str) -> np.random.Generator:
    try:
        return rngs[name]
    except KeyError:
        raise RenderError(f"no random stream {name!r} given (see imaging.source_rngs)") from None


# -- print ---------------------------------------------------------------------------------------
def ideal_texture_dn(code: FloorCode, scene: FloorScene, texels_per_module: int) -> np.ndarray:
    """The label as ideally printed, (m, m) float64 DN, m = (n + 2q)·r texels."""
    if int(texels_per_module) != texels_per_module or texels_per_module < 1:
        raise RenderError(f"texels_per_module must be an integer ≥ 1, got {texels_per_module}")
    r = int(texels_per_module)
    dark = np.pad(code.modules, code.quiet_zone_modules, constant_values=False)
    dark = np.kron(dark, np.ones((r, r), dtype=bool))
    return np.where(dark, scene.black_dn, scene.white_dn).astype(float)


def ink_coverage(dark: np.ndarray, spread_texels: float) -> np.ndarray:
    """Ink coverage (0..1) of each texel of a binary print ``dark`` ((m, m) bool) whose dark
    areas grow by ``spread_texels`` on every edge (shrink for a negative value).

    A texel whose centre lies d from the nearest texel centre of the other kind has its near
    side ≈ d − 1 from the edge; the ink covers the fraction clip(spread − (d − 1), 0, 1) of it
    (exact for an edge along the texel grid; the corners of the grown area are rounded, as
    real ink's are).
    """
    grow_dark = spread_texels >= 0
    source = dark if grow_dark else ~dark
    coverage = source.astype(float)
    if spread_texels == 0 or not source.any():
        return coverage if grow_dark else 1.0 - coverage
    other = (~source).astype(np.uint8)
    distance = cv2.distanceTransform(other, cv2.DIST_L2, cv2.DIST_MASK_PRECISE).astype(float)
    grown = np.clip(abs(spread_texels) - (distance - 1.0), 0.0, 1.0)
    coverage = np.where(source, 1.0, grown)
    return coverage if grow_dark else 1.0 - coverage


def print_label(
    code: FloorCode,
    scene: FloorScene,
    errors: ImagingErrors,
    rngs: Mapping[str, np.random.Generator],
    texels_per_module: int = DEFAULT_TEXELS_PER_MODULE,
) -> FloorCode:
    """``code`` as really printed and lying on the floor: a copy whose ``texture_dn`` carries
    ink spread, paper texture, glare, dirt and occlusion. ``code`` itself when no print effect
    is on (then it renders exactly as before). ``rngs``: :func:`source_rngs` streams of this
    code (e.g. key ``(code_index,)``); each effect draws only from its own stream."""
    if errors.prints_ideally:
        return code
    r = texels_per_module
    texture = ideal_texture_dn(code, scene, r)
    m = texture.shape[0]
    texel_m = code.module_m / r
    if errors.ink_spread_modules != 0:
        dark = texture == scene.black_dn
        coverage = ink_coverage(dark, errors.ink_spread_modules * r)
        texture = scene.white_dn + coverage * (scene.black_dn - scene.white_dn)
    if errors.paper_warp_m > 0:
        texture = warp_texture(
            texture, errors.paper_warp_m / texel_m, errors.paper_warp_scale_m / texel_m, _stream(rngs, "paper_warp")
        )
    if errors.paper_texture_sigma > 0:
        grain = _stream(rngs, "paper_texture").standard_normal((m, m))
        texture = texture * np.maximum(1.0 + errors.paper_texture_sigma * grain, 0.0)
    # Texel centres in metres from the label's top-left corner: x right, y down.
    centres_m = (np.arange(m) + 0.5) * texel_m
    x_m, y_m = np.meshgrid(centres_m, centres_m)
    side_m = m * texel_m
    if errors.dirt_spots_per_label > 0:
        rng = _stream(rngs, "dirt")
        count = rng.poisson(errors.dirt_spots_per_label)
        spots = rng.uniform(0.0, side_m, size=(count, 2))
        strengths = rng.uniform(0.0, errors.dirt_darkening, size=count)
        for (sx, sy), strength in zip(spots, strengths):
            profile = np.exp(-((x_m - sx) ** 2 + (y_m - sy) ** 2) / (2.0 * errors.dirt_radius_m**2))
            texture = texture * (1.0 - strength * profile)
    if errors.glare_peak_dn > 0:
        gx, gy = _stream(rngs, "glare").uniform(0.0, side_m, size=2)
        blob = np.exp(-((x_m - gx) ** 2 + (y_m - gy) ** 2) / (2.0 * errors.glare_sigma_m**2))
        texture = texture + errors.glare_peak_dn * blob
    if errors.occlusion_probability > 0:
        rng = _stream(rngs, "occlusion")
        occluded, along = rng.uniform(size=2)
        if occluded < errors.occlusion_probability:
            ox, oy = _point_on_outline(along * 4.0, side_m)
            radius_m = errors.occlusion_radius_fraction * side_m
            texture = np.where((x_m - ox) ** 2 + (y_m - oy) ** 2 <= radius_m**2, scene.floor_dn, texture)
    return dataclasses.replace(code, texture_dn=np.clip(texture, 0.0, 255.0))


def smooth_field(shape: tuple[int, int], scale: float, rng: np.random.Generator) -> np.ndarray:
    """A smooth random field (float64) of zero mean and unit standard deviation over ``shape``:
    normal draws on a grid of spacing ≈ ``scale`` (in array cells, at least 2 × 2 draws),
    interpolated bicubically."""
    height, width = shape
    rows = max(int(math.ceil(height / scale)), 2)
    cols = max(int(math.ceil(width / scale)), 2)
    coarse = rng.standard_normal((rows, cols)).astype(np.float32)
    field = cv2.resize(coarse, (width, height), interpolation=cv2.INTER_CUBIC).astype(float)
    spread = field.std()
    return (field - field.mean()) / spread if spread > 0 else np.zeros_like(field)


def warp_texture(texture: np.ndarray, rms_texels: float, scale_texels: float, rng: np.random.Generator) -> np.ndarray:
    """``texture`` displaced by a smooth random field of RMS ``rms_texels`` per axis (two
    :func:`smooth_field` draws, x then y), resampled bilinearly; beyond the edge the nearest
    texel is repeated."""
    m_rows, m_cols = texture.shape
    dx = rms_texels * smooth_field(texture.shape, scale_texels, rng)
    dy = rms_texels * smooth_field(texture.shape, scale_texels, rng)
    cols, rows = np.meshgrid(np.arange(m_cols, dtype=float), np.arange(m_rows, dtype=float))
    return cv2.remap(
        texture.astype(np.float32), (cols - dx).astype(np.float32), (rows - dy).astype(np.float32),
        cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE,
    ).astype(float)


def _point_on_outline(t: float, side_m: float) -> tuple[float, float]:
    """Point at perimeter parameter t ∈ [0, 4) of the square [0, side]²: one unit per edge."""
    edge, fraction = int(t) % 4, t - int(t)
    s = fraction * side_m
    return ((s, 0.0), (side_m, s), (side_m - s, side_m), (0.0, side_m - s))[edge]


def print_scene(scene: FloorScene, errors: ImagingErrors, seed: int, key: int = 0) -> FloorScene:
    """The scene with every code printed by :func:`print_label`, code i drawing from
    ``source_rngs(seed, key, i)``."""
    codes = tuple(print_label(code, scene, errors, source_rngs(seed, key, i)) for i, code in enumerate(scene.codes))
    return dataclasses.replace(scene, codes=codes)


# -- exposure: motion blur and rolling shutter -------------------------------------------------------
def render_exposure(
    scene: FloorScene,
    camera: PinholeCamera,
    pose_at_time: Callable[[float], np.ndarray],
    t_start_s: float,
    *,
    exposure_s: float = 0.0,
    line_delay_s: float = 0.0,
    time_samples: int = 1,
    rows_per_band: int = 16,
    supersample: int = 4,
    pixel_aperture: float = 1.0,
) -> np.ndarray:
    """Irradiance (height, width) float32 DN of a frame exposed while the camera moves.

    Row v is exposed from ``t_start_s + v · line_delay_s`` for ``exposure_s``; its value is the
    mean of ``time_samples`` renders at the times ``t_row + (j + ½)/N · exposure_s`` (the
    exposure's midpoints; one sample at ``t_row`` when ``exposure_s`` is 0). With a line delay
    rows are rendered in bands of ``rows_per_band``, every row of a band at the band's middle
    row's time (error ≤ ½ band · line delay · image speed). ``pose_at_time(t_s)`` gives
    T_world_cam (4×4). With no exposure and no line delay this is
    ``render_irradiance(scene, camera, pose_at_time(t_start_s), supersample)``.

    Codes visible at none of the frame's first, middle and last poses are skipped.
    """
    if exposure_s < 0 or line_delay_s < 0 or not math.isfinite(exposure_s + line_delay_s):
        raise RenderError(f"exposure_s ({exposure_s}) and line_delay_s ({line_delay_s}) must be finite and ≥ 0")
    if int(time_samples) != time_samples or time_samples < 1 or int(rows_per_band) != rows_per_band or rows_per_band < 1:
        raise RenderError(f"time_samples ({time_samples}) and rows_per_band ({rows_per_band}) must be integers ≥ 1")
    if exposure_s == 0 and line_delay_s == 0:
        return render_irradiance(scene, camera, pose_at_time(t_start_s), supersample, pixel_aperture=pixel_aperture)
    height = camera.height_px
    samples = int(time_samples) if exposure_s > 0 else 1
    offsets_s = (np.arange(samples) + 0.5) / samples * exposure_s if exposure_s > 0 else np.zeros(1)
    band = int(rows_per_band) if line_delay_s > 0 else height
    frame_end_s = t_start_s + (height - 1) * line_delay_s + exposure_s
    visible: set[int] = set()
    for t_s in (t_start_s, 0.5 * (t_start_s + frame_end_s), frame_end_s):
        visible.update(codes_in_view(scene, camera, pose_at_time(t_s)))
    seen = dataclasses.replace(scene, codes=tuple(scene.codes[i] for i in sorted(visible)))
    image = np.zeros((height, camera.width_px), dtype=np.float32)
    for v0 in range(0, height, band):
        v1 = min(v0 + band, height)
        t_row_s = t_start_s + 0.5 * (v0 + v1 - 1) * line_delay_s
        acc = np.zeros((v1 - v0, camera.width_px), dtype=np.float32)
        for offset_s in offsets_s:
            acc += render_irradiance(
                seen, camera, pose_at_time(t_row_s + offset_s), supersample, row_range=(v0, v1), pixel_aperture=pixel_aperture
            )[v0:v1]
        image[v0:v1] = acc / np.float32(samples)
    return image


# -- light, optics, sensor -----------------------------------------------------------------------
def illumination_gain(shape: tuple[int, int], sigma: float, scale_px: float, rng: np.random.Generator) -> np.ndarray:
    """A smooth gain field 1 + sigma · z (float32, clipped at ≥ 0.05), z of zero mean and unit
    standard deviation over the image: normal draws on a grid of ``scale_px`` spacing,
    interpolated bicubically."""
    z = smooth_field(shape, scale_px, rng)
    return np.maximum(1.0 + sigma * z, 0.05).astype(np.float32)


def vignetting_gain(camera: PinholeCamera, strength: float) -> np.ndarray:
    """(height, width) float32 gain 1 − strength · (1 − cos⁴ θ), θ each pixel centre's ray angle
    off the optical axis (through the lens distortion): cos² θ = 1 / (1 + x² + y²)."""
    x, y = undistorted_rays(camera)
    cos2 = 1.0 / (1.0 + x * x + y * y)
    return (1.0 - strength * (1.0 - cos2 * cos2)).astype(np.float32)


def disk_kernel(radius_px: float, subsamples: int = 16) -> np.ndarray:
    """Defocus PSF: a uniform disk of ``radius_px`` area-integrated over each kernel pixel
    (``subsamples``² samples per pixel), normalised to sum 1; shape (2k + 1)², k = ⌈R + ½⌉."""
    if not 0 < radius_px <= MAX_DEFOCUS_RADIUS_PX:
        raise RenderError(f"disk radius must lie in (0, {MAX_DEFOCUS_RADIUS_PX}] px, got {radius_px}")
    k = int(math.ceil(radius_px + 0.5))
    offsets = (np.arange(subsamples) + 0.5) / subsamples - 0.5
    centres = np.arange(-k, k + 1, dtype=float)
    sx = (centres[:, None] + offsets[None, :]).ravel()  # every sub-sample coordinate
    inside = (sx[:, None] ** 2 + sx[None, :] ** 2) <= radius_px**2
    n = 2 * k + 1
    coverage = inside.reshape(n, subsamples, n, subsamples).mean(axis=(1, 3))
    return (coverage / coverage.sum()).astype(np.float32)


def optical_image(
    irradiance_dn: np.ndarray,
    camera: PinholeCamera,
    errors: ImagingErrors,
    rngs: Mapping[str, np.random.Generator],
) -> np.ndarray:
    """Irradiance → the image on the sensor (float32 DN): illumination, vignetting, defocus,
    Gaussian blur. Draws from the ``illumination`` stream only when that source is on."""
    image = np.asarray(irradiance_dn, dtype=np.float32)
    if errors.illumination_sigma > 0:
        image = image * illumination_gain(
            image.shape, errors.illumination_sigma, errors.illumination_scale_px, _stream(rngs, "illumination")
        )
    if errors.vignetting_strength > 0:
        image = image * vignetting_gain(camera, errors.vignetting_strength)
    if errors.defocus_radius_px > 0:
        image = cv2.filter2D(image, -1, disk_kernel(errors.defocus_radius_px), borderType=cv2.BORDER_REFLECT)
    if errors.blur_sigma_px > 0:
        image = cv2.GaussianBlur(image, (0, 0), errors.blur_sigma_px, borderType=cv2.BORDER_REFLECT)
    return image


def sensor_image(
    image_dn: np.ndarray, errors: ImagingErrors, rngs: Mapping[str, np.random.Generator]
) -> np.ndarray:
    """Sensor noise on an optical image (float32 DN, before quantisation): shot noise
    (Poisson electrons, variance signal / gain in DN²) then read noise."""
    image = np.asarray(image_dn, dtype=np.float32)
    if errors.shot_gain_e_per_dn > 0:
        gain = errors.shot_gain_e_per_dn
        electrons = _stream(rngs, "shot_noise").poisson(np.maximum(image.astype(float), 0.0) * gain)
        image = (electrons / gain).astype(np.float32)
    if errors.read_noise_dn > 0:
        image = image + np.float32(errors.read_noise_dn) * _stream(rngs, "read_noise").standard_normal(
            image.shape, dtype=np.float32
        )
    return image


def quantise(image_dn: np.ndarray, jpeg_quality: int = 0) -> np.ndarray:
    """uint8 frame: round and clip to 0..255, then a JPEG round trip when ``jpeg_quality`` > 0."""
    frame = np.clip(np.rint(image_dn), 0, 255).astype(np.uint8)
    if jpeg_quality > 0:
        ok, buffer = cv2.imencode(".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
        if not ok:
            raise RenderError("OpenCV failed to JPEG-encode the frame")
        frame = cv2.imdecode(buffer, cv2.IMREAD_GRAYSCALE)
    return frame


def camera_frame(
    irradiance_dn: np.ndarray,
    camera: PinholeCamera,
    errors: ImagingErrors,
    rngs: Mapping[str, np.random.Generator],
) -> np.ndarray:
    """The uint8 frame a camera makes of an irradiance image (:func:`render_exposure` or
    :func:`agvviz.sim.render.render_irradiance`): optics, sensor noise, quantisation, JPEG."""
    image = optical_image(irradiance_dn, camera, errors, rngs)
    return quantise(sensor_image(image, errors, rngs), errors.jpeg_quality)


def render_camera_frame(
    scene: FloorScene,
    camera: PinholeCamera,
    pose_at_time: Callable[[float], np.ndarray],
    t_start_s: float,
    errors: ImagingErrors,
    rngs: Mapping[str, np.random.Generator],
    *,
    time_samples: int = 4,
    rows_per_band: int = 16,
    supersample: int = 4,
) -> np.ndarray:
    """One uint8 frame with every image-formation error of ``errors`` (print effects are in the
    scene already: :func:`print_scene`)."""
    irradiance = render_exposure(
        scene, camera, pose_at_time, t_start_s, exposure_s=errors.exposure_s, line_delay_s=errors.line_delay_s,
        time_samples=time_samples, rows_per_band=rows_per_band, supersample=supersample,
        pixel_aperture=errors.pixel_aperture,
    )
    return camera_frame(irradiance, camera, errors, rngs)
