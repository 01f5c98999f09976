"""The simulated lab: a driver that answers with the physics of a linear plant.

The structure (a :class:`~acquisition.ModalPlant`) is coupled to a
voltage-driven electrodynamic shaker (armature mass, suspension, back-EMF), so
the force it delivers drops at the structure's resonances as on a real rig.
The coupled system is linear; it is diagonalized once, and the response to a
sinusoidal drive is evaluated in closed form (steady-state part plus the
exactly decaying transient of every complex mode), vectorized over samples:
no time-stepping error and much faster than real time. Sensors add white
noise, ADC quantization and clipping (overload). The drive is treated as
ideally reconstructed (continuous sinusoid, phase-continuous on changes).

Faults can be injected (a driver fault at a given clock time, an overload
spike on a channel) to exercise the controller's safety logic.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from acquisition._demod import fit_harmonics
from acquisition._driver import ChannelSpec, DriverError, DriverInfo, PhasorBlock, SampleBlock
from acquisition._plant import ModalPlant


def _exp_grid(p: np.ndarray, m: int, rate: float, chunk: int = 64) -> np.ndarray:
    """``exp(p_s k / rate)`` for k < m, ``(n_s, m)``, as products of two short exponential tables."""
    n_j = -(-m // chunk)
    lo = np.exp(np.outer(p, np.arange(chunk) / rate))
    hi = np.exp(np.outer(p, np.arange(n_j) * chunk / rate))
    return (hi[:, :, None] * lo[:, None, :]).reshape(p.size, -1)[:, :m]


class SimLabError(ValueError):
    """Bad simulated-lab set-up (channel mapping, parameters)."""


@dataclass(frozen=True)
class ShakerModel:
    """A voltage-driven electrodynamic shaker attached through a stiff stinger.

    Force on the structure ``f = G*Bl/R * V - (Bl^2/R + c_s) v - m_a a - k_s x``
    with ``v, a, x`` the drive-point velocity, acceleration and displacement.
    The back-EMF term ``Bl^2/R`` makes the force drop at resonances.
    """

    force_constant_n_per_a: float = 10.0
    coil_resistance_ohm: float = 2.0
    amplifier_gain_v_per_v: float = 1.0
    armature_mass_kg: float = 0.02
    suspension_stiffness_n_per_m: float = 2000.0
    suspension_damping_ns_per_m: float = 1.0

    @property
    def gain_n_per_v(self) -> float:
        return self.amplifier_gain_v_per_v * self.force_constant_n_per_a / self.coil_resistance_ohm

    @property
    def electrical_damping_ns_per_m(self) -> float:
        return self.force_constant_n_per_a**2 / self.coil_resistance_ohm + self.suspension_damping_ns_per_m


@dataclass(frozen=True)
class CubicSpring:
    """A hardening (beta > 0) or softening cubic spring on one mode of a modal plant.

    The modal equation gains ``beta * w_r^2 * q^3`` (q the mass-normalized modal
    coordinate, m*sqrt(kg); ``beta`` in 1/(m^2 kg)). The lab applies it by
    equivalent linearization, updated every block from the present modal
    amplitude a: ``w_eq^2 = w_r^2 (1 + 3/4 beta a^2)``. The resonance then shifts with
    force level, which a linearity check detects. Harmonics are not generated.
    """

    mode: int
    beta_per_m2kg: float


@dataclass(frozen=True)
class Fault:
    """A fault to inject.

    kind : {"driver_error", "overload"}
        ``driver_error``: every ``read_block`` reaching ``at_s`` raises :class:`DriverError`;
        ``overload``: a spike of ``3 x range`` on channel ``channel`` at ``at_s``.
    at_s : float
        Driver clock time, s.
    """

    kind: str
    at_s: float
    channel: int = 0


class SimulatedLab:
    """A driver (see :class:`acquisition.Driver`) simulating a shaker test of ``plant``.

    Parameters
    ----------
    plant : ModalPlant
    drive_index : int
        Plant input the shaker drives.
    shaker : ShakerModel or None
        None for an ideal force source of ``gain_n_per_v``.
    gain_n_per_v : float
        Force per volt of the ideal source (used when ``shaker`` is None).
    noise_rms : float or (n_channels,) float
        White sensor noise, engineering units rms, per channel.
    adc_bits : int
        ADC resolution over each channel's ``±range_v``.
    faults : sequence of Fault
    seed : int
    kind : {"sampling", "demodulating"}
        Return raw :class:`SampleBlock` s (a DAQ) or :class:`PhasorBlock` s (lock-in amplifiers).
    n_harmonics : int
        Harmonics reported in demodulating mode.
    amplitude_ramp_s : float
        Amplitude changes ramp linearly over this time (the response to the ramp is exact too).
    nonlinearity : CubicSpring or None
        Optional amplitude-dependent mode (equivalent linearization per block).
    """

    def __init__(
        self,
        plant: ModalPlant,
        *,
        drive_index: int = 0,
        shaker: ShakerModel | None = ShakerModel(),
        gain_n_per_v: float = 5.0,
        noise_rms=1e-4,
        adc_bits: int = 24,
        faults: Sequence[Fault] = (),
        seed: int = 0,
        kind: str = "sampling",
        n_harmonics: int = 5,
        amplitude_ramp_s: float = 0.01,
        nonlinearity: "CubicSpring | None" = None,
    ):
        if not isinstance(plant, ModalPlant):
            raise SimLabError(f"plant must be a ModalPlant, got {type(plant).__name__}")
        if not 0 <= drive_index < plant.n_in:
            raise SimLabError(f"drive_index {drive_index} out of range for a plant with {plant.n_in} inputs")
        if kind not in ("sampling", "demodulating"):
            raise SimLabError(f"kind must be 'sampling' or 'demodulating', got {kind!r}")
        for f in faults:
            if f.kind not in ("driver_error", "overload"):
                raise SimLabError(f"unknown fault kind {f.kind!r}")
        self.plant = plant
        self.drive_index = drive_index
        self.shaker = shaker
        self.noise_rms = noise_rms
        self.adc_bits = int(adc_bits)
        self.faults = tuple(faults)
        self.kind = kind
        self.n_harmonics = n_harmonics
        self.amplitude_ramp_s = float(amplitude_ramp_s)
        self._rng = np.random.default_rng(seed)
        if nonlinearity is not None:
            if plant._abcd is not None or not 0 <= nonlinearity.mode < plant.frequencies_hz.size:
                raise SimLabError(f"nonlinearity needs a modal plant and a mode index in range, got mode {nonlinearity.mode}")
            self._omega_eq = 2 * np.pi * plant.frequencies_hz[nonlinearity.mode]
        self.nonlinearity = nonlinearity
        if plant.has_feedthrough and plant.quantity == "mobility":
            raise SimLabError("a plant with rigid-body/higher-mode feedthrough must be accelerance or receptance "
                              "(the mobility feedthrough is a 90-degree phase shift, not a real gain)")
        self._ft_cache: tuple[float, np.ndarray] | None = None
        self._gain_ideal = gain_n_per_v
        if plant._abcd is not None and plant.drive_point_form() is not None:
            self._cdrive_physical = plant._cdrive_physical
        self._build_coupled(gain_n_per_v)
        self._configured = False
        self._n = 0  # samples elapsed on the virtual clock
        self._rate = None
        self._freq = 0.0
        self._amp = 0.0
        self._target = 0.0
        self._ramp_left = 0
        self._slope = 0.0
        self._phase = 0.0
        self._faulted = False
        #: (time_s, frequency_hz, amplitude_v) every time the drive changed, for inspection.
        self.drive_log: list[tuple[float, float, float]] = []
        self.closed = False

    # ----------------------------------------------------------- physics set-up
    def _physical(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
        """Real realization ``(A, B, C, D, C_drive)`` of the plant; C_drive maps states to drive-point displacement."""
        A, B, C, D = self.plant.state_space()
        A = np.array(A, dtype=float)
        if self.plant._abcd is None:  # modal plant: states [q, q']
            n = self.plant.frequencies_hz.size
            Cd = np.hstack([self.plant.shapes_in, np.zeros_like(self.plant.shapes_in)])
            if self.nonlinearity is not None:
                r = self.nonlinearity.mode
                A[n + r, r] = -self._omega_eq**2
        else:
            cd = self.plant.drive_point_form()
            Cd = None if cd is None else self._cdrive_physical
        return A, np.asarray(B, float), np.asarray(C, float), np.asarray(D, float), Cd

    def _build_coupled(self, gain_ideal: float) -> None:
        """Couple plant and shaker into one linear system driven by the voltage, and diagonalize it."""
        A, B, C, D, Cd = self._physical()
        k = self.drive_index
        b = B[:, k]
        sh = self.shaker
        if sh is None or Cd is None:
            g = gain_ideal if sh is None else sh.gain_n_per_v
            K = np.zeros(A.shape[0])
            den = 1.0
        else:
            g = sh.gain_n_per_v
            cd = Cd[k]
            # f = g V - c_e v - m_a a - k_s x with v = cd A x, a = cd A^2 x + cd A b f (cd b = 0)
            K = sh.electrical_damping_ns_per_m * cd @ A + sh.armature_mass_kg * cd @ A @ A + sh.suspension_stiffness_n_per_m * cd
            den = 1.0 + sh.armature_mass_kg * float(cd @ A @ b)
        Acl = A - np.outer(b, K) / den
        lam, W = np.linalg.eig(Acl)
        Winv = np.linalg.inv(W)
        # rows: plant outputs (responses) then the force at the drive point
        Cy = np.vstack([C - np.outer(D[:, k], K) / den, -K[None, :] / den]) @ W
        bw = Winv @ (b * g / den)
        # The coupled system is real: keep one pole of each conjugate pair and
        # double its output (real poles kept once), halving the work.
        tol = 1e-9 * np.abs(lam).max()
        real = np.abs(lam.imag) <= tol
        sel = (lam.imag > tol) | real
        weight = np.where(real, 1.0, 2.0)[sel]
        x = None
        if hasattr(self, "_Wsel"):  # rebuild: carry the physical state over
            x = ((self._Wsel * self._weight) @ self._w).real
        self._Wsel = W[:, sel]
        self._weight = weight
        self._Winv_sel = Winv[sel]
        self._p = lam[sel]
        self._b = bw[sel]
        self._C = Cy[:, sel] * weight[None, :]
        self._D = np.concatenate([D[:, k] * g / den, [g / den]]).real
        self._w = np.zeros(self._p.size, dtype=complex) if x is None else self._Winv_sel @ x
        self.gain_n_per_v = g / den

    def _update_nonlinearity(self) -> None:
        """Equivalent linearization of the cubic spring at the present modal amplitude (quasi-static)."""
        nl = self.nonlinearity
        n = self.plant.frequencies_hz.size
        x = ((self._Wsel * self._weight) @ self._w).real
        w_drive = 2 * np.pi * max(self._freq, 1e-9)
        a2 = x[nl.mode] ** 2 + (x[n + nl.mode] / w_drive) ** 2
        w0 = 2 * np.pi * self.plant.frequencies_hz[nl.mode]
        w_eq = w0 * np.sqrt(max(1.0 + 0.75 * nl.beta_per_m2kg * a2, 0.05))
        if abs(w_eq / self._omega_eq - 1) > 1e-7:
            self._omega_eq = w_eq
            self._build_coupled(self._gain_ideal)

    # -------------------------------------------------------------- protocol
    def configure(self, channels: Sequence[ChannelSpec], sample_rate_hz: float | None) -> DriverInfo:
        """Map channels to plant outputs: ``physical="sim/<k>"`` picks plant output k, ``"sim/force"``
        (or role ``"force"``) the drive-point force, ``"sim/drive"`` the drive voltage;
        response channels without an address take plant outputs in order."""
        if sample_rate_hz is None or sample_rate_hz <= 0:
            raise SimLabError(f"the simulated lab needs a positive sample_rate_hz, got {sample_rate_hz}")
        rows, next_out = [], 0
        for c in channels:
            phys = c.physical
            if phys in ("sim/force",) or (not phys and c.role == "force"):
                rows.append(self.plant.n_out)
            elif phys == "sim/drive" or (not phys and c.role == "monitor"):
                rows.append(-1)
            elif phys.startswith("sim/"):
                try:
                    k = int(phys[4:])
                except ValueError:
                    raise SimLabError(f"channel {c.name!r}: bad simulated address {phys!r}") from None
                if not 0 <= k < self.plant.n_out:
                    raise SimLabError(f"channel {c.name!r}: plant has outputs 0..{self.plant.n_out - 1}, got {phys!r}")
                rows.append(k)
            elif not phys:
                if next_out >= self.plant.n_out:
                    raise SimLabError(f"channel {c.name!r}: more response channels than plant outputs ({self.plant.n_out})")
                rows.append(next_out)
                next_out += 1
            else:
                raise SimLabError(f"channel {c.name!r}: address {phys!r} is not a simulated channel ('sim/<k>')")
            if phys.startswith("sim/") and phys[4:].isdigit():
                next_out = max(next_out, int(phys[4:]) + 1)
        self._rows = np.array(rows)
        self._channels = tuple(channels)
        noise = np.broadcast_to(np.asarray(self.noise_rms, dtype=float), (len(channels),))
        self._noise = noise.copy()
        self._sens = np.array([c.sensitivity for c in channels], dtype=float)
        self._range = np.array([c.range_v for c in channels], dtype=float)
        self._rate = float(sample_rate_hz)
        self._configured = True
        return DriverInfo(
            name="sim",
            kind=self.kind,
            sample_rate_hz=self._rate,
            devices=("simulated-lab",),
            details={
                "n_modes": int(np.sum(self.plant.poles.imag > 0)),
                "shaker": None if self.shaker is None else self.shaker.__dict__,
                "adc_bits": self.adc_bits,
            },
        )

    def time_s(self) -> float:
        return self._n / self._rate if self._rate else 0.0

    def set_drive(self, frequency_hz: float, amplitude_v: float) -> None:
        if self.closed:
            raise DriverError("simulated lab is closed")
        if not np.isfinite(frequency_hz) or frequency_hz <= 0 or frequency_hz >= 0.5 * (self._rate or np.inf):
            raise DriverError(f"drive frequency {frequency_hz} Hz outside (0, Nyquist)")
        if not np.isfinite(amplitude_v) or amplitude_v < 0:
            raise DriverError(f"drive amplitude must be finite and >= 0, got {amplitude_v}")
        self._freq = float(frequency_hz)
        self._start_ramp(float(amplitude_v), self.amplitude_ramp_s)
        self.drive_log.append((self.time_s(), self._freq, float(amplitude_v)))

    def _start_ramp(self, target: float, duration_s: float) -> None:
        n = int(round(duration_s * self._rate)) if self._rate else 0
        self._target = target
        if n <= 0 or target == self._amp:
            self._amp = target
            self._ramp_left = 0
            return
        self._ramp_left = n
        self._slope = (target - self._amp) / (n / self._rate)

    @property
    def drive_amplitude_v(self) -> float:
        """Present drive amplitude (peak V); the target once a ramp has finished."""
        return self._amp

    def _segment(self, m: int, slope: float) -> tuple[np.ndarray, np.ndarray]:
        """Exact response over ``m`` samples to ``(A0 + slope*t) cos(phase0 + w t)``."""
        rate = self._rate
        w = 2 * np.pi * self._freq
        tau = np.arange(m) / rate
        phase = self._phase + w * tau
        amp = self._amp + slope * tau
        p = self._p
        gp = 1.0 / (1j * w - p)
        gm = 1.0 / (-1j * w - p)
        hb = 0.5 * self._b

        def zp(a, ph):  # particular (forced) solution for a linearly ramped sinusoid
            return hb * (np.exp(1j * ph) * (a * gp - slope * gp**2) + np.exp(-1j * ph) * (a * gm - slope * gm**2))

        h0 = self._w - zp(self._amp, self._phase)
        S1 = self._C @ (hb * gp) + (self._C @ (hb * gm)).conj()
        S2 = self._C @ (hb * gp**2) + (self._C @ (hb * gm**2)).conj()
        c, sn = np.cos(phase), np.sin(phase)
        drive = amp * c
        basis = [drive, amp * sn]
        coef = [S1.real + self._D, -S1.imag]
        if slope:
            basis += [c, sn]
            coef += [-slope * S2.real, slope * S2.imag]
        y = np.stack(coef, axis=1) @ np.stack(basis)
        y += ((self._C * h0) @ _exp_grid(p, m, rate)).real
        t_end = m / rate
        ph_end = self._phase + w * t_end
        a_end = self._amp + slope * t_end
        self._w = zp(a_end, ph_end) + h0 * np.exp(p * t_end)
        self._phase = float(np.mod(ph_end, 2 * np.pi))
        self._amp = a_end
        self._n += m
        return y, drive

    def _advance(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Exact response over the next ``n`` samples: (n_rows, n) noise-free engineering units, drive (n,) V."""
        ys, ds = [], []
        while n > 0:
            if self._ramp_left > 0:
                m = min(n, self._ramp_left)
                y, d = self._segment(m, self._slope)
                self._ramp_left -= m
                if self._ramp_left == 0:
                    self._amp = self._target
            else:
                m = n
                y, d = self._segment(m, 0.0)
            ys.append(y)
            ds.append(d)
            n -= m
        if not ys:
            return np.zeros((self._C.shape[0], 0)), np.zeros(0)
        y = np.hstack(ys)
        if self.plant.has_feedthrough:
            # rigid-body and higher modes: a real gain at the drive frequency on the delivered force (last row)
            y[: self.plant.n_out] += self._feedthrough()[:, None] * y[self.plant.n_out][None, :]
        return y, np.concatenate(ds)

    def _feedthrough(self) -> np.ndarray:
        """(n_out,) real feedthrough of the plant at the present drive frequency from the driven input."""
        if self._ft_cache is None or self._ft_cache[0] != self._freq:
            h = self.plant.feedthrough(self._freq)[0, :, self.drive_index]
            self._ft_cache = (self._freq, h.real.copy())
        return self._ft_cache[1]

    def _sensor(self, y: np.ndarray, drive: np.ndarray, t0: float) -> tuple[np.ndarray, np.ndarray]:
        """Sensor chain: noise (EU), sensitivity to volts, clipping at the range (overload), ADC LSB."""
        rows = self._rows
        data = y[np.maximum(rows, 0)]
        if np.any(rows < 0):
            data[rows < 0] = drive
        if np.any(self._noise > 0):
            data += self._noise[:, None] * self._rng.standard_normal(data.shape, dtype=np.float32)
        for f in self.faults:
            if f.kind == "overload":
                k = int(round((f.at_s - t0) * self._rate))
                if 0 <= k < data.shape[1] and 0 <= f.channel < data.shape[0]:
                    data[f.channel, k] += 3 * self._range[f.channel] / self._sens[f.channel]
        lsb = 2 * self._range / 2**self.adc_bits
        # in ADC counts: volts / lsb = data * sens / lsb
        data *= (self._sens / lsb)[:, None]
        full = (self._range / lsb)[:, None]
        overload = np.max(np.abs(data), axis=1) > full[:, 0]
        np.clip(data, -full, full, out=data)
        np.rint(data, out=data)
        data *= (lsb / self._sens)[:, None]
        return data, overload

    def read_block(self, n_cycles: int) -> SampleBlock | PhasorBlock:
        if not self._configured:
            raise DriverError("simulated lab used before configure()")
        if self.closed:
            raise DriverError("simulated lab is closed")
        if self._freq <= 0:
            raise DriverError("read_block before set_drive")
        n = max(int(round(n_cycles * self._rate / self._freq)), 8)
        t0 = self.time_s()
        for f in self.faults:
            if f.kind == "driver_error" and (self._faulted or t0 + n / self._rate >= f.at_s):
                self._faulted = True
                # the real hardware would have kept running up to the fault
                if f.at_s > t0:
                    self._advance(int((f.at_s - t0) * self._rate))
                raise DriverError(f"simulated driver fault at t = {f.at_s:.3f} s")
        if self.nonlinearity is not None:
            self._update_nonlinearity()
        y, drive = self._advance(n)
        data, overload = self._sensor(y, drive, t0)
        if self.kind == "sampling":
            return SampleBlock(t0_s=t0, rate_hz=self._rate, samples=data, overload=overload, drive=drive)
        # lock-in style: demodulate internally, phases relative to the drive at t0
        h = fit_harmonics(data, self._rate, self._freq, self.n_harmonics)
        ref = fit_harmonics(drive[None, :], self._rate, self._freq, 1)[0, 0]
        rel = np.exp(-1j * np.angle(ref) * np.arange(1, self.n_harmonics + 1))
        return PhasorBlock(
            t0_s=t0, frequency_hz=self._freq, duration_s=n / self._rate, harmonics=h * rel[None, :], overload=overload
        )

    def ramp_down(self, duration_s: float = 0.5) -> None:
        """Ramp the drive amplitude linearly to zero over ``duration_s`` of virtual time."""
        if self._rate and self._freq > 0 and (self._amp > 0 or self._ramp_left):
            self._start_ramp(0.0, duration_s)
            self._advance(self._ramp_left)
        self._amp = self._target = 0.0
        self._ramp_left = 0
        self.drive_log.append((self.time_s(), self._freq, 0.0))

    def close(self) -> None:
        self.ramp_down(0.0)
        self.closed = True
