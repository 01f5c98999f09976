"""The printed calibration result (``frfcal calibrate`` / ``frfcal run``): what each SD line claims."""

from types import SimpleNamespace

from frfcal.commands.calibrate import print_result


def _member(articles):
    return {
        "member": "all" if len(articles) > 1 else articles[0], "articles": list(articles),
        "sd_calibration_nominal": 0.2, "sd_calibration": 0.004, "validation": {},
        "sd_raw_calibration_start": 0.02, "sd_raw_calibration": 6e-4, "sd_raw_floor": 4e-4,
        "sd_raw_floor_source": "estimated from adjacent lines", "crossvalidation": {},
        "parameters": [{"name": "E", "nominal_si": 2.1e11, "calibrated_si": 2.2e11, "p": 0.05,
                        "identifiable": True, "identifiability": "identifiable"}],
        "identifiability": {"weak_combinations": [], "n_identifiable": 1},
    }


def test_article_scatter_is_named_only_where_articles_share_one_parameter_set(capsys):
    camp = SimpleNamespace(calibration=SimpleNamespace(zeta0=0.01))
    res = {"members": [_member(["A1", "A2", "A3"]), _member(["A1"])], "result_file": "r.json",
           "timings": {"total_s": 1.0}}
    print_result(camp, res)
    lines = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("raw calibration lines SD")]
    assert len(lines) == 2
    assert lines[0].endswith("(1.5x; the articles' scatter adds to it)")
    assert lines[1].endswith("(1.5x)")
