"""Campaign configuration: everything a calibration needs, in one TOML file (docs/campaign.md).

Paths are relative to the campaign file. Unknown keys are errors, every
field states its unit, defaults follow the method paper.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from calibration import BASIS_FACTOR, CalibrationError


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ModelSection(_Strict):
    """The FE model: Nastran deck, its unit system and the parameter file."""

    bdf: Path | None = Field(None, description="Nastran deck (default: [model] bdf of the parameter file)")
    units: str | None = Field(None, description="deck unit system, e.g. 'mm-t-s' or 'si' (default: parameter file)")
    parameters: Path = Field(description="femodel parameter TOML (names, cards, bounds on normalized p)")


class RunEntry(_Strict):
    """One test article's data: a run file (HDF5, acquisition.runfile) or a UFF58 file to import."""

    path: Path | None = Field(None, description="run file (HDF5)")
    uff: Path | None = Field(None, description="UFF58 FRF file, imported into <output dir>/runs/ (import stage)")
    article: str | None = Field(None, description="article label (default: the run file's article)")
    level: float | None = Field(None, gt=0, description="excitation force level of the run, N (default: the median "
                                "achieved force over its valid lines); runs of one article at several levels feed "
                                "the nonlinearity gate of the diagnosis")

    @model_validator(mode="after")
    def _one_source(self):
        if (self.path is None) == (self.uff is None):
            raise ValueError("give exactly one of path (run file) or uff (UFF58 file)")
        return self


class PretestSection(_Strict):
    """Settings of ``frfcal pretest``: the pretest stage writes ``<output dir>/layout.json`` from the deck."""

    sensors: int = Field(20, ge=1, description="number of sensors (a triax counts once)")
    modes: int | None = Field(None, ge=1, description="target: the first N elastic modes (default 20)")
    band_hz: tuple[float, float] | None = Field(None, description="target: elastic modes in [lo, hi] Hz")
    mode_numbers: list[int] | None = Field(None, description="target: 1-based mode numbers")
    direction: str | tuple[float, float, float] = Field("normal", description="normal, x, y, z or a vector")
    triax: bool = Field(False, description="triaxial sensors (kept whole)")
    candidates: list[int] | None = Field(None, description="candidate grids (default: all)")
    pids: list[int] | None = Field(None, description="candidate grids of these property ids")
    include: list[int] = Field(default_factory=list, description="grids that must carry a sensor")
    exclude: list[int] = Field(default_factory=list, description="grids that must not carry a sensor")
    min_distance_m: float = Field(0.0, ge=0, description="minimum sensor spacing, m")
    drives: int = Field(1, ge=0, description="drive points to put in the layout")
    shaker_candidates: int = Field(5, ge=1, description="ranked drive points to report")
    free_drive: bool = Field(False, description="rank drive points over all candidates (default: collocated)")
    drive_criterion: Literal["weakest", "adpr", "product"] = "weakest"
    sensor_mass_g: float = Field(0.5, ge=0, description="mass of one sensor, g")
    drive_mass_g: float = Field(5.0, ge=0, description="force sensor + stinger mass, g")
    refine_automac: float | None = Field(None, gt=0, description="autoMAC refinement, decades of det(FIM) given up")
    box_m: tuple[float, float, float, float, float, float] | None = Field(
        None, description="candidate grids inside this box: xmin, xmax, ymin, ymax, zmin, zmax, m")
    figures: bool = Field(True, description="write the layout and autoMAC figures beside the layout")

    def config(self):
        """The :class:`pretest.PretestConfig` of these settings (``frfcal pretest`` builds the same)."""
        import pretest

        return pretest.PretestConfig(
            n_sensors=self.sensors,
            n_modes=self.modes if (self.modes is not None or self.band_hz or self.mode_numbers) else 20,
            band_hz=tuple(self.band_hz) if self.band_hz else None,
            mode_numbers=tuple(self.mode_numbers) if self.mode_numbers else None,
            direction=self.direction,
            triax=self.triax,
            candidate_grids=tuple(self.candidates) if self.candidates else None,
            candidate_pids=tuple(self.pids) if self.pids else None,
            candidate_box_m=tuple(self.box_m) if self.box_m else None,
            include_grids=tuple(self.include),
            exclude_grids=tuple(self.exclude),
            min_distance_m=self.min_distance_m,
            n_drives=self.drives,
            n_shaker_candidates=self.shaker_candidates,
            collocated_drive=not self.free_drive,
            drive_criterion=self.drive_criterion,
            sensor_mass_kg=self.sensor_mass_g * 1e-3,
            drive_mass_kg=self.drive_mass_g * 1e-3,
            refine_automac_decades=self.refine_automac,
        )

    @model_validator(mode="after")
    def _one_target(self):
        given = [k for k in ("modes", "band_hz", "mode_numbers") if getattr(self, k) is not None]
        if len(given) > 1:
            raise ValueError(f"give one target of modes, band_hz, mode_numbers (got {', '.join(given)})")
        if self.band_hz is not None and not 0 <= self.band_hz[0] < self.band_hz[1]:
            raise ValueError(f"band_hz {list(self.band_hz)}: need 0 <= lo < hi")
        return self


class LayoutSection(_Strict):
    """An existing layout file (instead of ``[pretest]``)."""

    file: Path = Field(description="layout JSON (frfcal pretest, docs/layout.md)")


class AcquisitionSection(_Strict):
    """The acquire stage: a stepped-sine plan run by a driver into ``<output dir>/<dir>``."""

    plan: Path | dict = Field(description="plan TOML file, or the plan inline as [acquisition.plan] "
                              "(docs/acquisition.md); without layout/channels it uses the campaign's layout")
    driver: Literal["sim", "visa", "ni"] = Field("sim", description="backend")
    hardware: Path | None = Field(None, description="hardware TOML (needed for visa/ni, docs/hardware.md)")
    dir: Path = Field(Path("runs"), description="run files, relative to the output directory")

    @model_validator(mode="after")
    def _hardware(self):
        if self.driver != "sim" and self.hardware is None:
            raise ValueError(f"driver {self.driver!r} needs hardware = \"HW.toml\" (docs/hardware.md)")
        return self


class ChannelsSection(_Strict):
    """Which response channels calibrate and which are held out; which drives."""

    calibrate: list[str] = Field(min_length=1, description="response channel names used for calibration")
    holdout: list[str] = Field(default_factory=list, description="response channels for hold-out validation")
    drives: list[str] = Field(default_factory=list, description="force channel names (default: all drives of the runs)")

    @model_validator(mode="after")
    def _disjoint(self):
        both = sorted(set(self.calibrate) & set(self.holdout))
        if both:
            raise ValueError(f"channels {both} are both in calibrate and holdout")
        for name, lst in (("calibrate", self.calibrate), ("holdout", self.holdout), ("drives", self.drives)):
            if len(set(lst)) != len(lst):
                raise ValueError(f"channels.{name} lists a channel twice")
        return self


class BandSection(_Strict):
    """Calibration and validation band in Hz."""

    low_hz: float = Field(gt=0)
    high_hz: float = Field(gt=0)

    @model_validator(mode="after")
    def _order(self):
        if self.high_hz <= self.low_hz:
            raise ValueError(f"band: high_hz ({self.high_hz}) must exceed low_hz ({self.low_hz})")
        return self


class CalibrationSection(_Strict):
    """Metric, surrogate and minimizer settings."""

    zeta0: float = Field(0.01, gt=0, lt=0.5, description="equalized damping ratio (fraction)")
    samples_per_half_bandwidth: float = Field(3.0, gt=0, description="frequency samples per 2*zeta0*f")
    starts: int = Field(20, ge=0, description="Latin-hypercube starts besides the nominal one (at most, with "
                        "adaptive_starts)")
    adaptive_starts: bool = Field(
        True, description="stop the multi-start once its starts make a further minimum unlikely (Boender and "
        "Rinnooy Kan's Bayesian rule: 8 starts that all end in one minimum; docs/calibration.md); false: run "
        "every start")
    seed: int = Field(0, description="seed of the Latin hypercube")
    continuation_zeta: list[float] = Field(
        default_factory=lambda: [0.08, 0.03], description="damping continuation stages before zeta0 ([] = off)"
    )
    basis_factor: float = Field(BASIS_FACTOR, ge=1.1, description="modes up to basis_factor x band top enter the basis (with the first moments of the loads)")
    enrich: bool = Field(True, description="parameter-derivative enrichment of the basis")
    max_cycles: int = Field(3, ge=1, description="re-basis cycles (1 = keep the nominal basis)")
    cycle_tol: float = Field(1e-3, gt=0, description="stop cycling when max |dp| is below this")
    basis_tol: float = Field(
        0.05, ge=0, lt=1, description="equalized stage: re-basis only when the basis is inadequate at the new "
        "point: a Ritz frequency error of an in-band mode (from its energy-norm residual) above this fraction of "
        "the half-power bandwidth 2 zeta0 f (0: whenever p moved by more than cycle_tol); also gates the raw-line "
        "stage's second and later re-bases, against the least damped estimated mode (docs/calibration.md)")
    max_evaluations: int = Field(100, ge=5, description="residual evaluations per start and stage")
    level_factor: float = Field(
        4.0, ge=0, description="refuse the calibration when the model's FRF level at the nominal parameters "
        "differs from the data's by more than this factor (median over lines and channel-drive pairs; a unit "
        "mismatch: an mm-t-s deck read as SI is 1000x, g read as m/s^2 9.81x; 0 = no check)")
    refine: bool = Field(True, description="refine the equalized optimum on the raw calibration lines "
                         "(damping continuation down to the identified damping; see docs/calibration.md)")
    refine_floors: list[float] = Field(
        default_factory=lambda: [1.0, 0.3, 0.1, 0.0],
        description="damping floors of the refinement stages as multiples of zeta0, decreasing, ending in 0")
    refine_weights: Literal["noise", "uniform"] = Field(
        "noise", description="weights of the raw-line fits: 1 / the variance of each log ratio from the standard "
        "errors (the run's, else estimated from the lines), or every value alike as the paper's Eq. 2.23; the "
        "reported SDs stay unweighted (docs/calibration.md)")
    refine_cycles: int = Field(2, ge=0, description="re-basis cycles of the raw-line stage after the refinement")
    refine_basis_tol: float = Field(
        0.0, ge=0, lt=1, description="raw-line stage: as basis_tol, against the half-power bandwidth of the least "
        "damped estimated mode, for every re-basis including the first (0, the default: the first re-basis "
        "always, the later ones gated by basis_tol; docs/calibration.md)")
    rebasis_hold: float = Field(
        0.0, ge=0, description="in the raw stage after a re-basis, hold parameter combinations whose relative "
        "singular value is far below this at their value before the re-basis (0 = off; docs/calibration.md)")
    rebasis: Literal["iterated", "kept", "solved", "corrected", "compressed"] = Field(
        "compressed", description="how a cycle re-makes the basis at its end point: 'compressed' (default): the "
        "old basis plus the solved residuals of its modes and static solutions at the new point (no new "
        "factorization), cut back to a cold build's vectors made inside that span (no growth); 'corrected': the "
        "same without the cut (the basis grows, and every later stage pays for it); or rebuilt with the "
        "enrichment of the inverse-iterated old basis ('iterated'), the old parameter-derivative columns kept as "
        "they are ('kept'), or new derivative solves ('solved'). Models up to 1500 DOF are rebuilt "
        "('iterated') for 'compressed' (docs/calibration.md)")
    refine_rebasis: Literal["iterated", "kept", "solved", "corrected", "compressed"] = Field(
        "compressed", description="how the raw-line stage's second and later re-basis cycles re-make the basis "
        "(the first one, after the refinement's large step, as rebasis); the same choices as rebasis "
        "(docs/calibration.md)")
    ensemble: Literal["all", "article", "group"] = Field("all", description="calibrate on all articles, each, or each group")
    n_groups: int | None = Field(None, ge=1, description="number of article groups (default: largest gap)")

    @field_validator("refine_floors")
    @classmethod
    def _floors(cls, v):
        if not v or v[-1] != 0 or any(b > a for a, b in zip(v, v[1:])) or any(x < 0 for x in v):
            raise ValueError("refine_floors must be non-negative, decreasing, and end in 0 (the raw data)")
        return v

    @field_validator("continuation_zeta")
    @classmethod
    def _zetas(cls, v):
        if any(not 0 < z < 0.5 for z in v):
            raise ValueError("continuation_zeta values must be in (0, 0.5)")
        return v


class IdentificationSection(_Strict):
    """Subspace identification of the test data (skipped when the run file holds one and use_stored)."""

    order: int | None = Field(
        None, ge=2, description="state order (2 per mode); None = automatic (identification.select_order)"
    )
    low_hz: float | None = Field(
        None, gt=0, description="identification band low [Hz] (default: 0.8 x band low; clipped to the data)"
    )
    high_hz: float | None = Field(
        None, gt=0, description="identification band high [Hz] (default: 1.25 x band high; clipped to the data)"
    )
    use_stored: bool = Field(True, description="use /analysis/identification of the run file when present")


class ValidationSection(_Strict):
    target_sd: float | None = Field(None, gt=0, description="SD target of Eq. 2.24 (dimensionless)")
    mac_min: float = Field(0.6, ge=0, le=1, description="smallest MAC for damping mapping pairs")


class CrossValidationSection(_Strict):
    realizations: int = Field(20, ge=0, description="Monte Carlo half/half splits (0 = skip)")
    seed: int = 1
    max_evaluations: int = Field(30, ge=2, description="residual evaluations per recalibration")


class SimEffect(_Strict):
    """An effect the FE model lacks, built into the truth of the named simulated articles.

    ``kind = "spring"``: contact/joint springs of rate ``rate_n_per_m`` between
    each grid pair of ``pairs`` on every translation of ``components`` (a closed
    air gap: ``femodel.AddedSpring``). ``kind = "mass"``: a lumped mass
    ``mass_kg`` on each grid of ``grids`` (``femodel.AddedMass``).
    """

    name: str = Field(description="effect name (the added term's parameter name in the truth model)")
    kind: Literal["spring", "mass"]
    articles: list[str] = Field(min_length=1, description="articles that have the effect (names of the plan's ensemble)")
    pairs: list[tuple[int, int]] = Field(default_factory=list, description="spring: (grid, grid) pairs")
    components: list[int] = Field(default_factory=lambda: [1, 2, 3], description="spring: translations 1..3 joined")
    rate_n_per_m: float | None = Field(None, gt=0, description="spring: rate per DOF pair, N/m")
    grids: list[int] = Field(default_factory=list, description="mass: grids carrying one mass each")
    mass_kg: float | None = Field(None, gt=0, description="mass: lumped mass per grid, kg")

    @model_validator(mode="after")
    def _kind(self):
        if self.kind == "spring":
            if not self.pairs or self.rate_n_per_m is None:
                raise ValueError(f"effect {self.name!r}: kind 'spring' needs pairs and rate_n_per_m")
            if not set(self.components) <= {1, 2, 3} or not self.components:
                raise ValueError(f"effect {self.name!r}: components must be translations among 1, 2, 3")
        elif not self.grids or self.mass_kg is None:
            raise ValueError(f"effect {self.name!r}: kind 'mass' needs grids and mass_kg")
        return self


class SimLoosePart(_Strict):
    """A loose part on one article: a hardening cubic spring on one mode, engaged at the higher force levels.

    The lab applies it by equivalent linearization (``acquisition.CubicSpring``);
    its strength is given as the relative rise of the mode's frequency at
    resonance under ``from_level_n``. Runs below ``from_level_n`` see the linear
    article (the part rattles only when driven hard).
    """

    article: str = Field(description="the article with the loose part")
    mode: int | None = Field(None, ge=1, description="elastic mode number (1 = first elastic mode of the truth); "
                             "default: the in-band mode of the largest drive-point resonance")
    shift: float = Field(0.005, gt=0, lt=0.2, description="relative frequency rise at resonance at from_level_n")
    from_level_n: float = Field(gt=0, description="force level from which the part is engaged, N peak")


class SimulationSection(_Strict):
    """The simulated test articles of ``--driver sim`` (docs/campaign.md, [simulation]).

    Each article of the plan's ensemble is the deck at its own parameters
    (population offsets plus scatter), its own modal damping and the effects
    listed for it, solved as in ``frfcal.synth`` (modes up to ``mode_factor``
    x the sweep top, free-free rigid-body modes, the exact higher-mode
    residual); the simulated lab sweeps that plant.
    """

    offsets: Literal["paper"] | dict[str, float] = Field(
        "paper", description="population offsets of normalized p: 'paper' (the demo's Table 2.1 ratios) or {name = p}")
    scatter: float = Field(0.003, ge=0, description="article rms scatter of p around the population (absolute in p)")
    seed: int = Field(0, description="seed of the scatter, damping and sensor noise")
    zeta_range: tuple[float, float] = Field((1e-3, 3e-3), description="modal damping range, log-uniform per mode "
                                            "(fraction of critical)")
    mode_factor: float = Field(3.0, ge=1.5, description="modes up to mode_factor x sweep top are modes; the rest the "
                               "exact residual")
    noise_rms: float = Field(1e-3, ge=0, description="sensor noise, engineering units rms (m/s^2; N on the force)")
    shaker: Literal["electrodynamic", "ideal"] = Field("electrodynamic", description="simulated exciter")
    effect: list[SimEffect] = Field(default_factory=list, description="effects the model lacks, per article")
    loose_part: SimLoosePart | None = None

    @field_validator("zeta_range")
    @classmethod
    def _zeta(cls, v):
        if not 0 < v[0] <= v[1] < 0.5:
            raise ValueError(f"zeta_range must be 0 < low <= high < 0.5, got {list(v)}")
        return v

    @model_validator(mode="after")
    def _names(self):
        names = [e.name for e in self.effect]
        if len(set(names)) != len(names):
            raise ValueError(f"effect names must be unique, got {names}")
        return self


class ExecutionSection(_Strict):
    workers: int | None = Field(None, ge=1, description="local worker processes (default: all cores)")
    scheduler: str | None = Field(None, description="Dask: a scheduler address (tcp://host:8786), or \"local\" "
                                  "for a LocalCluster of `workers` processes started on `host`")
    host: str = Field("127.0.0.1", description="interface the local Dask cluster listens on (loopback by default)")


class DiagnosisSection(_Strict):
    """The diagnose stage (docs/diagnosis.md): run by ``frfcal diagnose`` and ``frfcal run``, never by
    ``frfcal calibrate``."""

    enabled: bool = Field(True, description="run the diagnose stage in `frfcal run` (`frfcal diagnose` "
                          "refuses a campaign with enabled = false)")
    ratio_threshold: float = Field(2.0, gt=1, description="residual SD / (noise floor + test-to-test scatter) "
                                   "above which the residual is significant (dimensionless)")
    z_threshold: float = Field(5.0, gt=0, description="chi-square size of the residual above which it is "
                               "significant, sigma")
    shift_threshold: float = Field(1.0, gt=0, description="model-test frequency shift above which a mode is "
                                   "flagged, half-power bandwidths (2 zeta f)")
    nonlinearity_z: float = Field(5.0, gt=0, description="significance of a level, sweep-direction "
                                  "difference above which it is flagged nonlinear, sigma")
    thd_threshold: float = Field(0.05, gt=0, lt=1, description="total harmonic distortion above which a line is "
                                 "distorted (fraction)")
    figures_channels: int = Field(4, ge=1, description="FRF overlays at this many most affected channels")
    families: list[str] | None = Field(None, description="candidate families (default: all of "
                                       "femodel.CANDIDATE_FAMILIES; docs/diagnosis.md)")
    candidates: dict[str, float | int | list[float] | list[int] | list[str]] = Field(
        default_factory=dict, description="femodel.CandidateOptions fields (units as documented there), e.g. "
        "{ contact_max_gap_m = 0.005, spread_grids = 40 }")
    top_n: int = Field(5, ge=1, description="candidates re-fitted nonlinearly after the linear screening")
    max_effects: int = Field(2, ge=1, description="at most this many effects accepted")
    max_evaluations: int = Field(40, ge=5, description="residual evaluations per screening fit stage")
    continuation_lines: Literal["raw", "half-bandwidth"] = Field(
        "half-bandwidth", description="lines of the debiased target's continuation stages (wider damping than zeta0): "
        "'raw' = every raw line; 'half-bandwidth' = the raw line nearest each point of that stage's half-bandwidth "
        "grid (calibration.thinned_lines; about the equalized target's count there, cheaper screening)")
    target: Literal["debiased", "equalized"] = Field(
        "debiased", description="what the screening and the acceptance's fits compare the model with: "
        "'debiased' = the raw calibration lines with the identified poles' damping raised to zeta0 and to each "
        "continuation damping (calibration.debiased_target; the identification's misfit cancels), weighted per "
        "line as a quadrature in log f; 'equalized' = the identified model equalized to those dampings on the "
        "half-bandwidth grids (the paper's target; it carries the identification's misfit)")


class OutputSection(_Strict):
    dir: Path = Field(Path("calibration-out"), description="output directory")
    figures: bool = True
    write_bdf: bool = True


class Campaign(_Strict):
    """A complete, re-runnable calibration campaign."""

    model: ModelSection
    pretest: PretestSection | None = None
    layout: LayoutSection | None = None
    acquisition: AcquisitionSection | None = None
    run: list[RunEntry] = Field(default_factory=list)
    channels: ChannelsSection
    band: BandSection
    calibration: CalibrationSection = CalibrationSection()
    identification: IdentificationSection = IdentificationSection()
    validation: ValidationSection = ValidationSection()
    crossvalidation: CrossValidationSection = CrossValidationSection()
    simulation: SimulationSection | None = None
    diagnosis: DiagnosisSection = DiagnosisSection()
    execution: ExecutionSection = ExecutionSection()
    output: OutputSection = OutputSection()
    base_dir: Path = Field(Path("."), exclude=True)
    source: Path | None = Field(None, exclude=True)

    @model_validator(mode="after")
    def _sources(self):
        if self.pretest is not None and self.layout is not None:
            raise ValueError("give [pretest] (plan a layout) or [layout] file (use one), not both")
        if not self.run and self.acquisition is None:
            raise ValueError("no data: give [[run]] entries (path = run file, or uff = UFF58 file) "
                             "or an [acquisition] section")
        if self.run and self.acquisition is not None:
            raise ValueError("give [[run]] entries or [acquisition] (whose run files are the runs), not both")
        return self

    def resolve(self, path: Path | None) -> Path | None:
        if path is None:
            return None
        return path if path.is_absolute() else (self.base_dir / path)


def _format_errors(source, exc: ValidationError) -> str:
    parts = []
    for err in exc.errors():
        loc = ".".join(str(x) for x in err["loc"])
        msg = err["msg"]
        if err["type"] == "extra_forbidden":
            msg = "unknown field"
        parts.append(f"{loc}: {msg}")
    return f"{source}: " + "; ".join(parts)


def campaign_from_dict(data: dict, base_dir=".", source="campaign") -> Campaign:
    """Validate a campaign dict (as read from TOML); CalibrationError names the bad field."""
    try:
        return Campaign(**data, base_dir=Path(base_dir))
    except ValidationError as exc:
        raise CalibrationError(_format_errors(source, exc)) from None
    except TypeError as exc:
        raise CalibrationError(f"{source}: {exc}") from None


def load_campaign(path) -> Campaign:
    """Read and validate a campaign TOML file."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            data = tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise CalibrationError(f"{path}: not valid TOML: {exc}") from None
    except FileNotFoundError:
        raise CalibrationError(f"{path}: campaign file not found") from None
    if "base_dir" in data or "source" in data:
        raise CalibrationError(f"{path}: {'base_dir' if 'base_dir' in data else 'source'}: unknown field")
    camp = campaign_from_dict(data, path.resolve().parent, str(path))
    return camp.model_copy(update={"source": path.resolve()})
