"""Simulated acquisition: the truth of each simulated test article and its stepped-sine sweeps.

The ``[simulation]`` section (docs/campaign.md) says what the articles of a
plan's ensemble *are*; the plan (docs/acquisition.md) says what the lab
*does* (lines, force levels, settling, channels). For every article:

1. its normalized parameters p_a = population offsets + Gaussian scatter
   (clipped into 95 % of the bounds), and the effects listed for it as added
   terms of the deck (``ParametricModel.with_terms``: a closed gap is a contact
   spring, p = 1 of the term; the articles without it have p = 0);
2. its exact FRF model, as ``frfcal.synth`` builds it (``article_truth``):
   modes up to ``mode_factor`` x the sweep top with per-mode damping, the
   free-free rigid-body modes at 0 Hz and the exact series of the higher modes;
3. that model as an :class:`acquisition.ModalPlant` (:func:`truth_plant`):
   elastic modes as states, rigid-body and higher modes as the plant's
   frequency-dependent feedthrough, so the plant's FRF *is* the truth's;
4. the simulated lab (:class:`acquisition.SimulatedLab`, electrodynamic shaker,
   sensor noise) swept by the stepped-sine controller at every force level of
   the plan; a loose part (``[simulation.loose_part]``) is a hardening cubic
   spring on one mode of its article, engaged in the runs at or above its
   ``from_level_n``.

Run files are ``<dir>/<plan>_<article>_<drive>_<level>N.h5`` (as ``frfcal acquire``).
The model used for the truth is the campaign's deck: no suspension springs,
free-free, the same boundary the calibration model has.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: The method paper's Table 2.1: (nominal, calibrated) of each parameter. Their
#: ratio is the demo's "true" change of the test articles against the model.
PAPER_TABLE_2_1 = {
    "E_main": (210.0, 217.0),
    "rho_main": (7850.0, 7750.0),
    "t_bracket_RHS": (2.5, 2.46),
    "t_bracket_LHS": (2.5, 2.52),
    "t_top_skin": (2.3, 2.21),
    "t_bottom_skin": (2.0, 1.96),
    "t_arm_base_RHS": (2.3, 2.33),
    "t_arm_base_LHS": (2.3, 2.22),
    "t_arm_RHS": (3.0, 3.02),
    "t_arm_LHS": (3.0, 3.04),
    "t_arm_ext_base_RHS": (2.3, 2.46),
    "t_arm_ext_base_LHS": (2.3, 2.35),
    "M1": (0.136, 0.135),
    "M2": (0.136, 0.138),
    "M3": (0.215, 0.211),
    "M4": (0.215, 0.227),
    "E_weld": (210.0, 207.0),
}

#: log-normal rms of the article-to-article damping factor (as frfcal.synth)
_ZETA_SCATTER = 0.05


class SimulationError(ValueError):
    """The [simulation] section does not fit the model or the plan (the message names the field)."""


def paper_offsets(names) -> np.ndarray:
    """Normalized parameter changes p of the paper's Table 2.1 ratios (0 for parameters not in it)."""
    return np.array([PAPER_TABLE_2_1[n][1] / PAPER_TABLE_2_1[n][0] - 1.0 if n in PAPER_TABLE_2_1 else 0.0
                     for n in names])


def truth_plant(truth, quantity: str = "accelerance"):
    """The simulated lab's plant of an exact FRF model (``frfcal.synth.ArticleTruth``).

    Elastic modes become the plant's damped modes; rigid-body modes (0 Hz,
    free-free) and the higher-mode series become its feedthrough
    (:meth:`acquisition.ModalPlant.feedthrough`), so ``plant.frf(f)`` equals
    ``truth.frf(f, quantity)`` to round-off.

    Parameters
    ----------
    truth : frfcal.synth.ArticleTruth
    quantity : {"accelerance", "receptance", "mobility"}

    Returns
    -------
    acquisition.ModalPlant
    """
    from acquisition import ModalPlant

    f = np.asarray(truth.frequencies_hz, float)
    rigid = f == 0.0
    if not np.any(~rigid):
        raise SimulationError("the truth has no elastic mode below its cut: nothing for the plant's states")
    out, inp = np.asarray(truth.out_modal, float), np.asarray(truth.in_modal, float)
    return ModalPlant(
        f[~rigid], np.asarray(truth.zeta, float)[~rigid], out[:, ~rigid], inp[~rigid].T, quantity=quantity,
        rigid_out=out[:, rigid] if rigid.any() else None, rigid_in=inp[rigid].T if rigid.any() else None,
        residual=truth.residual if truth.residual.size else None, residual_shift=float(truth.shift),
    )


@dataclass(frozen=True)
class SimulatedArticle:
    """One simulated article: what it is and the plant the lab sweeps.

    Attributes
    ----------
    name : str
    p : (n_params,) float
        Normalized parameters of the deck's parameters (the calibration's).
    effects : tuple of (str, float)
        Added terms of the truth (name, p of the term); p = 0: the article lacks it.
    truth : frfcal.synth.ArticleTruth
        Exact FRF model at the sensors and drives (SI, e^{+i w t}).
    plant : acquisition.ModalPlant
        ``truth_plant(truth)``.
    loose_mode : int or None
        Index of the plant mode carrying the loose part (None: linear article).
    loose_beta : float
        Cubic coefficient of that mode, 1/(m^2 kg) (0 without a loose part).
    loose_from_level_n : float
        Force level (N peak) from which the loose part is engaged (inf without).
    """

    name: str
    p: np.ndarray
    effects: tuple
    truth: object
    plant: object
    loose_mode: int | None = None
    loose_beta: float = 0.0
    loose_from_level_n: float = math.inf

    def nonlinearity(self, level_n: float):
        """The lab's ``CubicSpring`` at ``level_n`` (None below ``loose_from_level_n`` or for a linear article)."""
        from acquisition import CubicSpring

        if self.loose_mode is None or level_n < self.loose_from_level_n * (1 - 1e-9):
            return None
        return CubicSpring(self.loose_mode, self.loose_beta)


def _effect_terms(sim, pm):
    import femodel

    terms = []
    for e in sim.effect:
        if e.kind == "spring":
            dofs = [(g1, c, g2, c) for g1, g2 in e.pairs for c in e.components]
            terms.append(femodel.AddedSpring(e.name, dofs, scale=float(e.rate_n_per_m),
                                             description=f"simulated effect {e.name}"))
        else:
            terms.append(femodel.AddedMass(e.name, e.grids, scale=float(e.mass_kg),
                                           description=f"simulated effect {e.name}"))
    try:
        return pm.with_terms(terms) if terms else pm
    except femodel.ParameterError as exc:
        raise SimulationError(f"[simulation] effect: {exc}") from None


def simulated_articles(sim, pm, articles, sensors, drives, *, data_hz, log=print):
    """Truth and plant of every article of the plan.

    Parameters
    ----------
    sim : SimulationSection
    pm : femodel.ParametricModel
        The campaign's parametric model (SI inside).
    articles : sequence of str
        The plan's ensemble.
    sensors, drives : sequences of acquisition.ChannelSpec
        Channels with grid and direction (the layout).
    data_hz : (float, float)
        Swept range, Hz (the residual series holds to its top).
    log : callable

    Returns
    -------
    tuple of SimulatedArticle
    """
    import femodel

    from frfcal.synth import article_truth

    names = list(pm.parameters.names)
    arts = list(articles)
    for e in sim.effect:
        unknown = sorted(set(e.articles) - set(arts))
        if unknown:
            raise SimulationError(f"[simulation] effect {e.name!r}: articles {unknown} are not in the plan's "
                                  f"ensemble {arts}")
    if sim.loose_part is not None and sim.loose_part.article not in arts:
        raise SimulationError(f"[simulation] loose_part.article {sim.loose_part.article!r} is not in the plan's "
                              f"ensemble {arts}")
    if sim.offsets == "paper":
        p_pop = paper_offsets(names)
    else:
        unknown = sorted(set(sim.offsets) - set(names))
        if unknown:
            raise SimulationError(f"[simulation] offsets: unknown parameter(s) {unknown}; parameters are {names}")
        p_pop = np.array([float(sim.offsets.get(n, 0.0)) for n in names])
        bad = [n for n, x, lo, hi in zip(names, p_pop, pm.lower, pm.upper) if not lo < x < hi]
        if bad:
            raise SimulationError(f"[simulation] offsets: {bad} outside the parameter bounds")
    ext = _effect_terms(sim, pm)
    asm = ext.assembly
    try:
        C = femodel.sensor_matrix(asm, [c.grid for c in sensors], [c.direction for c in sensors])
        B = femodel.sensor_matrix(asm, [c.grid for c in drives], [c.direction for c in drives]).T.toarray()
    except femodel.ModelError as exc:
        raise SimulationError(f"[simulation] layout channels: {exc}") from None
    ss = np.random.SeedSequence(int(sim.seed))
    s_zeta, *s_art = ss.spawn(1 + len(arts))
    rz = np.random.default_rng(s_zeta)
    pool: list[float] = []
    lo_z, hi_z = sim.zeta_range

    def population_zeta(n):
        while len(pool) < n:
            pool.append(float(np.exp(rz.uniform(np.log(lo_z), np.log(hi_z)))))
        return np.array(pool[:n])

    d_lo, d_hi = float(data_hz[0]), float(data_hz[1])
    out = []
    for a, name in enumerate(arts):
        r = np.random.default_rng(s_art[a])
        p = np.clip(p_pop + sim.scatter * r.standard_normal(len(names)), 0.95 * pm.lower, 0.95 * pm.upper)
        variation = r.standard_normal(4096)

        def zeta_of_mode(n, variation=variation):
            return population_zeta(n) * np.exp(_ZETA_SCATTER * variation[:n])

        effects = tuple((e.name, 1.0 if name in e.articles else 0.0) for e in sim.effect)
        p_ext = np.concatenate([p, [x for _, x in effects]])
        truth = article_truth(ext.stiffness(p_ext), ext.mass(p_ext), C, B, p_ext, f_cut_hz=sim.mode_factor * d_hi,
                              f_max_hz=d_hi, zeta_of_mode=zeta_of_mode, shift_hz=d_lo, dofs=ext.aset)
        plant = truth_plant(truth)
        loose = {}
        if sim.loose_part is not None and sim.loose_part.article == name:
            loose = _loose_part(sim.loose_part, plant, (d_lo, d_hi))
        elastic = plant.frequencies_hz
        in_range = elastic[(elastic >= d_lo) & (elastic <= d_hi)]
        log(f"  {name}: {len(elastic)} elastic modes to {sim.mode_factor * d_hi:.0f} Hz ({len(in_range)} in "
            f"{d_lo:g}-{d_hi:g} Hz), {truth.n_rigid} rigid, higher modes by a {truth.residual.shape[0]}-term series"
            + "".join(f"; {n} ({'on' if x else 'off'})" for n, x in effects)
            + (f"; loose part on the {elastic[loose['loose_mode']]:.1f} Hz mode from {loose['loose_from_level_n']:g} N"
               if loose else ""))
        out.append(SimulatedArticle(name=name, p=p, effects=effects, truth=truth, plant=plant, **loose))
    return tuple(out)


def _loose_part(spec, plant, data_hz) -> dict:
    """Mode and cubic coefficient of a loose part: the mode's frequency rises by ``shift`` at resonance at ``level_n``."""
    f = plant.frequencies_hz
    if spec.mode is not None:
        if spec.mode > f.size:
            raise SimulationError(f"[simulation] loose_part.mode {spec.mode}: the article has {f.size} elastic modes")
        k = spec.mode - 1
    else:
        w = 2 * np.pi * f
        peak = np.abs(plant.shapes_in[0]) ** 2 / (2 * plant.damping * w**2)  # drive-point receptance at resonance
        peak[(f < data_hz[0]) | (f > data_hz[1])] = 0.0
        k = int(np.argmax(peak))
    w = 2 * np.pi * f[k]
    # modal amplitude at resonance under a force of spec.from_level_n (the controller holds the force level)
    a = abs(plant.shapes_in[0, k]) * spec.from_level_n / (2 * plant.damping[k] * w**2)
    if a <= 0:
        raise SimulationError(f"[simulation] loose_part: the drive point does not move in mode {k + 1}")
    beta = ((1 + spec.shift) ** 2 - 1) / (0.75 * a**2)  # w_eq = w (1 + shift) at amplitude a; more above it
    return {"loose_mode": k, "loose_beta": float(beta), "loose_from_level_n": float(spec.from_level_n)}


@dataclass(frozen=True)
class SimulatedRun:
    """One run file of the simulated acquisition."""

    article: str
    level_n: float
    path: Path
    nonlinear: bool
    n_lines: int
    clock_s: float
    wall_s: float


def acquire_simulated(sim, plan, pm, out_dir, *, levels=None, resume: bool = True, log=print, progress: bool = False):
    """Sweep every article of ``plan`` at every force level on its simulated truth.

    Parameters
    ----------
    sim : SimulationSection
    plan : acquisition.Plan
        Lines, levels, settling, the ensemble (articles) and the channels
        (layout); its own ``[sim]`` section is not used.
    pm : femodel.ParametricModel
    out_dir : path-like
        Run files ``<plan>_<article>_<drive>_<level>N.h5`` (one drive: the first of the layout
        or of ``ensemble.drives``).
    levels : mapping article -> sequence of float, optional
        Force levels (N peak) per article (default: every level of the plan for
        every article), e.g. the high level on a few articles only.
    resume : bool
        Keep completed run files of the same names (the caller guarantees the same settings);
        interrupted ones are swept again from the start.
    log : callable
    progress : bool
        A progress bar per sweep.

    Returns
    -------
    (tuple of SimulatedArticle, tuple of SimulatedRun)
    """
    import time
    from dataclasses import replace

    from acquisition import ShakerModel, SimulatedLab, read_run
    from acquisition._controller import plan_channels, run_sweep
    from acquisition._plan import plan_lines

    sensors, drives = plan_channels(plan)
    if plan.ensemble.drives:
        by_name = {d.name: d for d in drives}
        if plan.ensemble.drives[0] not in by_name:
            raise SimulationError(f"plan ensemble.drives {plan.ensemble.drives[0]!r} is not a drive of the layout")
        drives = (by_name[plan.ensemble.drives[0]],)
    drive = drives[0]
    lines = plan_lines(plan)
    levels = {a: sorted(plan.force.levels_n) for a in plan.ensemble.articles} if levels is None else \
        {a: sorted(float(x) for x in levels.get(a, ())) for a in plan.ensemble.articles}
    if not all(levels.values()):
        raise SimulationError(f"levels: every article of the plan needs at least one force level, got {levels}")
    log(f"simulated articles ({len(plan.ensemble.articles)}): truth from the deck, free-free, "
        f"{lines.size} planned lines {lines.min():.1f}-{lines.max():.1f} Hz, levels (N) "
        + ", ".join(f"{a} {v}" for a, v in levels.items()))
    articles = simulated_articles(sim, pm, plan.ensemble.articles, sensors, (drive,),
                                  data_hz=(plan.lines.start_hz, plan.lines.stop_hz), log=log)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    chans = tuple(replace(c, physical=f"sim/{k}") for k, c in enumerate(sensors)) + (replace(drive, physical="sim/force"),)
    runs = []
    for a, art in enumerate(articles):
        for j, level in enumerate(levels[art.name]):
            nl = art.nonlinearity(level)
            path = out / f"{plan.name}_{art.name}_{drive.name}_{level:g}N.h5"
            if resume and path.exists():
                old = read_run(path)
                if old.status == "completed":
                    runs.append(SimulatedRun(art.name, float(level), path, nl is not None, old.n_lines, 0.0, 0.0))
                    log(f"  {path.name}: already complete ({old.n_lines} lines)")
                    continue
            lab = SimulatedLab(art.plant, drive_index=0, shaker=ShakerModel() if sim.shaker == "electrodynamic" else None,
                               noise_rms=sim.noise_rms, seed=int(sim.seed) * 7919 + 100 * a + j, nonlinearity=nl)
            t0 = time.perf_counter()
            try:
                res = run_sweep(lab, plan, path, sensors=sensors, drive=drive, level_n=level, article=art.name,
                                progress=progress, driver_channels=chans, resume=False)
            finally:
                lab.close()
            wall = time.perf_counter() - t0
            runs.append(SimulatedRun(art.name, float(level), path, nl is not None, res.n_lines, res.clock_s, wall))
            log(f"  {path.name}: {res.n_lines} lines, {res.clock_s:.0f} s of lab time in {wall:.1f} s"
                + (" (loose part engaged)" if nl is not None else ""))
    return articles, tuple(runs)


def runs_by_level(runs) -> dict:
    """{article: [(level_n, path), ...] ascending in level} of run files (``SimulatedRun`` or paths).

    The campaign convention: the lowest level of each article is its calibration
    data; all levels together feed the nonlinearity check (level dependence).
    A run file's level is its plan's ``level_n``.
    """
    from acquisition import read_run

    out: dict[str, list] = {}
    for r in runs:
        if isinstance(r, SimulatedRun):
            out.setdefault(r.article, []).append((r.level_n, Path(r.path)))
            continue
        run = read_run(r)
        level = (run.plan or {}).get("level_n")
        if level is None:
            raise SimulationError(f"{r}: the run file's plan records no level_n")
        out.setdefault(run.article, []).append((float(level), Path(r)))
    return {k: sorted(v) for k, v in out.items()}


def level_checks(by_level, *, settle_tolerance: float | None = None, max_relative_noise: float = 0.05,
                 modes_hz: dict | None = None, **options) -> dict:
    """Level dependence (``calibration.level_dependence``) of every article measured at two or more levels.

    Parameters
    ----------
    by_level : dict
        :func:`runs_by_level` output.
    settle_tolerance : float, optional
        The sweeps' settle tolerance (relative FRF error the settle detector
        leaves on a line; ``plan.settle.tolerance``). That error is not in the
        per-line standard error (the block scatter after settling); the
        difference of two runs can hold up to twice it, so the model-free check
        allows ``scatter_delta = (2 tol)^2 / ln(10)^2`` (the SD of a 2 tol
        relative difference). None: noise only.
    max_relative_noise : float
        Lines with more relative noise are left out of the model-free check
        (antiresonances: a standard error from a few blocks is unreliable there).
    modes_hz : dict, optional
        Article -> the modes to check (Hz), e.g. the identified modes of its lowest-level run: closely spaced
        modes that the channel-averaged magnitude shows as one peak are then checked apart (without them,
        ``calibration.find_modes`` on the lowest level).
    **options
        Passed to ``calibration.level_dependence`` (e.g. ``z_threshold``).

    Returns
    -------
    dict article -> calibration.LevelDependence, or str
        The reason when the check could not be made on that article's data
        (e.g. a mode with too few lines), instead of failing the others.
    """
    from acquisition import read_run
    from calibration import CalibrationError, frf_level_from_run, level_dependence

    if settle_tolerance is not None:
        options.setdefault("scatter_delta", (2.0 * float(settle_tolerance)) ** 2 / math.log(10.0) ** 2)
    options["max_relative_noise"] = max_relative_noise
    out = {}
    for article, entries in by_level.items():
        if len(entries) < 2:
            continue
        levels = []
        for level, path in entries:
            run = read_run(path)
            levels.append(frf_level_from_run(run, level=level))
        try:
            modes = (modes_hz or {}).get(article)
            out[article] = level_dependence(levels, list(modes) if modes else None, **options)
        except CalibrationError as exc:
            out[article] = f"not checked: {exc}"
    return out
