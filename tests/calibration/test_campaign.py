"""Campaign config, pipeline end to end on run files, CLI, bad input."""

import json
from pathlib import Path

import numpy as np
import pytest

from calibration import CalibrationError
from frfcal.campaign import campaign_from_dict, load_campaign, run_campaign
from frfcal.cli import main
from tests.calibration._synthetic import make_campaign

P_TRUE = np.array([0.05, -0.04, 0.06, -0.05, 0.04, -0.03, 0.05, -0.06, 0.03,
                   -0.04, 0.05, -0.02, 0.08, -0.07, 0.06, -0.05, 0.04])


@pytest.fixture(scope="module")
def light(tmp_path_factory):
    """A coarse campaign (5 Hz lines) with a sensor on a grid the model lacks, for error paths."""
    tmp = tmp_path_factory.mktemp("light")
    return make_campaign(tmp, target_dof=1000, step_hz=5.0, bad_grid=True)


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("camp")
    path, p_true, pm = make_campaign(tmp, p_true=P_TRUE, target_dof=2000)
    return path, p_true, pm


@pytest.mark.slow
def test_campaign_end_to_end_cli_json(campaign, capsys):
    path, p_true, pm = campaign
    rc = main(["calibrate", str(path), "--json", "--starts", "1", "--realizations", "3"])
    out = capsys.readouterr().out
    assert rc == 0
    res = json.loads(out)
    m = res["members"][0]
    assert len(m["calibration"]["multistart"]["starts"]) == 2
    # calibration reduces the deviation to the identification floor; hold-out validation passes Eq. 2.24
    assert m["sd_calibration"] < 0.02 * m["sd_calibration_nominal"]
    v = m["validation"]
    assert v["improved"] and v["sd_calibrated"] < 0.05 * v["sd_nominal"]
    # flagged lines (NaN) excluded: 3 flagged lines of which 1 in band (line 150 is at 230 Hz)
    n_lines_in_band = int(np.sum((np.arange(80.0, 520.0, 1.0) >= 100) & (np.arange(80.0, 520.0, 1.0) <= 400)))
    assert v["n_values"] == (n_lines_in_band - 1) * 5
    cv = m["crossvalidation"]
    assert cv["realizations"] == 3 and cv["rse"] < 0.02
    # the well-determined global parameters come back close to the truth
    p = np.array([r["p"] for r in m["parameters"]])
    assert abs((1 + p[0]) / (1 + p_true[0]) - 1) < 0.02
    assert abs((1 + p[1]) / (1 + p_true[1]) - 1) < 0.02
    # calibrated deck written and readable with the calibrated values
    import femodel

    pm2 = femodel.parametric_model(pm.parameters, m["bdf"], units="mm-t-s")
    np.testing.assert_allclose(pm2.nominal, pm.nominal * (1 + p), rtol=1e-6)
    for fig in m["figures"]:
        assert fig.endswith(".png")


@pytest.mark.slow
def test_articles_grouped_and_calibrated_per_group(tmp_path):
    """Three articles, one with stiffer welds and heavier bushings: two groups, each calibrated."""
    odd = P_TRUE.copy()
    odd[16] += 0.3
    odd[12:16] += 0.3
    path, _, pm = make_campaign(tmp_path, p_true=np.array([P_TRUE, P_TRUE, odd]), target_dof=1500,
                                starts=0, realizations=0, extra='figures = false')
    text = path.read_text().replace("[calibration]", '[calibration]\nensemble = "group"')
    path.write_text(text)
    res = run_campaign(load_campaign(path), log=lambda m: None, upto="crossvalidate")
    groups = [m["articles"] for m in res["members"]]
    assert sorted(groups) == [["SF1", "SF2"], ["SF3"]]
    D = np.array(res["pairwise_sd"])
    assert D[0, 1] < 0.1 * D[0, 2]
    by = {tuple(m["articles"]): m for m in res["members"]}
    p_odd = np.array([r["p"] for r in by[("SF3",)]["parameters"]])
    p_main = np.array([r["p"] for r in by[("SF1", "SF2")]["parameters"]])
    assert p_odd[16] - p_main[16] > 0.15  # the stiffer welds show up in the odd group


def _variant(path, tmp_path, **subs):
    text = path.read_text()
    base = path.parent
    text = text.replace('path = "run1.h5"', f'path = "{base}/run1.h5"').replace('dir = "out"', f'dir = "{tmp_path}/o"')
    for a, b in subs.items():
        text = text.replace(a, b)
    out = tmp_path / "c.toml"
    out.write_text(text)
    return out


def test_bad_inputs_have_clear_errors(light, tmp_path):
    path, _, pm = light
    quiet = dict(log=lambda m: None)
    bad = _variant(path, tmp_path, **{"low_hz = 100.0": "low_hz = 100.0\nlow_freq = 3"})
    with pytest.raises(CalibrationError, match="band.low_freq: unknown field"):
        load_campaign(bad)
    bad = _variant(path, tmp_path, **{'"acc1"': '"accX"'})
    with pytest.raises(CalibrationError, match="accX"):
        run_campaign(load_campaign(bad), **quiet)
    bad = _variant(path, tmp_path, **{"high_hz = 400.0": "high_hz = 4000.0", "low_hz = 100.0": "low_hz = 3000.0"})
    with pytest.raises(CalibrationError, match="no valid lines"):
        run_campaign(load_campaign(bad), **quiet)
    # acc4 sits on grid 987654321, which the deck does not have
    with pytest.raises(CalibrationError, match=r"channel 'acc4' \(grid 987654321"):
        run_campaign(load_campaign(_variant(path, tmp_path)), **quiet)
    # a parameter naming a card that is not in the deck
    ptext = Path(pm.parameters.source).read_text().replace("id = 1\n", "id = 4242\n", 1)
    pfile = tmp_path / "params.toml"
    pfile.write_text(ptext.replace('bdf = "', f'bdf = "{Path(pm.parameters.source).parent}/'))
    bad = _variant(path, tmp_path, **{f'parameters = "{pm.parameters.source}"': f'parameters = "{pfile}"'})
    with pytest.raises(ValueError, match="4242"):
        run_campaign(load_campaign(bad), **quiet)
    # the CLI turns these into one line and exit status 2
    assert main(["calibrate", str(bad)]) == 2
    assert main(["calibrate", str(tmp_path / "missing.toml")]) == 2


def test_campaign_validation_rules():
    base = {"model": {"parameters": "p.toml"}, "run": [{"path": "a.h5"}],
            "channels": {"calibrate": ["a"]}, "band": {"low_hz": 100, "high_hz": 400}}
    c = campaign_from_dict(base)
    assert c.calibration.zeta0 == 0.01 and c.calibration.samples_per_half_bandwidth == 3
    assert c.calibration.starts == 20 and c.crossvalidation.realizations == 20
    with pytest.raises(CalibrationError, match="both in calibrate and holdout"):
        campaign_from_dict({**base, "channels": {"calibrate": ["a"], "holdout": ["a"]}})
    with pytest.raises(CalibrationError, match="high_hz"):
        campaign_from_dict({**base, "band": {"low_hz": 400, "high_hz": 100}})
    with pytest.raises(CalibrationError, match="run"):
        campaign_from_dict({**base, "run": []})


@pytest.mark.slow
def test_campaign_reports_identifiability_floor_and_per_article_damping(tmp_path):
    """Two noisy articles (1 % noise, standard errors stored): the log names both SDs, gives the hold-out
    SD beside its noise floor, says 'improved' (no target) and prints the identifiability table."""
    path, _, pm = make_campaign(tmp_path, p_true=P_TRUE, target_dof=1500, articles=2, noise=0.01, starts=0,
                                realizations=2, extra="figures = false")
    lines = []
    res = run_campaign(load_campaign(path), log=lines.append, upto="crossvalidate")
    text = "\n".join(lines)
    assert "calibration SD (equalized test model, zeta0=1 %)" in text
    assert "hold-out SD (raw lines, identified damping)" in text and "passed" not in text.lower()
    m = res["members"][0]
    v = m["validation"]
    floor = 0.01**2 / np.log(10) ** 2
    assert v["sd_floor"] == pytest.approx(floor, rel=0.02)
    assert v["verdict"] == "improved" and "passed" not in v
    assert f"floor ~{v['sd_floor']:.2g} ({v['floor_ratio']:.1f}x; at its floor a model scores " in text
    # two articles: their test-to-test scatter on the hold-out channels is reported beside the noise floor
    assert v["scatter"] > 0 and "hold-out floor of one parameter set for 2 articles" in text
    assert v["floor_with_scatter_ratio"] == pytest.approx(v["sd_calibrated"] / (v["sd_floor"] + v["scatter"]))
    # each article's hold-out lines were compared with its own identified damping
    assert [it["article"] for it in v["items"]] == ["SF1", "SF2"] and len(v["pairs_calibrated"]) == 2
    idf = m["identifiability"]
    assert [r["name"] for r in idf["parameters"]] == list(pm.parameters.names)
    assert len(idf["singular_values"]) == pm.n_params and idf["n_identifiable"] >= 1
    assert "parameters identifiable from these channels and band" in text
    cvp = np.array(m["crossvalidation"]["p"])
    span = pm.upper - pm.lower
    for j, (row, r) in enumerate(zip(m["parameters"], idf["parameters"])):
        assert row["identifiable"] == r["identifiable"]
        assert row["cv_percent"] is None or row["cv_percent"] > 0
        # the verdict was checked against the refits: an identifiable parameter neither scatters beyond
        # 5 % of its range nor ends at a bound in any of them
        pinned = row["cv_not_meaningful"] is not None
        assert (r["spread_p"] is None) == pinned
        if not pinned:
            assert r["spread_p"] == pytest.approx(np.std(cvp[:, j], ddof=1), rel=1e-9)
            assert r["std_p"] == pytest.approx(max(r["spread_p"], r["std_formal_p"]), rel=1e-12)
        if r["identifiable"]:
            assert not pinned and r["spread_p"] <= 0.05 * span[j]
    overruled = [ln for ln in lines if "NOT identifiable after all" in ln]
    assert all(("cross-validation" in ln) for ln in overruled)
    readmitted = [ln for ln in lines if " identifiable after all" in ln and "NOT" not in ln]
    assert all("weak combination" in ln for ln in readmitted)
