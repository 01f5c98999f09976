"""The pretest planner: FE model -> target modes -> sensors (EfI) -> drive point -> mass loading."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from pretest._candidates import CandidateSet, candidate_grids, candidate_set, parse_direction, select_target_modes
from pretest._efi import EfIResult, effective_independence, fim_logdet
from pretest._errors import PretestError
from pretest._massload import DEFAULT_SENSOR_MASS_KG, MassLoading, mass_loading_shifts
from pretest._metrics import LayoutMetrics, layout_metrics
from pretest._refine import refine_automac
from pretest._shaker import DriveRanking, rank_drive_points

__all__ = ["PretestConfig", "PretestResult", "TargetModes", "compute_target_modes", "plan_pretest", "evaluate_channels"]


class PretestConfig(BaseModel):
    """What to plan.  Unknown fields are rejected; units are in the field names.

    Exactly one of ``n_modes``, ``band_hz``, ``mode_numbers`` selects the
    target modes (default: the first 20 elastic modes).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    n_sensors: int = Field(20, ge=1, description="physical sensors (a triaxial bundle counts once)")
    n_modes: int | None = Field(None, ge=1, description="first N elastic modes as targets")
    band_hz: tuple[float, float] | None = Field(None, description="every elastic mode in [lo, hi] Hz")
    mode_numbers: tuple[int, ...] | None = Field(None, description="1-based mode numbers (rigid modes counted)")
    direction: str | tuple[float, float, float] = Field(
        "normal", description="single-axis direction: normal, x, y, z, or a vector in basic coordinates"
    )
    triax: bool = Field(False, description="triaxial sensors (three basic axes kept together)")
    candidate_grids: tuple[int, ...] | None = Field(None, description="grid ids allowed for sensors")
    candidate_pids: tuple[int, ...] | None = Field(None, description="property ids whose grids are allowed")
    candidate_box_m: tuple[float, float, float, float, float, float] | None = Field(
        None, description="xmin, ymin, zmin, xmax, ymax, zmax in basic coordinates, m"
    )
    include_grids: tuple[int, ...] = Field((), description="grids that must carry a sensor")
    exclude_grids: tuple[int, ...] = Field((), description="grids that must not carry a sensor")
    min_distance_m: float = Field(0.0, ge=0.0, description="minimum distance between sensors, m")
    n_drives: int = Field(1, ge=0, description="drive points to put in the layout")
    n_shaker_candidates: int = Field(5, ge=1, description="ranked drive candidates to report")
    collocated_drive: bool = Field(True, description="drive only at sensor positions and directions")
    drive_criterion: Literal["weakest", "adpr", "product"] = Field("weakest", description="drive ranking")
    sensor_mass_kg: float = Field(DEFAULT_SENSOR_MASS_KG, ge=0.0, description="mass of one sensor, kg")
    drive_mass_kg: float = Field(0.005, ge=0.0, description="force sensor + stinger moving mass at a drive, kg")
    extra_modes: int = Field(6, ge=0, description="modes solved beyond the targets (rigid modes, margin)")
    refine_automac_decades: float | None = Field(
        None, ge=0.0,
        description="after EfI, exchange sensors to lower the largest off-diagonal autoMAC while keeping "
        "log10 det(FIM) within this many decades of the EfI layout (None: no refinement)",
    )

    @field_validator("direction")
    @classmethod
    def _direction(cls, v):
        parse_direction(v if isinstance(v, str) else np.asarray(v, dtype=float))
        return v

    @field_validator("band_hz")
    @classmethod
    def _band(cls, v):
        if v is not None and not (0 <= v[0] <= v[1]):
            raise ValueError(f"band_hz {v} must satisfy 0 <= lo <= hi")
        return v


@dataclass(frozen=True)
class TargetModes:
    """The target modes at the model's independent DOF.

    Attributes
    ----------
    indices : ndarray, shape (n_target,)
        0-based indices among the computed modes.
    frequencies_hz : ndarray, shape (n_target,)
    shapes : ndarray, shape (n_a, n_target)
        Mass-normalized (SI: 1/sqrt(kg) per unit length DOF).
    n_rigid : int
        Rigid-body modes found.
    all_frequencies_hz : ndarray
        Every computed frequency.
    """

    indices: np.ndarray
    frequencies_hz: np.ndarray
    shapes: np.ndarray
    n_rigid: int
    all_frequencies_hz: np.ndarray


def compute_target_modes(assembly, *, n_modes=None, band_hz=None, mode_numbers=None, extra_modes: int = 6,
                         max_modes: int = 400) -> TargetModes:
    """Solve enough modes of ``assembly`` and pick the targets.

    For a band, the solve grows until the highest computed mode lies above
    the band (or ``max_modes`` is reached).
    """
    import femodel

    if mode_numbers is not None:
        n_solve = int(np.max(mode_numbers)) + 1
    else:
        n_solve = (20 if n_modes is None else int(n_modes)) + int(extra_modes)
    n_dof = assembly.stiffness().shape[0]
    while True:
        n_solve = min(n_solve, max_modes, n_dof - 1)
        modes = femodel.solve_modes(assembly, n_solve)
        f = np.asarray(modes.frequencies_hz)
        n_rigid = int(modes.n_rigid)
        enough = True
        if band_hz is not None and f[-1] < band_hz[1]:
            enough = False
        want = 20 if n_modes is None else int(n_modes)
        if band_hz is None and mode_numbers is None and f.size - n_rigid < want:
            enough = False
        if enough or n_solve >= min(max_modes, n_dof - 1):
            break
        n_solve = 2 * n_solve
    idx = select_target_modes(f, n_rigid, n_modes=n_modes, band_hz=band_hz, mode_numbers=mode_numbers)
    return TargetModes(idx, f[idx], np.asarray(modes.shapes)[:, idx], n_rigid, f)


@dataclass(frozen=True)
class PretestResult:
    """A planned layout with everything that judges it.

    Attributes
    ----------
    config : PretestConfig
    candidates : CandidateSet
        All candidate channels considered.
    sensors : CandidateSet
        The chosen channels (rows of ``candidates`` in ``efi.rows``).
    efi : EfIResult
    metrics : LayoutMetrics
        Metrics of the chosen channels for the target modes.
    target : TargetModes
    drive_candidates : CandidateSet
        Channels ranked as drive points.
    drive_ranking : DriveRanking
    drives : CandidateSet
        The chosen drive point(s) (best ranked, distinct grids).
    mass_loading : MassLoading
        Predicted shifts from the sensors and the drive hardware.
    channel_names : tuple of str
    drive_names : tuple of str
    """

    config: PretestConfig
    candidates: CandidateSet
    sensors: CandidateSet
    efi: EfIResult
    metrics: LayoutMetrics
    target: TargetModes
    drive_candidates: CandidateSet
    drive_ranking: DriveRanking
    drives: CandidateSet
    mass_loading: MassLoading
    channel_names: tuple[str, ...]
    drive_names: tuple[str, ...]
    extra: dict = field(default_factory=dict)


def _phi_at(assembly, cands: CandidateSet, shapes: np.ndarray) -> np.ndarray:
    import femodel

    c = femodel.sensor_matrix(assembly, cands.grids, cands.directions)
    return np.asarray(c @ shapes)


def _translations(assembly, grids, shapes) -> np.ndarray:
    """(n_points, 3, n_modes) basic translations of grids."""
    import femodel

    grids = np.asarray(grids, dtype=np.int64)
    g3 = np.repeat(grids, 3)
    d3 = np.tile(np.eye(3), (grids.size, 1))
    c = femodel.sensor_matrix(assembly, g3, d3)
    return np.asarray(c @ shapes).reshape(grids.size, 3, shapes.shape[1])


def _names(cands: CandidateSet, prefix: str) -> tuple[str, ...]:
    groups = list(dict.fromkeys(cands.group.tolist()))
    number = {g: i + 1 for i, g in enumerate(groups)}
    width = max(2, len(str(len(groups))))
    bundled = len(groups) < cands.n_rows
    out = []
    for g, a in zip(cands.group.tolist(), cands.axis.tolist()):
        base = f"{prefix}{number[g]:0{width}d}"
        out.append(base + a if bundled else base)
    return tuple(out)


def plan_pretest(model, config: PretestConfig | None = None, *, assembly=None, target: TargetModes | None = None) -> PretestResult:
    """Plan sensors and drive points for a model.

    Parameters
    ----------
    model : femodel.FEModel
    config : PretestConfig, optional
    assembly : femodel.Assembly, optional
        Reused if given (else assembled here).
    target : TargetModes, optional
        Reused if given (else solved here from the config's target selection).

    Returns
    -------
    PretestResult
    """
    import femodel

    cfg = config or PretestConfig()
    # Everything that can be checked on the deck alone is checked before the eigensolution.
    if cfg.include_grids:
        _check_in_model(model, cfg.include_grids, "include")
    if cfg.exclude_grids:
        _check_in_model(model, cfg.exclude_grids, "exclude")
    grids = candidate_grids(model, grids=cfg.candidate_grids, pids=cfg.candidate_pids, box_m=cfg.candidate_box_m)
    if cfg.include_grids:
        grids = np.union1d(grids, np.asarray(cfg.include_grids, dtype=np.int64))
    n_avail = np.setdiff1d(grids, np.asarray(cfg.exclude_grids, dtype=np.int64)).size
    if cfg.n_sensors > n_avail:
        raise PretestError(f"asked for {cfg.n_sensors} sensors but the candidate set has only {n_avail} grid(s)")
    direction = cfg.direction if isinstance(cfg.direction, str) else np.asarray(cfg.direction, dtype=float)
    cands = candidate_set(model, grids, direction=direction, triax=cfg.triax)
    asm = assembly if assembly is not None else femodel.assemble(model)
    if target is None:
        target = compute_target_modes(asm, n_modes=cfg.n_modes, band_hz=cfg.band_hz,
                                      mode_numbers=cfg.mode_numbers, extra_modes=cfg.extra_modes)
    phi = _phi_at(asm, cands, target.shapes)
    efi = effective_independence(
        phi,
        cfg.n_sensors,
        group_labels=cands.group,
        include=np.asarray(cfg.include_grids, dtype=np.int64) if cfg.include_grids else None,
        exclude=np.intersect1d(np.asarray(cfg.exclude_grids, dtype=np.int64), cands.group) if cfg.exclude_grids else None,
        positions=cands.xyz_m,
        min_distance=cfg.min_distance_m,
    )
    refine = None
    if cfg.refine_automac_decades is not None:
        refine = refine_automac(
            phi, efi.groups, group_labels=cands.group,
            include=np.asarray(cfg.include_grids, dtype=np.int64) if cfg.include_grids else None,
            exclude=np.intersect1d(np.asarray(cfg.exclude_grids, dtype=np.int64), cands.group) if cfg.exclude_grids else None,
            positions=cands.xyz_m, min_distance=cfg.min_distance_m, max_det_loss_decades=cfg.refine_automac_decades,
        )
        efi = replace(efi, groups=refine.groups, rows=refine.rows, logdet_fim=fim_logdet(phi[refine.rows]),
                      group_retention=np.full(refine.groups.size, np.nan),
                      effective_independence=np.full(refine.rows.size, np.nan))
    sensors = cands.subset(efi.rows)
    # order sensors by position along the structure for readable names: x, then y, then z
    order = np.lexsort((sensors.axis, sensors.xyz_m[:, 2], sensors.xyz_m[:, 1], sensors.xyz_m[:, 0]))
    order = _keep_bundles_together(sensors, order)
    sensors = sensors.subset(order)
    sel_rows = efi.rows[order]
    metrics = layout_metrics(phi[sel_rows], phi)

    if cfg.collocated_drive:
        drive_cands = sensors
        phi_drive = phi[sel_rows]
    else:
        drive_cands = cands if not cfg.triax else candidate_set(model, grids, direction="normal")
        phi_drive = phi if not cfg.triax else _phi_at(asm, drive_cands, target.shapes)
    ranking = rank_drive_points(phi_drive, target.frequencies_hz, criterion=cfg.drive_criterion)
    chosen, seen = [], set()
    for i in ranking.order.tolist():
        if len(chosen) >= cfg.n_drives:
            break
        g = int(drive_cands.grids[i])
        if g in seen:
            continue
        seen.add(g)
        chosen.append(i)
    drives = drive_cands.subset(np.asarray(chosen, dtype=np.int64))

    sensor_grids = np.unique(sensors.group)  # one sensor mass per physical sensor
    sensor_grid_of_group = np.array([sensors.grids[np.flatnonzero(sensors.group == g)[0]] for g in sensor_grids])
    load_grids = np.concatenate([sensor_grid_of_group, drives.grids])
    load_mass = np.concatenate([np.full(sensor_grid_of_group.size, cfg.sensor_mass_kg),
                                np.full(drives.n_rows, cfg.drive_mass_kg)])
    loading = mass_loading_shifts(target.frequencies_hz, _translations(asm, load_grids, target.shapes), load_mass)
    return PretestResult(
        config=cfg,
        candidates=cands,
        sensors=sensors,
        efi=efi,
        metrics=metrics,
        target=target,
        drive_candidates=drive_cands,
        drive_ranking=ranking,
        drives=drives,
        mass_loading=loading,
        channel_names=_names(sensors, "acc"),
        drive_names=tuple(f"drive{i + 1}" for i in range(drives.n_rows)),
        extra={} if refine is None else {"automac_refinement": {
            "decades_allowed": float(cfg.refine_automac_decades), "swaps": int(refine.n_swaps),
            "automac_before": refine.automac_before, "automac_after": refine.automac_after,
            "log10_det_before": refine.log10_det_before, "log10_det_after": refine.log10_det_after}},
    )


def _keep_bundles_together(cands: CandidateSet, order: np.ndarray) -> np.ndarray:
    """Reorder so rows of one bundle are adjacent, bundles in order of first appearance."""
    groups = cands.group[order]
    first = {}
    for pos, g in enumerate(groups.tolist()):
        first.setdefault(g, pos)
    key = np.array([first[g] for g in groups.tolist()])
    return order[np.argsort(key, kind="stable")]


def _check_in_model(model, grids, what: str) -> None:
    grids = np.asarray(grids, dtype=np.int64)
    missing = np.setdiff1d(grids, model.grid_ids)
    if missing.size:
        src = f" {model.path}" if model.path else " the model"
        raise PretestError(f"{what} grid(s) {missing.tolist()[:10]} not defined in{src}")


def evaluate_channels(assembly, grids, directions, target: TargetModes, *, phi_all=None) -> LayoutMetrics:
    """Metrics of any user-given layout (grids and basic directions) for the target modes.

    Parameters
    ----------
    assembly : femodel.Assembly
    grids : array_like of int, shape (n_channels,)
    directions : array_like, shape (n_channels, 3)
    target : TargetModes
    phi_all : array_like, shape (n_candidates, n_modes), optional
        Target modes at a candidate set, for ``mode_peak_fraction``.
    """
    import femodel

    c = femodel.sensor_matrix(assembly, np.asarray(grids, dtype=np.int64), np.asarray(directions, dtype=float))
    return layout_metrics(np.asarray(c @ target.shapes), phi_all)
