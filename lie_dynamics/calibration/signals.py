"""Recorded joint signals made ready for identification: on a uniform grid, low-passed, differentiated.

Recorded joint_states have irregular stamps, dropouts, quantised encoders, effort noise and
sometimes no velocity. `prepare(t, q, effort, qd=None)` returns a `Signals` with t, q, q̇, q̈ and
the effort on one uniform grid, in five steps:

1. Samples with a non-finite value (stamp, position, effort, or velocity when given) are dropped
   and counted (`Signals.dropped`); a repeated stamp keeps its first sample (`Signals.repeated`).
2. A stamp that goes backwards (a clock reset, a second run appended) or a gap longer than
   `max_gap` (longer than the filter can bridge) ends a segment: the recording is split
   (`split=True`) or refused with the reason (ValueError). Each segment is processed alone.
3. Each segment is interpolated onto a uniform grid at `rate` (default: the median sample rate)
   by a cubic spline: irregular stamps and short dropouts cost an error of the fourth order in
   the step, where linear interpolation would leave steps in q̇ that q̈ turns into spikes.
4. Positions and efforts go through the SAME zero-phase low-pass filter (a Butterworth filter of
   `order` run forwards and backwards, scipy.signal.sosfiltfilt), so that their phases match:
   the identification pairs each torque with the state it acted at (each end is extended by an
   odd reflection of PAD_PERIODS periods of the cutoff first). Its cutoff defaults to
   CUTOFF_FACTOR times the excitation's highest harmonic (`harmonic`, Hz: given, or estimated
   from the positions' spectrum); the factor was chosen from a measurement
   (bench/signals.py, docs/benchmarks.md).
5. q̇ and q̈ are central differences of the filtered positions (or, when velocities are given,
   q̇ is the filtered measured velocity and q̈ its central difference). The filter's start and
   end transients are trimmed: TRIM_PERIODS periods of the cutoff at each end of a segment.
   `terms` of the filtered state (the smooth Coulomb sign) are low-passed like the efforts, and
   `oversample` decimates the filtered grid (identify_dynamics keeps OVERSAMPLE per period).

Only the rigid-body and friction models are fitted afterwards; this module knows nothing of the
robot (no model, no rclpy import).
"""
from typing import NamedTuple

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.signal import butter, sosfiltfilt

__all__ = ['CUTOFF_FACTOR', 'HARMONIC_TAIL', 'MAX_GAP_PERIODS', 'ORDER', 'OVERSAMPLE', 'PAD_PERIODS', 'TRIM_PERIODS',
           'Signals',           'highest_harmonic', 'prepare']

# Cutoff = CUTOFF_FACTOR x the excitation's highest harmonic: bench/signals.py measured the q̈
# error of a quantised Fourier excitation against this factor (docs/benchmarks.md, section 10).
CUTOFF_FACTOR = 4.0
# Butterworth order (run twice: the gain is 1/(1 + (f/fc)^(2 ORDER)), no phase).
ORDER = 4
# The highest harmonic of a recording: the frequency below which all but this fraction of the
# positions' power (mean removed, Hann window, each joint normalised) lies.
HARMONIC_TAIL = 1e-5
# The longest gap bridged, in periods of the cutoff (bench/signals.py measured its error).
MAX_GAP_PERIODS = 0.1
# The filter's transients at the ends of a segment, trimmed: periods of the cutoff (measured).
TRIM_PERIODS = 3.0
# The signal is extended at each end by this many periods of the cutoff (odd reflection) before
# filtering: scipy's default (a few samples) left 3x the error in the first period.
PAD_PERIODS = 1.0
# identify_dynamics decimates the filtered grid to at least this many samples per period of the
# cutoff (prepare's `oversample`): the filtered signals hold nothing above a few cutoffs and the
# fit's cost is linear in the samples (bench/calibration.py measured the held-out error against
# it: docs/benchmarks.md, Calibration).
OVERSAMPLE = 25.0
# A segment with fewer grid samples than this after trimming is dropped (`Signals.short`).
MIN_SEGMENT_SAMPLES = 20


class Signals(NamedTuple):
    """Uniformly sampled signals of one recording (M samples, n joints).

    t (M,) s; q, qd, qdd, effort (M, n); segment (M,) the index of each sample's segment (the
    grid is uniform within a segment, t jumps between segments); rate (Hz, of the samples
    returned: the grid's over step) and cutoff (Hz) used;
    segments: how many were kept; dropped: samples with a non-finite value; repeated: samples
    whose stamp repeated the previous one; short: samples of segments too short to filter.
    terms: (M, ...) the `terms` callable's values, filtered like the efforts (None without it);
    step: the decimation (every step-th sample of the filtered grid kept: `oversample`).
    """
    t: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    effort: np.ndarray
    segment: np.ndarray
    rate: float
    cutoff: float
    segments: int
    dropped: int
    repeated: int
    short: int
    terms: object = None
    step: int = 1


def _matrix(name, a, N):
    a = np.asarray(a, dtype=float)
    if a.ndim == 1:
        a = a[:, None]
    if a.ndim != 2 or a.shape[0] != N:
        raise ValueError(f'{name} must have shape ({N}, joints) like the stamps, got {np.shape(a)}')
    return a


def highest_harmonic(t, q, tail=HARMONIC_TAIL):
    """The highest frequency (Hz) in positions q (M, n) on a uniform grid t: the frequency below
    which all but `tail` of the power lies (each joint's spectrum normalised to its power, mean
    removed, Hann window). A joint that never moves counts for nothing; all of them: ValueError."""
    q = np.asarray(q, dtype=float)
    dt = (t[-1] - t[0]) / (len(t) - 1)
    x = (q - q.mean(axis=0)) * np.hanning(len(t))[:, None]
    p = np.abs(np.fft.rfft(x, axis=0)) ** 2
    total = p.sum(axis=0)
    moving = total > 0
    if not moving.any():
        raise ValueError('no joint moves: the recording has no excitation to take a cutoff from')
    share = (p[:, moving] / total[moving]).mean(axis=1)
    k = int(np.searchsorted(np.cumsum(share), 1.0 - tail))
    return float(np.fft.rfftfreq(len(t), dt)[min(k, len(share) - 1)])


def _segments(t, max_gap, split):
    """[start, stop) index ranges of the pieces between backward stamps and long gaps."""
    step = np.diff(t)
    back = np.flatnonzero(step < 0)
    gap = np.flatnonzero(step > max_gap)
    if not split and len(back):
        k = int(back[0]) + 1
        raise ValueError(f'stamps go backwards at sample {k} (t = {t[k]:.9g} s after {t[k - 1]:.9g} s): '
                         'split the recording (split=True) or record again')
    if not split and len(gap):
        k = int(gap[0]) + 1
        raise ValueError(f'a gap of {step[k - 1]:.6g} s at t = {t[k - 1]:.9g} s is longer than the filter can '
                         f'bridge (max_gap {max_gap:.6g} s): split the recording (split=True) or record again')
    cuts = np.union1d(back, gap) + 1
    bounds = np.concatenate([[0], cuts, [len(t)]]).astype(int)
    return list(zip(bounds[:-1], bounds[1:]))


def _grid(t0, t1, rate):
    return t0 + np.arange(int(np.floor((t1 - t0) * rate + 1e-9)) + 1) / rate


def prepare(t, q, effort, qd=None, *, cutoff=None, harmonic=None, rate=None, order=ORDER, max_gap=None,
            split=True, trim=None, terms=None, oversample=None):
    """Signals (t, q, q̇, q̈, effort on a uniform grid) from a recording; see the module docstring.

    t (N,) stamps, s; q (N, n) positions; effort (N, n) measured efforts; qd (N, n) measured
    velocities or None (derived from the positions). cutoff: the low-pass cutoff, Hz (default
    CUTOFF_FACTOR x harmonic); harmonic: the excitation's highest harmonic, Hz (default:
    estimated from the positions, `highest_harmonic`); rate: the grid's rate, Hz (default: the
    median sample rate); max_gap: the longest gap between two samples bridged, s (default
    MAX_GAP_PERIODS / cutoff; inf: no limit); split: a backward stamp or a longer gap splits the recording (False:
    ValueError naming it); trim: seconds dropped at each end of every segment (default
    TRIM_PERIODS / cutoff). terms: a callable (q, q̇, q̈) -> (M, ...) array of terms that are
    nonlinear in the state, evaluated on each segment's filtered signals and then low-passed by
    the same filter as the efforts, so that they pair with the filtered efforts (the smooth
    Coulomb sign: a step that the filter rounds off in the efforts; returned as Signals.terms).
    oversample: decimate after filtering, keeping at least this many samples per period of the
    cutoff (identify_dynamics passes OVERSAMPLE; default None: every grid sample). Raises
    ValueError naming the problem.
    """
    t = np.asarray(t, dtype=float).reshape(-1)
    N = len(t)
    q = _matrix('q', q, N)
    effort = _matrix('effort', effort, N)
    if effort.shape[1] != q.shape[1]:
        raise ValueError(f'effort has {effort.shape[1]} joints, q has {q.shape[1]}')
    arrays = [q, effort]
    if qd is not None:
        qd = _matrix('qd', qd, N)
        if qd.shape[1] != q.shape[1]:
            raise ValueError(f'qd has {qd.shape[1]} joints, q has {q.shape[1]}')
        arrays.append(qd)
    finite = np.isfinite(t)
    for a in arrays:
        finite &= np.isfinite(a).all(axis=1)
    dropped = int(N - np.count_nonzero(finite))
    t, arrays = t[finite], [a[finite] for a in arrays]
    if len(t) < 2:
        raise ValueError(f'{len(t)} samples with finite values ({dropped} dropped as non-finite): too few')
    keep = np.concatenate([[True], np.diff(t) != 0])   # a repeated stamp: the same instant twice
    repeated = int(len(t) - np.count_nonzero(keep))
    t, arrays = t[keep], [a[keep] for a in arrays]
    steps = np.diff(t)
    forward = steps[steps > 0]
    if rate is None:
        if not len(forward):
            raise ValueError('the stamps never advance: no time step to resample on')
        rate = 1.0 / float(np.median(forward))
    if not (np.isfinite(rate) and rate > 0):
        raise ValueError(f'rate must be finite and > 0 Hz, got {rate}')
    for name, value in (('cutoff', cutoff), ('harmonic', harmonic), ('trim', trim)):
        if value is not None and not (np.isfinite(value) and (value > 0 or (name == 'trim' and value == 0))):
            raise ValueError(f'{name} must be finite and {">= 0" if name == "trim" else "> 0"}, got {value}')
    if max_gap is not None and not max_gap > 0:   # inf: never split at a gap
        raise ValueError(f'max_gap must be > 0 s, got {max_gap}')
    if cutoff is None and harmonic is None:
        # the longest forward run, resampled, tells the excitation's band
        runs = _segments(t, np.inf, True)
        a, b = max(runs, key=lambda r: t[r[1] - 1] - t[r[0]])
        if b - a < 4:
            raise ValueError('too few samples in order to estimate the excitation\'s highest harmonic')
        grid = _grid(t[a], t[b - 1], rate)
        harmonic = highest_harmonic(grid, CubicSpline(t[a:b], arrays[0][a:b], axis=0)(grid))
    if cutoff is None:
        cutoff = min(CUTOFF_FACTOR * harmonic, 0.4 * rate)
    if not cutoff < 0.5 * rate:
        raise ValueError(f'cutoff {cutoff:g} Hz must be below half the sample rate ({0.5 * rate:g} Hz)')
    if max_gap is None:
        max_gap = MAX_GAP_PERIODS / cutoff
    if trim is None:
        trim = TRIM_PERIODS / cutoff
    if oversample is not None and not (np.isfinite(oversample) and oversample > 0):
        raise ValueError(f'oversample must be finite and > 0, got {oversample}')
    step = 1 if oversample is None else max(1, int(rate / (oversample * cutoff)))
    sos = butter(order, cutoff, fs=rate, output='sos')
    edge = int(round(trim * rate))
    out = {k: [] for k in ('t', 'q', 'qd', 'qdd', 'effort', 'segment', 'terms')}
    short = 0
    for a, b in _segments(t, max_gap, split):
        grid = _grid(t[a], t[b - 1], rate)
        if len(grid) - 2 * edge < MIN_SEGMENT_SAMPLES or b - a < 4:
            short += b - a
            continue
        u = [CubicSpline(t[a:b], x[a:b], axis=0)(grid) for x in arrays]
        pad = min(len(grid) - 1, int(round(PAD_PERIODS * rate / cutoff)))
        qf, ef = (sosfiltfilt(sos, x, axis=0, padlen=pad) for x in u[:2])
        dt = 1.0 / rate
        v = (sosfiltfilt(sos, u[2], axis=0, padlen=pad) if qd is not None
             else np.gradient(qf, dt, axis=0, edge_order=2))
        acc = np.gradient(v, dt, axis=0, edge_order=2)
        cut = slice(edge, len(grid) - edge, step)
        if terms is not None:
            out['terms'].append(sosfiltfilt(sos, np.asarray(terms(qf, v, acc), dtype=float), axis=0,
                                            padlen=pad)[cut])
        for key, x in (('t', grid), ('q', qf), ('qd', v), ('qdd', acc), ('effort', ef)):
            out[key].append(x[cut])
        out['segment'].append(np.full(len(out['t'][-1]), len(out['segment'])))
    if not out['t']:
        raise ValueError(f'no segment is long enough to filter (each needs {MIN_SEGMENT_SAMPLES} samples after '
                         f'trimming {trim:.3g} s at both ends at {rate:g} Hz; {short} samples in short segments)')
    cat = {k: np.concatenate(v) if v else None for k, v in out.items()}
    return Signals(cat['t'], cat['q'], cat['qd'], cat['qdd'], cat['effort'], cat['segment'], float(rate / step),
                   float(cutoff), len(out['t']), dropped, repeated, short, cat['terms'], step)
