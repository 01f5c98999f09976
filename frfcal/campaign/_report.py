"""The campaign's outputs: calibration.json, calibrated BDF decks, PNG figures (written here, not in the library)."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from calibration import crossvalidation_figure, frf_figure, mac_figure, noise_floor_sd, parameter_figure
from frfcal.campaign._stages import (
    CalibrateResult,
    CrossValidationResult,
    GroupResult,
    MemberCalibration,
    MemberValidation,
    ValidationResult,
    floors_of,
    identified_modes,
    raw_data,
)


def json_default(o):
    """``json.dumps`` default for arrays, numpy scalars, paths; non-finite floats become null."""
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    if isinstance(o, float) and not np.isfinite(o):
        return None
    raise TypeError(f"not JSON serializable: {type(o).__name__}")


def reported_cycle(m: MemberCalibration, v: MemberValidation):
    """The CycleResult as reported: p and surrogate of the refinement, per-article estimates in it."""
    cyc, ref = m.cycle, m.refinement
    if ref is None:
        return cyc
    if v.articles:
        ref = replace(ref, articles=v.articles)
    return replace(cyc, p=m.p, surrogate=m.surrogate, refinement=ref)


def member_figures(camp, label, pm, sur0, arts, cyc, val, cv, identifiability):
    """The member's figures by file stem (frf, parameters, crossvalidation, mac); None entries left out."""
    c = camp.calibration
    band = (camp.band.low_hz, camp.band.high_hz)
    chans = list(camp.channels.calibrate[:3]) + list(camp.channels.holdout[:3])
    figs = {
        f"frf_{label}": frf_figure(label, sur0, cyc.surrogate, cyc.p, [raw_data(a, chans) for a in arts],
                                   identified_modes(arts[0]), chans, set(camp.channels.calibrate), c.zeta0,
                                   camp.validation.mac_min, band, arts[0].quantity),
        f"parameters_{label}": parameter_figure(label, pm, cyc.p, cyc.calibration.sd_nominal, cyc.sd, cv,
                                                identifiability),
    }
    if cv is not None:
        figs[f"crossvalidation_{label}"] = crossvalidation_figure(pm.parameters.names, cyc.p, cv)
    mac = mac_figure(val, arts[0].name)
    if mac is not None:
        figs[f"mac_{label}"] = mac
    return figs


def _raw_floor(camp, arts):
    """(noise floor SD of the raw calibration lines, its source), or (None, None): values-weighted over the
    articles, from their standard errors or, without, the estimate from their lines."""
    errs, src = floors_of(arts, camp.channels.calibrate)
    if errs is None:
        return None, None
    fl, n = [], []
    for a, se in zip(arts, errs):
        d = raw_data(a, camp.channels.calibrate)
        fl.append(noise_floor_sd(d, se))
        n.append(d.frf.size if d.mask is None else int(d.mask.sum()))
    return float(np.dot(fl, n) / sum(n)), src


def write_outputs(camp, pm, articles, groups: GroupResult, cal: CalibrateResult, val: ValidationResult,
                  xval: CrossValidationResult, timings: dict, stages: dict, outdir: Path, log=print) -> dict:
    """Write calibration.json (and per member the calibrated BDF and figures); return the result dict."""
    members = []
    nominal = pm.physical(np.zeros(pm.n_params))
    for m, v, x in zip(cal.members, val.members, xval.members):
        arts = [articles[i] for i in m.articles]
        cyc, cv = reported_cycle(m, v), x.crossvalidation
        idf = getattr(x, "identifiability", None) or m.identifiability  # checked against the refits when made
        raw_floor, raw_src = _raw_floor(camp, arts)
        params = []
        phys = pm.physical(cyc.p)
        for j, name in enumerate(pm.parameters.names):
            row = {"name": name, "nominal_si": nominal[name], "calibrated_si": phys[name], "p": float(cyc.p[j]),
                   "identifiable": bool(idf.identifiable[j]), "identifiability": idf.reasons[j] or None}
            if cv is not None:
                row["cv_mean_si"] = float(pm.nominal[j] * (1 + cv.mean_p[j]))
                row["cv_percent"] = cv.cv(j)
                row["cv_not_meaningful"] = cv.cv_reason[j] or None
            params.append(row)
        entry = {
            "member": m.label,
            "articles": [a.name for a in arts],
            "parameters": params,
            "sd_calibration_nominal": cyc.calibration.sd_nominal,
            "sd_calibration": cyc.sd,
            "sd_calibration_definition": "equalized identified test model at zeta0 on the half-bandwidth grid",
            "sd_raw_calibration": None if cyc.refinement is None else cyc.refinement.sd_raw,
            "sd_raw_calibration_start": None if cyc.refinement is None else cyc.refinement.sd_raw_start,
            "sd_raw_definition": "raw calibration lines, every value alike (Eq. 2.23); model with the identified "
                                 "damping mapped by MAC, then estimated per mode",
            # how the raw-line fit weighted the values (the reported SDs are unweighted either way)
            "raw_fit_weights": None if cyc.refinement is None else (
                "uniform" if camp.calibration.refine_weights == "uniform" or raw_src is None
                else f"noise: 1 / variance of each log ratio ({raw_src})"),
            "sd_raw_floor": raw_floor,
            "sd_raw_floor_source": raw_src,
            "identifiability": idf.to_dict(),
            "calibration": cyc.to_dict(),
            "validation": None if v.validation is None else {
                **v.validation.to_dict(),
                # several articles: their test-to-test scatter on the hold-out channels, beside the noise floor
                **({} if v.scatter is None else {"scatter": v.scatter,
                                                  "floor_with_scatter_ratio": v.floor_with_scatter_ratio})},
            "crossvalidation": None if cv is None else cv.to_dict(),
            "timings": {"calibration_s": m.time_s, "validation_s": v.time_s, "crossvalidation_s": x.time_s},
        }
        if camp.output.write_bdf:
            bdf_out = outdir / f"calibrated_{m.label}.bdf"
            pm.write_bdf(bdf_out, cyc.p)
            entry["bdf"] = str(bdf_out)
        if camp.output.figures:
            written = []
            for stem, fig in member_figures(camp, m.label, pm, cal.surrogate, arts, cyc, v.validation, cv,
                                            idf).items():
                path = outdir / f"{stem}.png"
                fig.savefig(path, dpi=90)
                written.append(str(path))
            entry["figures"] = written
        members.append(entry)
    sur0 = cal.surrogate
    result = {
        "campaign": {k: v for k, v in json.loads(camp.model_dump_json()).items()},
        "articles": [a.name for a in articles],
        "pairwise_sd": None if groups.pairwise_sd is None else groups.pairwise_sd.tolist(),
        "grouping": None if groups.grouping is None else groups.grouping.to_dict(),
        "surrogate": {"size": sur0.size, "modes": len(sur0.basis_frequencies_hz), "static": sur0.n_static,
                      "enrichment": sur0.n_enrich, "timings_s": sur0.timings_s},
        "level_check": dict(cal.level),
        "members": members,
        "timings": timings,
        "stages": stages,
    }
    path = outdir / "calibration.json"
    path.write_text(json.dumps(result, indent=1, default=json_default))
    result["result_file"] = str(path)
    log(f"wrote {path}")
    return result
