"""What a real camera adds to the studio's clean images: the settings (``capture.camera_effects``).

Under ``capture.realism: real`` every performance image and every ChArUco board image goes
through the camera model: lens (defocus from a thin lens, a residual lens blur, vignetting),
motion over the exposure (performance frames) and the sensor (photon shot noise, read noise,
quantisation to DN, saturation at full well); the board itself is printed slightly off its
nominal geometry and is not perfectly flat. ``realism: ideal`` skips all of it and renders
today's images bit for bit (``RenderSettings.shot_noise_gain``/``read_noise`` then apply).

The defaults describe a plausible head-capture camera: a 12-bit global-shutter machine-vision
sensor (Sony Pregius class: ~10 ke- full well, ~2.5 e- read noise) behind a 50 mm lens at f/8
focused on the head, 8 ms strobed exposures, and a laser-printed board on foam core. The
functions that apply them live in ``hardware.studio.sensor``, ``hardware.studio.optics`` and
``hardware.studio.printed_board``.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class SensorModel(BaseModel):
    """A linear sensor in physical units: electrons, DN, full well."""

    model_config = ConfigDict(frozen=True, extra="forbid")
    gain_e_per_dn: float = Field(
        2.5, gt=0, description="Conversion gain, electrons per digital number (DN). 2.5 e-/DN is a Pregius-class "
        "sensor at unity analogue gain in 12-bit mode (full well / 4095); raise it (lower analogue gain) for more "
        "dynamic range and coarser DN steps.")
    read_noise_e: float = Field(
        2.5, ge=0, description="Read noise, electrons RMS (Gaussian, added after the photon noise). 2-3 e- is a "
        "modern global-shutter CMOS sensor; 0 switches it off (tests of the shot-noise law).")
    bits: int = Field(
        12, ge=8, le=16, description="ADC bit depth: DN run 0 .. 2^bits - 1 and the white level (saturation) is "
        "the top code. Full well = gain_e_per_dn x (2^bits - 1) (2.5 x 4095 = 10.2 ke-).")
    white_level_linear: float = Field(
        2.0, gt=0, description="The linear radiance (the renderer's units) that fills the full well: the exposure. "
        "2.0 keeps the brightest full-on skin highlight (~1.0) a stop below saturation and puts 5100 e- per linear "
        "unit, close to the ideal model's shot_noise_gain (2e-4, i.e. 5000 e- per unit). Lower it to expose "
        "brighter (less noise, clipped highlights).")
    black_level_dn: float = Field(
        0.0, ge=0, description="Offset added before quantisation and subtracted after (a real sensor's pedestal "
        "keeps the read noise of dark pixels unclipped); 0 clips negative noise at zero, as the ideal model did.")

    @property
    def white_level_dn(self) -> int:
        """The top code of the ADC."""
        return 2 ** self.bits - 1

    @property
    def full_well_e(self) -> float:
        """Electrons at the white level."""
        return self.gain_e_per_dn * self.white_level_dn

    @property
    def electrons_per_linear(self) -> float:
        """Electrons collected per unit of linear radiance (the exposure)."""
        return self.full_well_e / self.white_level_linear


class LensModel(BaseModel):
    """A thin lens: defocus by depth, a residual blur and vignetting."""

    model_config = ConfigDict(frozen=True, extra="forbid")
    focal_length_mm: float = Field(
        50.0, gt=0, description="Physical focal length. With the rig's ~2800 px focal length at 768 px width this is "
        "an 18 um effective pixel (a binned 12 MP sensor); it sets the depth of field with f_number.")
    f_number: float = Field(
        8.0, gt=0, description="Aperture f-number. f/8 is typical for head capture (depth of field over the face at "
        "~1.1 m); lower it for a shallower focus (the board blurs more where it leaves the focus plane).")
    focus_distance_m: float | None = Field(
        None, gt=0, description="Distance the lenses are focused at, metres along each optical axis; None focuses "
        "every camera on the capture volume's centre (the head), as an operator would.")
    residual_blur_px: float = Field(
        0.35, ge=0, description="Gaussian sigma of the lens's in-focus blur (aberrations, sensor's optical low-pass) "
        "in native pixels; scaled with the image. 0.3-0.5 px is a good machine-vision lens at f/8.")
    vignetting_cos_power: float = Field(
        4.0, ge=0, description="Relative illumination falls as cos^p of the field angle: p = 4 is the natural "
        "cos^4 law (about 10% at the rig's corners); raise it to add mechanical vignetting, 0 switches it off.")


class MotionBlurModel(BaseModel):
    """The head's motion while the shutter is open."""

    model_config = ConfigDict(frozen=True, extra="forbid")
    exposure_s: float = Field(
        0.008, ge=0, description="Exposure (strobe) time per frame, seconds. 8 ms is a strobed LED capture at 24 "
        "fps; 0 switches motion blur off. The blur is the image smeared along the head's projected motion over "
        "this time (hardware.studio.optics.motion_blur).")


class BoardPrint(BaseModel):
    """How the ChArUco board was really printed and mounted (the calibration assumes the nominal board)."""

    model_config = ConfigDict(frozen=True, extra="forbid")
    scale_error: tuple[float, float] = Field(
        (0.0015, 0.0025), description="Relative scale error of the print along the board's x and y (0.0025 = "
        "+0.25%). Office and laser printers are 0.1-0.3% off, and differently along and across the paper feed; "
        "the anisotropic part cannot be absorbed by the board pose.")
    corner_jitter_m: float = Field(
        3e-5, ge=0, description="Standard deviation of each square corner's print position error, metres, per "
        "axis (30 um: toner placement and paper stretch of a 600 dpi print); the squares deform smoothly between.")
    bow_m: float = Field(
        8e-4, description="Sagitta of the board's bow: the centre stands this far towards the camera from the "
        "corners (0.5-1 mm for a print laminated on foam core); negative bows away.")
    flex_m: float = Field(
        3e-4, ge=0, description="Standard deviation, metres, of how much the board's shape changes from pose to "
        "pose: its bow and a twist (two opposite corners forward, two back), each drawn per pose. A foam-core "
        "board moved between poses by hand or on a stand sags and twists a few tenths of a millimetre "
        "differently each time; one refined board shape cannot absorb it, so it stays in the residuals as it "
        "does in a real calibration. 0 keeps every pose's board the same.")
    seed: int = Field(0, description="Seed of the corner jitter (one physical print) and of the per-pose flex.")


class CameraEffects(BaseModel):
    """Everything ``realism: real`` adds to the clean studio images."""

    model_config = ConfigDict(frozen=True, extra="forbid")
    sensor: SensorModel = Field(default_factory=SensorModel,
                                description="Photon and read noise, DN quantisation, saturation.")
    lens: LensModel = Field(default_factory=LensModel, description="Defocus, residual blur, vignetting.")
    motion: MotionBlurModel = Field(default_factory=MotionBlurModel, description="Motion blur over the exposure.")
    board_print: BoardPrint = Field(default_factory=BoardPrint,
                                    description="The calibration board's print errors and bow.")

    def metrics(self) -> dict[str, float]:
        """The model's parameters as capture metrics (numbers, units in the key)."""
        s, lens, p = self.sensor, self.lens, self.board_print
        return {"sensor_gain_e_per_dn": s.gain_e_per_dn, "read_noise_e": s.read_noise_e,
                "sensor_full_well_e": s.full_well_e, "sensor_bits": s.bits,
                "sensor_white_level_linear": s.white_level_linear, "exposure_s": self.motion.exposure_s,
                "lens_focal_length_mm": lens.focal_length_mm, "lens_f_number": lens.f_number,
                "lens_residual_blur_px": lens.residual_blur_px, "vignetting_cos_power": lens.vignetting_cos_power,
                "board_scale_error_x": p.scale_error[0], "board_scale_error_y": p.scale_error[1],
                "board_corner_jitter_mm": p.corner_jitter_m * 1e3, "board_bow_mm": p.bow_m * 1e3,
                "board_flex_mm": p.flex_m * 1e3}
