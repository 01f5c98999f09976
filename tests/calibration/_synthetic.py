"""Synthetic campaigns on the femodel example subframe: run files made from the model at known p."""

from __future__ import annotations

from pathlib import Path

import numpy as np

import femodel
from acquisition import ChannelSpec
from acquisition.runfile import FLAG_OVERLOAD, LineQuality, create_run
from calibration import FRFModel, build_surrogate, modal_frf, reduced_modes

N_SENSORS = 12
DRIVE = 5  # drive collocated with sensor 5


def layout(pm, n_sensors=N_SENSORS):
    """Sensor grids/directions spread over the model (deterministic)."""
    g = np.asarray(pm.assembly.model.grid_ids)
    grids = g[np.linspace(3, len(g) - 10, n_sensors).astype(int)]
    dirs = np.tile([0.0, 0.0, 1.0], (n_sensors, 1))
    dirs[1::4] = [1.0, 0.0, 0.0]
    dirs[2::4] = [0.0, 1.0, 0.0]
    return grids, dirs


def truth_frf(pm, grids, dirs, p, f, zeta_modes):
    """FRFs (n_f, n_sensors, 1) of the model at p with per-mode damping (a big fresh basis at p)."""
    C = femodel.sensor_matrix(pm.assembly, grids, dirs)
    B = C[[DRIVE]].T.toarray()
    model = FRFModel(pm.K, pm.M, B, C, parametric=pm)
    sur, _ = build_surrogate(model, p, (f.min(), f.max()), basis_factor=4.0, enrich=False)
    lam, X = reduced_modes(sur, p)
    fe_hz = np.sqrt(np.clip(lam, 0, None)) / (2 * np.pi)
    zeta = np.interp(fe_hz, [0, 1e6], [zeta_modes, zeta_modes]) if np.isscalar(zeta_modes) else zeta_modes(fe_hz)
    return modal_frf(lam, sur.outputs @ X, X.T @ sur.inputs, f, zeta, "accelerance", sur.rigid_hz)


def write_run(path, pm, grids, dirs, f, H, article, flagged=(), units_scale=1.0, std_error=None):
    """Run file of FRFs ``H`` (n_f, n_sensors, 1); ``std_error`` like H (default zeros: not measured)."""
    sensors = [
        ChannelSpec(name=f"acc{i + 1}", role="response", quantity="acceleration", unit="m/s^2",
                    grid=int(gid), direction=tuple(float(x) for x in d))
        for i, (gid, d) in enumerate(zip(grids, dirs))
    ]
    drives = [ChannelSpec(name="force", role="force", quantity="force", unit="N",
                          grid=int(grids[DRIVE]), direction=tuple(float(x) for x in dirs[DRIVE]))]
    with create_run(path, article=article, sensors=sensors, drives=drives, overwrite=True) as w:
        n_out = H.shape[1]
        for k, fk in enumerate(f):
            flags = FLAG_OVERLOAD if k in flagged else 0
            line = H[k] if not flags else np.full_like(H[k], np.nan)
            se = np.zeros((n_out, 1)) if std_error is None else std_error[k]
            q = LineQuality(force_n=np.ones(1), std_error=se, thd=np.zeros(n_out + 1), flags=flags)
            w.append_line(float(fk), line, q)
    return Path(path)


def make_campaign(tmp, units="mm-t-s", target_dof=3000, p_true=None, articles=1, noise=0.0, seed=0,
                  starts=2, realizations=4, extra="", step_hz=1.0, bad_grid=False):
    """Write model, parameter file, run files and campaign TOML under ``tmp``; return (campaign path, p_true, pm)."""
    tmp = Path(tmp)
    ex = femodel.example_subframe(tmp / "model", target_dof=target_dof, units=units)
    pm = femodel.parametric_model(ex.params)
    rng = np.random.default_rng(seed)
    if p_true is None:
        p_true = np.zeros(pm.n_params)
    # p_true: (n_p,) for every article, or (n_articles, n_p), one row per article
    grids, dirs = layout(pm)
    f = np.arange(80.0, 520.0, step_hz)
    runs = []
    p_articles = [np.asarray(p_true)] * articles if np.ndim(p_true) == 1 else [np.asarray(x) for x in p_true]
    for a in range(len(p_articles)):
        H = truth_frf(pm, grids, dirs, p_articles[a], f, lambda fh: 0.002 + 0.003 * (fh / 500.0))
        se = None
        if noise:
            se = noise * np.abs(H)  # rms of the complex error, as acquisition stores it
            H = H * (1 + noise * (rng.standard_normal(H.shape) + 1j * rng.standard_normal(H.shape)) / np.sqrt(2))
        g_run = grids.copy()
        if bad_grid:
            g_run[3] = 987654321  # acc4: a grid that is not in the model
        runs.append(write_run(tmp / f"run{a + 1}.h5", pm, g_run, dirs, f, H, f"SF{a + 1}", flagged=(10, 11, 150),
                              std_error=se))
    cal = [f"acc{i}" for i in (1, 2, 4, 6, 7, 9, 11)]
    hold = [f"acc{i}" for i in (3, 5, 8, 10, 12)]
    text = f"""
[model]
parameters = "{ex.params}"

{''.join(f'[[run]]{chr(10)}path = "{r.name}"{chr(10)}' for r in runs)}
[channels]
calibrate = {cal!r}
holdout = {hold!r}

[band]
low_hz = 100.0
high_hz = 400.0

[calibration]
starts = {starts}
max_cycles = 2

[identification]
order = 30

[crossvalidation]
realizations = {realizations}

[execution]
workers = 1

[output]
dir = "out"
{extra}
""".replace("'", '"')
    path = tmp / "campaign.toml"
    path.write_text(text)
    return path, np.asarray(p_true), pm
