"""The demo's calibration scenario: the simulated arm is not its URDF (PLANT below: masses,
CoMs, armature, friction, effort offsets and noise), and the dynamics node calibrates itself on it.

Phases, each a fresh set of processes (sim_node in lockstep with the node, as in demo.py):
  1. hold (URDF)        mode gravity on the URDF alone, HOLD x duration s: the hold torque error
                        (the node's command at rest against the plant's true gravity torque,
                        largest over the joints) and the drift (largest |q - HOME|)
  2. excitation         the optimised excitation (calibration.excitation, EXCITATION x duration s,
                        starting and ending at rest at HOME) played by trajectory_source `file`
                        through the node (feedforward + PD, URDF model) while the node records
                        (~/record); then identify_dynamics on that recording -> calibration.yaml
  3. hold (calibrated)  phase 1 with calibration_file set: the same two figures
  4. held-out tracking  the demo's cosine motion (never in the recording), duration s, feedforward
                        + PD with the URDF and then with calibration_file: RMS tracking error, and
                        the torque prediction error on that motion (the recorded efforts low-passed
                        as identify_dynamics does, against the URDF's and the calibration's
                        prediction), as a fraction of the torque RMS
The plant's friction is smooth (no stiction): once the node compensates it, a small gravity error
moves the arm, so the drift is reported, not gated.
"""
import os
import time

import numpy as np

from .. import default_urdf_path
from ..cli import ros_array

NAME = 'calibration'
# The simulated arm's true parameters (docs/benchmarks.md "Calibration demo: hold and held-out"
# lists them): per body (link1..link7) the URDF's mass times MASS_SCALE, its CoM moved by
# COM_SHIFT (m, link frame), its inertia about the CoM times MASS_SCALE; per joint
# (joint1..joint7) armature (kg m^2), viscous (N m s/rad) and Coulomb (N m, fc tanh(qd / 0.05))
# friction in place of the URDF's <dynamics>, an effort offset (N m: reported = true + offset)
# and Gaussian effort noise (std, N m) from a fixed seed.
PLANT = {
    'mass_scale': (0.88, 1.15, 1.12, 1.15, 0.87, 1.13, 1.10),
    'com_shift': ((0.010, 0.020, 0.015), (0.0, 0.020, 0.015), (-0.015, -0.010, 0.010), (0.0, -0.020, -0.010),
                  (0.010, 0.0, 0.020), (0.020, 0.010, 0.0), (0.0, -0.010, 0.015)),
    'armature': (0.20, 0.20, 0.15, 0.15, 0.05, 0.05, 0.03),
    'viscous': (0.8, 0.9, 0.6, 0.7, 0.3, 0.25, 0.15),
    'coulomb': (0.9, 1.0, 0.7, 0.8, 0.4, 0.35, 0.25),
    'offset': (0.4, -0.6, 0.3, 0.5, -0.15, 0.1, -0.08),
    'noise': (0.1, 0.1, 0.1, 0.1, 0.03, 0.03, 0.03),
    'seed': 0,
}
HOLD = 0.3         # x duration: each hold phase
EXCITATION = 2.0   # x duration: the excitation (and the recording)
# L-BFGS-B iterations of the excitation design (optimized_excitation's default is 2,500): a few seconds
# of one core, whatever the duration
ITERATIONS = 100
RECORD_SERVICE = '/dynamics_node/record'
COMMAND_TOPIC = '/effort_controller/commands'


def plant_calibration(model):
    """The PLANT as a CalibrationResult of `model` (the URDF's): what sim_node's calibration_file
    reads."""
    from ..calibration import CalibrationResult
    from ..calibration.regressor import parameter_names
    from ..calibration.result import parameters_of, physical

    inertial = []
    for b, p in enumerate(model.inertial_parameters().reshape(model.nb, 10)):
        m, c, i = physical(p)
        s = PLANT['mass_scale'][b]
        inertial.append(parameters_of(m * s, c + np.asarray(PLANT['com_shift'][b]), i * s))
    joints = np.stack([PLANT[k] for k in ('armature', 'viscous', 'coulomb', 'offset')], axis=1)
    k = len(parameter_names(model))
    return CalibrationResult(robot=model.name, joint_names=list(model.joint_names),
                             link_names=list(model.link_frames), body_links=list(model.body_link_names),
                             parameters=np.concatenate([np.ravel(inertial), joints.ravel()]),
                             std=np.full(k, np.nan), source=['identified'] * k)


def random_plant(model, seed=0, com_shift=(0.01, 0.02)):
    """Calibration parameters (calibration.regressor.parameter_names order) of a random robot
    that differs from `model`, its URDF: masses +-15 %, each CoM coordinate moved by
    com_shift[0]..com_shift[1] m with a random sign, inertias about the CoM scaled with the mass;
    per joint armature 0.05-0.3, viscous 0.1-1, Coulomb 0.1-0.8, offset +-1 (SI units). Seeded:
    the tests' and the calibration benchmark's simulated robots."""
    from ..calibration.result import parameters_of, physical

    rng = np.random.default_rng(seed)
    out = []
    for b in model.inertial_parameters().reshape(model.nb, 10):
        m, c, i = physical(b)
        f = 1 + rng.uniform(-0.15, 0.15)
        c2 = c + rng.choice([-1, 1], 3) * rng.uniform(*com_shift, 3)
        out.append(parameters_of(m * f, c2, i * f))
    n = model.n
    joints = np.stack([rng.uniform(0.05, 0.3, n), rng.uniform(0.1, 1.0, n), rng.uniform(0.1, 0.8, n),
                       rng.uniform(-1.0, 1.0, n)], axis=1)
    return np.concatenate([np.ravel(out), joints.reshape(-1)])


def sim_params(plant_file):
    return {'calibration_file': plant_file, 'coulomb_friction': 'true',
            'effort_noise': ros_array(PLANT['noise']), 'noise_seed': str(PLANT['seed'])}


def run(duration, rate=1000.0, out='demo_out', log_dir=None, domain=None, iterations=ITERATIONS):
    """Run the four phases; a record dict of the figures (metrics) and 'interrupted'. iterations:
    of the excitation's optimisation (optimized_excitation). Writes
    <out>/calibration/: plant.yaml (the truth), excitation.csv, the node's recording,
    calibration.yaml and report/ (identify_dynamics' report)."""
    from ..calibration import identify_dynamics, load_calibration, with_calibration, write_report
    from ..calibration.excitation import optimized_excitation, write_csv
    from ..calibration.recordings import read_recording
    from ..model.urdf import load_urdf
    from .demo import AMPLITUDE, FREQUENCY, HOME, KD, KP, log_folder
    from .domains import reserve_domains

    folder = os.path.abspath(os.path.join(out, 'calibration'))
    os.makedirs(folder, exist_ok=True)
    log_dir = log_dir or log_folder(out, NAME)
    domain = domain if domain is not None else reserve_domains(1)[0]
    urdf = load_urdf(default_urdf_path())
    plant_file = plant_calibration(urdf).save(os.path.join(folder, 'plant.yaml'))
    plant = with_calibration(urdf, plant_file)
    g_true = plant.gravity(np.asarray(HOME))
    # the wall-clock timeouts relaxed as in demo.py; no observer: the URDF's model error would show
    # as external torque and raise ~/collision
    common = {'stale_timeout': '1.0', 'desired_timeout': '1.0', 'kp': ros_array(KP), 'kd': ros_array(KD),
              'recording_dir': os.path.join(folder, 'recordings'), 'observer.enabled': 'false'}
    cosine = {'home': ros_array(HOME), 'amplitude': ros_array(AMPLITUDE), 'frequency': ros_array(FREQUENCY)}
    hold_s = HOLD * duration
    res = {'scenario': NAME, 'interrupted': False, 'duration': duration}

    def phase(tag, node, seconds, traj=None, record=False):
        rec = _phase(domain, os.path.join(log_dir, tag), dict(common, **node), seconds, rate,
                     dict(sim_params(plant_file), initial_positions=ros_array(HOME)), traj, record)
        res['interrupted'] = res['interrupted'] or rec['interrupted']
        return rec

    def hold(tag, node):
        rec = phase(tag, dict(node, mode='gravity'), hold_s)
        res[f'hold_error_{tag}'] = float(np.max(np.abs(rec['command0'] - g_true)))
        res[f'drift_{tag}'] = float(np.max(np.abs(rec['q'] - np.asarray(HOME))))

    hold('before', {})
    t, q, qd, qdd = optimized_excitation(urdf, duration=EXCITATION * duration, rate=100.0, home=HOME,
                                         iterations=iterations)
    csv = os.path.join(folder, 'excitation.csv')
    write_csv(csv, t, q, qd, qdd, urdf.joint_names)
    # `joints` given: the node knows its layout before the first state, so ~/record starts before
    # the simulator steps and the recording holds the whole excitation, however slow the machine
    rec = phase('excitation', {'mode': 'feedforward', 'joints': '[' + ','.join(urdf.joint_names) + ']'},
                EXCITATION * duration, {'file': csv}, record=True)
    if not rec.get('recording'):
        raise RuntimeError(f"~/record gave no recording: {rec.get('record_message')}")
    data = stepped(read_recording(rec['recording']))
    cols = [data.joint_names.index(j) for j in urdf.joint_names]
    started = time.monotonic()
    result = identify_dynamics(urdf, data.t, data.q[:, cols], data.effort[:, cols],
                               None if data.qd is None else data.qd[:, cols])
    res['identify_s'] = time.monotonic() - started
    cal_file = result.save(os.path.join(folder, 'calibration.yaml'))
    write_report(result, os.path.join(folder, 'report'), urdf.joint_names)
    rep = result.report
    res['recording_holdout'] = float(np.sqrt(np.mean(rep['rms_after'] ** 2) / np.mean(rep['rms_effort'] ** 2)))
    hold('after', {'calibration_file': cal_file})
    calibrated = load_calibration(cal_file)
    for tag, node in (('before', {}), ('after', {'calibration_file': cal_file})):
        rec = phase(f'track_{tag}', dict(node, mode='feedforward'), duration, cosine)
        from .trajectory_source import desired_state
        q_des = desired_state(rec['t'][:, None], *(np.asarray(x) for x in (HOME, AMPLITUDE, FREQUENCY)))[0]
        res[f'track_rms_{tag}'] = float(np.sqrt(np.mean((rec['q'] - q_des) ** 2)))
        if tag == 'after':
            res.update(torque_prediction(urdf, calibrated, rec))
    return res


def torque_prediction(model, calibration, rec):
    """RMS of (predicted - measured) effort over every joint and sample, as a fraction of the
    measured effort's RMS: the URDF's prediction (<dynamics> friction, no armature, no offsets) and
    the calibration's. The signals are prepared as identify_dynamics prepares a recording
    (calibration.identify.prepare_recording: the Coulomb columns low-passed like the efforts)."""
    from ..calibration.identify import prepare_recording
    from ..calibration.regressor import calibration_regressor, prior_parameters

    s = prepare_recording(rec['t'], rec['q'], rec['tau'], rec['qd'], eps=calibration.eps)
    Y = calibration_regressor(model, s.q, s.qd, s.qdd, calibration.eps, s.terms)
    scale = np.sqrt(np.mean(s.effort ** 2))
    out = {'torque_rms': float(scale)}
    for tag, p in (('before', prior_parameters(model)), ('after', calibration.parameters)):
        out[f'torque_error_{tag}'] = float(np.sqrt(np.mean((Y @ p - s.effort) ** 2)) / scale)
    return out


def stepped(data):
    """The recording from the simulator's first step on. ~/record starts before the simulator, which
    holds its initial state on its brakes, re-sent until the first command, at simulated time 0: a
    zero stamp, which the recording replaces by the receive time (read_recording), so those states
    come first, ahead of the stepped ones by the wall clock's epoch, and their efforts are no
    dynamics (a long hold made them the longest run the filter's band was estimated from)."""
    back = np.flatnonzero(np.diff(data.t) < 0)
    if not len(back):
        return data
    k = int(back[-1]) + 1
    return data._replace(t=data.t[k:] - data.t[k], q=data.q[k:], effort=data.effort[k:],
                         qd=None if data.qd is None else data.qd[k:], dropped=data.dropped + k,
                         t0_ns=data.t0_ns + int(round(data.t[k] * 1e9)))


def _phase(domain, log_dir, node_params, seconds, rate, sim_extra, traj=None, record=False):
    """One run: dynamics_node (the bundled URDF, no friction parameters set: the URDF's or the
    calibration's friction is compensated; + node_params), trajectory_source (traj:
    its parameters, None: none) and sim_node (lockstep, `seconds` simulated). Records joint_states
    (t, q, qd, tau) and the node's first command (command0); with `record`, calls ~/record true once
    the simulation runs and false at its end (recording: the folder)."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from std_msgs.msg import Float64MultiArray
    from std_srvs.srv import SetBool

    from .demo import DESIRED_TOPIC, LOCKSTEP_TIMEOUT, Stack, check_stop, record_states

    env = dict(os.environ, ROS_DOMAIN_ID=str(domain))
    env.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    os.makedirs(log_dir, exist_ok=True)
    steps = int(round(seconds * rate))
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain)
    rec = {'t': [], 'q': [], 'qd': [], 'tau': [], 'command0': None, 'interrupted': False}
    node = ex = None
    try:
        node = rclpy.create_node('demo_calibration_recorder', context=ctx)
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(node)

        record_states(node, rec)

        def on_command(msg):
            if rec['command0'] is None:
                rec['command0'] = np.array(msg.data)
        node.create_subscription(Float64MultiArray, COMMAND_TOPIC, on_command, 10)
        client = node.create_client(SetBool, RECORD_SERVICE) if record else None

        def wait(cond, timeout, stack):
            end = time.monotonic() + timeout
            while not cond():
                if time.monotonic() > end:
                    return False
                ex.spin_once(timeout_sec=0.05)
                stack.check()
                check_stop()
            return True

        def call(value, stack):
            future = client.call_async(SetBool.Request(data=value))
            if not wait(future.done, 60.0, stack):
                raise RuntimeError(f'{RECORD_SERVICE} did not answer')
            return future.result()

        stack = Stack(env, log_dir)
        try:
            with stack:
                stack.start('dynamics_node', 'lie_dynamics.dynamics_node',
                            dict({'urdf_path': default_urdf_path(), 'command_topic': COMMAND_TOPIC}, **node_params))
                if not wait(lambda: node.count_subscribers('joint_states') >= 2 and (
                        client is None or client.service_is_ready()), 30.0, stack):
                    raise RuntimeError('dynamics_node did not come up')
                answers = []

                def recording():   # ~/record refuses until the node has its model
                    answers.append(call(True, stack))
                    return answers[-1].success
                if record and not wait(recording, 60.0, stack):   # before the simulator starts: no state missed
                    raise RuntimeError(f'{RECORD_SERVICE} refused for 60 s: {answers[-1].message}')
                if traj is not None:
                    stack.start('trajectory_source', 'lie_dynamics.sim.trajectory_source',
                                dict(traj, min_subscribers='1'))
                    if not wait(lambda: node.count_subscribers('joint_states') >= 3, 30.0, stack):
                        raise RuntimeError('trajectory_source did not come up')
                stack.start('sim_node', 'lie_dynamics.sim.sim_node', dict(
                    sim_extra, rate=f'{rate:.1f}', lockstep='true', hold_until_command='true',
                    lockstep_timeout=f'{LOCKSTEP_TIMEOUT:.1f}', min_subscribers=str(2 + (traj is not None)),
                    max_steps=str(steps), **({'lockstep_stamped_topic': DESIRED_TOPIC} if traj is not None else {})),
                    ends_by_itself=True)
                # the simulator ends by itself; its last states reach this reader within seconds
                wait(lambda: rec['t'] and rec['t'][-1] >= seconds - 0.5 / rate, 600.0, stack)
                if record:
                    answer = call(False, stack)
                    rec['recording'] = answer.message if answer.success else None
                    rec['record_message'] = answer.message
        except KeyboardInterrupt:
            rec['interrupted'] = True
            raise
    finally:
        if ex is not None:
            ex.shutdown()
        if node is not None:
            node.destroy_node()
        rclpy.shutdown(context=ctx)
    for k in ('t', 'q', 'qd', 'tau'):
        rec[k] = np.array(rec[k], dtype=float)
    if rec['command0'] is None:
        rec['command0'] = np.full(7, np.nan)
    return rec


ROWS = (('hold torque error, URDF (N m)', 'hold_error_before'), ('hold torque error, calibrated (N m)',
                                                                   'hold_error_after'),
        ('drift, URDF (rad)', 'drift_before'), ('drift, calibrated (rad)', 'drift_after'),
        ('held-out torque error, URDF (x RMS)', 'torque_error_before'),
        ('held-out torque error, calibrated (x RMS)', 'torque_error_after'),
        ('held-out torque RMS (N m)', 'torque_rms'),
        ('recording hold-out torque error (x RMS)', 'recording_holdout'),
        ('tracking RMS, URDF (rad)', 'track_rms_before'), ('tracking RMS, calibrated (rad)', 'track_rms_after'),
        ('identify_dynamics (s)', 'identify_s'))


def table(res):
    """The scenario's figures, one per line."""
    if not res:
        return []
    return ['', f"calibration ({res['duration']:g} s tracking, {HOLD * res['duration']:g} s holds, "
                f"{EXCITATION * res['duration']:g} s excitation)"] + [
        f'  {label:44s} {res[key]:.3e}' for label, key in ROWS if key in res]


def csv_lines(res):
    return ['figure,value'] + [f'{key},{res[key]}' for _, key in ROWS if key in res]

