"""Command vocabularies of the instruments the VISA driver speaks (no I/O here).

Transport (a pyvisa resource, see :mod:`acquisition.drivers.visa`) is kept apart
from vocabulary: this module only builds command strings and parses replies,
so the same vocabulary serves the real instruments, the loopback instrument
server (:mod:`acquisition._scpi_server`) and the transcript tests.

Two instruments are spoken:

* :class:`GeneratorVocabulary` -- a Keysight 33500B-style function generator
  (SCPI): ``FUNC SIN``, ``FREQ``, ``VOLT`` (peak-to-peak), ``OUTP``,
  ``OUTP:LOAD INF`` (the amplifier input is high impedance), ``OUTP:SYNC ON``
  (the sync output is the lock-ins' reference), ``SYST:ERR?`` error queue.
  The 33500B changes the frequency of a running sine phase-continuously.
* :class:`LockinVocabulary` -- a Stanford Research SR830-style lock-in
  amplifier referenced externally to the generator's sync output:
  ``SENS`` (full-scale sensitivity, V rms), ``OFLT`` (time constant),
  ``OFSL`` (filter slope), ``SNAP? 1,2`` (X and Y read at one instant, V rms),
  ``LIAS?`` (latched status: input, filter and output overload, reference
  unlock; reading clears it).

Phase convention: the lock-in reports X + iY = R e^{i theta}, theta the phase
of the signal relative to the reference (the drive); with e^{+iwt} the complex
peak amplitude of the channel is ``sqrt(2) * (X + iY)``.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np


class ScpiReplyError(ValueError):
    """A reply that does not parse as the vocabulary says it must (a garbled reply)."""


_NUMBER = r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?"
_ERROR_RE = re.compile(r"^\s*([+-]?\d+)\s*,\s*\"(.*)\"\s*$")


def parse_float(reply: str) -> float:
    """One number, e.g. ``"+1.00000000000000E+02"``."""
    text = reply.strip()
    if not re.fullmatch(_NUMBER, text):
        raise ScpiReplyError(f"expected a number, got {reply!r}")
    return float(text)


def parse_int(reply: str) -> int:
    """One integer, e.g. ``"5"`` or ``"+0"``."""
    text = reply.strip()
    if not re.fullmatch(r"[+-]?\d+", text):
        raise ScpiReplyError(f"expected an integer, got {reply!r}")
    return int(text)


def parse_floats(reply: str, count: int) -> tuple[float, ...]:
    """``count`` comma-separated numbers, e.g. the reply to ``SNAP? 1,2``."""
    parts = reply.strip().split(",")
    if len(parts) != count:
        raise ScpiReplyError(f"expected {count} comma-separated numbers, got {reply!r}")
    return tuple(parse_float(p) for p in parts)


def parse_idn(reply: str) -> str:
    """``*IDN?`` reply: four comma-separated fields (maker, model, serial, firmware)."""
    text = reply.strip()
    if text.count(",") < 3 or not text.isprintable():
        raise ScpiReplyError(f"expected 'maker,model,serial,firmware', got {reply!r}")
    return text


@dataclass(frozen=True)
class GeneratorVocabulary:
    """Keysight 33500B-style function generator, channel 1.

    Amplitudes at the interface are peak volts; the instrument is set to
    ``VOLT:UNIT VPP`` so ``VOLT`` carries twice the peak value.
    """

    min_vpp: float = 0.001
    max_vpp: float = 20.0
    error_query: str = "SYST:ERR?"
    idn_query: str = "*IDN?"

    def setup(self) -> tuple[str, ...]:
        """Reset to a known state with the output off and a sine selected."""
        return (
            "*RST",
            "*CLS",
            "OUTP OFF",
            "OUTP:LOAD INF",
            "FUNC SIN",
            "VOLT:UNIT VPP",
            "VOLT:OFFS 0",
            f"VOLT {self.min_vpp:.6g}",
            "OUTP:SYNC ON",
        )

    def frequency(self, frequency_hz: float) -> str:
        return f"FREQ {frequency_hz:.10g}"

    def amplitude(self, amplitude_v_peak: float) -> str:
        """``VOLT`` in peak-to-peak volts, clamped up to the instrument minimum."""
        vpp = max(2.0 * amplitude_v_peak, self.min_vpp)
        return f"VOLT {vpp:.6g}"

    def output(self, on: bool) -> str:
        return "OUTP ON" if on else "OUTP OFF"

    def parse_error(self, reply: str) -> tuple[int, str]:
        """``SYST:ERR?`` reply ``+0,"No error"`` -> ``(0, "No error")``."""
        m = _ERROR_RE.match(reply)
        if m is None:
            raise ScpiReplyError(f"expected 'code,\"message\"', got {reply!r}")
        return int(m.group(1)), m.group(2)


def _decades(first: float, last: float, mantissas: tuple[float, ...]) -> tuple[float, ...]:
    values = []
    exponent = math.floor(math.log10(first)) - 1
    while True:
        for m in mantissas:
            v = float(f"{m}e{exponent}")
            if v > last * (1 + 1e-9):
                return tuple(values)
            if v >= first * (1 - 1e-9):
                values.append(v)
        exponent += 1


#: SR830 ``SENS i`` full-scale sensitivities, V rms (i = 0 is 2 nV, 26 is 1 V).
SR830_SENSITIVITIES_V = _decades(2e-9, 1.0, (1, 2, 5))
#: SR830 ``OFLT i`` time constants, s (i = 0 is 10 us, 19 is 30 ks).
SR830_TIME_CONSTANTS_S = _decades(10e-6, 30e3, (1, 3))
#: SR830 ``OFSL i`` slopes, dB/octave (6 dB per cascaded RC stage).
SR830_SLOPES_DB = (6, 12, 18, 24)

#: ``LIAS?`` status bits.
LIAS_INPUT_OVERLOAD = 1
LIAS_FILTER_OVERLOAD = 2
LIAS_OUTPUT_OVERLOAD = 4
LIAS_UNLOCK = 8


def enbw_hz(time_constant_s: float, slope_db: int) -> float:
    """Equivalent noise bandwidth of the lock-in output filter (cascaded RC stages), Hz.

    ``1/(4 tau)``, ``1/(8 tau)``, ``3/(32 tau)``, ``5/(64 tau)`` for 6, 12, 18
    and 24 dB/octave (SR830 manual, "noise measurements").
    """
    factor = {6: 1 / 4, 12: 1 / 8, 18: 3 / 32, 24: 5 / 64}[slope_db]
    return factor / time_constant_s


@dataclass(frozen=True)
class LockinVocabulary:
    """SR830-style lock-in amplifier, externally referenced, input A, AC coupled."""

    model: str = "SR830"
    sensitivities_v: tuple[float, ...] = SR830_SENSITIVITIES_V
    time_constants_s: tuple[float, ...] = SR830_TIME_CONSTANTS_S
    slopes_db: tuple[int, ...] = SR830_SLOPES_DB
    snap_query: str = "SNAP? 1,2"
    status_query: str = "LIAS?"
    time_constant_query: str = "OFLT?"
    idn_query: str = "*IDN?"

    def setup(self) -> tuple[str, ...]:
        """External reference (TTL rising edge), input A, AC coupling, float ground, fundamental."""
        return ("*RST", "*CLS", "FMOD 0", "RSLP 1", "ISRC 0", "ICPL 0", "IGND 0", "HARM 1")

    def sensitivity_index(self, full_scale_v_rms: float) -> int:
        """Smallest sensitivity whose full scale (V rms) holds ``full_scale_v_rms``."""
        for i, s in enumerate(self.sensitivities_v):
            if s >= full_scale_v_rms * (1 - 1e-9):
                return i
        return len(self.sensitivities_v) - 1

    def sensitivity(self, index: int) -> str:
        return f"SENS {index}"

    def time_constant_index(self, max_time_constant_s: float) -> int:
        """Largest time constant not above ``max_time_constant_s`` (the smallest if none is)."""
        best = 0
        for i, tc in enumerate(self.time_constants_s):
            if tc <= max_time_constant_s * (1 + 1e-9):
                best = i
        return best

    def time_constant(self, index: int) -> str:
        return f"OFLT {index}"

    def slope(self, slope_db: int) -> str:
        if slope_db not in self.slopes_db:
            raise ValueError(f"lock-in filter slope must be one of {self.slopes_db} dB/octave, got {slope_db}")
        return f"OFSL {self.slopes_db.index(slope_db)}"

    def parse_snap(self, reply: str) -> complex:
        """``SNAP? 1,2`` reply ``"x,y"`` (V rms) -> complex ``x + iy``."""
        x, y = parse_floats(reply, 2)
        return complex(x, y)

    def parse_status(self, reply: str) -> int:
        value = parse_int(reply)
        if not 0 <= value <= 255:
            raise ScpiReplyError(f"expected a status byte 0..255, got {reply!r}")
        return value


def rms_to_peak(phasor_v_rms: complex | np.ndarray) -> complex | np.ndarray:
    """Lock-in X + iY (V rms) -> complex peak amplitude (V)."""
    return np.sqrt(2.0) * phasor_v_rms
