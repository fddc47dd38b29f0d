"""The node's payload identification and direct payload setting without ROS (payload_service.py):
the bounded recording, the smoothing derivative, the fit under each effort convention, the
refusals, and the ~/set_payload request check."""
import numpy as np
import pytest

from lie_dynamics import default_urdf_path, load_urdf
from lie_dynamics.algorithms.identification import excitation_trajectory
from lie_dynamics.ros.core.compensator import Compensator
from lie_dynamics.ros.features.base import Features
from lie_dynamics.ros.features.payload_service import (MAX_SAMPLES, Identification, PayloadRecording, Recording,
                                                       check_payload_request, fit, smooth_derivative)

MASS, COM, INERTIA = 1.3, [0.01, -0.02, 0.05], [3e-3, 1e-4, 0.0, 4e-3, -2e-4, 2e-3]


@pytest.fixture(scope='module')
def arm():
    return load_urdf(default_urdf_path())


def recorded(model, seconds=6.0, rate=200.0, noise=0.0, static=False, payload=True, seed=0):
    t, q, qd, qdd = excitation_trajectory(model, duration=seconds, rate=rate, seed=seed)
    if static:
        qd, qdd = np.zeros_like(qd), np.zeros_like(qdd)
    loaded = model.with_body_inertias(model.J_links)
    if payload:
        loaded.set_payload('hand', MASS, COM, INERTIA)
    tau = loaded.inverse_dynamics(q, qd, qdd)
    tau = tau + noise * np.random.default_rng(seed).normal(size=tau.shape)
    return t, q, qd, tau


def test_recording_is_bounded_and_keeps_the_whole_span():
    rec = Recording(2, duration=1e9, capacity=100)
    for k in range(10_000):
        rec.add(0.001 * k, np.zeros(2), np.zeros(2), np.zeros(2))
    assert rec.size <= 100 and rec.stride == 128
    t = rec.arrays()[0]
    assert t[0] == 0.0 and t[-1] > 9.0 and np.all(np.diff(t) > 0)  # uniform over the whole recording
    assert rec.add(5.0, np.zeros(2), np.zeros(2), np.zeros(2)) is False  # older than the last: not taken
    assert rec.seen == 10_000


def test_recording_ends_after_its_duration():
    rec = Recording(1, duration=0.5)
    done = [rec.add(0.01 * k, [0.0], [0.0], [0.0]) for k in range(100)]
    assert done.index(True) == 50 and all(done[50:])  # the caller stops at the first True


def test_smooth_derivative_of_a_sine_with_noise():
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.uniform(0.004, 0.006, 2000))  # jittery stamps
    x = np.sin(2 * np.pi * 0.5 * t)[:, None] + 1e-4 * rng.normal(size=(len(t), 1))
    grid, dx = smooth_derivative(t, x)
    truth = np.pi * np.cos(2 * np.pi * 0.5 * grid)
    assert np.max(np.abs(dx[:, 0] - truth)) < 0.02 and grid[0] > t[0] and grid[-1] < t[-1]


@pytest.mark.parametrize('convention', ['total', 'gravity_removed'])
def test_fit_recovers_the_payload(arm, convention):
    t, q, qd, tau = recorded(arm)
    model = arm.with_body_inertias(arm.J_links)
    effort = tau - model.gravity(q) if convention == 'gravity_removed' else tau
    res, changes, text = fit(model, 'hand', t, q, qd, effort, 'dynamic', convention, 0.3)
    assert res.mass == pytest.approx(MASS, rel=2e-3)
    assert np.allclose(res.com, COM, atol=2e-3)
    assert changes['payload.link'] == 'hand' and changes['payload.mass'] == pytest.approx(MASS, rel=2e-3)
    assert len(changes['payload.inertia']) == 6 and 'payload.* parameters set' in text


def test_static_mode_determines_mass_and_com_only(arm):
    t, q, qd, tau = recorded(arm, static=True, noise=0.01)
    res, changes, text = fit(arm, 'hand', t, q, qd, tau, 'static', 'total', 0.3)
    assert res.mass == pytest.approx(MASS, rel=0.02) and np.allclose(res.com, COM, atol=0.01)
    assert changes['payload.inertia'] == [] and 'inertia not determined' in text


def test_refusals(arm):
    t, q, qd, tau = recorded(arm, payload=False, noise=0.05)
    with pytest.raises(ValueError, match='not positive|bad fit'):  # nothing to find: no payload invented
        fit(arm, 'hand', t, q, qd, tau, 'dynamic', 'total', 0.3)
    t, q, qd, tau = recorded(arm)
    with pytest.raises(ValueError, match='static mode: only 0 samples at rest'):
        fit(arm, 'hand', t, q, qd, tau, 'static', 'total', 0.3)
    with pytest.raises(ValueError, match='only 3 joint_states'):
        fit(arm, 'hand', t[:3], q[:3], qd[:3], tau[:3], 'dynamic', 'total', 0.3)
    bad = tau + np.random.default_rng(1).normal(scale=5.0, size=tau.shape)  # noise far above the payload's torque
    with pytest.raises(ValueError, match='bad fit|not positive'):
        fit(arm, 'hand', t, q, qd, bad, 'dynamic', 'total', 0.3)


def test_identification_records_only_accepted_states_with_efforts(arm):
    core = Compensator({'identify.duration': 1.0, 'payload.link': 'hand', 'payload.mass': 0.5})
    core.set_model(load_urdf(default_urdf_path()))
    feature = PayloadRecording(clock=lambda: 0.0)
    features, ident = Features([feature], events=core.events), feature.ident
    names, q = core.layout, np.zeros(7)
    features.feed(core)
    assert not feature.active
    assert ident.begin(core) == 'hand'
    with pytest.raises(ValueError, match='already running'):
        ident.begin(core)
    assert feature.active
    for k in range(30):
        stamp = 10**9 + k * 5_000_000   # 5 ms apart
        core.on_joint_state(names, q, np.zeros(7), [] if k % 2 else np.ones(7), stamp=stamp)
        features.feed(core)
        features.feed(core)   # the same message twice: counted once
    core.on_joint_state(names, [np.nan] * 7, stamp=2 * 10**9)  # rejected: not recorded
    features.feed(core)
    assert ident.recording is not None and ident._rec.size == 15 and ident._rec.no_effort == 15
    ident.stop('test')
    with pytest.raises(ValueError, match='test'):
        ident.take(core)
    ident.finish(False, 'test')
    assert not ident.busy and 'refused: test' in dict(ident.report())['payload_identification_last']


def test_identification_refused_at_once(arm):
    core = Compensator({'measured_effort': 'none', 'identify.link': 'hand'})
    ident = Identification()
    with pytest.raises(ValueError, match='no robot model'):
        ident.begin(core)
    core.set_model(load_urdf(default_urdf_path()))
    with pytest.raises(ValueError, match="measured_effort is 'none'"):
        ident.begin(core)
    core.update({'measured_effort': 'total', 'identify.link': 'base_link'})
    with pytest.raises(ValueError, match='not a link that moves a controlled joint'):
        ident.begin(core)
    core.update({'identify.link': ''})
    with pytest.raises(ValueError, match='set identify.link'):
        ident.begin(core)
    assert not ident.busy


def test_set_payload_request(arm):
    ok = check_payload_request({'payload.link': 'hand', 'payload.mass': 2, 'payload.com': COM,
                                'payload.inertia': INERTIA}, arm)
    assert ok == {'payload.link': 'hand', 'payload.mass': 2.0, 'payload.com': COM, 'payload.inertia': INERTIA}
    cleared = check_payload_request({'payload.link': '', 'payload.mass': 0.0}, arm)
    assert cleared['payload.mass'] == 0.0 and cleared['payload.link'] == ''
    bad = [({'payload.link': 'hand', 'payload.mass': 2.0, 'payload.com': COM}, 'payload.inertia required'),
           ({'payload.link': 'hand', 'payload.mass': 2.0, 'payload.com': COM,
             'payload.inertia': [1e-3, 0, 0, 1e-3, 0, 1e-2]}, 'triangle inequality'),
           ({'payload.link': 'hand', 'payload.mass': -1.0, 'payload.com': COM, 'payload.inertia': INERTIA},
            r'payload.mass must be in \[0.0, 1000.0\], got -1.0'),
           ({'payload.link': 'hand', 'payload.mass': 1.0, 'payload.com': [0.0, np.nan, 0.0],
             'payload.inertia': INERTIA}, 'payload.com must contain finite values'),
           ({'payload.link': 'nope', 'payload.mass': 1.0, 'payload.com': COM, 'payload.inertia': INERTIA},
            "unknown link 'nope' for payload: not a link of robot"),
           ({'payload.link': 'base_link', 'payload.mass': 1.0, 'payload.com': COM, 'payload.inertia': INERTIA},
            "payload link 'base_link' is not a link that moves a controlled joint"),
           ({'payload.mass': 1.0}, 'payload.link .* is required'),
           ({'payload.link': 'hand', 'mass': 1.0}, 'unknown names'),
           ({'payload.link': 'hand', 'payload.mass': True}, 'payload.mass must be a double')]
    for request, why in bad:
        with pytest.raises(ValueError, match=why):
            check_payload_request(request, arm)


def test_max_samples_bounds_memory():
    rec = Recording(7, duration=1e9)
    for k in range(3 * MAX_SAMPLES):
        rec.add(float(k), np.zeros(7), np.zeros(7), np.zeros(7))
    assert rec.size <= MAX_SAMPLES and rec.q.shape == (MAX_SAMPLES, 7)


def test_modelled_friction_is_not_payload(arm):
    from lie_dynamics.laws import make_friction
    t, q, qd, tau = recorded(arm)
    friction = make_friction(np.full(7, 0.5), np.full(7, 0.3), 0.05)
    effort = tau + 0.5 * qd + 0.3 * np.tanh(qd / 0.05)
    res, _, _ = fit(arm, 'hand', t, q, qd, effort, 'dynamic', 'total', 0.3, friction)
    assert res.mass == pytest.approx(MASS, rel=2e-3) and np.allclose(res.com, COM, atol=2e-3)


def test_benchmark_runs_and_errors_follow_the_noise(tmp_path):
    """bench/payload.py --quick: table, CSV, chart; noise-free fits exact, noisy ones not, the
    largest noise refused or worse."""
    from bench import payload as bench_payload
    res = bench_payload.run(quick=True, out=str(tmp_path), seeds=1)
    rows = {(r['sweep'], r['mode'], r['noise'], r['duration']): r for r in res['rows']}
    exact, noisy = rows[('noise', 'dynamic', 0.0, 10.0)], rows[('noise', 'dynamic', 0.1, 10.0)]
    assert exact['mass_err'] < 1e-5 and exact['refused'] == 0 and 0 < noisy['mass_err'] < 0.01
    assert rows[('noise', 'static', 0.0, 10.0)]['determined'] == 4   # mass and CoM only
    assert (tmp_path / 'payload.png').read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    header = (tmp_path / 'payload.csv').read_text().splitlines()[0]
    assert header == ','.join(bench_payload.FIELDS) and (tmp_path / 'payload.md').read_text().startswith('# ')


def test_recording_that_never_covers_its_duration_is_abandoned(monkeypatch):
    from lie_dynamics.ros.features import payload_service
    monkeypatch.setattr(payload_service, 'WALL_EXTRA', 0.0)   # wall limit: 5 x 0.1 s
    core = Compensator({'identify.duration': 0.1, 'identify.link': 'hand'})
    core.set_model(load_urdf(default_urdf_path()))
    ident = Identification()
    ident.begin(core)
    ident.wait()   # no joint_states at all
    with pytest.raises(ValueError, match=r'covered only 0.00 of 0.1 s'):
        ident.take(core)
    ident.finish(False, 'x')
    assert ident.recording is None and not ident.busy
