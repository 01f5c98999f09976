"""identify(): FRFs in, a labelled continuous-time model and modal parameters out."""

from __future__ import annotations

import json
from dataclasses import dataclass, field

import numpy as np

from ._errors import IdentificationError
from ._metrics import channel_deviation
from ._poles import LABELS, ModalParameters, Poles, label_poles, normalize_shapes
from ._statespace import QUANTITIES, StateSpace, frequency_grid
from ._subspace import (
    _separable,
    bilinear_alpha,
    fit_bd,
    fit_cd,
    importance,
    real_modal_form,
    realize,
    subspace_basis,
    unit_circle,
)


@dataclass(frozen=True)
class Identification:
    """Result of :func:`identify`.

    Attributes
    ----------
    model : StateSpace
        Real continuous-time model in real modal (block-diagonal) form, all
        poles kept (physical and residual), in the orientation of the data.
    singular_values : ndarray (q n_out',)
        Singular values of the projected data matrix (order-selection aid).
    poles : Poles
        Every pole (pair) of ``model`` with its label.
    modal : ModalParameters
        Modal parameters of the poles labelled ``"physical"``.
    band_hz : (2,) analysed band [Hz].
    order : int
        Order (state dimension) of the subspace model, as set or chosen.
        After the modal refit the model holds more states (residual poles):
        ``model.A.shape[0]``.
    fit_deviation : ndarray (n_out, n_in)
        Square deviation of log10 ratios (paper Eq. 2.5) per channel, model vs
        data, over the lines in band.
    settings : dict
        The numerical settings used (block_rows, alpha_rad_s, thresholds...).
    order_selection : OrderSelection or None
        How the order was chosen when it was not given (:func:`select_order`).
    """

    model: StateSpace
    singular_values: np.ndarray
    poles: Poles
    modal: ModalParameters
    band_hz: tuple[float, float]
    order: int
    fit_deviation: np.ndarray
    settings: dict = field(default_factory=dict)
    order_selection: object | None = None  # OrderSelection (identification._order)

    @property
    def quantity(self) -> str:
        return self.model.quantity

    @property
    def fit_deviation_total(self) -> float:
        """Square deviation over all channels and lines in band."""
        return float(np.mean(self.fit_deviation))

    def frf(self, freq_hz) -> np.ndarray:
        """Model FRF at any frequencies [Hz] -> (n_f, n_out, n_in)."""
        return self.model.frf(freq_hz)

    def to_arrays(self) -> tuple[dict[str, np.ndarray], dict]:
        """Plain arrays and scalar attributes for storage (e.g. ``write_analysis``).

        Returns
        -------
        arrays : dict of ndarray
        attrs : dict of str/int/float (JSON-serializable)
        """
        arrays = {
            "A": np.asarray(self.model.A),
            "B": np.asarray(self.model.B),
            "C": np.asarray(self.model.C),
            "D": np.asarray(self.model.D),
            "singular_values": np.asarray(self.singular_values),
            "pole_eigenvalues_rad_s": np.asarray(self.poles.eigenvalues),
            "pole_labels": np.array(self.poles.labels, dtype="S16"),
            "pole_contribution": np.asarray(self.poles.contribution),
            "pole_importance": np.asarray(self.poles.importance),
            "mode_eigenvalues_rad_s": np.asarray(self.modal.eigenvalues),
            "mode_shapes": np.asarray(self.modal.shapes),
            "mode_participation": np.asarray(self.modal.participation),
            "fit_deviation": np.asarray(self.fit_deviation),
        }
        attrs = {
            "format": "frfcal.identification/1",
            "quantity": self.model.quantity,
            "order": int(self.order),
            "band_lo_hz": float(self.band_hz[0]),
            "band_hi_hz": float(self.band_hz[1]),
            "settings_json": json.dumps(self.settings),
        }
        if self.order_selection is not None:
            attrs["order_selection_json"] = json.dumps(self.order_selection.to_dict())
        return arrays, attrs

    @classmethod
    def from_arrays(cls, arrays: dict, attrs: dict) -> Identification:
        """Inverse of :meth:`to_arrays`."""
        try:
            fmt = attrs.get("format", "")
            if isinstance(fmt, bytes):
                fmt = fmt.decode()
            if not str(fmt).startswith("frfcal.identification/"):
                raise IdentificationError(f"identification record has format {fmt!r}, expected frfcal.identification/1")
            quantity = attrs["quantity"]
            quantity = quantity.decode() if isinstance(quantity, bytes) else str(quantity)
            model = StateSpace(
                np.asarray(arrays["A"]),
                np.asarray(arrays["B"]),
                np.asarray(arrays["C"]),
                np.asarray(arrays["D"]),
                quantity,
            )
            labels = tuple(
                s.decode() if isinstance(s, bytes) else str(s) for s in np.asarray(arrays["pole_labels"]).tolist()
            )
            poles = Poles(
                np.asarray(arrays["pole_eigenvalues_rad_s"]),
                labels,
                np.asarray(arrays["pole_contribution"]),
                np.asarray(arrays["pole_importance"]),
            )
            modal = ModalParameters(
                np.asarray(arrays["mode_eigenvalues_rad_s"]),
                np.asarray(arrays["mode_shapes"]),
                np.asarray(arrays["mode_participation"]),
            )
            settings = attrs.get("settings_json", "{}")
            settings = json.loads(settings.decode() if isinstance(settings, bytes) else settings)
            selection = attrs.get("order_selection_json")
            if selection is not None:
                from ._order import OrderSelection

                selection = json.loads(selection.decode() if isinstance(selection, bytes) else selection)
                selection = OrderSelection.from_dict(selection)
            return cls(
                model=model,
                singular_values=np.asarray(arrays["singular_values"]),
                poles=poles,
                modal=modal,
                band_hz=(float(attrs["band_lo_hz"]), float(attrs["band_hi_hz"])),
                order=int(attrs["order"]),
                fit_deviation=np.asarray(arrays["fit_deviation"]),
                settings=settings,
                order_selection=selection,
            )
        except KeyError as exc:
            raise IdentificationError(f"identification record lacks field {exc.args[0]!r}") from None


@dataclass(frozen=True)
class _Data:
    """Validated data restricted to the band, possibly transposed (dual)."""

    freq_hz: np.ndarray  # (n_f,)
    omega: np.ndarray  # rad/s
    H: np.ndarray  # (n_f, p, m) in identification orientation
    W: np.ndarray  # (n_f, p, m) weights 1/sigma
    out_scale: np.ndarray  # (p,) scale of each output for the subspace step
    band_hz: tuple[float, float]  # effective band: requested band clipped to the valid lines
    dual: bool
    alpha: float
    quantity: str
    requested_band_hz: tuple[float, float] | None  # as given (None: default = data range)


def prepare_data(freq_hz, H, *, band_hz, weights, valid, quantity) -> _Data:
    f = frequency_grid(freq_hz)
    Ha = np.asarray(H)
    if Ha.ndim != 3:
        raise IdentificationError(f"H must be (n_freq, n_out, n_in), got shape {Ha.shape}")
    if Ha.shape[0] != f.size:
        raise IdentificationError(f"H has {Ha.shape[0]} lines but freq_hz has {f.size}")
    Ha = Ha.astype(complex)
    if quantity not in QUANTITIES:
        raise IdentificationError(f"quantity must be one of {QUANTITIES}, got {quantity!r}")
    keep = np.ones(f.size, dtype=bool)
    if valid is not None:
        v = np.asarray(valid, dtype=bool)
        if v.shape != f.shape:
            raise IdentificationError(f"valid must be ({f.size},) booleans, got shape {v.shape}")
        keep &= v
    if not keep.any():
        raise IdentificationError("no valid line: `valid` is False everywhere")
    data_lo, data_hi = float(f[keep].min()), float(f[keep].max())
    if band_hz is None:
        requested = None
        band = (data_lo, data_hi)
    else:
        b = np.asarray(band_hz, dtype=float).reshape(-1)
        if b.size != 2 or not np.all(np.isfinite(b)) or not (0 <= b[0] < b[1]):
            raise IdentificationError(f"band_hz must be (lo, hi) with 0 <= lo < hi, got {band_hz!r}")
        requested = (float(b[0]), float(b[1]))
        # never analyse (nor label poles as physical) beyond the measured lines
        band = (max(requested[0], data_lo), min(requested[1], data_hi))
        if band[0] >= band[1]:
            raise IdentificationError(
                f"band_hz {requested[0]:g}-{requested[1]:g} Hz does not overlap the valid data "
                f"({data_lo:g}-{data_hi:g} Hz)"
            )
        keep &= (f >= band[0]) & (f <= band[1])
    bad = ~np.all(np.isfinite(Ha.reshape(f.size, -1)), axis=1)
    if np.any(bad & keep):
        k = int(np.flatnonzero(bad & keep)[0])
        raise IdentificationError(f"H holds NaN/Inf at line {k} ({f[k]:g} Hz); mark it invalid with `valid`")
    if keep.sum() < 2:
        raise IdentificationError(f"fewer than 2 valid lines in band {band} Hz")
    n_f, p, m = Ha.shape
    if weights is None:
        rms = np.sqrt(np.mean(np.abs(Ha[keep]) ** 2, axis=(0, 2)))
        if np.any(rms == 0):
            raise IdentificationError(f"output channel {int(np.flatnonzero(rms == 0)[0])} is identically zero in band")
        W = np.broadcast_to((1.0 / rms)[None, :, None], Ha.shape)
    else:
        w = np.asarray(weights, dtype=float)
        if w.shape == (p,):
            if np.any(~np.isfinite(w)) or np.any(w <= 0):
                raise IdentificationError("weights (per-output noise level) must be finite and > 0")
            W = np.broadcast_to((1.0 / w)[None, :, None], Ha.shape)
        elif w.shape == Ha.shape:
            if np.any(~np.isfinite(w[keep])) or np.any(w[keep] <= 0):
                raise IdentificationError("weights (per-line standard errors) must be finite and > 0 in band")
            W = 1.0 / np.where(w > 0, w, 1.0)
        else:
            raise IdentificationError(
                f"weights must be ({p},) per-output noise levels or {Ha.shape} standard errors, got {w.shape}"
            )
    fk = f[keep]
    Hk = Ha[keep]
    Wk = np.array(W[keep], dtype=float)
    dual = m > p
    if dual:  # identify the transposed system: the data matrices grow with n_in
        Hk = Hk.transpose(0, 2, 1)
        Wk = Wk.transpose(0, 2, 1)
    out_scale = np.sqrt(np.mean(Wk**2, axis=(0, 2)))
    omega = 2 * np.pi * fk
    alpha = bilinear_alpha(2 * np.pi * band[0], 2 * np.pi * band[1])
    return _Data(fk, omega, np.ascontiguousarray(Hk), Wk, out_scale, band, dual, alpha, quantity, requested)


def default_block_rows(order: int, n_out: int) -> int:
    """Default number of block rows ``q``.

    ``q n_out >= 2 n``, ``q >= n/n_out + 2`` and ``q >= min(n, 16)``: on
    lightly damped measured data with few outputs a taller data matrix
    averages the noise much better (free-beam data: q = 4 misplaces a mode by
    0.3 Hz, q = 16 by 0.05 Hz).
    """
    n, p = int(order), int(n_out)
    return int(max(int(np.ceil(2 * n / p)), int(np.ceil(n / p)) + 2, min(n, 16)))


def choose_block_rows(data: _Data, order: int, block_rows: int | None) -> int:
    """``block_rows`` or the default, capped by the number of lines; checked against the order."""
    nf, p, m = data.H.shape
    if block_rows is None:
        q = default_block_rows(order, p)
        q_max = (2 * nf * m) // (m + p)  # the QR needs at least as many rows as columns
        q = max(min(q, q_max), int(order) // p + 1)
    else:
        q = int(block_rows)
    if q * p <= order:
        raise IdentificationError(
            f"block_rows={q} too small for order {order} with {p} outputs: need block_rows * {p} > {order}"
        )
    return q


def data_basis(data: _Data, block_rows: int):
    z = unit_circle(data.omega, data.alpha)
    Hs = data.H * data.out_scale[None, :, None]
    p, m = data.H.shape[1:]
    if 2 * data.H.shape[0] * m < block_rows * (m + p):
        raise IdentificationError(
            f"too few lines ({data.H.shape[0]}) for block_rows={block_rows}: need "
            f"2 n_f n_in >= q (n_in + n_out); lower the order or widen the band"
        )
    return subspace_basis(z, Hs, block_rows)


def _fit(data: _Data, basis, sv, order: int, *, enforce_stability: bool, refine: int):
    """Model of one order from the shared basis, in identification orientation."""
    p = data.H.shape[1]
    n = int(order)
    Ad, Cd = realize(basis, sv, n, p)
    eye = np.eye(n)
    try:
        Pi = np.linalg.inv(Ad + eye)
    except np.linalg.LinAlgError:
        raise IdentificationError(f"order {n}: identified pole at z = -1 (infinite frequency)") from None
    A = data.alpha * (Ad - eye) @ Pi
    C = (Cd @ Pi) / data.out_scale[:, None]
    Am, _, Cm, blocks = real_modal_form(A, None, C)
    was_unstable = np.zeros(len(blocks), dtype=bool)
    for i, blk in enumerate(blocks):
        if Am[blk.start, blk.start] > 0:
            was_unstable[i] = True
            if enforce_stability:  # reflect into the left half plane, keep the frequency
                for j in range(blk.start, blk.stop):
                    Am[j, j] = -Am[j, j]
    B, D = fit_bd(data.omega, data.H, data.W, Am, Cm)
    for _ in range(int(refine)):
        Cm, D = fit_cd(data.omega, data.H, data.W, Am, B)
        B, D = fit_bd(data.omega, data.H, data.W, Am, Cm)
    return Am, B, Cm, D, blocks, was_unstable


def block_poles(A: np.ndarray, blocks) -> np.ndarray:
    """One eigenvalue (Im >= 0) per block of a real modal-form ``A``."""
    lam = np.empty(len(blocks), dtype=complex)
    for i, b in enumerate(blocks):
        if b.stop - b.start == 1:
            lam[i] = A[b.start, b.start]
        else:
            s, w = A[b.start, b.start], A[b.start, b.start + 1]
            lam[i] = complex(s, abs(w))
    return lam


def block_modal(A, B, C, blocks):
    """Per block: eigenvalue (Im>=0), shape ``C x`` (p,), participation ``y B`` (m,)."""
    shapes, parts = [], []
    for b in blocks:
        Ab = A[b, b]
        lam, X = np.linalg.eig(Ab)
        i = int(np.argmax(lam.imag))
        Y = np.linalg.inv(X)
        shapes.append(C[:, b] @ X[:, i])
        parts.append(Y[i, :] @ B[b, :])
    return np.array(shapes).T, np.array(parts)


def contributions(data: _Data, A, B, C, blocks) -> np.ndarray:
    """Largest weighted ratio, over the lines, of each block's own FRF term to the data."""
    ref = np.linalg.norm((data.W * data.H).reshape(data.H.shape[0], -1), axis=1)
    ref = np.where(ref > 0, ref, np.inf)
    s = 1j * data.omega
    out = np.empty(len(blocks))
    for i, b in enumerate(blocks):
        lam, X = np.linalg.eig(A[b, b])
        R = np.einsum("pr,rm->rpm", C[:, b] @ X, np.linalg.solve(X, B[b, :].astype(complex)))
        Hb = np.einsum("rpm,fr->fpm", R, 1.0 / (s[:, None] - lam[None, :]))
        out[i] = np.max(np.linalg.norm((data.W * Hb).reshape(Hb.shape[0], -1), axis=1) / ref)
    return out


#: Below this many lines :func:`identify` runs with one BLAS thread (:func:`_one_blas_thread`).
ONE_THREAD_BELOW_LINES = 10_000


def _one_blas_thread(fn):
    """Run ``fn(freq_hz, ...)`` with BLAS limited to one thread when it has fewer than
    :data:`ONE_THREAD_BELOW_LINES` lines (threadpoolctl; unlimited without it).

    The identification's products are skinny (lines x a state of 10-100) and many. On stepped-sine data
    (hundreds to a few thousand lines) OpenBLAS's threads cost more than they give; on long FFT data
    (tens of thousands of lines) they pay (docs/identification.md, "Threads").
    """
    import functools

    @functools.wraps(fn)
    def limited(freq_hz, *args, **kwargs):
        try:
            from threadpoolctl import threadpool_limits
        except ImportError:
            return fn(freq_hz, *args, **kwargs)
        if np.size(freq_hz) >= ONE_THREAD_BELOW_LINES:
            return fn(freq_hz, *args, **kwargs)
        with threadpool_limits(limits=1, user_api="blas"):
            return fn(freq_hz, *args, **kwargs)

    return limited


@_one_blas_thread
def identify(
    freq_hz,
    H,
    order: int | None = None,
    *,
    band_hz=None,
    weights=None,
    quantity: str = "accelerance",
    valid=None,
    block_rows: int | None = None,
    enforce_stability: bool = True,
    zeta_max: float = 0.2,
    min_contribution: float = 0.05,
    min_importance: float = 1.0,
    refine: int = 1,
    modal_refit: bool = False,
) -> Identification:
    """Frequency-domain subspace identification of a continuous-time model from FRFs.

    McKelvey-Akcay-Ljung (1996) subspace algorithm on an arbitrary frequency
    grid, in continuous time through the exact scaled bilinear map
    (``alpha = 2/T = sqrt(omega_lo omega_hi)``); ``D`` is always estimated;
    ``B, D`` then ``C, D`` then ``B, D`` are refined by weighted linear least
    squares on the data. Unstable poles are reflected into the left half plane
    (when ``enforce_stability``) and labelled ``"unstable"``; every pole stays
    in the model, only those labelled ``"physical"`` enter :attr:`Identification.modal`.

    Parameters
    ----------
    freq_hz : array_like (n_f,)
        Frequencies [Hz], any (non-uniform) grid.
    H : array_like, complex (n_f, n_out, n_in)
        Measured FRFs, e^{+i omega t} convention.
    order : int, optional
        State dimension ``n`` (two per mode; e.g. 44 = 22 pole pairs). None:
        automatic, the lowest order whose physical poles are the stable poles
        of the stabilization diagram (:func:`select_order` with its default
        criteria; the record is :attr:`Identification.order_selection`).
    band_hz : (lo, hi), optional
        Analysed band [Hz]; lines outside are ignored and poles outside are
        labelled ``"out-of-band"``. The band is clipped to the range of the
        valid lines (never beyond the data); the effective band is
        :attr:`Identification.band_hz`, the request
        ``settings["requested_band_hz"]``. Default: the data range.
    weights : array_like, optional
        ``(n_out,)`` noise standard deviation per output (FRF units) or
        ``(n_f, n_out, n_in)`` standard error per line. Residuals are divided
        by it. Default: each output scaled by its RMS level in band.
    quantity : {"accelerance", "mobility", "receptance"}
        FRF quantity, carried by the model.
    valid : array_like of bool (n_f,), optional
        Lines to use (e.g. a run file's ``valid`` mask).
    block_rows : int, optional
        Number of block rows ``q`` of the data matrices (default
        :func:`default_block_rows`).
    enforce_stability : bool
        Reflect unstable poles into the left half plane before the
        least-squares refinement.
    zeta_max : float
        Poles with larger damping ratio are labelled ``"overdamped"``.
    min_contribution : float
        Poles whose own FRF term never reaches this fraction of the data
        (weighted Frobenius norm over channels, per line) are ``"negligible"``.
    min_importance : float
        Poles whose removal (with ``B, D`` refitted) raises the weighted
        residual sum of squares by less than this factor of itself are
        ``"negligible"``: the data do not need them (noise modes, split poles).
    refine : int
        Rounds of alternating ``C, D`` / ``B, D`` least-squares refinement.
    modal_refit : bool
        Refit the model on its physical poles (refined) and fixed residual
        poles outside the band that stand for the out-of-band modes (off by
        default here; ``frfcal identify`` and the campaign use it)
        (:mod:`identification._refit`); kept only where it lowers the
        weighted residual. The record is ``settings["modal_refit"]``; the
        subspace order is ``settings["subspace_order"]``.

    Returns
    -------
    Identification

    Raises
    ------
    IdentificationError
        On inconsistent shapes, NaNs in band, too few lines for the order, etc.
    """
    if order is None:
        from ._order import select_order

        result = select_order(
            freq_hz, H, band_hz=band_hz, weights=weights, quantity=quantity, valid=valid, block_rows=block_rows,
            enforce_stability=enforce_stability, zeta_max=zeta_max, min_contribution=min_contribution,
            min_importance=min_importance, refine=refine,
        )
        if not modal_refit:
            return result
        data = prepare_data(freq_hz, H, band_hz=band_hz, weights=weights, valid=valid, quantity=quantity)
    else:
        n = int(order)
        if n < 1 or n != order:
            raise IdentificationError(f"order must be a positive integer, got {order!r}")
        data = prepare_data(freq_hz, H, band_hz=band_hz, weights=weights, valid=valid, quantity=quantity)
        q = choose_block_rows(data, n, block_rows)
        basis, sv = data_basis(data, q)
        result = identification_of_order(data, basis, sv, n, q, enforce_stability, zeta_max, min_contribution,
                                          min_importance, refine)
        if not modal_refit:
            return result
    return refitted(data, result, enforce_stability, zeta_max, min_contribution, min_importance, refine)


def refitted(data: _Data, result: Identification, enforce_stability, zeta_max, min_contribution, min_importance,
             refine) -> Identification:
    """``result`` after the modal refit (:func:`identification._refit.modal_refit`) when that fits better."""
    from dataclasses import replace

    from ._refit import modal_refit

    settings = dict(result.settings, subspace_order=int(result.order))
    out = modal_refit(data, result.poles.eigenvalues[result.poles.physical], zeta_max)
    if isinstance(out, str):
        return replace(result, settings=dict(settings, modal_refit={"used": False, "reason": out}))
    A, B, C, D, blocks, phys, info = out
    old = result.model.transposed() if data.dual else result.model
    ssr_old = weighted_ssr(data, old.A, old.B, old.C, old.D)
    ssr_new = weighted_ssr(data, A, B, C, D)
    info = dict(info, ssr_subspace=ssr_old, ssr=ssr_new, used=bool(ssr_new < ssr_old))
    if not info["used"]:
        return replace(result, settings=dict(settings, modal_refit=info))
    labels = tuple("physical" if k else "out-of-band" for k in phys)
    new = _assemble(data, result.singular_values, A.shape[0], int(result.settings["block_rows"]),
                    (A, B, C, D, blocks, np.zeros(len(blocks), bool)), enforce_stability, zeta_max,
                    min_contribution, min_importance, refine, labels=labels)
    return replace(new, order=result.order, order_selection=result.order_selection,
                   settings=dict(settings, **new.settings, modal_refit=info))


def identification_of_order(data, basis, sv, n, q, enforce_stability, zeta_max, min_contribution, min_importance, refine):
    A, B, C, D, blocks, was_unstable = _fit(data, basis, sv, n, enforce_stability=enforce_stability, refine=refine)
    return _assemble(data, sv, n, q, (A, B, C, D, blocks, was_unstable), enforce_stability, zeta_max,
                     min_contribution, min_importance, refine)


def weighted_ssr(data: _Data, A, B, C, D) -> float:
    """Weighted residual sum of squares of a model (identification orientation) on the data's lines."""
    H = StateSpace(A, B, C, D, data.quantity).frf(data.freq_hz)
    return float(np.sum(np.abs(data.W * (H - data.H)) ** 2))


def local_pole_fit(data: _Data, A, B, C, D, blocks, i: int, window_hz, zeta_max: float = 0.2):
    """The eigenvalue of block ``i`` that best explains, on the lines within ``window_hz`` (lo, hi), what the
    rest of the model leaves there.

    On those lines the residual ``R = H - (H_model - H_i)`` of every pair is
    fitted by ``c / (s - lam) + c' / (s - conj lam) + d0 + d1 s`` (free complex
    residues per pair, a local background) for ``lam`` on a grid of frequency
    (steps of a quarter half-power bandwidth, at least 1e-4 relative) x
    damping (2e-4 .. min(zeta_max, 0.05), 25 log steps), then polished
    (Nelder-Mead). Pairs are weighted by their mean weight there.

    Returns
    -------
    (lam, ratio, bare) : the eigenvalue (Im > 0), the local weighted SSR with it
        over the SSR of the background alone (``bare``): the share of the local
        residual the pole leaves (small: a resonance is there).
    """
    from scipy.optimize import minimize

    lam_all, X = np.linalg.eig(A)
    l0 = block_poles(A, blocks)[i]
    f0 = abs(l0) / (2 * np.pi)
    w_lo, w_hi = float(window_hz[0]), float(window_hz[1])
    loc = (data.freq_hz >= w_lo) & (data.freq_hz <= w_hi)
    if loc.sum() < 8:
        return l0, 1.0, 0.0
    Xi = np.linalg.inv(X)
    own = np.abs(Xi[:, blocks[i]]).sum(axis=1) > 1e-9 * np.abs(Xi).max()
    s = 1j * data.omega[loc]
    Hm = StateSpace(A, B, C, D, data.quantity).frf(data.freq_hz[loc])
    g = 1.0 / (s[:, None] - lam_all[own][None, :])
    Hi = np.einsum("pr,fr,rm->fpm", C @ X[:, own], g, Xi[own] @ B)
    w = data.W[loc].mean(axis=0)
    Y = ((data.H[loc] - (Hm - Hi)) * w[None]).reshape(loc.sum(), -1)

    def cost(lam):
        G = np.stack([1 / (s - lam), 1 / (s - np.conj(lam)), np.ones_like(s), s], axis=1)
        Q, _ = np.linalg.qr(G)
        return float(np.sum(np.abs(Y - Q @ (Q.conj().T @ Y)) ** 2))

    G0 = np.stack([np.ones_like(s), s], axis=1)
    Q0, _ = np.linalg.qr(G0)
    bare = float(np.sum(np.abs(Y - Q0 @ (Q0.conj().T @ Y)) ** 2))
    zs = np.geomspace(2e-4, min(zeta_max, 0.05), 25)
    yy = float(np.sum(np.abs(Y) ** 2))

    def lam_of(fz, z):
        wn = 2 * np.pi * fz
        return complex(-z * wn, wn * np.sqrt(max(1 - z * z, 0.0)))

    best = (np.inf, None)
    for z in zs:  # frequency steps of a quarter half-power bandwidth at this damping, batched
        fr = np.arange(w_lo, w_hi, max(z / 2, 1e-4) * f0)
        wn = 2 * np.pi * fr
        lt = -z * wn + 1j * wn * np.sqrt(1 - z * z)
        G = np.empty((fr.size, s.size, 4), complex)
        G[:, :, 0] = 1 / (s[None, :] - lt[:, None])
        G[:, :, 1] = 1 / (s[None, :] - np.conj(lt)[:, None])
        G[:, :, 2] = 1.0
        G[:, :, 3] = s[None, :]
        Q = np.linalg.qr(G)[0]
        c = yy - np.sum(np.abs(np.einsum("kfj,fp->kjp", Q.conj(), Y)) ** 2, axis=(1, 2))
        j = int(np.argmin(c))
        if c[j] < best[0]:
            best = (float(c[j]), (fr[j], z))
    fz, z = best[1]
    res = minimize(lambda x: cost(lam_of(x[0] * f0, np.exp(x[1]))), [fz / f0, np.log(z)], method="Nelder-Mead",
                   options={"xatol": 1e-7, "fatol": 1e-12 * max(bare, 1e-300), "maxiter": 400})
    fz, z = float(np.clip(res.x[0] * f0, w_lo, w_hi)), float(np.exp(res.x[1]))
    lam = lam_of(fz, z)
    c = cost(lam)
    return lam, (c / bare if bare > 0 else 1.0), bare


def with_pole(data: _Data, A, B, C, D, blocks, i: int, lam, refine: int):
    """The model with block ``i``'s eigenvalue set to ``lam`` (Im > 0), ``B, D`` / ``C, D`` refitted."""
    A = A.copy()
    b = blocks[i]
    if b.stop - b.start != 2:
        raise IdentificationError("only a complex pole pair can be moved")
    sgn = np.sign(A[b.start, b.start + 1]) or 1.0
    A[b.start, b.start] = A[b.start + 1, b.start + 1] = lam.real
    A[b.start, b.start + 1] = sgn * abs(lam.imag)
    A[b.start + 1, b.start] = -sgn * abs(lam.imag)
    B, D = fit_bd(data.omega, data.H, data.W, A, C)
    for _ in range(max(int(refine), 1)):
        C, D = fit_cd(data.omega, data.H, data.W, A, B)
        B, D = fit_bd(data.omega, data.H, data.W, A, C)
    return A, B, C, D


def _assemble(data, sv, n, q, fitted, enforce_stability, zeta_max, min_contribution, min_importance, refine,
              confirmed=(), labels=None):
    """The Identification of fitted matrices: poles, labels, modal parameters, fit, settings.

    ``confirmed`` : block indices whose pole a local fit confirmed (:func:`local_pole_fit`); they are
    labelled "physical" unless unstable, real, overdamped, out of band or below ``min_contribution``
    (the global importance, measured against the residual of the whole band, is not asked of them).
    ``labels`` : the labels of the blocks when already decided (the modal refit); none are computed then.
    """
    A, B, C, D, blocks, was_unstable = fitted
    lam = block_poles(A, blocks)
    contrib = contributions(data, A, B, C, blocks)
    sep = _separable(data.W)
    # the same weights as the B, D fit: per output when they factor, else per line
    imp = importance(data.omega, data.H, sep[0] if sep is not None else data.W, A, C, blocks)
    if labels is None:
        labels = label_poles(lam, contrib, imp, was_unstable, data.band_hz, zeta_max, min_contribution,
                             min_importance)
    if confirmed:
        labels = tuple("physical" if (k in confirmed and lab == "negligible" and contrib[k] >= min_contribution)
                       else lab for k, lab in enumerate(labels))
    model = StateSpace(A, B, C, D, data.quantity)
    H_data = data.H
    if data.dual:
        model = model.transposed()
        H_data = H_data.transpose(0, 2, 1)
    phys = [i for i, s in enumerate(labels) if s == "physical"]
    shapes, parts = block_modal(model.A, model.B, model.C, [blocks[i] for i in phys])
    if not phys:
        shapes = np.zeros((model.n_out, 0), complex)
        parts = np.zeros((0, model.n_in), complex)
    shapes, parts = normalize_shapes(shapes, parts)
    modal = ModalParameters(lam[phys], shapes, parts)
    H_model = model.frf(data.freq_hz)
    with np.errstate(divide="ignore", invalid="ignore"):
        fit = channel_deviation(H_model, H_data) if np.all(H_data != 0) else np.full(H_data.shape[1:], np.nan)
    settings = {
        "block_rows": int(q),
        "alpha_rad_s": float(data.alpha),
        "dual": bool(data.dual),
        "enforce_stability": bool(enforce_stability),
        "zeta_max": float(zeta_max),
        "min_contribution": float(min_contribution),
        "min_importance": float(min_importance),
        "refine": int(refine),
        "n_lines": int(data.freq_hz.size),
        "n_reflected": int(np.sum(was_unstable)) if enforce_stability else 0,
        "requested_band_hz": None if data.requested_band_hz is None else list(data.requested_band_hz),
        "band_clipped": data.requested_band_hz is not None and tuple(data.requested_band_hz) != data.band_hz,
    }
    if confirmed:
        settings["locally_confirmed_hz"] = [float(abs(lam[k]) / (2 * np.pi)) for k in sorted(confirmed)]
    return Identification(
        model=model,
        singular_values=sv,
        poles=Poles(lam, labels, contrib, imp),
        modal=modal,
        band_hz=data.band_hz,
        order=n,
        fit_deviation=fit,
        settings=settings,
    )


__all__ = ["Identification", "identify", "default_block_rows", "LABELS"]
