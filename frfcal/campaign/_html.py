"""The campaign report: one self-contained HTML page (figures embedded, CSS inline, no network; docs/report.md).

:func:`write_report` takes the typed stage results (:class:`ReportResults`)
and writes ``<outdir>/report.html``. Sections follow issue 15's order:
layout, sweep quality, stabilization, FRF overlays, parameters,
validation and cross-validation, grouping, diagnosis, versions and the
campaign file. A section whose stage did not run (or whose data the run files
do not hold, e.g. sweep quality of a UFF58 import) shows a one-line note
instead. Figures are PNG ``data:`` URIs; tables are HTML tables. A small
inline script marks, after the page has loaded, how many images the
browser could not decode (``<body data-broken-images="n">``), which the
headless-browser test reads back.
"""

from __future__ import annotations

import base64
import html
import io
import json
import platform
import tempfile
import time
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Mapping

import numpy as np

from frfcal.campaign._report_figures import (
    frf_overlay_figure,
    overlay,
    layout_figure,
    level_figure,
    pairwise_sd_figure,
    sweep_quality,
    sweep_quality_figure,
)
from frfcal.campaign._stages import floor_std_error, identified_modes, raw_data

#: Resolution of the embedded PNG figures, dots per inch (a page of ~20 figures stays a few MB).
REPORT_DPI = 80

_CSS = """
body{font-family:system-ui,-apple-system,'Segoe UI',sans-serif;margin:0 auto;max-width:1200px;padding:0 1.5em 3em;
color:#1d1d1d;background:#fff;line-height:1.4}
h1{border-bottom:3px solid #2a5d9f;padding-bottom:.2em}
h2{border-bottom:1px solid #bbb;margin-top:2em;color:#2a5d9f}
h3{margin-bottom:.3em}
table{border-collapse:collapse;margin:.5em 0 1em;font-size:.85em}
th,td{border:1px solid #ccc;padding:.2em .5em;text-align:left;vertical-align:top}
th{background:#eef2f8}
td.num{text-align:right;font-variant-numeric:tabular-nums}
tr.bad td{background:#fbeaea}
figure{margin:.5em 0 1.5em}
figure img{max-width:100%;border:1px solid #ddd}
figcaption{font-size:.85em;color:#555}
p.skipped{color:#777;font-style:italic}
pre{background:#f6f6f6;border:1px solid #ddd;padding:.6em;overflow-x:auto;font-size:.8em}
nav ol{columns:2;font-size:.9em}
"""

_SCRIPT = """
window.addEventListener('load', function () {
  var imgs = document.images, broken = 0;
  for (var i = 0; i < imgs.length; i++) {
    if (!imgs[i].complete || imgs[i].naturalWidth === 0) { broken++; imgs[i].setAttribute('data-broken', '1'); }
  }
  document.body.setAttribute('data-images', String(imgs.length));
  document.body.setAttribute('data-broken-images', String(broken));
});
"""


@dataclass(frozen=True)
class ReportResults:
    """What the report shows: the typed results of the stages that ran (None: the stage did not run).

    Attributes
    ----------
    load : LoadResult or None
    identify : IdentifyResult or None
    group : GroupResult or None
    calibrate : CalibrateResult or None
    validate : ValidationResult or None
    crossvalidate : CrossValidationResult or None
    model : femodel.ParametricModel or None
        The campaign's parametric model (layout, parameter names and values).
    pretest : pretest.PretestResult or None
        The pretest layout when the campaign planned one.
    diagnosis : object or None
        The diagnosis stage's result: anything with ``to_dict()`` (rendered
        generically: scalars as a key/value table, lists of dicts as tables,
        nested dicts as sub-sections); its ``figures`` (a mapping name ->
        matplotlib Figure, or a method returning one) are embedded, and its
        ``extended`` (a mapping member label -> (Surrogate, p)) is drawn in
        the FRF overlays.
    extended : mapping member label -> (Surrogate, p), or None
        Extended models to overlay (overrides the diagnosis' ``extended``).
    stages : mapping stage name -> record dict, or None
        ``run_campaign``'s stage records (status "ran"/"reused", time_s).
    campaign_file : Path or None
        The campaign TOML (shown verbatim); None shows the validated campaign as JSON.
    max_stabilization : int
        Articles whose stabilization diagram is computed (one subspace
        factorization each), the first ones.
    """

    load: object | None = None
    identify: object | None = None
    group: object | None = None
    calibrate: object | None = None
    validate: object | None = None
    crossvalidate: object | None = None
    model: object | None = None
    pretest: object | None = None
    diagnosis: object | None = None
    extended: Mapping | None = None
    stages: Mapping | None = None
    campaign_file: Path | None = None
    max_stabilization: int = 6


class _Skip(Exception):
    """A section that cannot be shown; the message is its one-line note."""


# ----------------------------------------------------------------------------- HTML helpers


def _esc(x) -> str:
    return html.escape(str(x), quote=True)


def _fmt(v) -> str:
    if v is None:
        return "&ndash;"
    if isinstance(v, (bool, np.bool_)):
        return "yes" if v else "no"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        v = float(v)
        return "&ndash;" if not np.isfinite(v) else f"{v:.4g}"
    if isinstance(v, (list, tuple)):
        if len(v) > 12:
            return _esc(", ".join(_plain(x) for x in v[:12]) + f", ... ({len(v)} values)")
        return _esc(", ".join(_plain(x) for x in v))
    if isinstance(v, dict):
        return _esc(json.dumps(v, default=_plain)[:400])
    return _esc(v)


def _plain(x) -> str:
    if isinstance(x, (float, np.floating)):
        return f"{float(x):.4g}"
    return str(x)


def _sd_cell(a: dict) -> str:
    """An accepted effect's size uncertainty: "12" (% of the size, 1 s.d.), "not identifiable: ...", or ""."""
    if "size_identifiable" not in a:
        return ""
    if not a["size_identifiable"]:
        return "not identifiable: " + str(a.get("size_identifiability", ""))
    v = a.get("size_std_percent")
    return "" if v is None else f"{v:.2g}"


def _table(header, rows, bad_rows=()) -> str:
    """An HTML table; numbers right-aligned and formatted to 4 significant digits."""
    out = ["<table><thead><tr>" + "".join(f"<th>{_esc(h)}</th>" for h in header) + "</tr></thead><tbody>"]
    for i, r in enumerate(rows):
        cls = ' class="bad"' if i in bad_rows else ""
        cells = []
        for v in r:
            num = isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))
            cells.append(f'<td class="num">{_fmt(v)}</td>' if num else f"<td>{_fmt(v)}</td>")
        out.append(f"<tr{cls}>" + "".join(cells) + "</tr>")
    out.append("</tbody></table>")
    return "".join(out)


def _kv(pairs) -> str:
    """A two-column key/value table."""
    return _table(("quantity", "value"), [(k, v) for k, v in pairs])


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=REPORT_DPI)
    return buf.getvalue()


def _img(data: bytes, caption: str) -> str:
    b64 = base64.b64encode(data).decode("ascii")
    return (f'<figure><img alt="{_esc(caption)}" src="data:image/png;base64,{b64}">'
            f"<figcaption>{_esc(caption)}</figcaption></figure>")


def _fig(fig, caption: str) -> str:
    return _img(_png(fig), caption)


def _note(text: str) -> str:
    return f'<p class="skipped">{_esc(text)}</p>'


def _articles(r: ReportResults):
    if r.load is None:
        raise _Skip("the load stage did not run: no articles")
    arts = list(r.load.articles)
    return list(r.identify.attached(arts)) if r.identify is not None else arts


# ----------------------------------------------------------------------------- sections


def _layout(camp, r: ReportResults, tmp: Path) -> str:
    if r.model is None or r.load is None:
        raise _Skip("no model or no run files loaded: layout not shown")
    fe = r.model.assembly.model
    out = [_fig(layout_figure(fe, r.load.channels, r.load.drives),
                "FE mesh with the response channels (blue arrows: sensing direction) and the shaker (red star, "
                "arrow: force direction), basic coordinates in m")]
    rows = [(t.name, "calibration" if t.name in camp.channels.calibrate else "hold-out", t.grid,
             ", ".join(f"{x:+.3g}" for x in t.direction)) for t in r.load.channels]
    rows += [(t.name, "drive", t.grid, ", ".join(f"{x:+.3g}" for x in t.direction)) for t in r.load.drives]
    out.append(_table(("channel", "role", "FE grid", "direction (basic)"), rows))
    if r.pretest is not None:
        from pretest import plot_automac, plot_layout

        out.append("<h3>Pretest layout</h3>")
        out.append(_img(plot_layout(fe, r.pretest, tmp / "pretest_layout.png").read_bytes(),
                        "pretest layout: planned sensors and drive points"))
        out.append(_img(plot_automac(r.pretest, tmp / "pretest_automac.png").read_bytes(),
                        "autoMAC of the target modes at the planned channels"))
    else:
        out.append(_note("no pretest in this campaign: the layout is the run files' channels"))
    return "".join(out)


def _sweep(camp, r: ReportResults, tmp: Path) -> str:
    from acquisition.runfile import read_run

    if r.load is None:
        raise _Skip("the load stage did not run: no run files")
    out, rows, notes, by_article = [], [], [], {}
    for a in r.load.articles:
        run = read_run(a.path)
        q = sweep_quality(run)
        if q is None:
            notes.append(f"{Path(a.path).name}: imported from UFF58, no acquisition quality (std error, THD, force)")
            continue
        rows.append(q.summary())
        out.append(_fig(sweep_quality_figure(q), f"{a.name} ({Path(a.path).name}): per-line relative standard "
                        "error (median pair) with the coherence proxy, THD, achieved force against the target"))
        if q.level_n is not None:
            by_article.setdefault(a.name, []).append((q.level_n, run))
    if not rows:
        raise _Skip("; ".join(notes) if notes else "no run file holds acquisition quality")
    keys = list(dict.fromkeys(k for row in rows for k in row))
    head = _table(keys, [[row.get(k) for k in keys] for row in rows])
    levels = []
    for name, runs in by_article.items():
        lv = sorted({lvl for lvl, _ in runs})
        if len(lv) < 2:
            continue
        runs = sorted(runs, key=lambda t: t[0])
        levels.append(_fig(level_figure(name, [(lvl, np.asarray(rn.frequency_hz, float), np.asarray(rn.frf),
                                                np.asarray(rn.valid, bool)) for lvl, rn in runs]),
                           f"{name}: the same article at {', '.join(f'{x:g}' for x in lv)} N"))
    lev = "".join(levels) if levels else _note("one force level per article: no level comparison")
    return head + "".join(_note(n) for n in notes) + "".join(out) + "<h3>Level comparison</h3>" + lev


def _stabilization(camp, r: ReportResults, tmp: Path) -> str:
    from identification import plot_stabilization, stabilization

    from frfcal.campaign._identify import line_weights
    from frfcal.commands.identify import _stabilization_orders

    arts = _articles(r)
    if r.identify is None:
        raise _Skip("the identify stage did not run")
    rows, out = [], []
    for i, a in enumerate(arts):
        idn = a.identification
        sel = idn.order_selection
        how = "set" if sel is None else f"automatic: {sel.reason}"
        m = idn.modal
        rows.append((a.name, idn.order, how, m.n_modes, f"{idn.band_hz[0]:.4g}-{idn.band_hz[1]:.4g}",
                     idn.settings.get("weights"), [f"{f:.2f}" for f in m.frequency_hz],
                     [f"{100 * z:.3f}" for z in m.damping]))
        ln = a.lines
        if i >= r.max_stabilization or ln is None:
            continue
        w = None if ln.std_error is None else line_weights(ln.std_error, ln.frf, ln.valid)
        # poles of each order from the shift invariance alone (labels=False): the B, D fit and the
        # importance of every order cost ~8x more (outside frame+plate, order 92: 36 s -> 4.4 s wall per article)
        stab = stabilization(ln.frequency_hz, ln.frf, _stabilization_orders(idn.order), band_hz=idn.band_hz,
                             weights=w, quantity=a.quantity, valid=ln.valid, labels=False)
        png = plot_stabilization(stab, tmp / f"stab_{i}.png", ln.frequency_hz, ln.frf,
                                 title=f"{a.name}: stabilization (chosen order {idn.order}; poles of each order, "
                                       "no fit-based labels)")
        out.append(_img(png.read_bytes(), f"{a.name}: poles per model order (shift invariance, no B, D fit: the "
                        "'negligible' test of the identification is not made here); filled green = stable in "
                        "frequency, damping and shape"))
    table = _table(("article", "order", "order selection", "modes", "band Hz", "weights", "f Hz", "zeta %"), rows)
    more = len(arts) - r.max_stabilization
    tail = _note(f"stabilization diagrams of the first {r.max_stabilization} articles shown; {more} more "
                 "in the table only") if more > 0 else ""
    return table + "".join(out) + tail


def _extended(r: ReportResults) -> Mapping:
    if r.extended is not None:
        return r.extended
    ext = getattr(r.diagnosis, "extended", None)
    return ext if isinstance(ext, Mapping) else {}


def _overlays(camp, r: ReportResults, tmp: Path) -> str:
    from frfcal.campaign._report import reported_cycle

    arts = _articles(r)
    if r.calibrate is None:
        raise _Skip("the calibrate stage did not run")
    chans = list(camp.channels.calibrate[:3]) + list(camp.channels.holdout[:3])
    ext = _extended(r)
    band = (camp.band.low_hz, camp.band.high_hz)
    out, rows = [], []
    vals = {v.label: v for v in r.validate.members} if r.validate is not None else {}
    for m in r.calibrate.members:
        marts = [arts[i] for i in m.articles]
        p = m.p
        if m.label in vals:
            p = reported_cycle(m, vals[m.label]).p
        ov = overlay(r.calibrate.surrogate, m.surrogate, p, [raw_data(a, chans) for a in marts],
                     [floor_std_error(a, chans)[0] for a in marts], identified_modes(marts[0]), chans,
                     camp.calibration.zeta0, camp.validation.mac_min, band, marts[0].quantity, ext.get(m.label),
                     floor_source=floor_std_error(marts[0], chans)[1] or "per-line standard errors")
        dev = ov.deviation()
        floor = None if dev["floor"] is None else float(np.nanmedian(dev["floor"]))
        for name, _ in ov.models:
            med = float(np.nanmedian(dev[name]))
            rows.append((m.label, marts[0].name, name, med, floor, None if not floor else med / floor))
        fig = frf_overlay_figure(m.label, ov, set(camp.channels.calibrate), camp.calibration.zeta0, band,
                                 marts[0].quantity)
        out.append(_fig(fig, f"{m.label} ({', '.join(a.name for a in marts)}): test lines (grey) with their "
                        "+-2 standard-error band, nominal model, calibrated model"
                        + (", extended model" if m.label in ext else "")
                        + "; bottom: relative deviation of each model from the first article against its floor"))
    out.insert(0, "<p>Median over the first article's lines of the relative deviation |H_model/H_test - 1| "
               "(RMS over the channels drawn, first drive), and of the floor std error/|H_test|:</p>"
               + _table(("member", "article", "model", "median rel. deviation", "median floor", "ratio to floor"),
                        rows))
    if not ext:
        accepted = [m.label for m in getattr(r.diagnosis, "members", ()) if getattr(m, "accepted", ())]
        out.append(_note("the extended model of " + ", ".join(accepted) + " is drawn in the Diagnosis section"
                         if accepted else "no extended model (the diagnosis did not run or accepted no effect)"))
    return "".join(out)


def _parameters(camp, r: ReportResults, tmp: Path) -> str:
    if r.calibrate is None or r.model is None:
        raise _Skip("the calibrate stage did not run")
    pm = r.model
    names = list(pm.parameters.names)
    nominal = pm.physical(np.zeros(pm.n_params))
    xs = {x.label: x for x in r.crossvalidate.members} if r.crossvalidate is not None else {}
    out = []
    for m in r.calibrate.members:
        x = xs.get(m.label)
        cv = None if x is None else x.crossvalidation
        idf = getattr(x, "identifiability", None) or m.identifiability  # checked against the refits when made
        phys = pm.physical(m.p)
        rows, bad = [], []
        for j, n in enumerate(names):
            bound = {-1: "lower", 1: "upper"}.get(int(idf.at_bound[j]), "")
            if cv is not None and cv.n_at_bound[j]:
                bound = (bound + "; " if bound else "") + f"CV: {int(cv.n_at_bound[j])}/{cv.p.shape[0]} at a bound"
            std = float(idf.std[j])
            row = [n, nominal[n], phys[n], 100 * float(m.p[j]), 100 * std if np.isfinite(std) else None,
                   "yes" if idf.identifiable[j] else f"NO: {idf.reasons[j]}"]
            if cv is not None:
                cvj = cv.cv(j)
                row += [cvj if cvj is not None else f"n/a: {cv.cv_reason[j]}"]
            row += [bound or "no"]
            rows.append(row)
            if not idf.identifiable[j]:
                bad.append(j)
        head = ["parameter", "nominal (SI)", "calibrated (SI)", "p = change %", "std of p %", "identifiable"]
        head += (["CV %"] if cv is not None else []) + ["at bound"]
        out.append(f"<h3>{_esc(m.label)}</h3>")
        out.append(_table(head, rows, bad))
        weak = idf.weak()
        if weak:
            out.append(_table(("relative singular value", "weak combination"), weak))
        out.append(f"<p>{idf.n_identifiable} of {len(names)} parameters identifiable from these channels and band"
                   + ("" if cv is not None else "; cross-validation did not run (no CV column)")
                   + ("" if idf.spread is None else "; the verdict includes the spread of the cross-validation "
                      "refits (a parameter whose refits scatter beyond 5 % of its range, or end at a bound, is not "
                      "identifiable whatever its formal std)") + ".</p>")
        cal = getattr(getattr(m, "cycle", None), "calibration", None)
        if cal is not None:  # how many starts ran and into how many minima (docs/calibration.md, the stopping rule)
            out.append(f"<p>Multi-start (equalized stage): {_esc(cal.describe_starts())}.</p>")
    level = r.calibrate.level
    if level:  # the level check before the fit (docs/campaign.md): a unit mismatch would read 1000 x or 1e-3 x
        out.append("<p>Level check, the model's FRFs over the data's at the nominal parameters (median over lines "
                   "and channel-drive pairs): " + _esc(", ".join(f"{n} {f:.3g}" for n, f in level.items())) + ".</p>")
    return "".join(out)


def _validation(camp, r: ReportResults, tmp: Path) -> str:
    from calibration import crossvalidation_figure, mac_figure, range_text

    if r.calibrate is None:
        raise _Skip("the calibrate stage did not run")
    vals = {v.label: v for v in r.validate.members} if r.validate is not None else {}
    xv = {x.label: x.crossvalidation for x in r.crossvalidate.members} if r.crossvalidate is not None else {}
    names = [a.name for a in r.load.articles] if r.load is not None else []
    out = []
    for m in r.calibrate.members:
        cyc, ref = m.cycle, m.refinement
        rows = [("calibration SD, equalized test model (nominal -> calibrated)",
                 f"{cyc.calibration.sd_nominal:.4g} -> {cyc.sd:.4g}")]
        if ref is not None:
            rows.append(("raw-line SD, identified damping (start -> refined)", f"{ref.sd_raw_start:.4g} -> "
                         f"{ref.sd_raw:.4g}"))
        v = vals.get(m.label)
        val = None if v is None else v.validation
        if val is not None:
            rows += [("hold-out SD, raw lines (nominal -> calibrated)", f"{val.sd_nominal:.4g} -> "
                      f"{val.sd_calibrated:.4g}"),
                     ("hold-out noise floor SD" + (f" ({val.floor_source})" if getattr(val, "floor_source", None)
                                                   and "estimated" in val.floor_source else ""), val.sd_floor),
                     ("hold-out SD / floor", val.floor_ratio)]
            if getattr(val, "floor_range", None):
                rows.append(("hold-out SD of a model at its floor (5-95 % of noise draws)",
                             range_text(*val.floor_range)))
            rows += [("verdict", val.verdict), ("compared values", val.n_values)]
        cv = xv.get(m.label)
        if cv is not None:
            rows += [("cross-validation RSE (mean SD on the held-back half)", cv.rse),
                     ("cross-validation realizations", int(cv.p.shape[0]))]
        out.append(f"<h3>{_esc(m.label)}</h3>" + _kv(rows))
        if ref is not None:
            for line in ref.describe_unpaired([names[i] for i in m.articles] if names else None):
                out.append(_note(line))
        if val is None:
            out.append(_note("no hold-out validation (no hold-out channels or the validate stage did not run)"))
        else:
            if val.items:
                keys = list(dict.fromkeys(k for it in val.items for k in it))
                out.append(_table(keys, [[it.get(k) for k in keys] for it in val.items]))
            fig = mac_figure(val, names[m.articles[0]] if names else m.label)
            if fig is not None:
                out.append(_fig(fig, f"{m.label}: MAC of the identified modes against the FE modes"))
        if v is not None and v.articles:
            out.append("<p>Each article's own estimate started from the member's (the scatter of the articles):</p>")
            out.append(_table(("article", "raw-line SD", "hold-out SD"),
                              [(a["article"], a["sd_raw_calibration"], a["sd_holdout"]) for a in v.articles]))
        if cv is not None:
            out.append(_fig(crossvalidation_figure(r.model.parameters.names if r.model is not None
                                                   else cv.parameter_names, m.p, cv),
                            f"{m.label}: parameter scatter over the half/half recalibrations, and SD on the "
                            "calibration half against the other half"))
        else:
            out.append(_note("cross-validation did not run for this member"))
    return "".join(out)


def _grouping(camp, r: ReportResults, tmp: Path) -> str:
    if r.group is None:
        raise _Skip("the group stage did not run")
    names = [a.name for a in r.load.articles] if r.load is not None else []
    g = r.group
    out = [f"<p>ensemble = <b>{_esc(camp.calibration.ensemble)}</b></p>",
           _table(("member", "articles"), [(lab, ", ".join(names[i] if names else str(i) for i in idx))
                                            for lab, idx in g.members])]
    if g.pairwise_sd is None:
        out.append(_note("no pairwise comparison (ensemble 'all' or 'article', or a single article)"))
        return "".join(out)
    D = np.asarray(g.pairwise_sd)
    out.append("<p>Pairwise SD between the articles' equalized FRFs:</p>")
    out.append(_table([""] + names, [[n] + list(D[i]) for i, n in enumerate(names)]))
    out.append(_fig(pairwise_sd_figure(names, D), "article-to-article SD"))
    if g.grouping is not None:
        out.append(f"<p>{_esc(g.grouping.describe(names))}</p>")
        splits = g.grouping.splits
        if splits:
            keys = list(dict.fromkeys(k for t in splits for k in t))
            out.append(_table(keys, [[_groups_text(t.get(k), names) if k == "groups" else t.get(k) for k in keys]
                                     for t in splits]))
    return "".join(out)


def _groups_text(groups, names) -> str:
    if not groups:
        return ""
    return " | ".join(",".join(names[i] if names else str(i) for i in grp) for grp in groups)


def _generic(d, depth: int = 0) -> str:
    """A result dict as HTML: scalars in a key/value table, lists of dicts as tables, dicts as sub-sections."""
    scalars, parts = [], []
    for k, v in d.items():
        if _is_figure(v):
            parts.append(_fig(v, str(k)))
        elif isinstance(v, dict) and depth < 3:
            parts.append(f"<h4>{_esc(k)}</h4>" + _generic(v, depth + 1))
        elif isinstance(v, (list, tuple)) and v and all(isinstance(x, dict) for x in v):
            keys = list(dict.fromkeys(kk for x in v for kk in x))
            parts.append(f"<h4>{_esc(k)}</h4>" + _table(keys, [[x.get(kk) for kk in keys] for x in v]))
        else:
            scalars.append((k, v))
    return (_kv(scalars) if scalars else "") + "".join(parts)


def _separation_row(x: dict) -> tuple:
    """One row of the per-article effect table: the articles' sizes with their groups, not the raw dict."""
    sep = x.get("separation") or {}
    arts, groups = sep.get("articles") or [], sep.get("groups") or []
    per = "; ".join(f"{a} {v:.4g}" + (f" (group {int(groups[k]) + 1})" if k < len(groups) else "")
                    for k, (a, v) in enumerate(zip(arts, x.get("value") or [])))
    return (x.get("member"), x.get("name"), x.get("family"), per, x.get("unit") or "", bool(x.get("separates")),
            sep.get("reason", ""))


def _is_figure(v) -> bool:
    return hasattr(v, "savefig") and hasattr(v, "axes")


_SD_ROWS = (("calibration, equalized", "calibration_equalized", "calibration_equalized", None),
            ("calibration, raw lines", "calibration_raw", "calibration_raw", "floor"),
            ("hold-out, raw lines", "holdout", "holdout_refined", "holdout_floor"),
            ("cross-validation RSE", "crossvalidation_rse", "crossvalidation_rse", None))


def _diagnosis_member(camp, m) -> str:
    """One member of a DiagnosisResult: verdict, SD before/after beside the floor, ranking, trials, overlay."""
    from frfcal.campaign._diagnose import overlay_figure

    out = [f"<h3>{_esc(m.label)} ({_esc(', '.join(m.articles))}): {_esc(m.verdict)}</h3><p>{_esc(m.reason)}</p>"]
    sd = m.sd or {}
    after = sd.get("after") or {}
    rows = []
    for name, kb, ka, kf in _SD_ROWS:
        after_v = after.get(ka, after.get("holdout")) if ka == "holdout_refined" else after.get(ka)
        floor = sd.get(kf) if kf else None
        if kf == "floor" and floor is not None:
            floor = floor + sd.get("scatter", 0.0)
        rows.append((name, sd.get(kb), after_v if after else None, floor))
    out.append(_table(("SD", "calibrated model", "with the accepted effect(s)", "floor"), rows))
    out.append(_note("floor of the raw calibration lines: noise floor ({}) + test-to-test scatter of the group's "
                     "articles; of the hold-out: the validation's noise floor".format(sd.get("floor_source", "?"))))
    if m.channels:
        out.append(f"<p>most affected channels: {_esc(', '.join(m.channels[:8]))}</p>")
    if m.n_candidates:
        out.append(f"<p>candidates screened: {_esc(', '.join(f'{k} {v}' for k, v in m.n_candidates.items()))}</p>")
    if m.ranked:
        out.append("<h4>Screening: candidates ranked by the fraction of the residual they explain</h4>" + _table(
            ("rank", "family", "name", "size", "explained %", "re-fitted", "significant", "description"),
            [(x["rank"], x["family"], x["name"], x["size"], 100 * x["explained"], x["checked"], x["significant"],
              x["description"]) for x in m.ranked]))
    if m.trials:
        out.append("<h4>Recalibrations tried</h4>" + _table(
            ("effect(s)", "c", "hold-out SD before", "after", "decision"),
            [(" + ".join(t["names"]), t["c"], t["holdout_before"], t["holdout_after"],
              ("accepted: " if t["decision"]["accepted"] else "not accepted: ") + str(t["decision"].get("reason", ""))
              if "decision" in t else "not decided (a better combination was taken)") for t in m.trials]))
    if m.accepted:
        out.append("<h4>Accepted</h4>" + _table(("family", "name", "size", "s.d. % (noise)", "description"),
                                                [(a["family"], a["name"], a["size"],
                                                  _sd_cell(a), a["description"])
                                                 for a in m.accepted]))
        bdf = camp.resolve(camp.output.dir) / f"extended_{m.label}.bdf"
        if bdf.exists():
            out.append(f"<p>extended deck: {_esc(bdf)}</p>")
    if m.nonlinear_modes:
        out.append("<h4>Nonlinearity evidence</h4>" + _table(
            ("article", "check", "frequency Hz", "levels N", "values", "z sigma"),
            [(x["article"], x["check"], x.get("frequency_hz"), x.get("levels_n"), x.get("values"), x.get("z"))
             for x in m.nonlinear_modes]))
    if m.overlay is not None:
        fig = overlay_figure(m.overlay, f"[{m.label}] {m.verdict}: {m.overlay['article']}")
        out.append(_fig(fig, f"{m.label}: test FRF, calibrated model" + (", extended model"
                                                                         if m.overlay.get("after") is not None else "")
                        + " at the most affected channels"))
    return "".join(out)


def _diagnosis(camp, r: ReportResults, tmp: Path) -> str:
    d = r.diagnosis
    if d is None:
        raise _Skip("the diagnosis stage did not run")
    if not hasattr(d, "to_dict"):
        raise _Skip(f"the diagnosis result ({type(d).__name__}) has no to_dict(): not shown")
    gates, members = getattr(d, "gates", None), getattr(d, "members", None)
    if gates is not None and members is not None and all(hasattr(m, "verdict") for m in members):
        rows = []
        for g in gates:
            nl = g.nonlinearity
            rows.append((g.article, None if nl is None else nl.flagged, "no check" if nl is None else nl.verdict,
                         sorted({x.level for x in g.runs}), "; ".join(g.notes)))
        out = ["<h3>Nonlinearity gate</h3>" + _table(("article", "flagged", "verdict", "levels N", "notes"), rows)]
        out += [_diagnosis_member(camp, m) for m in members]
        seps = [dict(x) for x in getattr(d, "separations", ())]
        if seps:
            out.append("<h3>Effects fitted per article against the groups</h3>"
                       "<p>Each accepted effect re-fitted on every article alone (with the deck parameters) at the "
                       "screening's damping: the sizes separate the groups or not; the accepted size is the one "
                       "refined on the raw lines above.</p>" + _table(
                           ("member", "effect", "family", "per article", "unit", "separates", "why"),
                           [_separation_row(x) for x in seps]))
        return "".join(out)
    out = [_generic(d.to_dict())]
    figs = getattr(d, "figures", None)
    figs = figs() if callable(figs) else figs
    if isinstance(figs, Mapping):
        out += [_fig(f, str(name)) for name, f in figs.items() if _is_figure(f)]
    elif isinstance(figs, (list, tuple)):
        out += [_fig(f, f"diagnosis figure {k + 1}") for k, f in enumerate(figs) if _is_figure(f)]
    return "".join(out)


def versions() -> dict:
    """Versions of frfcal, Python, numpy, scipy, pyNastran, matplotlib, h5py and the sparse backend in use."""
    from importlib.metadata import PackageNotFoundError, version

    import frfcal

    out = {"frfcal": frfcal.__version__, "python": platform.python_version()}
    for dist in ("numpy", "scipy", "pyNastran", "matplotlib", "h5py"):
        try:
            out[dist] = version(dist)
        except PackageNotFoundError:
            out[dist] = "not installed"
    try:
        from femodel import default_backend

        out["sparse backend"] = default_backend()
    except (ImportError, RuntimeError, ValueError) as exc:  # a broken backend set-up is reported, not fatal
        out["sparse backend"] = f"unavailable ({exc})"
    out["platform"] = platform.platform()
    return out


def _versions(camp, r: ReportResults, tmp: Path) -> str:
    out = [_kv(versions().items())]
    if r.stages:
        out.append("<h3>Stages</h3>")
        out.append(_table(("stage", "status", "time s", "fingerprint"),
                          [(k, v.get("status"), v.get("time_s"), str(v.get("fingerprint", ""))[:16])
                           for k, v in r.stages.items()]))
    out.append("<h3>Campaign file</h3>")
    if r.campaign_file is not None:
        path = Path(r.campaign_file)
        out.append(f"<p>{_esc(path)}</p><pre>{_esc(path.read_text())}</pre>")
    else:
        out.append(_note("campaign file not given: the validated campaign as JSON"))
        out.append(f"<pre>{_esc(camp.model_dump_json(indent=1))}</pre>")
    return "".join(out)


#: (anchor, title, builder) in the issue's order.
SECTIONS = (
    ("layout", "Layout", _layout),
    ("sweep", "Sweep quality", _sweep),
    ("stabilization", "Identification and stabilization", _stabilization),
    ("frf", "FRF overlays", _overlays),
    ("parameters", "Parameters", _parameters),
    ("validation", "Validation and cross-validation", _validation),
    ("grouping", "Grouping", _grouping),
    ("diagnosis", "Diagnosis", _diagnosis),
    ("versions", "Versions and campaign file", _versions),
)


def _summary(camp, r: ReportResults) -> str:
    rows = []
    if r.load is not None:
        rows.append(("articles", ", ".join(a.name for a in r.load.articles)))
        rows.append(("quantity", r.load.articles[0].quantity))
    rows.append(("band Hz", f"{camp.band.low_hz:g}-{camp.band.high_hz:g}"))
    rows.append(("channels", f"{len(camp.channels.calibrate)} calibration, {len(camp.channels.holdout)} hold-out"))
    if r.model is not None:
        rows.append(("parameters", len(r.model.parameters.names)))
    if r.calibrate is not None:
        mvs = {v.label: v for v in r.validate.members} if r.validate is not None else {}
        for m in r.calibrate.members:
            mv = mvs.get(m.label)
            v = None if mv is None else mv.validation
            txt = f"calibration SD {m.cycle.calibration.sd_nominal:.4g} -> {m.cycle.sd:.4g}"
            if v is not None:
                txt += f"; hold-out SD {v.sd_nominal:.4g} -> {v.sd_calibrated:.4g}"
                if mv.floor_with_scatter_ratio is not None:  # several articles: one parameter set cannot remove
                    txt += (f" ({mv.floor_with_scatter_ratio:.2g}x the floor of one parameter set for "  # their scatter
                            f"{len(m.articles)} articles: noise {v.sd_floor:.2g} + test-to-test scatter "
                            f"{mv.scatter:.2g}; {v.floor_ratio:.2g}x the noise alone)")
                elif v.floor_ratio is not None:
                    txt += f" ({v.floor_ratio:.2g}x the floor)"
            rows.append((f"member {m.label}", txt))
    for m in getattr(r.diagnosis, "members", ()):
        if hasattr(m, "verdict"):
            acc = "; ".join(f"{a['family']} {a['name']}: {a['size']}" for a in m.accepted)
            rows.append((f"diagnosis {m.label}", m.verdict + (f": {acc}" if acc else "")))
    flagged = [g.article for g in getattr(r.diagnosis, "gates", ())
               if getattr(g, "nonlinearity", None) is not None and g.nonlinearity.flagged]
    if hasattr(r.diagnosis, "gates"):
        rows.append(("nonlinear articles", ", ".join(flagged) or "none"))
    return _kv(rows)


def write_report(camp, outdir, results, *, name: str = "report.html", log=print) -> Path:
    """Write the campaign report as one self-contained HTML page.

    Parameters
    ----------
    camp : Campaign
    outdir : path-like
        Folder of the page (created).
    results : ReportResults or mapping
        The typed stage results (a mapping is read as ``ReportResults(**mapping)``).
    name : str
        File name of the page.

    Returns
    -------
    Path
        The HTML file: figures as ``data:image/png;base64`` URIs, CSS and the
        image-check script inline, no external reference.

    Raises
    ------
    ValueError
        ``results`` names a field ``ReportResults`` does not have.
    """
    if not isinstance(results, ReportResults):
        known = {f.name for f in fields(ReportResults)}
        unknown = sorted(set(results) - known)
        if unknown:
            raise ValueError(f"write_report: unknown result(s) {unknown}; known: {sorted(known)}")
        results = ReportResults(**results)
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    label = Path(results.campaign_file).stem if results.campaign_file is not None else camp.resolve(camp.output.dir).name
    title = f"frfcal campaign report: {label}"
    body, toc = [], []
    with tempfile.TemporaryDirectory(prefix="frfcal-report-") as tmpdir:
        for anchor, heading, build in SECTIONS:
            t0 = time.perf_counter()
            try:
                content = build(camp, results, Path(tmpdir))
            except _Skip as why:
                content = _note(str(why))
            body.append(f'<section id="{anchor}"><h2>{_esc(heading)}</h2>{content}</section>')
            toc.append(f'<li><a href="#{anchor}">{_esc(heading)}</a></li>')
            log(f"report: {heading} ({time.perf_counter() - t0:.1f} s)")
    page = ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<title>{_esc(title)}</title><style>{_CSS}</style></head><body>"
            f"<h1>{_esc(title)}</h1><p>written {time.strftime('%Y-%m-%d %H:%M:%S %Z')}</p>"
            + _summary(camp, results) + "<nav><ol>" + "".join(toc) + "</ol></nav>" + "".join(body)
            + f"<script>{_SCRIPT}</script></body></html>\n")
    path = outdir / name
    path.write_text(page, encoding="utf-8")
    log(f"wrote {path} ({path.stat().st_size / 1e6:.2f} MB)")
    return path


def report_stage(camp, results, log=print) -> Path:
    """The report stage: :func:`write_report` into the campaign's output directory (``report.html``)."""
    return write_report(camp, camp.resolve(camp.output.dir), results, log=log)
