"""Campaign configuration: everything a calibration needs, in one TOML file (docs/campaign.md).

Paths are relative to the campaign file. Unknown keys are errors, every
field states its unit, defaults follow the method paper.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from calibration import CalibrationError


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ModelSection(_Strict):
    """The FE model: Nastran deck, its unit system and the parameter file."""

    bdf: Path | None = Field(None, description="Nastran deck (default: [model] bdf of the parameter file)")
    units: str | None = Field(None, description="deck unit system, e.g. 'mm-t-s' or 'si' (default: parameter file)")
    parameters: Path = Field(description="femodel parameter TOML (names, cards, bounds on normalized p)")


class RunEntry(_Strict):
    """One run file (HDF5, acquisition.runfile) of one test article."""

    path: Path
    article: str | None = Field(None, description="article label (default: the run file's article)")
    level: float | None = Field(None, gt=0, description="excitation force level of the run, N (default: the median "
                                "achieved force over its valid lines); runs of one article at several levels feed "
                                "the nonlinearity gate of the diagnosis")


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
    starts: int = Field(20, ge=0, description="Latin-hypercube starts besides the nominal one")
    seed: int = Field(0, description="seed of the Latin hypercube")
    continuation_zeta: list[float] = Field(
        default_factory=lambda: [0.08, 0.03], description="damping continuation stages before zeta0 ([] = off)"
    )
    basis_factor: float = Field(2.0, ge=1.1, description="modes up to basis_factor x band top enter the basis")
    enrich: bool = Field(True, description="parameter-derivative enrichment of the basis")
    max_cycles: int = Field(3, ge=1, description="re-basis cycles (1 = keep the nominal basis)")
    cycle_tol: float = Field(1e-3, gt=0, description="stop cycling when max |dp| is below this")
    max_evaluations: int = Field(100, ge=5, description="residual evaluations per start and stage")
    refine: bool = Field(True, description="refine the equalized optimum on the raw calibration lines "
                         "(damping continuation down to the identified damping; see docs/calibration.md)")
    refine_floors: list[float] = Field(
        default_factory=lambda: [1.0, 0.3, 0.1, 0.0],
        description="damping floors of the refinement stages as multiples of zeta0, decreasing, ending in 0")
    refine_cycles: int = Field(2, ge=0, description="re-basis cycles of the raw-line stage after the refinement")
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


class ExecutionSection(_Strict):
    workers: int | None = Field(None, ge=1, description="local worker processes (default: all cores)")
    scheduler: str | None = Field(None, description="Dask scheduler address, e.g. tcp://host:8786")


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


class OutputSection(_Strict):
    dir: Path = Field(Path("calibration-out"), description="output directory")
    figures: bool = True
    write_bdf: bool = True


class Campaign(_Strict):
    """A complete, re-runnable calibration campaign."""

    model: ModelSection
    run: list[RunEntry] = Field(min_length=1)
    channels: ChannelsSection
    band: BandSection
    calibration: CalibrationSection = CalibrationSection()
    identification: IdentificationSection = IdentificationSection()
    validation: ValidationSection = ValidationSection()
    crossvalidation: CrossValidationSection = CrossValidationSection()
    diagnosis: DiagnosisSection = DiagnosisSection()
    execution: ExecutionSection = ExecutionSection()
    output: OutputSection = OutputSection()
    base_dir: Path = Field(Path("."), exclude=True)

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
    if "base_dir" in data:
        raise CalibrationError(f"{path}: base_dir: unknown field")
    return campaign_from_dict(data, path.resolve().parent, str(path))
