"""``frfcal identify`` on a run file written through acquisition.runfile."""

from __future__ import annotations

import json

import numpy as np
import pytest

from acquisition._driver import ChannelSpec
from acquisition.runfile import LineQuality, create_run, read_analysis
from frfcal.cli import main
from identification import Identification
from tests.identification.synthetic import ring


@pytest.fixture(scope="module")
def run_file(tmp_path_factory):
    t = ring(n_lines=300, seed=3)
    path = tmp_path_factory.mktemp("id") / "ring.h5"
    sensors = [ChannelSpec(f"acc{i}", "response", "acceleration", "m/s^2", grid=i + 1) for i in range(20)]
    drives = [ChannelSpec(f"force{j}", "force", "force", "N", grid=j + 1) for j in range(2)]
    with create_run(path, article="ring", sensors=sensors, drives=drives, quantity="accelerance") as w:
        for k, f in enumerate(t.freq_hz):
            q = LineQuality(force_n=np.ones(2), std_error=t.sigma[k], thd=np.zeros(22), n_blocks=4)
            w.append_line(f, t.H[k], q)
    return path, t


def test_identify_json_stores_result_in_run_file(run_file, capsys, tmp_path):
    path, t = run_file
    rc = main(["identify", str(path), "--band", "100", "550", "--order", "44", "--zeta0", "0.01", "--json", "--plot", str(tmp_path)])
    assert rc == 0
    obj = json.loads(capsys.readouterr().out)
    f = np.array([p["frequency_hz"] for p in obj["physical_poles"]])
    z = np.array([p["damping"] for p in obj["physical_poles"]])
    assert f.size == 20
    np.testing.assert_allclose(f, t.f_n, rtol=1e-4)
    np.testing.assert_allclose(z, t.zeta, rtol=0.1)
    assert obj["band_hz"] == [100.0, 550.0] and obj["order"] == 44 and obj["quantity"] == "accelerance"
    assert obj["stored"] == "analysis/identification"
    arrays, attrs = read_analysis(path, "identification")
    back = Identification.from_arrays(arrays, attrs)
    np.testing.assert_allclose(back.modal.frequency_hz, f)
    assert attrs["equalized_zeta0"] == 0.01 and attrs["weights"] == "std_error"
    lam = np.linalg.eigvals(arrays["equalized_A"])
    lam = lam[lam.imag > 0]
    assert np.sum(np.abs(-lam.real / np.abs(lam) - 0.01) < 1e-10) == 20
    for name in ("stabilization.png", "fit.png"):
        png = tmp_path / name
        assert png.stat().st_size > 10_000 and png.read_bytes()[:4] == b"\x89PNG"


def test_identify_human_output_and_errors(run_file, capsys):
    path, _ = run_file
    assert main(["identify", str(path), "--order", "40", "--no-store"]) == 0
    out = capsys.readouterr().out
    assert "20 physical" in out and "f_n [Hz]" in out
    assert main(["identify", str(path), "--order", "40", "--band", "600", "100"]) == 2
    assert "band_hz" in capsys.readouterr().err
