"""The whole chain on a CBAR frame written with scalar masses, a CONM1 and a PBAR-section parameter table.

The example frame's deck is rewritten the way another lab's deck might be: the fuel tank as three
grounded CMASS2 (one per translation, at the grid: its offset and inertia dropped), a 0.8 kg bracket as
a CONM1 with rotary inertia, and a parameter table that calibrates the rails' bending (PBAR I1) and the CMASS2 tank
mass beside E, rho, the engine CONM2s and the mounts. Truth data come from ``frfcal.synth`` (parameter
offsets, 0.3 % article scatter, damping varying from mode to mode, free-free, noise, UFF58), then
import-uff -> calibrate through the command line; the result is compared with the floor (the truth
itself against its own noisy lines).
"""

import json
import re

import numpy as np
import pytest

import femodel
from frfcal.cli import main
from frfcal.synth import SynthChannel, synthesize

BAND = (60.0, 350.0)
SCATTER = 0.003


def _rewrite_deck(src, dst, tank_grid: int, bracket_grid: int) -> None:
    """The example deck with CONM2 9003 (tank) as three CMASS2 and a CONM1 bracket added."""
    text = src.read_text()
    lines = text.splitlines(keepends=True)
    k = next(i for i, ln in enumerate(lines) if re.match(r"CONM2\*\s+9003\b", ln))
    mass = float(lines[k][56:72])
    end = k + 1
    while end < len(lines) and lines[end].startswith("*"):  # the large-field continuations (offset, inertia)
        end += 1
    del lines[k:end]
    tank = "".join(f"CMASS2,{97000 + c},{mass!r},{tank_grid},{c}\n" for c in (1, 2, 3))
    bracket = (f"CONM1,97010,{bracket_grid},,0.8,,0.8,,\n,0.8,,0.,,1.e-3,,,\n,,1.e-3,,,,,,1.e-3\n")
    text = "".join(lines).replace("ENDDATA", tank + bracket + "ENDDATA")
    dst.write_text(text)


@pytest.fixture(scope="module")
def chain(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("frame_cards")
    ex = femodel.example_frame(tmp / "model")
    fe0 = femodel.read_bdf(ex.bdf)
    tank = int(fe0.elements["CONM2"]["nodes"][list(fe0.elements["CONM2"].ids).index(9003), 0])
    g = np.asarray(fe0.grid_ids)
    deck = tmp / "model" / "frame_cards.bdf"
    _rewrite_deck(ex.bdf, deck, tank, int(g[40]))
    fe = femodel.read_bdf(deck)
    assert len(fe.elements["CMASS2"]) == 3 and len(fe.elements["CONM1"]) == 1 and 9003 not in fe.elements["CONM2"].ids
    params = tmp / "model" / "params.json"  # a lab's table, JSON with units, as docs/parameters.md allows
    params.write_text(json.dumps({"model": {"bdf": deck.name, "units": "si"}, "parameter": [
        {"name": "E_ladder", "card": "MAT1", "id": 1, "field": "E", "lower": -0.2, "upper": 0.2},
        {"name": "rho_ladder", "card": "MAT1", "id": 1, "field": "RHO", "lower": -0.2, "upper": 0.2},
        {"name": "I1_rails", "card": "PBAR", "id": 1, "field": "I1", "lower": -0.3, "upper": 0.3, "unit": "mm^4"},
        {"name": "E_cradle", "card": "MAT1", "id": 2, "field": "E", "lower": -0.3, "upper": 0.3},
        {"name": "M_engine", "card": "CONM2", "ids": [9001, 9002], "field": "M", "lower": -0.5, "upper": 0.5},
        {"name": "M_tank", "card": "CMASS2", "ids": [97001, 97002, 97003], "field": "M", "lower": -0.5,
         "upper": 0.5, "unit": "kg"},
        {"name": "k_mount_xy", "card": "CELAS2", "ids": [8011, 8012, 8021, 8022, 8031, 8032, 8041, 8042],
         "field": "K", "lower": -0.5, "upper": 0.5},
        {"name": "k_mount_z", "card": "CELAS2", "ids": [8013, 8023, 8033, 8043], "field": "K", "lower": -0.5,
         "upper": 0.5},
    ]}))
    pm = femodel.parametric_model(params)
    gi = np.asarray(pm.assembly.model.grid_ids)
    pick = gi[np.linspace(2, len(gi) - 3, 16).astype(int)]
    dirs = [(0.0, 0.0, 1.0), (0.0, 1.0, 0.0), (0.0, 0.0, -1.0), (1.0, 0.0, 0.0)]
    sensors = [SynthChannel(f"s{i + 1}", int(gid), dirs[i % 4]) for i, gid in enumerate(pick)]
    drives = [SynthChannel("F1", int(pick[3]), (0.0, 0.0, 1.0))]
    sc = synthesize(deck, params, tmp / "data", sensors=sensors, drives=drives, band_hz=BAND, n_articles=1,
                    seed=8, scatter=SCATTER)
    run = tmp / "runs" / "A1.h5"
    assert main(["import-uff", str(sc.uff_paths[0]), "--out", str(run), "--article", "A1"]) == 0
    names = [s.name for s in sensors]
    cal, hold = names[0::2] + names[1::4], names[3::4]
    camp = tmp / "campaign.toml"
    camp.write_text(
        f'[model]\nparameters = "{params}"\n[[run]]\npath = "{run}"\n'
        + f"[channels]\ncalibrate = {json.dumps(cal)}\nholdout = {json.dumps(hold)}\n"
        + f"[band]\nlow_hz = {BAND[0]}\nhigh_hz = {BAND[1]}\n"
        + "[calibration]\nstarts = 4\n[crossvalidation]\nrealizations = 3\n[execution]\nworkers = 2\n"
        + f'[output]\ndir = "{tmp / "out"}"\nfigures = false\n'
    )
    assert main(["calibrate", str(camp), "--quiet"]) == 0
    return sc, pm, json.loads((tmp / "out" / "calibration.json").read_text()), cal, hold


def test_chain_with_scalar_masses_and_section_parameters_reaches_the_floor(chain):
    sc, pm, result, cal, hold = chain
    (m,) = result["members"]
    p = np.array([row["p"] for row in m["parameters"]])
    floor_hold, floor_cal = sc.floor_sd(hold, BAND), sc.floor_sd(cal, BAND)
    assert m["validation"]["sd_nominal"] > 100 * floor_hold
    assert m["validation"]["sd_calibrated"] < 2.0 * floor_hold, (m["validation"]["sd_calibrated"], floor_hold)
    assert sc.model_sd(p, 0, hold, BAND) < 2.0 * floor_hold
    assert m["sd_raw_calibration"] < 2.0 * floor_cal
    err = np.abs((1 + p) / (1 + sc.p_true[0]) - 1)
    ident = np.array([row["identifiable"] for row in m["parameters"]])
    names = [row["name"] for row in m["parameters"]]
    assert ident[names.index("M_tank")] and ident[names.index("I1_rails")], [r["identifiability"] for r in
                                                                             m["parameters"]]
    assert err[ident].max() < 3 * SCATTER, dict(zip(names, np.round(100 * err, 3)))
