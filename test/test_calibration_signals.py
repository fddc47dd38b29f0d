"""lie_dynamics.calibration.signals.prepare on analytic signals: known derivatives, irregular stamps,
quantised positions, effort noise, dropouts, backward stamps, non-finite samples."""
import numpy as np
import pytest

from lie_dynamics.calibration import signals
from lie_dynamics.calibration.signals import prepare

F = np.array([0.1, 0.2, 0.3, 0.5])     # Hz: the harmonics (highest 0.5)
A = np.array([[0.4, -0.2, 0.1, 0.05], [0.3, 0.1, -0.15, 0.02]])   # two joints


def analytic(t):
    """(q, q̇, q̈) of two joints, sums of sines with frequencies F."""
    w = 2 * np.pi * F
    S, C = np.sin(np.outer(t, w) + 0.3), np.cos(np.outer(t, w) + 0.3)
    return S @ A.T, (C * w) @ A.T, -(S * w ** 2) @ A.T


def effort_of(q, qd, qdd):
    """A torque linear in the state (what the filter preserves exactly): 3 q + 0.5 q̇ + 0.2 q̈ + 1."""
    return 3.0 * q + 0.5 * qd + 0.2 * qdd + 1.0


def recorded(seed=0, duration=40.0, rate=500.0, quantum=2 * np.pi / 2 ** 17, noise=0.01, jitter=0.3e-3, loss=0.02):
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, duration, 1.0 / rate) + rng.uniform(-jitter, jitter, int(round(duration * rate)))
    t = np.sort(t[rng.random(len(t)) >= loss])
    q, qd, qdd = analytic(t)
    e = effort_of(q, qd, qdd) + noise * rng.normal(size=q.shape)
    return t, np.round(q / quantum) * quantum, qd, e


def rel(err, ref):
    return np.sqrt(np.mean(err ** 2)) / np.sqrt(np.mean(ref ** 2))


def test_derivatives_of_a_quantised_noisy_irregular_recording():
    t, q, _, e = recorded()
    s = prepare(t, q, e)
    assert s.segments == 1 and s.dropped == 0 and s.short == 0
    assert s.cutoff == pytest.approx(signals.CUTOFF_FACTOR * 0.5, rel=0.1)   # the harmonic was estimated
    dt = np.diff(s.t)
    assert np.allclose(dt, 1.0 / s.rate, rtol=1e-9) and abs(s.rate - 500.0) < 5.0   # uniform grid
    q0, qd0, qdd0 = analytic(s.t)
    assert rel(s.q - q0, q0) < 1e-5
    assert rel(s.qd - qd0, qd0) < 1e-4
    assert rel(s.qdd - qdd0, qdd0) < 2e-3
    tau0 = effort_of(q0, qd0, qdd0)
    assert rel(s.effort - tau0, tau0) < 2e-3   # noise 0.01 N m at 500 Hz, filtered at 2 Hz
    trim = signals.TRIM_PERIODS / s.cutoff
    assert s.t[0] == pytest.approx(t[0] + trim, abs=2.0 / s.rate)   # the filter's transients are cut
    assert s.t[-1] == pytest.approx(t[-1] - trim, abs=2.0 / s.rate)


def test_decimation_keeps_every_step_th_sample_and_terms_are_filtered_like_efforts():
    """oversample keeps every step-th sample of the filtered grid (the same values); `terms` are
    evaluated on the filtered state and low-passed by the efforts' filter: a term equal to a
    torque linear in the state comes out as the filtered effort of that torque."""
    t, q, _, e = recorded(noise=0.0, quantum=1e-12, jitter=0.0, loss=0.0)
    full = prepare(t, q, e, harmonic=0.5)
    s = prepare(t, q, e, harmonic=0.5, oversample=10.0, terms=lambda q_, qd_, qdd_: effort_of(q_, qd_, qdd_))
    assert s.step == int(500.0 / (10.0 * s.cutoff)) > 1 and s.rate == pytest.approx(full.rate / s.step)
    assert np.array_equal(s.t, full.t[::s.step]) and np.array_equal(s.qdd, full.qdd[::s.step])
    assert np.allclose(np.diff(s.t), 1.0 / s.rate, rtol=1e-9)
    assert full.terms is None and s.terms.shape == s.effort.shape
    assert rel(s.terms - s.effort, s.effort) < 1e-3
    with pytest.raises(ValueError, match='oversample'):
        prepare(t, q, e, harmonic=0.5, oversample=0.0)


def test_filtered_effort_and_state_keep_their_relation():
    """The same zero-phase filter on positions and efforts: a torque linear in the state stays that
    function of the filtered state, even with a cutoff that visibly attenuates the signal."""
    t, q, _, e = recorded(noise=0.0, quantum=1e-12, jitter=0.0, loss=0.0)
    s = prepare(t, q, e, cutoff=0.7)   # 0.5 Hz passes at 0.86: every signal is off by percent
    q0, qd0, qdd0 = analytic(s.t)
    assert rel(s.qdd - qdd0, qdd0) > 0.01
    rebuilt = effort_of(s.q, s.qd, s.qdd)
    assert rel(s.effort - rebuilt, s.effort - 1.0) < 1e-5
    # a lag of one sample between the two would break it by far more
    assert rel(s.effort[1:] - rebuilt[:-1], s.effort - 1.0) > 1e-3


def test_measured_velocity_is_used_and_missing_velocity_derived():
    t, q, qd, e = recorded(seed=1)
    noisy_qd = qd + 1e-3 * np.random.default_rng(5).normal(size=qd.shape)
    a = prepare(t, q, e, noisy_qd, harmonic=0.5)
    b = prepare(t, q, e, harmonic=0.5)
    assert np.array_equal(a.t, b.t)
    q0, qd0, qdd0 = analytic(a.t)
    for s in (a, b):
        assert rel(s.qd - qd0, qd0) < 1e-3 and rel(s.qdd - qdd0, qdd0) < 5e-3
    assert not np.allclose(a.qd, b.qd, rtol=0, atol=1e-9)   # a's came from the given velocity


def test_non_finite_and_repeated_samples_are_dropped_and_counted():
    t, q, _, e = recorded(seed=2)
    q, e, t = q.copy(), e.copy(), t.copy()
    q[100, 1] = np.nan
    e[2000, 0] = np.inf
    t[3000] = np.nan
    t = np.insert(t, 500, t[499])   # the same stamp twice
    q, e = np.insert(q, 500, q[499], axis=0), np.insert(e, 500, e[499], axis=0)
    s = prepare(t, q, e, harmonic=0.5)
    assert (s.dropped, s.repeated, s.segments) == (3, 1, 1)
    q0, _, qdd0 = analytic(s.t)
    assert np.isfinite(s.qdd).all() and rel(s.qdd - qdd0, qdd0) < 2e-3


def test_backward_stamps_split_or_refuse():
    t, q, _, e = recorded(seed=3)
    k = len(t) // 2
    t2 = t.copy()
    t2[k:] -= 5.0   # the clock went back 5 s: a second run
    s = prepare(t2, q, e, harmonic=0.5)
    assert s.segments == 2 and set(np.unique(s.segment)) == {0, 1}
    for seg in (0, 1):
        ts = s.t[s.segment == seg]
        assert np.allclose(np.diff(ts), 1.0 / s.rate)
    first = s.segment == 0
    q0, _, qdd0 = analytic(s.t[first])   # the first run's times are the true ones
    assert rel(s.qdd[first] - qdd0, qdd0) < 2e-3
    with pytest.raises(ValueError, match=r'stamps go backwards at sample \d+'):
        prepare(t2, q, e, harmonic=0.5, split=False)


def test_a_gap_longer_than_the_filter_bridges_splits_or_refuses():
    t, q, _, e = recorded(seed=4)
    cutoff = signals.CUTOFF_FACTOR * 0.5
    bridged = signals.MAX_GAP_PERIODS / cutoff
    mid = (t > 20.0) & (t < 20.0 + 0.8 * bridged)
    s = prepare(t[~mid], q[~mid], e[~mid], harmonic=0.5, split=False)   # bridged
    q0, _, qdd0 = analytic(s.t)
    assert s.segments == 1 and rel(s.qdd - qdd0, qdd0) < 2e-3
    long = (t > 20.0) & (t < 21.0)
    s = prepare(t[~long], q[~long], e[~long], harmonic=0.5)
    assert s.segments == 2 and not np.any((s.t > 20.0) & (s.t < 21.0))
    with pytest.raises(ValueError, match='longer than the filter can bridge'):
        prepare(t[~long], q[~long], e[~long], harmonic=0.5, split=False)


def test_short_segments_are_dropped_and_counted():
    t, q, _, e = recorded(seed=5)
    t2 = t.copy()
    t2[-50:] -= 100.0   # a stray tail from another clock: far too short to filter
    s = prepare(t2, q, e, harmonic=0.5)
    assert s.segments == 1 and s.short == 50
    with pytest.raises(ValueError, match='no segment is long enough'):
        prepare(t[:200], q[:200], e[:200], harmonic=0.5)


def test_highest_harmonic():
    t = np.arange(0.0, 60.0, 0.002)
    q, _, _ = analytic(t)
    assert signals.highest_harmonic(t, q) == pytest.approx(0.5, abs=0.05)
    with pytest.raises(ValueError, match='no joint moves'):
        signals.highest_harmonic(t, np.ones((len(t), 2)))


@pytest.mark.parametrize('kwargs, match', [
    ({'cutoff': 300.0}, 'below half the sample rate'),
    ({'cutoff': -1.0}, 'cutoff must be finite and > 0'),
    ({'harmonic': np.nan}, 'harmonic must be finite'),
    ({'max_gap': 0.0}, 'max_gap must be > 0'),
    ({'trim': -0.1}, 'trim must be finite and >= 0'),
    ({'rate': 0.0}, 'rate must be finite and > 0'),
])
def test_bad_options(kwargs, match):
    t, q, _, e = recorded(seed=6, duration=10.0)
    with pytest.raises(ValueError, match=match):
        prepare(t, q, e, **kwargs)


def test_bad_shapes():
    t, q, _, e = recorded(seed=7, duration=10.0)
    with pytest.raises(ValueError, match='effort must have shape'):
        prepare(t, q, e[:-1])
    with pytest.raises(ValueError, match='effort has 1 joints, q has 2'):
        prepare(t, q, e[:, 0])
    with pytest.raises(ValueError, match='qd has 3 joints'):
        prepare(t, q, e, np.zeros((len(t), 3)))
    with pytest.raises(ValueError, match='too few'):
        prepare(t[:1], q[:1], e[:1])
