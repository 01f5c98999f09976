"""Stepped-sine sweep plans as validated data (TOML in, frozen pydantic models).

A plan holds the frequency lines, force level(s), settle and measure rules,
limits, optional adaptive refinement and linearity check, the ensemble
(articles x drive points x levels), the channel set-up (a pretest layout file
or inline channels) and, for the simulated lab, the plant. Every field states
its unit; unknown fields are rejected. :func:`summarize_plan` prints it with an
estimated duration before anything moves.
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator


class PlanError(ValueError):
    """A plan file or plan field is invalid; the message names the file and field."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Pole(_Strict):
    """A known (e.g. pretest-predicted) resonance."""

    frequency_hz: float = Field(gt=0)
    damping: float = Field(gt=0, lt=1, description="modal damping ratio (0.001 = 0.1 %)")


class LinesSpec(_Strict):
    """Frequency lines.

    ``linear``: ``start_hz..stop_hz`` every ``step_hz``; ``log``: ``n_lines``
    geometric; ``bandwidth``: a geometric background with ratio
    ``1 + background_step`` plus ``lines_per_bandwidth`` lines per half-power
    bandwidth (2 zeta f) within ``span_bandwidths`` bandwidths of each known pole.
    """

    kind: Literal["linear", "log", "bandwidth"] = "linear"
    start_hz: float = Field(gt=0)
    stop_hz: float = Field(gt=0)
    step_hz: float | None = Field(default=None, gt=0)
    n_lines: int | None = Field(default=None, ge=2)
    background_step: float = Field(default=0.02, gt=0, lt=1, description="relative step between background lines")
    lines_per_bandwidth: float = Field(default=4.0, gt=0)
    span_bandwidths: float = Field(default=3.0, gt=0, description="half-width of the dense region, in half-power bandwidths")
    poles: tuple[Pole, ...] = ()

    @model_validator(mode="after")
    def _check(self):
        if self.stop_hz <= self.start_hz:
            raise ValueError(f"stop_hz ({self.stop_hz}) must exceed start_hz ({self.start_hz})")
        if self.kind == "linear" and self.step_hz is None:
            raise ValueError("kind='linear' needs step_hz")
        if self.kind == "log" and self.n_lines is None:
            raise ValueError("kind='log' needs n_lines")
        return self


class ForceSpec(_Strict):
    levels_n: tuple[float, ...] = Field(default=(1.0,), min_length=1, description="force amplitudes, N peak")
    tolerance: float = Field(default=0.02, gt=0, lt=1, description="allowed relative force deviation")
    max_corrections: int = Field(default=10, ge=0, description="amplitude corrections per line")
    initial_drive_v: float = Field(default=0.05, gt=0, description="first drive amplitude, V peak")


class SettleSpec(_Strict):
    """Settle rule. ``detector``: wait until the estimated remaining transient error
    (block-to-block change times q/(1-q), q = exp(-T_block/tau)) is below ``tolerance``;
    ``fixed``: dwell ``fixed_dwell_s`` after each step."""

    mode: Literal["detector", "fixed"] = "detector"
    tolerance: float = Field(default=1e-3, gt=0, description="relative FRF error left by the transient")
    min_blocks: int = Field(default=3, ge=2)
    block_min_s: float = Field(default=0.05, gt=0, description="shortest block, s")
    block_max_s: float = Field(default=1.0, gt=0, description="longest block, s")
    blocks_per_tau: float = Field(default=3.0, gt=0, description="block length = tau/blocks_per_tau (clipped)")
    assumed_damping: float = Field(default=0.001, gt=0, lt=1, description="damping bound for tau when no pole is known")
    max_time_s: float = Field(default=120.0, gt=0, description="give up settling a line after this, s")
    fixed_dwell_s: float = Field(default=2.0, ge=0, description="dwell of mode 'fixed', s")


class MeasureSpec(_Strict):
    blocks: int = Field(default=4, ge=2, description="blocks averaged per line")
    n_harmonics: int = Field(default=5, ge=1, description="harmonics estimated (fundamental included)")
    thd_limit: float = Field(default=0.05, gt=0, description="flag lines with response THD above this fraction")
    std_error_limit: float = Field(default=0.01, gt=0, description="flag lines with relative standard error above this")


class LimitsSpec(_Strict):
    drive_v_max: float = Field(default=5.0, gt=0, description="drive amplitude limit, V peak")
    force_n_max: float = Field(default=20.0, gt=0, description="force amplitude limit, N peak")
    acceleration_m_s2_max: float = Field(default=500.0, gt=0, description="response amplitude limit, m/s^2 peak")
    on_overload: Literal["abort", "flag"] = "abort"
    ramp_down_s: float = Field(default=0.5, ge=0, description="ramp-down duration on every exit, s")


class RefineSpec(_Strict):
    """Adaptive refinement near resonances found during the sweep."""

    enabled: bool = False
    lines_per_bandwidth: float = Field(default=4.0, gt=0)
    span_bandwidths: float = Field(default=3.0, gt=0)
    peak_ratio: float = Field(default=1.3, gt=1, description="a local max this much above its neighbours is a peak")


class LinearitySpec(_Strict):
    enabled: bool = False
    level_ratio: float = Field(default=0.5, gt=0, description="second level relative to the first")
    tolerance: float = Field(default=0.01, gt=0, description="flag if the FRF changes more than this fraction")
    peaks_only: bool = True


class EnsembleSpec(_Strict):
    articles: tuple[str, ...] = ("article1",)
    drives: tuple[str, ...] | None = Field(default=None, description="drive names (default: all drives of the layout)")


class ChannelEntry(_Strict):
    name: str
    role: Literal["response", "force", "monitor"] = "response"
    quantity: Literal["acceleration", "velocity", "displacement", "force", "voltage"] = "acceleration"
    unit: str | None = None
    grid: int = 0
    direction: tuple[float, float, float] = (0.0, 0.0, 1.0)
    xyz_m: tuple[float, float, float] | None = None
    sensitivity_v_per_unit: float = Field(default=0.01, gt=0)
    range_v: float = Field(default=5.0, gt=0)
    physical: str = ""
    serial: str = ""
    iepe_current_a: float | None = None


class SimModes(_Strict):
    """Inline modal model: mass-normalized shapes at the sensors and the drive points."""

    frequencies_hz: tuple[float, ...]
    damping: float | tuple[float, ...] = 0.001
    shapes_out: tuple[tuple[float, ...], ...] = Field(description="(n_sensors, n_modes), m/sqrt(kg)")
    shapes_in: tuple[tuple[float, ...], ...] = Field(description="(n_drives, n_modes), m/sqrt(kg)")


class SimSpec(_Strict):
    """The plant and rig of ``--driver sim``: inline ``modes`` or a ``model`` .npz file
    (arrays ``frequencies_hz``, ``damping``, ``shapes_out``, ``shapes_in``)."""

    modes: SimModes | None = None
    model: str | None = None
    noise_rms: float = Field(default=1e-4, ge=0, description="sensor noise, engineering units rms")
    adc_bits: int = Field(default=24, ge=8, le=32)
    shaker: Literal["electrodynamic", "ideal"] = "electrodynamic"
    article_scatter: float = Field(default=0.0, ge=0, description="relative frequency scatter between articles")
    seed: int = 0

    @model_validator(mode="after")
    def _one_source(self):
        if (self.modes is None) == (self.model is None):
            raise ValueError("give exactly one of [sim.modes] or sim.model")
        return self


class Plan(_Strict):
    """A complete stepped-sine plan (see ``docs/acquisition.md`` for the TOML form)."""

    name: str = "sweep"
    sample_rate_hz: float = Field(default=51200.0, gt=0, description="shared sample clock, Hz")
    layout: str | None = Field(default=None, description="pretest layout JSON (relative to the plan file)")
    channels: tuple[ChannelEntry, ...] = ()
    lines: LinesSpec
    force: ForceSpec = ForceSpec()
    settle: SettleSpec = SettleSpec()
    measure: MeasureSpec = MeasureSpec()
    limits: LimitsSpec = LimitsSpec()
    refine: RefineSpec = RefineSpec()
    linearity: LinearitySpec = LinearitySpec()
    ensemble: EnsembleSpec = EnsembleSpec()
    sim: SimSpec | None = None
    base_dir: str = Field(default=".", description="directory relative paths are resolved against")

    @model_validator(mode="after")
    def _check(self):
        if self.layout is None and not self.channels:
            raise ValueError("give a 'layout' file or inline [[channels]]")
        if self.lines.stop_hz >= 0.45 * self.sample_rate_hz:
            raise ValueError(f"lines.stop_hz {self.lines.stop_hz} too close to Nyquist of sample_rate_hz {self.sample_rate_hz}")
        return self

    def resolve(self, relative: str) -> Path:
        p = Path(relative)
        return p if p.is_absolute() else Path(self.base_dir) / p


def load_plan(path) -> Plan:
    """Read and validate a TOML plan; errors name the file and the field."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise PlanError(f"{path}: plan file not found") from None
    except tomllib.TOMLDecodeError as exc:
        raise PlanError(f"{path}: not valid TOML: {exc}") from None
    data.setdefault("base_dir", str(path.resolve().parent))
    return plan_from_dict(data, source=str(path))


def plan_from_dict(data: dict, source: str = "plan") -> Plan:
    """Validate a plan given as a dict (the TOML structure)."""
    try:
        return Plan.model_validate(data)
    except ValidationError as exc:
        msgs = []
        for err in exc.errors():
            loc = ".".join(str(x) for x in err["loc"]) or "(plan)"
            msgs.append(f"{loc}: {err['msg']}")
        raise PlanError(f"{source}: " + "; ".join(msgs)) from None


def plan_lines(plan: Plan) -> np.ndarray:
    """The planned frequency lines (Hz, ascending) before refinement found during the sweep."""
    ls = plan.lines
    if ls.kind == "linear":
        f = np.arange(ls.start_hz, ls.stop_hz + 0.5 * ls.step_hz, ls.step_hz)
        return f[f <= ls.stop_hz * (1 + 1e-12)]
    if ls.kind == "log":
        return np.geomspace(ls.start_hz, ls.stop_hz, ls.n_lines)
    n_bg = max(int(math.ceil(math.log(ls.stop_hz / ls.start_hz) / math.log1p(ls.background_step))), 1) + 1
    background = np.geomspace(ls.start_hz, ls.stop_hz, n_bg)
    return dense_lines(background, ls.poles, ls.lines_per_bandwidth, ls.span_bandwidths, ls.start_hz, ls.stop_hz)


def dense_lines(existing, poles, lines_per_bandwidth, span_bandwidths, lo, hi) -> np.ndarray:
    """Merge ``existing`` lines with dense lines around ``poles`` (objects with frequency_hz, damping)."""
    f = np.asarray(existing, dtype=float)
    extra = []
    for p in poles:
        bw = 2 * p.damping * p.frequency_hz
        step = bw / lines_per_bandwidth
        k = np.arange(-math.ceil(span_bandwidths * lines_per_bandwidth), math.ceil(span_bandwidths * lines_per_bandwidth) + 1)
        dense = p.frequency_hz + k * step
        f = f[np.abs(f - p.frequency_hz) > span_bandwidths * bw + step]
        extra.append(dense)
    f = np.concatenate([f] + extra) if extra else f
    f = np.unique(np.round(f[(f >= lo) & (f <= hi)], 9))
    return f


def tau_bound_s(plan: Plan, frequency_hz: float) -> float:
    """Upper bound of the transient time constant at a line, s: the slowest known pole
    within 20 % of the line, else ``settle.assumed_damping`` at the line frequency."""
    poles = [p for p in plan.lines.poles if abs(p.frequency_hz / frequency_hz - 1) < 0.2]
    if poles:
        return max(1 / (2 * np.pi * p.frequency_hz * p.damping) for p in poles)
    return 1 / (2 * np.pi * frequency_hz * plan.settle.assumed_damping)


def block_cycles(plan: Plan, frequency_hz: float) -> int:
    """Whole drive cycles per block at a line."""
    T = tau_bound_s(plan, frequency_hz) / plan.settle.blocks_per_tau
    T = min(max(T, plan.settle.block_min_s), plan.settle.block_max_s)
    return max(int(round(T * frequency_hz)), 1)


def estimate_duration_s(plan: Plan, lines=None) -> np.ndarray:
    """Estimated seconds per line (settle + measure), ``(n_lines,)``.

    The transient left by a step is estimated from the known poles (sum of
    single-mode FRFs); without poles a 10 % change is assumed. Settling then
    takes ``tau * ln(change / tolerance)``; a fixed dwell takes ``fixed_dwell_s``.
    """
    f = plan_lines(plan) if lines is None else np.asarray(lines, dtype=float)
    poles = plan.lines.poles
    if poles:
        fr = np.array([p.frequency_hz for p in poles])
        zr = np.array([p.damping for p in poles])
        H = np.sum(1.0 / (fr[None] ** 2 - f[:, None] ** 2 + 2j * zr[None] * fr[None] * f[:, None]), axis=1)
        change = np.abs(np.diff(H, prepend=H[0])) / np.abs(H)
        change[0] = 1.0
    else:
        change = np.full(f.shape, 0.1)
        change[0] = 1.0
    out = np.empty(f.shape)
    for k, fk in enumerate(f):
        T = block_cycles(plan, fk) / fk
        measure = plan.measure.blocks * T
        if plan.settle.mode == "fixed":
            settle = plan.settle.fixed_dwell_s
        else:
            tau = tau_bound_s(plan, fk)
            settle = max(plan.settle.min_blocks * T, tau * math.log(max(change[k] / plan.settle.tolerance, 1.0)))
            settle = min(settle, plan.settle.max_time_s)
        out[k] = settle + measure
    return out * len(plan.force.levels_n) * (1 + 0.5 * plan.linearity.enabled)


def summarize_plan(plan: Plan, n_drives: int | None = None) -> str:
    """A human-readable summary with line count and estimated duration."""
    f = plan_lines(plan)
    per_run = estimate_duration_s(plan, f).sum() / len(plan.force.levels_n)
    n_art = len(plan.ensemble.articles)
    n_drv = len(plan.ensemble.drives) if plan.ensemble.drives else (n_drives or 1)
    n_runs = n_art * n_drv * len(plan.force.levels_n)
    lines = [
        f"plan {plan.name!r}: {f.size} lines {f.min():.2f}-{f.max():.2f} Hz ({plan.lines.kind}"
        + (f", {len(plan.lines.poles)} known poles" if plan.lines.poles else "")
        + (", refinement on" if plan.refine.enabled else "")
        + ")",
        f"  force levels {list(plan.force.levels_n)} N +-{plan.force.tolerance:.1%};"
        f" settle {plan.settle.mode} (tol {plan.settle.tolerance:g}); {plan.measure.blocks} blocks averaged",
        f"  limits: drive {plan.limits.drive_v_max} V, force {plan.limits.force_n_max} N,"
        f" acceleration {plan.limits.acceleration_m_s2_max} m/s^2; overload -> {plan.limits.on_overload}",
        f"  ensemble: {n_art} article(s) x {n_drv} drive point(s) x {len(plan.force.levels_n)} level(s) = {n_runs} run file(s)",
        f"  estimated duration: {per_run:.0f} s per run, {per_run * n_runs / 3600:.2f} h in total"
        + (" (excluding lines added by refinement)" if plan.refine.enabled else ""),
    ]
    return "\n".join(lines)


def sim_plant_arrays(plan: "Plan"):
    """The modal plant of a plan's ``[sim]`` section (inline ``[sim.modes]`` or a ``.npz`` model).

    Returns
    -------
    frequencies_hz, damping, shapes_out, shapes_in : float arrays
        As :class:`acquisition.ModalPlant` takes them.

    Raises
    ------
    ValueError
        No ``[sim]`` section, a missing model file or a missing array (named).
    """
    sim = plan.sim
    if sim is None:
        raise ValueError("the plan has no [sim] section: the simulated plant needs [sim.modes] or sim.model")
    if sim.modes is not None:
        m = sim.modes
        return tuple(np.asarray(v, float) for v in (m.frequencies_hz, m.damping, m.shapes_out, m.shapes_in))
    path = plan.resolve(sim.model)
    try:
        with np.load(path) as z:
            return tuple(np.asarray(z[k], float) for k in ("frequencies_hz", "damping", "shapes_out", "shapes_in"))
    except FileNotFoundError:
        raise ValueError(f"sim.model: file {path} not found") from None
    except KeyError as exc:
        raise ValueError(f"sim.model {path}: missing array {exc}") from None
