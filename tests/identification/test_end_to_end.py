"""Simulated stepped-sine lab -> run file -> ``frfcal identify``: the plant's modes come back."""

from __future__ import annotations

import json

import numpy as np

from acquisition import ChannelSpec, ModalPlant, ShakerModel, SimulatedLab, plan_from_dict, run_sweep
from acquisition.runfile import read_analysis
from frfcal.cli import main
from identification import Identification

MODES_HZ = (120.0, 185.0, 262.0)
ZETA = 0.001


def test_simulated_lab_run_is_identified(tmp_path, capsys):
    shapes_out = np.array([[0.5, 0.4, 0.3], [0.35, -0.45, 0.5], [0.42, 0.25, -0.33]])
    plant = ModalPlant(MODES_HZ, ZETA, shapes_out, shapes_out[:1])
    sensors = tuple(
        ChannelSpec(f"acc{k}", "response", "acceleration", "m/s^2", sensitivity=0.0102, physical=f"sim/{k}",
                    grid=10 + k, direction=(0.0, 0.0, 1.0))
        for k in range(3)
    )
    drive = ChannelSpec("force", "force", "force", "N", sensitivity=0.0225, physical="sim/force", grid=10,
                        direction=(0.0, 0.0, 1.0))
    plan = plan_from_dict({
        "name": "e2e",
        "sample_rate_hz": 4096.0,
        "channels": [{"name": c.name} for c in sensors] + [{"name": "force", "role": "force", "quantity": "force"}],
        "lines": {"kind": "bandwidth", "start_hz": 100.0, "stop_hz": 300.0, "background_step": 0.04,
                  "lines_per_bandwidth": 3, "span_bandwidths": 2,
                  "poles": [{"frequency_hz": f, "damping": ZETA} for f in MODES_HZ]},
    })
    lab = SimulatedLab(plant, shaker=ShakerModel(), noise_rms=1e-4, seed=2, kind="demodulating")
    path = tmp_path / "e2e.h5"
    res = run_sweep(lab, plan, path, sensors=sensors, drive=drive, level_n=1.0)
    lab.close()
    assert res.status == "completed"
    # over-modelled 2x: still exactly the three modes
    assert main(["identify", str(path), "--order", "12", "--zeta0", "0.02", "--json"]) == 0
    obj = json.loads(capsys.readouterr().out)
    f = np.array([p["frequency_hz"] for p in obj["physical_poles"]])
    z = np.array([p["damping"] for p in obj["physical_poles"]])
    np.testing.assert_allclose(f, MODES_HZ, rtol=1e-5)
    np.testing.assert_allclose(z, ZETA, rtol=0.02)
    ident = Identification.from_arrays(*read_analysis(path, "identification"))
    assert ident.model.n_out == 3 and ident.model.n_in == 1 and ident.quantity == "accelerance"
