"""The stepped-sine controller: plan + driver -> run file, with the safety logic.

Per line: step the drive phase-continuously (amplitude predicted from the
previous line's force/volt gain), demodulate each block over whole cycles of the
shared clock (fundamental + harmonics), correct the drive amplitude in closed
loop until the force is within tolerance, wait for steady state, then average
blocks (FRF = response phasor / force phasor per block, mean and standard error).

Steady-state detector. A transient decaying as ``exp(-t/tau)`` changes the
block estimate by ``d_k`` from block to block; the error still left in the
estimate is the tail of a geometric series, ``|d_k| q/(1-q)`` with
``q = exp(-T_block/tau)``, about ``tau/T_block`` times the block-to-block change
a naive test would compare with the tolerance. The detector uses that tail;
``q`` is the larger of a bound from the known poles (or an assumed minimum
damping) and the decay ratio measured from successive changes.

Safety: every exit path (normal end, Ctrl-C, exception, limit breach, overload,
driver fault) goes through one ``finally`` that ramps the drive to zero and
closes the run file (``"aborted"`` unless the sweep finished).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from acquisition._demod import phasors, thd
from acquisition._driver import ChannelSpec, Driver, DriverError
from acquisition._plan import Plan, Pole, block_cycles, dense_lines, plan_lines, tau_bound_s
from acquisition.runfile import (
    FLAG_FORCE,
    FLAG_NOISY,
    FLAG_NONLINEAR,
    FLAG_NOT_SETTLED,
    FLAG_OVERLOAD,
    FLAG_THD,
    LineQuality,
    RunWriter,
    create_run,
    read_run,
    resume_run,
)
from labdata import CHANNEL_UNITS, RESPONSE_QUANTITY, frf_quantity_of

_MOTION = tuple(RESPONSE_QUANTITY.values())


class AcquisitionAbort(RuntimeError):
    """The controller stopped a run on purpose (limit breach, overload); the drive was ramped down."""


class LimitBreach(AcquisitionAbort):
    """A plan limit (drive voltage, force, acceleration) would be or was exceeded."""


class OverloadAbort(AcquisitionAbort):
    """An input channel overloaded and the plan says ``on_overload = "abort"``."""


@dataclass(frozen=True)
class SweepResult:
    """Outcome of one run: file, final status, why it stopped, lines and clock time."""

    path: str
    status: str
    reason: str
    n_lines: int
    n_new_lines: int
    lines_added_by_refinement: int
    clock_s: float
    found_poles: tuple[tuple[float, float], ...] = ()


@dataclass(frozen=True)
class _LineResult:
    frf: np.ndarray  # (n_out,)
    quality: LineQuality
    norm: float


def quantity_of(sensors: Sequence[ChannelSpec]) -> str:
    """FRF quantity implied by the response sensors (all must measure the same quantity)."""
    qs = {c.quantity for c in sensors}
    if len(qs) != 1 or next(iter(qs)) not in _MOTION:
        raise ValueError(f"response sensors must all measure one of {list(_MOTION)}, got {sorted(qs)}")
    return frf_quantity_of(qs.pop())


def settle_metric(history: Sequence[np.ndarray], q_bound: float) -> float:
    """Estimated relative error the transient still leaves in the latest block estimate.

    Parameters
    ----------
    history : sequence of (n,) complex
        Block estimates since the last drive change; the last entry of each is
        the force/volt gain, the others FRF values.
    q_bound : float
        ``exp(-T_block / tau_bound)``, the slowest decay per block expected.

    Returns
    -------
    float
        ``max_j |d_j| / |h_j| * q / (1 - q)`` with ``d`` the last block-to-block
        change (the tail of the geometric series of changes), ``q`` the larger
        of ``q_bound`` and the measured ratio of successive changes; FRF
        magnitudes are floored at 5 % of the largest.
    """
    d = history[-1] - history[-2]
    q = q_bound
    if len(history) >= 3:
        n0, n1 = np.linalg.norm(history[-2] - history[-3]), np.linalg.norm(d)
        if n0 > 0:
            q = max(q, min(n1 / n0, 0.995))
    h = history[-1]
    den = np.concatenate([np.maximum(np.abs(h[:-1]), 0.05 * np.abs(h[:-1]).max()), [abs(h[-1])]])
    return float(np.max(np.abs(d) / den) * q / (1 - q))


class _Sweep:
    """State of one sweep (one article, one drive point, one level)."""

    def __init__(self, driver: Driver, plan: Plan, sensors, drive: ChannelSpec, level_n: float):
        self.driver = driver
        self.plan = plan
        self.sensors = tuple(sensors)
        self.drive = drive
        self.level = float(level_n)
        self.n_out = len(self.sensors)
        self.force_idx = self.n_out
        self.gain = None  # |F|/V of the last line, N/V
        self.amp = 0.0
        self.gain_hist: list[tuple[float, float]] = []
        self.accel_idx = np.array([k for k, c in enumerate(self.sensors) if c.quantity == "acceleration"], dtype=int)

    # ---------------------------------------------------------------- blocks
    def _phasors(self, frequency_hz: float, n_cycles: int) -> tuple[np.ndarray, bool]:
        blk = self.driver.read_block(n_cycles)
        X = phasors(blk, frequency_hz, self.plan.measure.n_harmonics)
        if X.shape[0] != self.n_out + 1:
            raise DriverError(f"driver returned {X.shape[0]} channels, expected {self.n_out + 1}")
        overload = bool(np.any(blk.overload))
        if overload and self.plan.limits.on_overload == "abort":
            names = [c.name for c, o in zip(self.sensors + (self.drive,), np.atleast_1d(blk.overload)) if o]
            raise OverloadAbort(f"input overload on {names} at {frequency_hz:.3f} Hz")
        lim = self.plan.limits
        force = abs(X[self.force_idx, 0])
        if force > lim.force_n_max:
            raise LimitBreach(f"force {force:.3g} N exceeds limits.force_n_max {lim.force_n_max} N at {frequency_hz:.3f} Hz")
        if self.accel_idx.size:
            acc = np.abs(X[self.accel_idx, 0])
            if acc.max() > lim.acceleration_m_s2_max:
                name = self.sensors[self.accel_idx[int(np.argmax(acc))]].name
                raise LimitBreach(
                    f"acceleration {acc.max():.3g} m/s^2 on {name} exceeds limits.acceleration_m_s2_max "
                    f"{lim.acceleration_m_s2_max} at {frequency_hz:.3f} Hz"
                )
        return X, overload

    def _set(self, frequency_hz: float, amplitude_v: float) -> None:
        if amplitude_v > self.plan.limits.drive_v_max:
            raise LimitBreach(
                f"drive {amplitude_v:.3g} V needed for {self.level:g} N at {frequency_hz:.3f} Hz exceeds "
                f"limits.drive_v_max {self.plan.limits.drive_v_max} V"
            )
        self.driver.set_drive(frequency_hz, amplitude_v)
        self.amp = amplitude_v

    def _predict_gain(self, f: float) -> float:
        """Force/volt gain expected at ``f``: linear extrapolation of the last two lines when close."""
        g = self.gain
        if len(self.gain_hist) >= 2:
            (f1, g1), (f2, g2) = self.gain_hist[-2:]
            if f1 != f2 and abs(f - f2) <= 2 * abs(f2 - f1):
                g = g2 + (g2 - g1) * (f - f2) / (f2 - f1)
                g = float(np.clip(g, 0.5 * g2, 2 * g2))
        return g

    # ------------------------------------------------------------------ line
    def measure_line(self, f: float, level_n: float) -> _LineResult:
        plan = self.plan
        st = plan.settle
        n_cyc = block_cycles(plan, f)
        T = n_cyc / f
        q_bound = math.exp(-T / tau_bound_s(plan, f))
        amp = plan.force.initial_drive_v if self.gain is None else level_n / self._predict_gain(f)
        self._set(f, amp)
        t_start = self.driver.time_s()
        corrections = 0
        flags = 0
        overload_seen = False
        metric = np.inf
        t_change = t_start
        H_hist: list[np.ndarray] = []
        while True:  # settle (and correct the force) ------------------------
            X, ov = self._phasors(f, n_cyc)
            overload_seen |= ov
            F = X[self.force_idx, 0]
            # settle on the FRF and on the force/volt gain together
            H_hist.append(np.concatenate([X[: self.n_out, 0] / F, [abs(F) / self.amp]]))
            now = self.driver.time_s()
            settled = False
            if st.mode == "fixed":
                if now - t_change >= st.fixed_dwell_s:
                    metric = float("nan")
                    settled = True
            elif len(H_hist) >= 2:
                metric = settle_metric(H_hist, q_bound)
                settled = len(H_hist) >= st.min_blocks and metric <= st.tolerance
            if settled:
                self.gain = abs(F) / self.amp
                force_err = abs(abs(F) / level_n - 1)
                if force_err > 0.5 * plan.force.tolerance and corrections < plan.force.max_corrections:
                    # closed-loop force: the settled gain is exact for a linear rig
                    self._set(f, self.amp * level_n / abs(F))
                    corrections += 1
                    H_hist = []
                    t_change = now
                    continue
                break
            if now - t_start > st.max_time_s:
                flags |= FLAG_NOT_SETTLED
                break
        t_settled = self.driver.time_s()
        Hb, Fb, harm = [], [], []
        for _ in range(plan.measure.blocks):  # measure ---------------------------
            X, ov = self._phasors(f, n_cyc)
            overload_seen |= ov
            Hb.append(X[: self.n_out, 0] / X[self.force_idx, 0])
            Fb.append(abs(X[self.force_idx, 0]))
            harm.append(np.abs(X))
        Hb = np.array(Hb)
        H = Hb.mean(axis=0)
        se = np.sqrt(np.sum(np.abs(Hb - H) ** 2, axis=0) / (len(Hb) - 1) / len(Hb))
        force = float(np.mean(Fb))
        self.gain = force / self.amp
        self.gain_hist.append((f, self.gain))
        th = thd(np.mean(harm, axis=0))
        if abs(force / level_n - 1) > plan.force.tolerance:
            flags |= FLAG_FORCE
        if overload_seen:
            flags |= FLAG_OVERLOAD
        if np.max(th[: self.n_out]) > plan.measure.thd_limit:
            flags |= FLAG_THD
        scale = np.maximum(np.abs(H), 0.05 * np.abs(H).max())
        if np.max(se / scale) > plan.measure.std_error_limit:
            flags |= FLAG_NOISY
        q = LineQuality(
            force_n=np.array([force]),
            std_error=se[:, None],
            thd=th,
            settle_metric=metric,
            overload=overload_seen,
            flags=flags,
            drive_v=self.amp,
            time_s=self.driver.time_s(),
            settle_time_s=t_settled - t_start,
            n_blocks=plan.measure.blocks,
        )
        return _LineResult(frf=H, quality=q, norm=float(np.linalg.norm(H)))


def _parabola(fs: np.ndarray, norms: np.ndarray) -> tuple[float, float] | None:
    """Resonance and damping from 1/|H|^2, quadratic in f within a few bandwidths of an isolated mode."""
    y = 1.0 / norms**2
    a, b, c = np.polyfit(fs, y, 2)
    if a <= 0:
        return None
    fr = -b / (2 * a)
    ymin = c - b * b / (4 * a)
    if not (fs.min() <= fr <= fs.max()) or ymin <= 0:
        return None
    return float(fr), float(np.clip(math.sqrt(ymin / a) / fr, 1e-4, 0.1))


def _v_estimate(pts: list[tuple[float, float]]) -> float:
    """Resonance from the peak line and its neighbour across the peak (1/|H| ~ |f - f_r| on the skirts)."""
    (fa, na), (fb, nb), (fc, nc) = pts
    fr = (fa * na + fc * nc) / (na + nc)
    if fr > fb:
        return (fb * nb + fc * nc) / (nb + nc)
    return (fa * na + fb * nb) / (na + nb)


class _PeakSearch:
    """Locate a resonance bracketed by three lines: probe the estimated peak until the
    bracket is about a bandwidth wide, then return (f_r, zeta) for dense lines."""

    def __init__(self, pts, zeta_assumed: float, max_probes: int = 6):
        self.pts = sorted(pts)
        self.zeta = zeta_assumed
        self.probes = 0
        self.max_probes = max_probes

    def _bracket(self):
        k = int(np.argmax([n for _, n in self.pts]))
        k = min(max(k, 1), len(self.pts) - 2)
        return self.pts[k - 1 : k + 2]

    def next_probe(self) -> float | None:
        """Next frequency to measure, or None when the peak is located."""
        br = self._bracket()
        fs = np.array([f for f, _ in br])
        ns = np.array([n for _, n in br])
        bw = 2 * self.zeta * fs[1]
        if fs[2] - fs[0] <= 3 * bw or self.probes >= self.max_probes:
            return None
        est = _parabola(fs, ns)
        fr = est[0] if est is not None and fs[2] - fs[0] <= 10 * bw else _v_estimate(list(zip(fs, ns)))
        fr = float(np.clip(fr, fs[0] + 0.25 * bw, fs[2] - 0.25 * bw))
        if min(abs(f - fr) for f, _ in self.pts) < 0.25 * bw:
            # already measured there: halve the wider side of the bracket instead
            fr = 0.5 * (fs[0] + fs[1]) if fs[1] - fs[0] > fs[2] - fs[1] else 0.5 * (fs[1] + fs[2])
        self.probes += 1
        return fr

    def add(self, f: float, norm: float) -> None:
        self.pts = sorted(self.pts + [(f, norm)])

    def result(self) -> tuple[float, float]:
        br = self._bracket()
        fs = np.array([f for f, _ in br])
        ns = np.array([n for _, n in br])
        est = _parabola(fs, ns)
        if est is not None:
            return est
        return float(fs[int(np.argmax(ns))]), self.zeta


def _resume_refinement(plan: Plan, writer: RunWriter, dense_regions: list, history: list,
                       extra: list) -> "_PeakSearch | None":
    """Rebuild the refinement state of a resumed run from its committed lines.

    Clusters of lines much closer than the background (refined peaks) become
    dense regions; the other lines, ascending, become the peak-detection history.
    A peak at the end of that history (the run was killed during its search) is
    searched again, reusing the lines already measured around it; dense lines
    of a region cut short are appended to ``extra``.
    """
    run = read_run(writer.path)
    order = np.argsort(run.frequency_hz)
    f = run.frequency_hz[order]
    norms = np.linalg.norm(run.frf[order, :, 0], axis=1)
    zeta = plan.settle.assumed_damping
    close = np.diff(f) <= 2 * (2 * zeta * f[1:]) / plan.refine.lines_per_bandwidth
    k = 0
    in_cluster = np.zeros(f.size, dtype=bool)
    while k < close.size:
        if close[k]:
            j = k
            while j < close.size and close[j]:
                j += 1
            if j - k + 1 >= 4:  # a refined region: lines k..j
                centre = 0.5 * (f[k] + f[j])
                half = 0.5 * (f[j] - f[k])
                z = max(zeta, half / (2 * centre * (plan.lines.span_bandwidths + 1)))
                dense_regions.append((float(centre), float(z)))
                in_cluster[k : j + 1] = True
                # complete a region whose dense lines were cut short by the interruption
                top = k + np.argsort(norms[k : j + 1])[-3:]
                pk = _parabola(f[np.sort(top)], norms[np.sort(top)]) or (float(f[top[-1]]), zeta)
                spacing = 2 * pk[1] * pk[0] / plan.refine.lines_per_bandwidth
                for x in dense_lines([], [Pole(frequency_hz=pk[0], damping=pk[1])], plan.refine.lines_per_bandwidth,
                                     plan.refine.span_bandwidths, plan.lines.start_hz, plan.lines.stop_hz):
                    if np.min(np.abs(f - x)) > 0.5 * spacing:
                        extra.append(float(x))
            k = j
        k += 1
    background = plan_lines(plan)
    is_bg = np.array([np.min(np.abs(background - x)) <= 1e-6 for x in f]) & ~in_cluster
    history.extend((float(a), float(b)) for a, b in zip(f[is_bg], norms[is_bg]))
    if len(history) >= 3:
        (fa, na), (fb, nb), (fc, nc) = history[-3:]
        if nb > plan.refine.peak_ratio * max(na, nc) and not any(
            abs(fb - fr) <= (plan.lines.span_bandwidths + 1) * 2 * z * fr for fr, z in dense_regions
        ):
            search = _PeakSearch(history[-3:], zeta)
            for x, n in zip(f[~is_bg & ~in_cluster], norms[~is_bg & ~in_cluster]):
                if fa < x < fc:  # probes measured before the interruption
                    search.add(float(x), float(n))
                    search.probes += 1
            return search
    return None


def run_sweep(
    driver: Driver,
    plan: Plan,
    path,
    *,
    sensors: Sequence[ChannelSpec],
    drive: ChannelSpec,
    level_n: float,
    article: str = "article1",
    progress: bool = False,
    on_line: Callable[[float, np.ndarray, LineQuality], None] | None = None,
    resume: bool = True,
    driver_channels: Sequence[ChannelSpec] | None = None,
) -> SweepResult:
    """Run one stepped-sine sweep (one article, drive point and force level) into ``path``.

    Parameters
    ----------
    driver : Driver
        Any driver (simulated lab, VISA, NI); the controller only uses the protocol.
    plan : Plan
    path : str or Path
        Run file; if it exists and ``resume``, completed lines are kept and skipped.
    sensors : sequence of ChannelSpec
        Response channels (FRF outputs).
    drive : ChannelSpec
        The force channel at the drive point (FRF input).
    level_n : float
        Target force amplitude, N peak.
    on_line : callable(frequency_hz, frf (n_out, 1), quality), optional
        Called after each line (live plot).
    driver_channels : sequence of ChannelSpec, optional
        Channel specs handed to ``driver.configure`` (default ``sensors + [drive]``),
        e.g. with driver-specific physical addresses.

    Returns
    -------
    SweepResult

    Raises
    ------
    KeyboardInterrupt, DriverError, AcquisitionAbort, ...
        Re-raised after the drive was ramped to zero and the run closed as aborted.
    """
    path = Path(path)
    sensors = tuple(sensors)
    quantity = quantity_of(sensors)
    try:
        info = driver.configure(tuple(driver_channels or (sensors + (drive,))), plan.sample_rate_hz)
    except BaseException:
        driver.ramp_down(plan.limits.ramp_down_s)  # safe in any state, per the protocol
        raise
    hardware = {"driver": info.name, "kind": info.kind, "sample_rate_hz": info.sample_rate_hz,
                "devices": list(info.devices), "details": info.details}
    if path.exists() and resume:
        old = read_run(path)
        if [c.name for c in old.sensors] != [c.name for c in sensors] or old.drives[0].name != drive.name:
            raise ValueError(f"{path}: existing run has other channels; cannot resume it with this plan")
        writer = resume_run(path)
    else:
        writer = create_run(path, article=article, sensors=sensors, drives=(drive,), quantity=quantity,
                            plan=plan.model_dump(mode="json") | {"level_n": level_n}, hardware=hardware,
                            overwrite=not resume)
    sweep = _Sweep(driver, plan, sensors, drive, level_n)
    t0 = driver.time_s()
    done = list(writer.frequency_hz_done)
    n_before = len(done)
    queue = [f for f in plan_lines(plan) if not done or np.min(np.abs(np.asarray(done) - f)) > 1e-6]
    history: list[tuple[float, float]] = []  # (f, ||H||) of background lines, ascending
    found: list[tuple[float, float]] = []
    dense_regions = [(p.frequency_hz, p.damping) for p in plan.lines.poles]
    added = 0
    search: _PeakSearch | None = None
    probe = None
    status, reason = "aborted", "interrupted"
    bar = None
    try:
        if plan.refine.enabled and n_before:
            extra: list[float] = []
            search = _resume_refinement(plan, writer, dense_regions, history, extra)
            queue = sorted(extra) + queue
            added += len(extra)
            if search is not None:
                probe = search.next_probe()
                if probe is not None:
                    queue.insert(0, probe)
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=len(queue), unit="line", desc=path.stem, dynamic_ncols=True)
        while queue:
            f = float(queue.pop(0))
            res = sweep.measure_line(f, level_n)
            q = res.quality
            if plan.linearity.enabled and (
                not plan.linearity.peaks_only
                or any(abs(f - fr) <= plan.refine.span_bandwidths * 2 * z * fr for fr, z in dense_regions)
            ):
                res2 = sweep.measure_line(f, level_n * plan.linearity.level_ratio)
                dev = float(np.max(np.abs(res2.frf - res.frf) / np.maximum(np.abs(res.frf), 0.05 * np.abs(res.frf).max())))
                flags = q.flags | (FLAG_NONLINEAR if dev > plan.linearity.tolerance else 0)
                q = replace(q, linearity=dev, flags=flags)
            writer.append_line(f, res.frf[:, None], q)
            done.append(f)
            if on_line is not None:
                on_line(f, res.frf[:, None], q)
            if bar is not None:
                bar.set_postfix(f=f"{f:.2f}Hz", F=f"{q.force_n[0]:.3f}N", settle=f"{q.settle_time_s:.2f}s",
                                refresh=False)
                bar.update(1)
            if search is not None and f == probe:
                search.add(f, res.norm)
            elif plan.refine.enabled and not any(
                abs(f - fr) <= (plan.lines.span_bandwidths + 1) * 2 * z * fr for fr, z in dense_regions
            ):
                history.append((f, res.norm))
                if search is None and len(history) >= 3:
                    (fa, na), (fb, nb), (fc, nc) = history[-3:]
                    if fa < fb < fc and nb > plan.refine.peak_ratio * max(na, nc):
                        search = _PeakSearch(history[-3:], plan.settle.assumed_damping)
            if search is not None:
                probe = search.next_probe()
                if probe is not None:
                    queue.insert(0, probe)
                    added += 1
                else:
                    pk = search.result()
                    search = None
                    found.append(pk)
                    dense_regions.append(pk)
                    new = dense_lines([], [Pole(frequency_hz=pk[0], damping=pk[1])],
                                      plan.refine.lines_per_bandwidth, plan.refine.span_bandwidths,
                                      plan.lines.start_hz, plan.lines.stop_hz)
                    arr = np.asarray(done + queue)
                    spacing = 2 * pk[1] * pk[0] / plan.refine.lines_per_bandwidth
                    new = [x for x in new if np.min(np.abs(arr - x)) > 0.3 * spacing]
                    queue = sorted(new) + queue
                    added += len(new)
                if bar is not None:
                    bar.total = len(done) + len(queue)
                    bar.refresh()
        status, reason = "completed", "all lines measured"
    except AcquisitionAbort as exc:
        reason = str(exc)
        raise
    except DriverError as exc:
        reason = f"driver fault: {exc}"
        raise
    except KeyboardInterrupt:
        reason = "interrupted (Ctrl-C)"
        raise
    except BaseException as exc:
        reason = f"{type(exc).__name__}: {exc}"
        raise
    finally:
        try:
            driver.ramp_down(plan.limits.ramp_down_s)
        finally:
            if bar is not None:
                bar.close()
            writer.close(status)
    return SweepResult(
        path=str(path),
        status=status,
        reason=reason,
        n_lines=len(done),
        n_new_lines=len(done) - n_before,
        lines_added_by_refinement=added,
        clock_s=driver.time_s() - t0,
        found_poles=tuple(found),
    )


def plan_channels(plan: Plan) -> tuple[tuple[ChannelSpec, ...], tuple[ChannelSpec, ...]]:
    """Response sensors and drive (force) channels of a plan: from its layout file or inline channels."""
    if plan.layout is not None:
        from acquisition._layout import read_layout

        lay = read_layout(plan.resolve(plan.layout))
        sensors = tuple(c for c in lay.sensors if c.role == "response")
        return sensors, lay.drives
    specs = []
    for c in plan.channels:
        d = np.asarray(c.direction, dtype=float)
        n = np.linalg.norm(d)
        if n == 0:
            raise ValueError(f"plan channel {c.name!r}: direction is the zero vector")
        specs.append(ChannelSpec(name=c.name, role=c.role, quantity=c.quantity, unit=c.unit or CHANNEL_UNITS[c.quantity],
                                 sensitivity=c.sensitivity_v_per_unit, physical=c.physical, range_v=c.range_v,
                                 grid=c.grid, direction=tuple(float(x) for x in d / n), serial=c.serial,
                                 iepe_current_a=c.iepe_current_a))
    sensors = tuple(c for c in specs if c.role == "response")
    drives = tuple(c for c in specs if c.role == "force")
    if not sensors or not drives:
        raise ValueError("plan channels need at least one 'response' and one 'force' channel")
    return sensors, drives


def run_plan(
    plan: Plan,
    make_driver: Callable[[str, int, ChannelSpec], Driver],
    out_dir,
    *,
    progress: bool = False,
    on_line=None,
    driver_channels: Callable[[Sequence[ChannelSpec], ChannelSpec], Sequence[ChannelSpec]] | None = None,
) -> list[SweepResult]:
    """Run the whole ensemble: one run file per (article, drive point, force level).

    ``make_driver(article, drive_index, drive_channel)`` returns a fresh driver
    for each run (closed afterwards). Files are named
    ``<plan>_<article>_<drive>_<level>N.h5`` in ``out_dir``; completed files are
    skipped and interrupted ones resumed. Stops at the first aborted run
    (re-raising its exception after the drive was ramped down).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    sensors, drives = plan_channels(plan)
    names = plan.ensemble.drives or tuple(d.name for d in drives)
    by_name = {d.name: k for k, d in enumerate(drives)}
    for n in names:
        if n not in by_name:
            raise ValueError(f"ensemble.drives names {n!r}, not a drive of the layout (have {sorted(by_name)})")
    results = []
    for article in plan.ensemble.articles:
        for name in names:
            k = by_name[name]
            for level in plan.force.levels_n:
                path = out / f"{plan.name}_{article}_{name}_{level:g}N.h5"
                if path.exists():
                    old = read_run(path)
                    if old.status == "completed":
                        results.append(SweepResult(str(path), "completed", "already complete", old.n_lines, 0, 0, 0.0))
                        continue
                driver = make_driver(article, k, drives[k])
                try:
                    chans = driver_channels(sensors, drives[k]) if driver_channels else None
                    results.append(run_sweep(driver, plan, path, sensors=sensors, drive=drives[k], level_n=level,
                                             article=article, progress=progress, on_line=on_line,
                                             driver_channels=chans))
                finally:
                    driver.close()
    return results
