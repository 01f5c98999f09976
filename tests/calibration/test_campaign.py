"""Campaign config, pipeline end to end on run files, CLI, bad input."""

import json

import numpy as np
import pytest

from calibration import CalibrationError, campaign_from_dict, load_campaign, run_campaign
from frfcal.cli import main
from tests.calibration._synthetic import make_campaign

P_TRUE = np.array([0.05, -0.04, 0.06, -0.05, 0.04, -0.03, 0.05, -0.06, 0.03,
                   -0.04, 0.05, -0.02, 0.08, -0.07, 0.06, -0.05, 0.04])


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("camp")
    path, p_true, pm = make_campaign(tmp, p_true=P_TRUE, target_dof=2000)
    return path, p_true, pm


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
    # flagged lines (NaN) excluded: 3 flagged lines of which 1 in band (line 400 is at 280 Hz)
    n_lines_in_band = int(np.sum((np.arange(80.0, 520.0, 0.5) >= 100) & (np.arange(80.0, 520.0, 0.5) <= 400)))
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


def test_bad_inputs_have_clear_errors(campaign, tmp_path):
    path, _, _ = campaign
    text = path.read_text()
    base = path.parent
    bad = tmp_path / "c.toml"
    bad.write_text(text.replace('low_hz = 100.0', 'low_hz = 100.0\nlow_freq = 3').replace('dir = "out"', f'dir = "{tmp_path}/o"')
                   .replace('path = "run1.h5"', f'path = "{base}/run1.h5"').replace('parameters = "', 'parameters = "'))
    with pytest.raises(CalibrationError, match="band.low_freq: unknown field"):
        load_campaign(bad)
    # unknown channel
    bad.write_text(text.replace('"acc1"', '"accX"', 1).replace('path = "run1.h5"', f'path = "{base}/run1.h5"'))
    with pytest.raises(CalibrationError, match="accX"):
        run_campaign(load_campaign(bad), log=lambda m: None)
    # band without data
    bad.write_text(text.replace("high_hz = 400.0", "high_hz = 4000.0").replace("low_hz = 100.0", "low_hz = 3000.0")
                   .replace('path = "run1.h5"', f'path = "{base}/run1.h5"'))
    with pytest.raises(CalibrationError, match="no valid lines"):
        run_campaign(load_campaign(bad), log=lambda m: None)
    # CLI prints one line and exits 2
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
