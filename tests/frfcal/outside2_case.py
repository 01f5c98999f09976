"""A second outside data set, built independently of frfcal's generators (issue 14 + 12).

What a car-industry lab would hand over: a Nastran deck in mm-t-s (tonne, mm, s, N, MPa) of two sheet
parts (a floor panel of CQUAD4 with a CTRIA3 corner, a U-rail of CQUAD4 on top, its flange spot-welded by
RBE2 spiders), a motor mass (CONM2 with offset and inertia) on four CBUSH mounts, CELAS1/PELAS 11 end
springs, free-free; a parameter table (TOML: nominal, absolute bounds in named units, descriptions); and one
UFF58 file per test article: 3 references x 16 responses, accelerance in mm/s^2/N (units dataset 164
mm-N, records labelled or NONE as lab software writes them), responses named by entity ("FLR07" ...),
some pointing -X/-Y, and two skewed accelerometers whose direction code is in a local displacement
coordinate system of the node (datasets 2411 + 2420, as test geometry is exported).

The articles: the population offset of the parameters (5-15 %), 0.3 % article scatter, modal damping
0.05-0.3 % varying by mode, noise 0.7 % of |H| plus a floor; on articles A4 and A5 the rail flange's
unwelded end touches the panel (a gap of 4 mm closed: contact springs between the facing grid pairs),
an effect the deck lacks. Each article's deck is written with its own card values and solved with
femodel (read + assembly are validated against Nastran; dense eigen-solution of the whole model), and
its FRFs are the exact modal sum of all modes (rigid-body mass line included).

``build(out_dir)`` writes everything and returns a dict with the truth.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

#: the deck's nominal values (deck units: mm, t, MPa, N/mm, N mm/rad)
NOMINAL = {"E_panel": 210000.0, "t_panel": 1.2, "t_rail": 1.5, "k_mount": 800.0, "k_end": 300.0,
           "m_motor": 4.0e-3}
#: the population offset of the test articles (relative), and the article scatter (rms, relative)
OFFSETS = {"E_panel": -0.06, "t_panel": 0.08, "t_rail": -0.05, "k_mount": 0.15, "k_end": -0.12,
           "m_motor": 0.10}
SCATTER = 0.003
ARTICLES = ("A1", "A2", "A3", "A4", "A5")
GAP_ARTICLES = ("A4", "A5")
#: contact spring per facing pair where the gap closed, N/mm (z)
GAP_RATE_N_PER_MM = 30.0
BAND_HZ = (8.0, 130.0)
DF_HZ = 0.0625
NOISE_REL, NOISE_FLOOR_REL = 0.007, 2e-4   # noise: 0.7 % of |H| + 2e-4 x the median |H| of the channel

# geometry (mm): panel 600 x 400 at z = 0, 50 mm CQUAD4; rail along x at y = 150..250, flange at z = 4
NX, NY, H = 12, 8, 50.0
RAIL_Y0, RAIL_W, RAIL_H, FLANGE_Z = 150.0, 100.0, 60.0, 4.0


def panel_grid(i, j):
    return 1000 + 100 * j + i        # i = 0..NX along x, j = 0..NY along y


def rail_grid(part, i, k=0):
    # part: 1 flange (y = RAIL_Y0 .. +50, z = 4), 2 web (x-z plane at y = RAIL_Y0 + 50... see deck)
    return 2000 + 1000 * part + 100 * k + i


def _r(x: float) -> str:
    """A real for a free-field card (pyNastran refuses an integer-looking real)."""
    return f"{x:.7E}"


def deck_text(v: dict, contact: float = 0.0) -> str:
    """The deck with the card values ``v`` (deck units); ``contact`` N/mm springs across the closed gap."""
    L = []
    g = L.append
    g("$ outside case 2: floor panel + U-rail, mm-t-s")
    g("SOL 103\nCEND\nTITLE = FLOOR PANEL WITH RAIL\nMETHOD = 1\nBEGIN BULK")
    g("PARAM,GRDPNT,0")
    g("EIGRL,1,,,30")
    # panel grids
    for j in range(NY + 1):
        for i in range(NX + 1):
            g(f"GRID,{panel_grid(i, j)},,{i * H:.1f},{j * H:.1f},0.0")
    # panel elements: CQUAD4, the corner cell (i=NX-1, j=NY-1) as two CTRIA3
    eid = 1
    for j in range(NY):
        for i in range(NX):
            a, b, c, d = panel_grid(i, j), panel_grid(i + 1, j), panel_grid(i + 1, j + 1), panel_grid(i, j + 1)
            if (i, j) in ((NX - 1, NY - 1), (0, NY - 1)):
                g(f"CTRIA3,{eid},1,{a},{b},{c}")
                g(f"CTRIA3,{eid + 1},1,{a},{c},{d}")
                eid += 2
            else:
                g(f"CQUAD4,{eid},1,{a},{b},{c},{d}")
                eid += 1
    # rail: flange (z = 4, y = 150..200) of 2 rows of grids, web (y = 200, z = 4..64), top flange
    # (z = 64, y = 200..250); 50 mm / 30 mm elements
    ys_fl = (RAIL_Y0, RAIL_Y0 + 50.0)
    for k, y in enumerate(ys_fl):
        for i in range(NX + 1):
            g(f"GRID,{rail_grid(1, i, k)},,{i * H:.1f},{y:.1f},{FLANGE_Z:.1f}")
    zs_web = (FLANGE_Z + 30.0, FLANGE_Z + RAIL_H)
    for k, z in enumerate(zs_web):
        for i in range(NX + 1):
            g(f"GRID,{rail_grid(2, i, k)},,{i * H:.1f},{RAIL_Y0 + 50.0:.1f},{z:.1f}")
    for i in range(NX + 1):
        g(f"GRID,{rail_grid(3, i)},,{i * H:.1f},{RAIL_Y0 + RAIL_W:.1f},{FLANGE_Z + RAIL_H:.1f}")
    eid = 5001
    for i in range(NX):
        rows = [(rail_grid(1, i, 0), rail_grid(1, i + 1, 0), rail_grid(1, i + 1, 1), rail_grid(1, i, 1)),
                (rail_grid(1, i, 1), rail_grid(1, i + 1, 1), rail_grid(2, i + 1, 0), rail_grid(2, i, 0)),
                (rail_grid(2, i, 0), rail_grid(2, i + 1, 0), rail_grid(2, i + 1, 1), rail_grid(2, i, 1)),
                (rail_grid(2, i, 1), rail_grid(2, i + 1, 1), rail_grid(3, i + 1), rail_grid(3, i))]
        for q in rows:
            g(f"CQUAD4,{eid},2,{q[0]},{q[1]},{q[2]},{q[3]}")
            eid += 1
    # spot welds: RBE2 spiders, flange grid (independent) -> the panel grid 4 mm below, on x = 0..300 mm
    # (i = 0..6, both flange rows); the flange beyond x = 300 mm lies free, 4 mm above the panel
    rid = 7001
    for k in range(2):
        for i in range(0, 7):
            g(f"RBE2,{rid},{rail_grid(1, i, k)},123456,{panel_grid(i, 3 + k)}")
            rid += 1
    # the rail ends on the panel through rubber pads: CELAS1 (PELAS 11) on z, web bottom at x = 0 / 600 mm
    g(f"PELAS,11,{_r(v['k_end'])}")
    for n, i in enumerate((0, NX)):
        g(f"CELAS1,{8001 + n},11,{rail_grid(3, i)},3,{panel_grid(i, 5)},3")
    # motor: CONM2 at grid 9001 (offset 20 mm in z, inertia), on 4 CBUSH mounts (PBUSH 21) to panel grids
    g("GRID,9001,,450.0,75.0,40.0")
    g(f"CONM2,9101,9001,0,{_r(v['m_motor'])},0.0,0.0,20.0,,+CM1")
    g("+CM1,8.0,0.3,10.0,0.0,0.0,6.0")
    # K1, K2 (shear) fixed at the nominal vertical rate: the table's parameter is K3 only
    g(f"PBUSH,21,K,{_r(NOMINAL['k_mount'])},{_r(NOMINAL['k_mount'])},{_r(v['k_mount'])},2.0e5,2.0e5,2.0e5")
    for n, (i, j) in enumerate(((8, 1), (10, 1), (8, 2), (10, 2))):
        g(f"CBUSH,{9201 + n},21,9001,{panel_grid(i, j)},,,,0")
    if contact:
        # the closed gap: the free flange end (x = 450..600) touches the panel, springs on z between facing grids
        cid = 9501
        for k in range(2):
            for i in range(9, NX + 1):
                g(f"CELAS2,{cid},{_r(contact)},{rail_grid(1, i, k)},3,{panel_grid(i, 3 + k)},3")
                cid += 1
    g(f"PSHELL,1,1,{_r(v['t_panel'])},1,,1")
    g(f"PSHELL,2,2,{_r(v['t_rail'])},2,,2")
    g(f"MAT1,1,{_r(v['E_panel'])},,0.3,7.85-9")
    g("MAT1,2,210000.0,,0.3,7.85-9")
    g("ENDDATA")
    return "\n".join(L) + "\n"


PARAMS_TOML = """\
# floor panel with rail: calibration parameters (lab table)
[model]
bdf = "floor.bdf"
units = "mm-t-s"

[[parameter]]
name = "E_panel"
card = "MAT1"
id = 1
field = "E"
nominal = 210000.0
lower_value = 170000.0
upper_value = 250000.0
unit = "MPa"
description = "Young's modulus of the floor panel steel"

[[parameter]]
name = "t_panel"
card = "PSHELL"
id = 1
field = "T"
nominal = 1.2
lower_value = 1.0
upper_value = 1.5
unit = "mm"
description = "floor panel sheet thickness"

[[parameter]]
name = "t_rail"
card = "PSHELL"
id = 2
field = "T"
nominal = 1.5
lower_value = 1.2
upper_value = 1.8
unit = "mm"
description = "rail sheet thickness"

[[parameter]]
name = "k_mount"
card = "PBUSH"
id = 21
field = "K3"
nominal = 800.0
lower_value = 400.0
upper_value = 1600.0
unit = "N/mm"
description = "motor mount rubber, vertical rate"

[[parameter]]
name = "k_end"
card = "PELAS"
id = 11
field = "K"
nominal = 300.0
lower_value = 100.0
upper_value = 900.0
unit = "N/mm"
description = "rail end pads, vertical rate"

[[parameter]]
name = "m_motor"
card = "CONM2"
id = 9101
field = "M"
nominal = 4.0
lower_value = 3.0
upper_value = 5.5
unit = "kg"
description = "motor mass"
"""

#: responses: (entity name, grid, direction code, local CS or None). Codes in the node's displacement
#: system; two skewed sensors carry a local system (2420) rotated about x / y.
RESPONSES = [
    ("FLR01", panel_grid(1, 1), 3), ("FLR02", panel_grid(4, 0), 3), ("FLR03", panel_grid(6, 2), 3),
    ("FLR04", panel_grid(11, 1), 3), ("FLR05", panel_grid(2, 6), 3), ("FLR06", panel_grid(5, 7), 3),
    ("FLR07", panel_grid(9, 6), 3), ("FLR08", panel_grid(12, 8), 3), ("FLR09", panel_grid(3, 4), -3),
    ("FLR10", panel_grid(12, 4), -1), ("FLR11", panel_grid(0, 8), -2),
    ("RAL01", rail_grid(3, 2), 3), ("RAL02", rail_grid(3, 10), 3), ("RAL03", rail_grid(2, 6, 1), -2),
    ("RAL04", rail_grid(2, 11, 0), 3), ("MOT01", 9001, 3),
]
#: skewed: node -> (rotation axis, angle deg) of its local displacement system
SKEWED = {panel_grid(12, 4): ("y", 30.0), rail_grid(2, 11, 0): ("x", -35.0)}
REFERENCES = [("SHK1", panel_grid(2, 1), 3), ("SHK2", rail_grid(3, 8), 3), ("SHK3", panel_grid(0, 6), -1)]
CALIBRATE = ("FLR01", "FLR03", "FLR05", "FLR07", "FLR09", "FLR11", "RAL01", "RAL03", "MOT01")
HOLDOUT = ("FLR02", "FLR04", "FLR06", "FLR08", "FLR10", "RAL02", "RAL04")


def _rot(axis, deg):
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return {"x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
            "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
            "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])}[axis]


def direction(node, code):
    """Basic-system unit vector of a (node, code) channel: code in the node's local system when skewed."""
    e = np.zeros(3)
    e[abs(code) - 1] = np.sign(code)
    if node in SKEWED:
        e = _rot(*SKEWED[node]) @ e
    return e


def article_values(seed=2024):
    """Per article: card values (deck units) = nominal x (1 + offset + scatter)."""
    rng = np.random.default_rng(seed)
    out = {}
    for a in ARTICLES:
        out[a] = {k: NOMINAL[k] * (1 + OFFSETS[k] + SCATTER * rng.standard_normal()) for k in NOMINAL}
    return out


def solve(deck_path):
    """All modes of a deck (femodel read + assembly; dense generalized eigen-solution): (f_hz, shapes, asm)."""
    import scipy.linalg as sla

    import femodel

    model = femodel.read_bdf(deck_path, units="mm-t-s")
    asm = femodel.assemble(model)
    K, M = asm.stiffness().toarray(), asm.mass().toarray()
    # massless DOF (shell rotations under lumped mass) condensed exactly: their response is static
    m = np.abs(M).sum(axis=1) > 0
    s = ~m
    X = np.linalg.solve(K[np.ix_(s, s)], K[np.ix_(s, m)])
    Kr = K[np.ix_(m, m)] - K[np.ix_(m, s)] @ X
    lam, psi = sla.eigh(0.5 * (Kr + Kr.T), M[np.ix_(m, m)])
    phi = np.empty((K.shape[0], lam.size))
    phi[m], phi[s] = psi, -X @ psi
    lam = np.clip(lam, 0.0, None)
    return np.sqrt(lam) / (2 * np.pi), phi, asm


def accelerance(f_hz, fn, phi_out, phi_in, zeta):
    """Exact modal sum (SI, m/s^2/N): rigid-body modes (fn < 0.5 Hz) as the mass line."""
    w = 2 * np.pi * f_hz[:, None]
    wn = 2 * np.pi * np.where(fn < 0.5, 0.0, fn)[None, :]
    den = wn**2 - w**2 + 2j * zeta[None, :] * wn * w
    return np.einsum("fk,ok,ik->foi", -w**2 / den, phi_out, phi_in)


def write_uff(path, f_hz, H_si, article, xyz_mm, *, labelled=True):
    """One UFF58 file per article as lab software writes it: 164 (mm-N), 2420 + 2411, 58 in mm/s^2/N."""
    import pyuff

    sets = [{"type": 164, "units_code": 5, "units_description": "mm newton", "temp_mode": 2,
             "length": 1000.0, "force": 1.0, "temp": 1.0, "temp_offset": 273.15}]
    # local displacement systems of the skewed nodes: 2420 (one CS per skewed node) and 2411 nodes
    cs = {node: 10 + n for n, node in enumerate(SKEWED)}
    sets.append({"type": 2420, "Part_UID": 1, "Part_Name": "floor",
                 "CS_sys_labels": [c for c in cs.values()], "CS_types": [0] * len(cs),
                 "CS_colors": [8] * len(cs), "CS_names": [f"CS{c}" for c in cs.values()],
                 "CS_matrices": [np.vstack([_rot(*SKEWED[n]).T, np.zeros(3)]) for n in cs]})
    nodes = sorted({n for _, n, _ in RESPONSES} | {n for _, n, _ in REFERENCES})
    sets.append({"type": 2411, "node_nums": np.array(nodes, float),
                 "def_cs": np.zeros(len(nodes)), "disp_cs": np.array([cs.get(n, 0) for n in nodes], float),
                 "color": np.full(len(nodes), 11.0),
                 "x": np.array([xyz_mm[n][0] for n in nodes]), "y": np.array([xyz_mm[n][1] for n in nodes]),
                 "z": np.array([xyz_mm[n][2] for n in nodes])})
    H_mm = H_si * 1000.0
    for i, (rname, rnode, rcode) in enumerate(REFERENCES):
        for o, (oname, onode, ocode) in enumerate(RESPONSES):
            sets.append({"type": 58, "func_type": 4, "rsp_node": onode, "rsp_dir": ocode, "rsp_ent_name": oname,
                         "ref_node": rnode, "ref_dir": rcode, "ref_ent_name": rname,
                         "id1": f"{article} {oname}/{rname}", "id2": "floor panel", "id3": "", "id4": "", "id5": "",
                         "data": H_mm[:, o, i], "x": f_hz, "abscissa_spacing": 1, "abscissa_spec_data_type": 18,
                         "ordinate_spec_data_type": 12, "orddenom_spec_data_type": 13,
                         "abscissa_axis_units_lab": "Hz",
                         "ordinate_axis_units_lab": "mm/s^2" if labelled else "NONE",
                         "orddenom_axis_units_lab": "N" if labelled else "NONE"})
    path = Path(path)
    path.unlink(missing_ok=True)
    pyuff.UFF(str(path)).write_sets(sets, mode="add")


def build(out, *, seed=2024, n_articles=len(ARTICLES)):
    """Write floor.bdf, floor_params.toml, data/A*.uff, truth.json under ``out``; return the truth."""
    import femodel

    out = Path(out)
    (out / "data").mkdir(parents=True, exist_ok=True)
    (out / "truth").mkdir(exist_ok=True)
    (out / "floor.bdf").write_text(deck_text(NOMINAL))
    (out / "floor_params.toml").write_text(PARAMS_TOML)
    m0 = femodel.read_bdf(out / "floor.bdf", units="mm-t-s")
    xyz0 = {int(gid): 1000.0 * x for gid, x in zip(m0.grid_ids, m0.xyz)}
    rng = np.random.default_rng(seed + 1)
    f_hz = np.arange(0.0, BAND_HZ[1] * 1.25 + DF_HZ / 2, DF_HZ)   # analyzer lines from DC
    vals = article_values(seed)
    truth = {"articles": {}, "band_hz": BAND_HZ, "f_hz_step": DF_HZ}
    zeta_by_mode = None
    for a in ARTICLES[:n_articles]:
        contact = GAP_RATE_N_PER_MM if a in GAP_ARTICLES else 0.0
        deck = out / "truth" / f"{a}.bdf"
        deck.write_text(deck_text(vals[a], contact=contact))
        fn, phi, asm = solve(deck)
        if zeta_by_mode is None:
            # 0.05-0.3 % by mode (log-uniform, fixed per mode index), x a 5 % article factor
            zeta_by_mode = np.exp(np.random.default_rng(seed + 2).uniform(np.log(5e-4), np.log(3e-3), fn.size))
        zeta = zeta_by_mode * np.exp(0.05 * rng.standard_normal())
        Co = femodel.sensor_matrix(asm, [n for _, n, _ in RESPONSES], [direction(n, c) for _, n, c in RESPONSES])
        Ci = femodel.sensor_matrix(asm, [n for _, n, _ in REFERENCES], [direction(n, c) for _, n, c in REFERENCES])
        H = accelerance(f_hz[1:], fn, Co @ phi, Ci @ phi, zeta)
        H = np.concatenate([np.zeros((1,) + H.shape[1:], complex), H])   # the DC line
        scale = np.median(np.abs(H[1:]), axis=0, keepdims=True)
        noise = (NOISE_REL * np.abs(H) + NOISE_FLOOR_REL * scale) / np.sqrt(2)
        Hn = H + noise * (rng.standard_normal(H.shape) + 1j * rng.standard_normal(H.shape))
        Hn[0] = 0.0
        write_uff(out / "data" / f"{a}.uff", f_hz, Hn, a, xyz0, labelled=a not in ("A2", "A5"))
        np.savez(out / "truth" / f"{a}.npz", f_hz=f_hz, H=H, Hn=Hn)
        el = fn >= 0.5
        truth["articles"][a] = {"values": vals[a], "contact_n_per_mm": contact,
                                "n_rigid": int((~el).sum()),
                                "elastic_hz": fn[el][:40].tolist(), "zeta": zeta[el][:40].tolist()}
    (out / "truth.json").write_text(json.dumps(truth, indent=1))
    return truth


CAMPAIGN_TOML = """\
[model]
parameters = "floor_params.toml"

{runs}
[channels]
calibrate = {cal}
holdout = {hold}

[band]
low_hz = {lo}
high_hz = {hi}

[calibration]
ensemble = "group"
starts = 4

[crossvalidation]
realizations = 4

[output]
dir = "out"
"""


def campaign(out, names: dict) -> Path:
    """campaign.toml with the channel names import-uff printed (``names``: entity -> channel name)."""
    out = Path(out)
    runs = "\n".join(f'[[run]]\nuff = "data/{a}.uff"\narticle = "{a}"\n' for a in ARTICLES)
    text = CAMPAIGN_TOML.format(runs=runs, cal=json.dumps([names[c] for c in CALIBRATE]),
                                hold=json.dumps([names[c] for c in HOLDOUT]), lo=BAND_HZ[0], hi=BAND_HZ[1])
    (out / "campaign.toml").write_text(text)
    return out / "campaign.toml"


def group_floor(out, articles) -> dict:
    """SD floors of a group calibrated as one model: the group's mean-parameter truth (its effect included)
    against each article's noisy lines in the band, with the article's damping; mean over the articles.

    Also each article's own truth against its own noisy lines (``own_cal``, ``own_holdout``).
    """
    import femodel

    out = Path(out)
    t = json.loads((out / "truth.json").read_text())
    v = {k: float(np.mean([t["articles"][a]["values"][k] for a in articles])) for k in NOMINAL}
    contact = GAP_RATE_N_PER_MM if articles[0] in GAP_ARTICLES else 0.0
    deck = out / "truth" / f"mean_{'_'.join(articles)}.bdf"
    deck.write_text(deck_text(v, contact=contact))
    fn, phi, asm = solve(deck)
    Co = femodel.sensor_matrix(asm, [n for _, n, _ in RESPONSES], [direction(n, c) for _, n, c in RESPONSES])
    Ci = femodel.sensor_matrix(asm, [n for _, n, _ in REFERENCES], [direction(n, c) for _, n, c in REFERENCES])
    names = [e for e, _, _ in RESPONSES]
    sets = {"cal": [names.index(c) for c in CALIBRATE], "holdout": [names.index(c) for c in HOLDOUT]}
    zeta_by_mode = np.exp(np.random.default_rng(2024 + 2).uniform(np.log(5e-4), np.log(3e-3), fn.size))
    acc = {k: [] for k in ("cal", "holdout", "own_cal", "own_holdout")}
    for a in articles:
        z = np.load(out / "truth" / f"{a}.npz")
        sel = (z["f_hz"] >= BAND_HZ[0]) & (z["f_hz"] <= BAND_HZ[1])
        factor = t["articles"][a]["zeta"][0] / zeta_by_mode[6]      # the article's damping factor
        H = accelerance(z["f_hz"][sel], fn, Co @ phi, Ci @ phi, zeta_by_mode * factor)
        for k, idx in sets.items():
            acc[k].append(np.mean(np.abs(np.log10(H[:, idx] / z["Hn"][sel][:, idx])) ** 2))
            acc["own_" + k].append(np.mean(np.abs(np.log10(z["H"][sel][:, idx] / z["Hn"][sel][:, idx])) ** 2))
    return {k: float(np.mean(x)) for k, x in acc.items()}
