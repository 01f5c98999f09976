"""The campaign report: one self-contained HTML page, its numbers, its figures, and a real browser rendering it.

A small campaign (example frame, 492 DOF; three synthetic articles, ``frfcal.synth``; two groups; 1 start,
2 cross-validation realizations) runs once through ``run_campaign``; ``frfcal report CAMPAIGN.toml`` then
writes the page from the stored stages. Headless Chromium (Debian's ``chromium``) renders it when it is on
PATH: an inline script in the page counts the images the browser could not decode.
"""

import base64
import io
import re
import shutil
import subprocess
from dataclasses import dataclass, replace
from html.parser import HTMLParser

import numpy as np
import pytest

import femodel
from calibration import range_text
from frfcal.campaign import LoadResult, load_campaign, run_campaign
from frfcal.campaign._html import SECTIONS, ReportResults, write_report
from frfcal.campaign._report_figures import sweep_quality
from frfcal.cli import main
from frfcal.commands.report import stored_results
from frfcal.synth import SynthChannel, synthesize

BAND = (60.0, 300.0)


class _Page(HTMLParser):
    """Tags of interest of a page: img sources, every src/href, tables, section ids, body attributes."""

    def __init__(self):
        super().__init__()
        self.imgs, self.refs, self.sections, self.tables, self.body = [], [], [], 0, {}
        self.tags = set()

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        self.tags.add(tag)
        if tag == "img":
            self.imgs.append(a.get("src", ""))
        for k in ("src", "href", "action", "data"):
            if k in a:
                self.refs.append((tag, k, a[k]))
        if tag == "section":
            self.sections.append(a.get("id"))
        if tag == "table":
            self.tables += 1
        if tag == "body":
            self.body = a


def _parse(text):
    p = _Page()
    p.feed(text)
    return p


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("report")
    ex = femodel.example_frame(tmp / "model")
    pm = femodel.parametric_model(ex.params)
    g = np.asarray(pm.assembly.model.grid_ids)
    pick = g[np.linspace(2, len(g) - 3, 10).astype(int)]
    dirs = [(0.0, 0.0, 1.0), (0.0, 1.0, 0.0)]
    sensors = [SynthChannel(f"s{i + 1}", int(gid), dirs[i % 2]) for i, gid in enumerate(pick)]
    drives = [SynthChannel("F1", int(pick[3]), (0.0, 0.0, 1.0))]
    sc = synthesize(ex.bdf, ex.params, tmp / "data", sensors=sensors, drives=drives, band_hz=BAND, n_articles=3,
                    seed=3, base_lines=150, lines_per_bandwidth=3)
    names = [s.name for s in sensors]
    path = sc.write_campaign(tmp / "campaign.toml", calibrate=names[0::2], holdout=names[1::2],
                             calibration={"starts": 1, "ensemble": "group", "n_groups": 2, "max_cycles": 1,
                                          "refine_cycles": 0},
                             crossvalidation={"realizations": 2}, execution={"workers": 1},
                             output={"dir": "out", "figures": False})
    camp = load_campaign(path)
    run_campaign(camp, log=lambda m: None, upto="crossvalidate")
    assert main(["report", str(path), "--quiet"]) == 0
    page = tmp / "out" / "report.html"
    return sc, camp, path, page, stored_results(camp, campaign_file=path, log=lambda m: None)


def test_report_has_no_external_reference(campaign):
    _, _, _, page, _ = campaign
    text = page.read_text()
    p = _parse(text)
    assert not {"link", "iframe", "object", "embed"} & p.tags
    for tag, attr, value in p.refs:
        if attr == "href":
            assert value.startswith("#"), (tag, value)
        else:
            assert value.startswith("data:image/png;base64,"), (tag, value[:60])
    assert "http" not in "".join(v for _, _, v in p.refs)
    assert "url(" not in text and "@import" not in text


def test_every_embedded_image_decodes(campaign):
    from PIL import Image

    _, _, _, page, _ = campaign
    p = _parse(page.read_text())
    # layout, 3 x sweep quality, 3 x stabilization, 2 x FRF, 2 x MAC, 2 x cross-validation, pairwise SD
    assert len(p.imgs) == 14
    for src in p.imgs:
        im = Image.open(io.BytesIO(base64.b64decode(src.split(",", 1)[1], validate=True)))
        im.load()
        assert im.format == "PNG" and im.size[0] >= 300 and im.size[1] >= 150
        px = np.asarray(im.convert("L"), float)
        assert px.std() > 5  # not a blank canvas


def test_sections_in_the_issue_order_with_tables(campaign):
    _, _, _, page, r = campaign
    text = page.read_text()
    p = _parse(text)
    assert p.sections == [s[0] for s in SECTIONS]
    assert p.tables >= 15
    assert "the diagnosis stage did not run" in text  # the one stage this campaign has not
    assert "no pretest in this campaign" in text
    assert "one force level per article" in text
    # the campaign file verbatim (escaped) and the versions
    assert "[calibration]" in text and "ensemble = &quot;group&quot;" in text
    for k in ("numpy", "scipy", "pyNastran", "sparse backend"):
        assert f"<td>{k}</td>" in text


def _rows(text, first_cell):
    """The cells of every table row whose first cell is ``first_cell``."""
    out = []
    for row in re.findall(r"<tr[^>]*>(.*?)</tr>", text):
        cells = [re.sub("<[^>]+>", "", c) for c in re.findall(r"<td[^>]*>(.*?)</td>", row)]
        if cells and cells[0] == first_cell:
            out.append(cells)
    return out


def test_parameter_table_holds_the_calibrated_values(campaign):
    """Every parameter row: nominal and calibrated SI values and p as the stored calibration has them."""
    _, _, _, page, r = campaign
    text = page.read_text()
    pm = r.model
    nominal = pm.physical(np.zeros(pm.n_params))
    members = r.calibrate.members
    assert len(members) == 2
    for j, name in enumerate(pm.parameters.names):
        rows = _rows(text, name)
        assert len(rows) == len(members)
        for m, cells in zip(members, rows):
            assert float(cells[1]) == pytest.approx(nominal[name], rel=1e-3)
            assert float(cells[2]) == pytest.approx(pm.physical(m.p)[name], rel=1e-3)
            assert float(cells[3]) == pytest.approx(100 * m.p[j], rel=1e-3, abs=1e-3)
            assert cells[5] == ("yes" if m.identifiability.identifiable[j] else f"NO: {m.identifiability.reasons[j]}")
    for m in members:  # how many starts ran, and into how many minima
        assert f"Multi-start (equalized stage): {m.cycle.calibration.describe_starts()}." in text
    level = r.calibrate.level  # the level check before the fit: the model about level with the data
    assert level and all(0.7 < f < 1.4 for f in level.values())
    assert "Level check, the model's FRFs over the data's at the nominal parameters" in text
    # the reported values are the calibration's, and it moved towards the truth: the one-article member (which
    # of three alike articles stands alone under n_groups = 2 is the identified models' chance)
    (single,) = [m for m in members if len(m.articles) == 1]
    truth = np.asarray(campaign[0].truth()["p_true"])[single.articles[0]]
    np.testing.assert_allclose(single.p, truth, atol=0.01)


def test_validation_numbers_and_floor(campaign):
    """The hold-out SD falls from nominal to calibrated, and the page states it as the validation has it."""
    _, _, _, page, r = campaign
    text = page.read_text()
    for v in r.validate.members:
        val = v.validation
        assert val.sd_calibrated < 0.1 * val.sd_nominal
        assert f"{val.sd_nominal:.4g} -&gt; {val.sd_calibrated:.4g}" in text
        assert [f"{val.floor_ratio:.4g}"] == _rows(text, "hold-out SD / floor")[r.validate.members.index(v)][1:]
        # the range a model at its floor scores, as the validation has it
        lo, hi = val.floor_range
        assert lo < val.sd_floor < hi
        row = _rows(text, "hold-out SD of a model at its floor (5-95 % of noise draws)")[r.validate.members.index(v)]
        assert row[1:] == [range_text(lo, hi)]


def test_frf_overlay_deviation_against_the_floor(campaign):
    """One-article member: the calibrated model meets its article to the noise floor, the nominal does not."""
    _, _, _, page, r = campaign
    text = page.read_text()
    (single,) = [m.label for m in r.calibrate.members if len(m.articles) == 1]
    (other,) = [m.label for m in r.calibrate.members if m.label != single]
    rows = {(c[0], c[2]): c for c in _rows(text, single) if len(c) == 6}
    nominal, calibrated = rows[(single, "nominal")], rows[(single, "calibrated")]
    assert nominal[4] == calibrated[4]  # the same floor
    assert float(calibrated[5]) < 2.0  # the data's own noise
    assert float(nominal[5]) > 20.0  # 5-15 % parameter offsets: resonances off by more than a bandwidth
    assert (other, "nominal") in {(c[0], c[2]) for c in _rows(text, other) if len(c) == 6}


def test_sweep_quality_of_an_acquired_run_and_level_comparison(campaign, tmp_path):
    """An acquisition-like run (target force, tolerance, THD) and the same article at a second level."""
    from acquisition.runfile import LineQuality, create_run, read_run

    _, camp, _, _, r = campaign
    a0 = r.load.articles[0]
    src = read_run(a0.path)
    n_ch = len(src.sensors) + len(src.drives)
    paths = []
    for level, thd in ((1.0, 0.002), (4.0, 0.03)):
        path = tmp_path / f"level{level:g}.h5"
        plan = {"level_n": level, "force": {"tolerance": 0.02}, "measure": {"thd_limit": 0.05,
                                                                           "std_error_limit": 0.01}}
        with create_run(path, article="A1", sensors=src.sensors, drives=src.drives, quantity=src.quantity,
                        plan=plan, hardware={"driver": "test"}, overwrite=True) as w:
            for k in range(src.n_lines):
                force = level * (1 + (0.05 if k == 7 else 0.005))  # one line 5 % off the target
                w.append_line(src.frequency_hz[k], src.frf[k],
                              LineQuality(force_n=np.full(len(src.drives), force), std_error=src.std_error[k],
                                          thd=np.full(n_ch, thd), flags=0, n_blocks=4))
            w.close("completed")
        paths.append(path)
    q = sweep_quality(read_run(paths[1]))
    assert q.level_n == 4.0 and q.force_tolerance == 0.02
    row = q.summary()
    assert row["max force deviation %"] == pytest.approx(5.0, rel=1e-6)
    assert row["lines within tolerance %"] == pytest.approx(100 * (src.n_lines - 1) / src.n_lines)
    assert row["max THD response %"] == pytest.approx(3.0)
    # the coherence proxy from the standard error of a 4-block mean: 1 / (1 + 4 (se/|H|)^2)
    rel = np.nanmedian((src.std_error / np.abs(src.frf)).reshape(src.n_lines, -1), axis=1)
    np.testing.assert_allclose(q.coherence, 1 / (1 + 4 * rel ** 2))
    arts = tuple(replace(a0, path=p) for p in paths)
    load = LoadResult(arts, r.load.channels, r.load.drives)
    out = write_report(camp, tmp_path / "out", ReportResults(load=load, model=r.model), log=lambda m: None)
    text = out.read_text()
    assert "A1: the same article at 1, 4 N" in text
    assert len(_rows(text, "level4.h5")) == 1 and "target force N" in text
    # every later stage did not run: a one-line note each, no exception
    for note in ("the identify stage did not run", "the calibrate stage did not run", "the group stage did not run",
                 "the diagnosis stage did not run"):
        assert note in text


def test_uff_import_has_no_sweep_quality(campaign, tmp_path):
    _, camp, _, _, r = campaign
    sc = campaign[0]
    uff = sc.uff_paths[0]
    run = tmp_path / "imported.h5"
    assert main(["import-uff", str(uff), "--out", str(run), "--article", "A1"]) == 0
    from acquisition.runfile import read_run

    assert sweep_quality(read_run(run)) is None
    load = LoadResult((replace(r.load.articles[0], path=run),), r.load.channels, r.load.drives)
    text = write_report(camp, tmp_path, {"load": load}, log=lambda m: None).read_text()
    assert "imported from UFF58, no acquisition quality" in text
    assert "no model or no run files loaded" in text


@dataclass(frozen=True)
class _Diagnosis:
    """Stands in for the diagnosis stage's result: a to_dict(), figures and the extended model per member."""

    extended: dict
    figures: dict

    def to_dict(self):
        return {"verdict": "gap closed by a contact spring", "sd_before": 0.0123, "sd_after": 0.0041,
                "sd_floor": 0.0039,
                "candidates": [{"name": "contact_g12_g57", "kind": "AddedSpring", "explained_fraction": 0.81},
                               {"name": "sensor_mass_common", "kind": "AddedMass", "explained_fraction": 0.07}],
                "accepted": [{"name": "contact_g12_g57", "value_si": 2.4e5, "cv_gain": 0.62}]}


def test_diagnosis_rendered_from_its_dict(campaign, tmp_path):
    from matplotlib.figure import Figure

    _, camp, path, _, r = campaign
    fig = Figure()
    ax = fig.subplots()
    ax.plot([0, 1], [1, 0])
    m = r.calibrate.members[0]
    d = _Diagnosis(extended={m.label: (m.surrogate, m.p)}, figures={"before/after": fig})
    text = write_report(camp, tmp_path, replace(r, diagnosis=d, max_stabilization=0), log=lambda m: None).read_text()
    assert len(_rows(text, "contact_g12_g57")) == 2  # ranked candidates and accepted effects
    assert _rows(text, "sensor_mass_common")[0][1:] == ["AddedMass", "0.07"]
    assert _rows(text, "sd_after")[0][1] == "0.0041"
    assert "before/after" in text and f"{m.label} (" in text and ", extended model" in text
    assert "the diagnosis stage did not run" not in text


def test_unknown_result_is_an_error(campaign, tmp_path):
    _, camp, _, _, _ = campaign
    with pytest.raises(ValueError, match="unknown result.*'calibration'"):
        write_report(camp, tmp_path, {"calibration": None})


def _browser():
    return shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.mark.skipif(_browser() is None, reason="no chromium on PATH (Debian: apt-get install chromium)")
def test_renders_in_headless_chromium(campaign, tmp_path):
    """A real browser loads the page, decodes every image (the page's own check) and paints it."""
    from PIL import Image

    _, _, _, page, _ = campaign
    n_img = len(_parse(page.read_text()).imgs)
    common = [_browser(), "--headless", "--disable-gpu", "--no-sandbox", "--hide-scrollbars",
              f"--user-data-dir={tmp_path / 'profile'}"]
    dom = subprocess.run(common + ["--virtual-time-budget=10000", "--dump-dom", page.as_uri()],
                         capture_output=True, text=True, timeout=180)
    assert dom.returncode == 0, dom.stderr[-2000:]
    body = _parse(dom.stdout).body
    assert body.get("data-images") == str(n_img), "the page's image check did not run"
    assert body.get("data-broken-images") == "0"
    # the check can fail: the same page with one image's PNG signature destroyed shows one broken image
    bad = tmp_path / "broken.html"
    bad.write_text(page.read_text().replace("data:image/png;base64,iVBOR", "data:image/png;base64,AAAAA", 1))
    dom = subprocess.run(common + ["--virtual-time-budget=10000", "--dump-dom", bad.as_uri()],
                         capture_output=True, text=True, timeout=180)
    assert _parse(dom.stdout).body.get("data-broken-images") == "1"
    shot = tmp_path / "report.png"
    res = subprocess.run(common + [f"--screenshot={shot}", "--window-size=1280,4000", page.as_uri()],
                         capture_output=True, text=True, timeout=180)
    assert res.returncode == 0 and shot.exists(), res.stderr[-2000:]
    px = np.asarray(Image.open(shot).convert("L"), float)
    assert px.shape == (4000, 1280)
    assert px.std() > 20  # text, tables and figures, not a blank page
    assert (px < 100).mean() > 0.005  # dark ink: headings, text, plot lines


def test_pretest_layout_section(campaign, tmp_path):
    """With a pretest result the layout section adds the planned layout and its autoMAC."""
    from pretest import PretestConfig, plan_pretest

    _, camp, _, _, r = campaign
    plan = plan_pretest(r.model.assembly.model, PretestConfig(n_sensors=6, n_modes=6, direction="z"),
                        assembly=r.model.assembly)
    text = write_report(camp, tmp_path, {"load": r.load, "model": r.model, "pretest": plan},
                        log=lambda m: None).read_text()
    p = _parse(text)
    assert "<h3>Pretest layout</h3>" in text and "no pretest in this campaign" not in text
    assert "autoMAC of the target modes" in text
    assert len(p.imgs) == 3 + 3  # layout, pretest layout, autoMAC; three sweep-quality figures


def test_report_command_needs_a_campaign_that_ran(campaign, tmp_path, capsys):
    _, _, path, _, _ = campaign
    assert main(["report", str(path), "--out", str(tmp_path / "empty")]) == 2
    assert "no stored load stage" in capsys.readouterr().err


_SIM_PLAN = """
name = "lvl"
sample_rate_hz = 4096.0
layout = "layout.json"
[lines]
kind = "bandwidth"
start_hz = 110.0
stop_hz = 135.0
background_step = 0.04
lines_per_bandwidth = 2
span_bandwidths = 1.5
poles = [{ frequency_hz = 120.0, damping = 0.001 }]
[force]
levels_n = [0.5, 1.0]
[ensemble]
articles = ["SF01"]
drives = ["d1"]
[sim]
noise_rms = 1e-4
[sim.modes]
frequencies_hz = [120.0, 185.0]
damping = 0.001
shapes_out = [[0.5, 0.4], [0.35, -0.45]]
shapes_in = [[0.5, 0.4]]
"""

_SIM_LAYOUT = {
    "format": "frfcal-layout", "version": 1, "model": {"path": "m.bdf", "units": "mm-t-s"},
    "channels": [{"name": f"acc{k}", "role": "response", "quantity": "acceleration", "unit": "m/s^2",
                  "grid": 10 + k, "direction": [0, 0, 1], "xyz_m": [0.1 * k, 0, 0]} for k in range(2)],
    "drives": [{"name": "d1", "role": "force", "quantity": "force", "unit": "N", "grid": 10, "direction": [0, 0, 1],
                "xyz_m": [0, 0, 0]}],
    "target_modes_hz": [120.0], "metrics": {},
}


def test_sweep_quality_of_simulated_acquisitions_at_two_levels(campaign, tmp_path):
    """``frfcal acquire --driver sim`` at 0.5 and 1 N: the force held within the plan's 2 %, the level comparison."""
    import json

    _, camp, _, _, r = campaign
    (tmp_path / "layout.json").write_text(json.dumps(_SIM_LAYOUT))
    (tmp_path / "plan.toml").write_text(_SIM_PLAN)
    assert main(["acquire", str(tmp_path / "plan.toml"), "--driver", "sim", "--out", str(tmp_path / "runs")]) == 0
    runs = sorted((tmp_path / "runs").glob("*.h5"))
    assert len(runs) == 2
    a0 = r.load.articles[0]
    load = LoadResult(tuple(replace(a0, name="SF01", path=p) for p in runs), r.load.channels, r.load.drives)
    text = write_report(camp, tmp_path / "out", {"load": load}, log=lambda m: None).read_text()
    for p, level in zip(runs, (0.5, 1.0)):
        (row,) = _rows(text, p.name)
        assert row[1] == "SF01" and row[3] == "0"  # no flagged line
        cells = dict(zip(re.findall(r"<th>(.*?)</th>", text[text.index("<section id=\"sweep\">"):])[:len(row)], row))
        assert float(cells["target force N"]) == level
        assert float(cells["max force deviation %"]) < 2.0
        assert cells["lines within tolerance %"] == "100"
        assert float(cells["max THD response %"]) < 1.0
    assert "SF01: the same article at 0.5, 1 N" in text


def test_diagnosis_result_rendered_per_member(campaign, tmp_path):
    """The diagnose stage's DiagnosisResult: gate table, per member the verdict, SD before/after beside the floor,
    the ranking, the recalibrations tried and the before/after FRF overlay."""
    from frfcal.campaign._diagnose import ArticleGate, DiagnosisResult, LevelRun, MemberDiagnosis

    _, camp, _, _, r = campaign
    f = np.linspace(100.0, 400.0, 60)
    H = (1.0 / (1 - (f / 250.0) ** 2 + 0.02j))[:, None, None] * np.ones((1, 2, 1))
    overlay = {"article": "A1", "freq_hz": f, "channels": ["acc1", "acc2"], "drives": ["force1"], "test": H,
               "before": 1.1 * H, "after": 1.01 * H}
    ranked = ({"rank": 1, "name": "contact_p1_p2_1", "family": "contact_spring", "size": "2.4e+05 N/m",
               "explained": 0.81, "checked": True, "significant": True, "description": "contact springs (z)"},
              {"rank": 2, "name": "mass_g7", "family": "lumped_mass", "size": "0.2 kg", "explained": 0.07,
               "checked": True, "significant": False, "description": "lumped mass at grid 7"})
    trial = {"names": ["contact_p1_p2_1"], "c": [2.4], "holdout_before": 0.0123, "holdout_after": 0.0043,
             "decision": {"accepted": True, "reason": "hold-out SD x0.35"}}
    sd = {"calibration_equalized": 0.02, "calibration_raw": 0.0123, "holdout": 0.0125, "holdout_floor": 0.0039,
          "crossvalidation_rse": 0.011, "floor": 0.003, "scatter": 0.001, "floor_source": "per-line standard errors",
          "after": {"calibration_equalized": 0.004, "calibration_raw": 0.0041, "holdout": 0.0043,
                    "holdout_refined": 0.0042, "crossvalidation_rse": 0.004}}
    m = MemberDiagnosis("all", ("A1", "A2"), "effect(s) found", "accepted: contact springs (z): 2.4e+05 N/m", None,
                        sd=sd, channels=("acc2", "acc1"), n_candidates={"contact_spring": 3, "lumped_mass": 40},
                        ranked=ranked, accepted=(dict(ranked[0]),), trials=(trial,), overlay=overlay)
    gate = ArticleGate("A1", None, (LevelRun("A1", tmp_path / "a.h5", 1.0, "run file", "up"),),
                       ("A1: one run file: no level-dependence check",))
    d = DiagnosisResult((gate,), (m,))
    text = write_report(camp, tmp_path, replace(r, diagnosis=d, max_stabilization=0), log=lambda m: None).read_text()
    assert "all (A1, A2): effect(s) found" in text
    assert _rows(text, "hold-out, raw lines")[0][1:] == ["0.0125", "0.0042", "0.0039"]
    assert _rows(text, "calibration, raw lines")[0][1:] == ["0.0123", "0.0041", "0.004"]  # floor = noise + scatter
    assert [x[1:5] for x in _rows(text, "2") if "mass_g7" in x] == [["lumped_mass", "mass_g7", "0.2 kg", "7"]]
    assert len(_rows(text, "contact_p1_p2_1")) == 1 and len(_rows(text, "contact_spring")) == 1  # tried, accepted
    assert "accepted: hold-out SD x0.35" in text
    assert [x[:3] for x in _rows(text, "A1") if "no check" in x] == [["A1", "&ndash;", "no check"]]
    assert "all: test FRF, calibrated model, extended model at the most affected channels" in text
    assert "is drawn in the Diagnosis section" in text
    assert _rows(text, "diagnosis all") == [["diagnosis all", "effect(s) found: contact_spring contact_p1_p2_1: 2.4e+05 N/m"]]
    assert _rows(text, "nonlinear articles") == [["nonlinear articles", "none"]]
