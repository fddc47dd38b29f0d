"""The node's contact decisions in plain Python (features/contact_link.py), with a first-order
residual as the observer gives it: the link only on a settled residual, the wrench while the
flag is up and one zero wrench after it, the tool wrench every sample, re-initialisation."""
import numpy as np
import pytest

from lie_dynamics import default_urdf_path, load_urdf
from lie_dynamics.algorithms import contact_isolation as ci
from lie_dynamics.ros.core.settings import Settings
from lie_dynamics.ros.features.contact_link import ContactIsolation

K, DT = 50.0, 1e-3
TH = np.array([3.0, 3.0, 3.0, 3.0, 0.5, 0.5, 0.5])
Q = np.array([0.0, -0.6, 0.0, 2.0, 0.0, 1.6, 0.8])


def settings(**extra):
    return Settings({'observer.gain': K, 'collision.threshold': TH.tolist(), **extra})


def test_the_link_waits_for_a_settled_residual_and_the_wrench_follows_the_flag():
    model = load_urdf(default_urdf_path())
    iso = ContactIsolation()
    iso.adopt(settings(**{'contact.wrench_frame': 'tool0'}), model)
    f = np.array([12.0, -20.0, 8.0])
    F = np.concatenate([f, np.cross([0.04, 0.03, 0.02], f)])    # at tool0: isolated at link7
    tau = model.jacobian(Q, 'tool0', 'local').T @ F
    links, wrenches, tools = [], [], []
    on, off = 10, 300
    for k in range(400):
        t = k * DT
        r = tau * (1 - np.exp(-K * (t - on * DT))) if on <= k < off else \
            tau * (np.exp(-K * (t - off * DT)) - np.exp(-K * (t - on * DT))) if k >= off else np.zeros(7)
        flag = on + 2 <= k < off + 40
        pub = iso.update(t, Q, r, flag, TH)
        links.append(pub.link)
        wrenches.append(pub.wrench)
        tools.append(pub.tool)
    first = next(k for k, w in enumerate(wrenches) if w is not None)
    assert links[first] == 'link7' and all(x is None for x in links[:first])
    assert (first - on) * DT > 3.0 / K            # not on the rising residual
    # while settled the wrench of the mean residual is renewed, and published, every SETTLE_STEP time constant
    assert all(w is None or w[0] == 'link7' for w in wrenches[first:off + 40])
    sent = [k for k in range(first, off + 40) if wrenches[k] is not None]
    step = ci.SETTLE_STEP / K / DT
    assert max(np.diff(sent)) <= int(np.ceil(step)) + 1 and sent[-1] >= off + 40 - step - 1
    J7 = model.jacobian(Q, 'link7', 'local')
    np.testing.assert_allclose(J7.T @ wrenches[max(k for k in sent if k < off)][1], tau, atol=1e-3 * np.abs(tau).max())
    # the fall: one zero wrench, then nothing; the link goes back to ''
    assert wrenches[off + 40] == ('link7', wrenches[off + 40][1]) and not np.any(wrenches[off + 40][1])
    assert all(w is None for w in wrenches[off + 41:])
    assert [x for x in links if x is not None] == ['link7', '']
    # the tool wrench at every sample, F once settled (a fit serves one time constant: lag only)
    assert all(w is not None for w in tools)
    np.testing.assert_allclose(tools[off - 1], F, rtol=1e-3, atol=1e-3 * np.abs(F).max())
    level, values = iso.report(0, [])
    assert dict(values)['contact_isolation'] == 'no contact' and dict(values)['contact_wrench_frame'] == 'tool0'
    assert any("collision at link 'link7'" in text for _, _, text in iso.events)


def test_the_settled_mean_is_the_external_torque_exactly_through_the_rise():
    """The observer's trapezoid (algorithms/observer.py) follows a constant tau_ext with
    r_k = a r_(k-1) + (1 - a) tau_ext; the node's mean, (integral of r + (r_end - r_start) / K) / T
    with the integral a trapezoid over every sample (held ones included), then equals tau_ext to
    rounding, though the stretch starts on the rise's tail (a trapezoid over the checkpoints
    alone, half a time constant apart, missed it by 2.5e-4 N m here)."""
    model = load_urdf(default_urdf_path())
    iso = ContactIsolation()
    iso.adopt(settings(), model)
    tau = model.jacobian(Q, 'link7', 'local').T @ np.array([10.0, -20.0, 5.0, 0.5, -1.0, 2.0])
    a = (1 - 0.5 * K * DT) / (1 + 0.5 * K * DT)
    r = np.zeros(7)
    for k in range(1, 260):   # the decision ~9 time constants after the step, the end at 12.5
        r = a * r + (1 - a) * tau if k > 10 else np.zeros(7)
        iso.update(k * DT, Q, r.copy(), k > 12, TH)
    assert iso.isolation is not None and iso.isolation.link == 'link7'
    assert abs(r - tau).max() > 1e-6 * abs(tau).max()   # the estimate itself still lags
    np.testing.assert_allclose(iso.residual, tau, rtol=0, atol=1e-10 * abs(tau).max())


def test_changes_that_restart_the_observer_restart_isolation_and_a_lost_frame_turns_the_tool_off():
    model = load_urdf(default_urdf_path())
    iso = ContactIsolation()
    s = settings(**{'contact.wrench_frame': 'tool0'})
    iso.adopt(s, model)
    tau = model.jacobian(Q, 'link7', 'local').T @ np.array([10.0, -20.0, 5.0, 0.5, -1.0, 2.0])
    for k in range(200):
        iso.update(k * DT, Q, tau, True, TH)
    assert iso.link == 'link7' and iso.isolation is not None
    level, values = iso.report(0, [])
    assert dict(values)['contact_isolation'] == 'isolated' and dict(values)['contact_wrench_rank'] == '6'
    iso.adopt(s.replace({'gravity': [0.0, 0.0, -9.0]}), model)     # as the observer: a new integral
    assert iso.isolation is None
    assert dict(iso.report(0, [])[1])['contact_isolation'] == 'settling'   # the flag was up
    iso.adopt(s.replace({'collision.hold_time': 0.02}), model)   # not an observer change
    other = load_urdf(default_urdf_path())
    other.name = 'renamed'
    iso.adopt(s.replace({}), other)
    assert iso.frame == 'tool0'
    xml = open(default_urdf_path()).read().replace('tool0', 'tool9')
    iso.adopt(s.replace({}), load_urdf(xml))
    assert iso.frame == '' and any('tool_wrench off' in text for _, _, text in iso.events)


def test_the_collision_line_names_the_link():
    model = load_urdf(default_urdf_path())
    iso = ContactIsolation()
    iso.adopt(settings(), model)
    f = np.array([12.0, -20.0, 8.0])
    tau = model.jacobian(Q, 'tool0', 'local').T @ np.concatenate([f, np.cross([0.04, 0.03, 0.02], f)])
    iso.inbox.append(('warn', 'collision', 'collision: external torque beyond collision.threshold (total 1)'))
    iso.flush()
    assert iso.events == []   # held until the link is decided
    for k in range(200):
        iso.update(k * DT, Q, tau.copy(), True, TH)
        iso.flush()
    lines = [text for _, key, text in iso.events if key == 'collision']
    assert len(lines) == 1 and lines[0].startswith('collision: external torque') and "contact link 'link7'" in lines[0]
    assert not [e for e in iso.events if e[1] == 'collision:link']
    # the flag falls before the estimate settles: the line says so
    iso.update(0.3, Q, tau.copy(), False, TH)
    iso.events.clear()
    iso.inbox.append(('warn', 'collision', 'collision: external torque beyond collision.threshold (total 2)'))
    iso.flush()
    iso.update(0.301, Q, tau * 0.5, True, TH)
    iso.inbox.append(('info', 'collision:clear', 'collision flag cleared'))
    iso.flush()
    assert [key for _, key, _ in iso.events] == ['collision', 'collision:clear']
    assert '(total 2); contact link not decided' in iso.events[0][2]


def test_the_measured_noise_lets_a_lightly_loaded_joint_name_its_link():
    """A push on link7 with joint 7 at 4 % of its threshold (under the fixed tolerance of 5 %),
    the residual a first-order filter of the torques plus white effort noise of 5 % of each
    threshold: after a second of free motion the node knows the residual's noise, decides on the
    mean of the settled stretch (its noise about 0.5 % of the threshold) and names link7; it
    never names link6."""
    model = load_urdf(default_urdf_path())
    iso = ContactIsolation()
    iso.adopt(settings(), model)
    f = np.array([9.0, -60.0, 18.0])
    F7 = np.concatenate([f, np.cross([0.0, 0.0, 0.05], f)])   # through joint 7's axis
    F7[5] += 0.04 * TH[6]
    tau = model.jacobian(Q, 'link7', 'local').T @ F7
    assert abs(tau[6]) == pytest.approx(0.04 * TH[6]) and np.abs(tau[:6]).max() > 3 * TH.max()
    rng = np.random.default_rng(7)
    r, links, on = np.zeros(7), [], 1000
    for k in range(1600):
        ext = tau if k >= on else 0.0
        r = r + K * DT * (ext + rng.normal(0.0, 0.05, 7) * TH - r)   # the observer's filter
        pub = iso.update(k * DT, Q, r, k >= on + 5, TH)
        links.append(pub.link)
    named = [x for x in links if x]
    assert named and set(named) == {'link7'}, named
    assert iso.isolation.status == 'isolated' and iso.link == 'link7'


def test_the_mean_residual_is_of_the_current_configuration():
    """The arm yields 0.01 rad at joint 6 under a settled push on link7: J^T F changes by about 2 %,
    less than settling notices, and the mean keeps only the checkpoints within MOVE_RAD of the
    current joints, so the published wrench is F again (a mean over both poses is off by ~0.5 %)."""
    from lie_dynamics.ros.features import contact_link
    model = load_urdf(default_urdf_path())
    iso = ContactIsolation()
    iso.adopt(settings(), model)
    F = np.array([10.0, -20.0, 5.0, 0.5, -1.0, 2.0])
    Q2 = Q + np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.01, 0.0])
    taus = [model.jacobian(x, 'link7', 'local').T @ F for x in (Q, Q2)]
    assert 0.01 < np.abs(taus[1] - taus[0]).max() / np.abs(taus[0]).max() < ci.SETTLE_TOLERANCE
    r, sent = np.zeros(7), []
    for k in range(800):
        q, tau = (Q, taus[0]) if k < 600 else (Q2, taus[1])
        r = r + K * DT * (tau - r)
        pub = iso.update(k * DT, q, r, True, TH)
        if pub.wrench is not None:
            sent.append((k, pub.wrench[1]))
    assert iso.link == 'link7' and iso.settling.update(0.8, r, TH)   # settled throughout: one stretch
    k, w = sent[-1]
    assert k > 700 and contact_link.MOVE_RAD < 0.01
    np.testing.assert_allclose(w, F, rtol=1e-3, atol=1e-3 * np.abs(F).max())


def test_a_weak_push_through_its_own_joints_axis_is_not_named_the_link_before():
    """A push on link4 through joint 4's axis at 1.5x the threshold: its residual is that of a
    wrench on link3. With contact.strict_below 2 (the default) the strict rule decides it: ambiguous,
    never link3; with the tier off (0) the default rule names link3. At 3x both name link3 alike."""
    model = load_urdf(default_urdf_path())
    J4 = model.jacobian(Q, 'link4', 'local')
    v, w = J4[:3, 3], J4[3:, 3]
    p = np.cross(w, v) / (w @ w) + 0.03 * w / np.linalg.norm(w)   # on joint 4's axis
    f = np.array([1.0, 1.0, 0.0])
    tau1 = J4.T @ np.concatenate([f, np.cross(p, f)])
    assert abs(tau1[3]) < 1e-12 * np.abs(tau1).max()
    for multiple, below, expect in ((1.5, None, ''), (1.5, 0.0, 'link3'), (3.0, None, 'link3'), (3.0, 0.0, 'link3')):
        tau = multiple / np.max(np.abs(tau1) / TH) * tau1
        iso = ContactIsolation()
        iso.adopt(settings(**({} if below is None else {'contact.strict_below': below})), model)
        assert iso.strict_below == (ci.STRICT_BELOW if below is None else below) and ci.STRICT_BELOW == 2.0
        links = [iso.update(k * DT, Q, tau.copy(), True, TH).link for k in range(200)]
        assert iso.isolation is not None and iso.isolation.link == expect, (multiple, below, iso.isolation)
        assert [x for x in links if x] == ([expect] if expect else [])
        if not expect:
            assert iso.isolation.status == 'ambiguous' and 'link4' in iso.isolation.candidates
