"""Parameters of the dynamics node: one table, plain Python (no rclpy import).

The node turns each `ParamSpec` into a declared ROS parameter with a descriptor (range,
read-only flag, description); `check_value` is the single place where a value is
validated, used both at start-up and for live updates (`ros2 param set`). The rules are data of
the specs (choices, lengths, per-joint shape, minimum, norm), not code per name; what needs the
joint count is `per_joint_values`, on the one expansion rule `broadcast_joints`.
"""
import math
from dataclasses import dataclass
from typing import Optional, Tuple

import numpy as np

# MODES: the torque laws (lie_dynamics.laws). Every mode but `gravity` needs the desired-state stream.
from ...algorithms.contact_isolation import RADIUS, RCOND, STRICT_BELOW, TOLERANCE
from ...laws import COULOMB_VELOCITY_EPSILON, MODES
from ...model.joint_names import broadcast_joints
from .diagnostics import clip

STALE_ACTIONS = ('hold_gravity_at_last_state', 'zero')
# load_urdf's policy for physically inconsistent link inertias.
INERTIA_POLICIES = ('warn', 'strict', 'repair')
# What joint_states effort holds (contact.py: motor_torque).
EFFORT_CONVENTIONS = ('total', 'gravity_removed', 'none')
# How ~/identify_payload gets the accelerations (payload_service.py).
IDENTIFY_MODES = ('dynamic', 'static')
# Which robot descriptions may replace the running model.
DESCRIPTION_UPDATES = ('same_robot', 'any', 'none')
# The dynamics topics (dynamics_topics.py) and the Jacobian frames (as Model.jacobian's).
DYNAMICS_TERMS = ('gravity', 'coriolis', 'mass_matrix', 'jacobian')
JACOBIAN_FRAMES = ('world_aligned', 'local', 'world')

# kinds: 'bool', 'integer', 'double', 'string', 'double_array', 'string_array'
# Per-joint shapes of a double array (ParamSpec.per_joint): one value for every joint or one per
# controlled joint (per_joint_values); empty means the URDF's values ('urdf'), zeros ('zero'), or
# is refused ('required').
PER_JOINT_SHAPES = ('urdf', 'zero', 'required')


@dataclass(frozen=True)
class ParamSpec:
    name: str
    kind: str
    default: object          # None for arrays that default to "empty / from the URDF"
    description: str
    live: bool               # False: read-only after start-up
    range: Optional[Tuple[float, float]] = None   # inclusive, integers and doubles
    constraints: str = ''
    choices: Tuple[str, ...] = ()   # strings: the accepted values; string arrays: of each entry
    lengths: Tuple[int, ...] = ()   # double arrays: the accepted lengths (empty: any)
    per_joint: str = ''             # double arrays: a PER_JOINT_SHAPES entry ('': not per joint)
    minimum: Optional[float] = None  # double arrays: every entry >= minimum (> with above)
    above: bool = False
    norm_max: Optional[float] = None  # double arrays: the largest Euclidean norm
    unit: str = ''                  # of the entries, as rejection reasons quote it
    nonempty: bool = False          # strings: '' (or blanks) refused

    def __post_init__(self):
        if self.choices and not self.constraints:  # what `ros2 param describe` shows
            object.__setattr__(self, 'constraints', ' or '.join(self.choices))
        if self.per_joint not in ('',) + PER_JOINT_SHAPES:
            raise ValueError(f'{self.name}: per_joint must be one of {PER_JOINT_SHAPES}, got {self.per_joint!r}')


PARAMS = (
    ParamSpec('robot_description', 'string', '',
              'URDF XML. If non-empty it is loaded at start-up (before urdf_path); setting it later '
              'loads it. The robot_description topic replaces the model whenever it publishes.', True),
    ParamSpec('urdf_path', 'string', '',
              'URDF file, used at start-up when robot_description is empty; setting it later loads it.',
              True),
    ParamSpec('joints', 'string_array', None,
              'Controlled joints = the effort controller\'s joint list; order of the command array. '
              'Empty: every movable non-mimic joint in URDF order.', False),
    ParamSpec('command_topic', 'string', 'effort_controller/commands',
              'std_msgs/Float64MultiArray effort command topic. Relative names resolve in the node\'s '
              'namespace: /effort_controller/commands without one, /<ns>/effort_controller/commands '
              'under -r __ns:=/<ns>.', False, nonempty=True),
    ParamSpec('publish_joint_state', 'bool', False,
              'Also publish the command as sensor_msgs/JointState (names + efforts) on ~/commanded_efforts.',
              True),
    ParamSpec('enabled', 'bool', True,
              'Publish commands. Disabling publishes one all-zero command, then nothing.', True),
    ParamSpec('mode', 'string', 'gravity',
              'Torque law. gravity: g(q) [+ C(q, qd) qd] + friction at the measured state. feedforward: '
              'M(q_d) qdd_d + C(q_d, qd_d) qd_d + g(q_d) + friction(qd_d) + Kp e + Kd de. computed_torque: '
              'M(q) (qdd_d + Kp e + Kd de) + C(q, qd) qd + g(q) + friction(qd). pd: Kp e + Kd de only. '
              'e = q_d - q, de = qd_d - qd. Without a fresh desired state: gravity at the measured state.',
              True, choices=MODES),
    ParamSpec('kp', 'double_array', [0.0],
              'Position gains of feedforward / computed_torque / pd (computed_torque: 1/s^2, else N m/rad); '
              'one value: every joint, or one per controlled joint in `joints` order.', True,
              constraints='empty (= 0), 1 or n finite doubles >= 0', per_joint='zero', minimum=0.0),
    ParamSpec('kd', 'double_array', [0.0],
              'Velocity gains, as kp (computed_torque: 1/s, else N m s/rad).', True,
              constraints='empty (= 0), 1 or n finite doubles >= 0', per_joint='zero', minimum=0.0),
    ParamSpec('desired_topic', 'string', '~/desired',
              'trajectory_msgs/JointTrajectory desired-state topic: one point with positions, optional '
              'velocities and accelerations (absent = 0), joints mapped by name.', False, nonempty=True),
    ParamSpec('desired_timeout', 'double', 0.1,
              'Seconds after the last valid desired state before a mode that needs it falls back to '
              'gravity compensation at the measured state.', True, (0.001, 60.0)),
    ParamSpec('gravity', 'double_array', [0.0, 0.0, -9.81],
              'Gravity in the URDF root frame, m/s^2 (3 doubles; wall or ceiling mounts).', True,
              constraints='3 finite doubles, norm <= 100', lengths=(3,), norm_max=100.0, unit='m/s^2'),
    ParamSpec('gravity_scale', 'double', 1.0, 'Scale of the gravity torques.', True, (0.0, 1.0)),
    ParamSpec('include_velocity_terms', 'bool', False,
              'Add C(q, qd) qd computed with the measured velocities.', True),
    ParamSpec('friction.viscous', 'double_array', None,
              'Viscous friction compensation b*qd, N m s/rad per joint. Empty: URDF <dynamics damping>; '
              'one value: every joint; [0.0]: off.', True, constraints='empty, 1 or n finite doubles >= 0',
              per_joint='urdf', minimum=0.0),
    ParamSpec('friction.coulomb', 'double_array', None,
              'Coulomb friction compensation fc*tanh(qd/eps), N m per joint. Empty: URDF <dynamics friction>; '
              'one value: every joint; [0.0]: off.', True, constraints='empty, 1 or n finite doubles >= 0',
              per_joint='urdf', minimum=0.0),
    ParamSpec('friction.coulomb_velocity_epsilon', 'double', COULOMB_VELOCITY_EPSILON,
              'eps of the smooth Coulomb term tanh(qd/eps), rad/s (or m/s).', True, (1e-6, 10.0)),
    ParamSpec('effort_limit_scale', 'double', 1.0,
              'Commands are clamped to URDF effort limits times this factor.', True, (0.0, 1.0)),
    ParamSpec('stale_timeout', 'double', 0.1,
              'Seconds without a valid joint_states message before stale_action is applied.', True,
              (0.005, 60.0)),
    ParamSpec('stale_action', 'string', 'hold_gravity_at_last_state',
              'On stale input publish once: gravity torques at the last valid state '
              '(hold_gravity_at_last_state) or zeros (zero).', True, choices=STALE_ACTIONS),
    ParamSpec('inertia_policy', 'string', 'warn',
              'Physically inconsistent link inertias in the description (see load_urdf). warn: use them as '
              'written, one log line per link and a WARN in the diagnostics. strict: reject the description '
              '(the previous model keeps running). repair: replace them by consistent ones, log before/after. '
              'Setting it reloads the current description.', True, choices=INERTIA_POLICIES),
    ParamSpec('description_update', 'string', 'same_robot',
              'Which robot descriptions may replace the running model (topic, parameters, ~/reload_model). '
              'same_robot: the same robot name and controlled joints; any: any description with the controlled '
              'joints; none: the first model stays, updates are refused. What changed (masses, limits) is logged.',
              True, choices=DESCRIPTION_UPDATES),
    ParamSpec('max_description_bytes', 'integer', 2_000_000,
              'Largest robot description accepted (UTF-8 bytes, or file size); larger ones are refused unread.',
              True, (1_000, 1_000_000_000)),
    ParamSpec('max_description_links', 'integer', 256,
              'Most <link> elements a robot description may have; more are refused before parsing (model build '
              'time and memory grow quickly with the link count).', True, (1, 1_000_000)),
    ParamSpec('max_trajectory_points', 'integer', 10_000,
              'Most points of a ~/trajectory_in message; longer trajectories are refused unprocessed.', True,
              (1, 100_000_000)),
    ParamSpec('position_margin', 'double', 0.5,
              'joint_states positions beyond a URDF joint limit by more than this (rad or m) are rejected '
              'like non-finite ones (nothing published).', True, (0.0, 1000.0)),
    ParamSpec('continuous_position_bound', 'double', 1e4,
              'Plausibility bound |q| (rad or m) for joints without URDF limits (continuous ones) and for '
              'locked joints: beyond it a joint_states message is rejected.', True, (1.0, 1e12)),
    ParamSpec('ramp_time', 'double', 0.2,
              'Seconds of the safe transitions (0: off): on enable the command ramps up from zero, on disable '
              'down to zero before going silent; a mode, payload, gravity or model change, and the return of '
              'joint_states after stale input, blend from the previous command to the new law. The stale action '
              'and the effort clamp apply during a ramp.', True, (0.0, 10.0)),
    ParamSpec('calibration_file', 'string', '',
              'calibration.yaml (identify_dynamics) applied to the model: its link inertias, armature and '
              'friction (as Model.damping / Model.friction, which empty friction.viscous / friction.coulomb use), '
              'and its effort offsets, subtracted from every measured effort the node reads (observer, payload '
              'identification). Empty: none. A file that is missing, malformed, for another robot or physically '
              'invalid is refused and the old values kept.', True),
    ParamSpec('payload.link', 'string', '', 'Link the payload is rigidly attached to (empty: none).', True),
    ParamSpec('payload.mass', 'double', 0.0, 'Payload mass, kg (0: no payload).', True, (0.0, 1000.0)),
    ParamSpec('payload.com', 'double_array', [0.0, 0.0, 0.0],
              'Payload centre of mass in the link frame, m (3 doubles).', True, constraints='3 finite doubles',
              lengths=(3,)),
    ParamSpec('payload.inertia', 'double_array', None,
              'Payload inertia about its CoM in link axes: ixx, ixy, ixz, iyy, iyz, izz (kg m^2). '
              'Empty: point mass.', True, constraints='empty or 6 finite doubles', lengths=(0, 6)),
    # gravity from a topic, robots that compensate gravity, payload identification (gravity_source.py,
    # payload_service.py)
    ParamSpec('gravity_topic', 'string', '',
              'geometry_msgs/Vector3Stamped gravity in the URDF root frame (a tilting or mobile base), m/s^2; '
              'followed while fresh, else the gravity parameter. Empty: off.', False),
    ParamSpec('gravity_timeout', 'double', 0.5,
              'Seconds after the last valid gravity_topic message before the gravity parameter is used again.',
              True, (0.001, 60.0)),
    ParamSpec('robot_compensates_gravity', 'bool', False,
              'The robot adds g(q) to the command itself (libfranka torque control, KUKA FRI torque mode, ...): '
              'every law leaves its gravity term out, the hold_gravity stale action is zero.', True),
    ParamSpec('identify.duration', 'double', 5.0,
              'Seconds of joint_states (stamp time) ~/identify_payload records.', True, (0.1, 600.0)),
    ParamSpec('identify.link', 'string', '', 'Link ~/identify_payload fits a payload on (empty: payload.link).',
              True),
    ParamSpec('identify.mode', 'string', 'dynamic',
              'dynamic: the arm moves, qdd is a smoothing derivative of the recorded qd (mass, CoM and inertia as '
              'far as the motion excites them); static: only samples at rest (mass and CoM).', True,
              choices=IDENTIFY_MODES),
    ParamSpec('identify.max_residual_ratio', 'double', 0.3,
              'An identification whose residual RMS exceeds this fraction of the payload torque RMS is refused.',
              True, (0.0, 1.0)),
    # recording for calibration (features/recording.py)
    ParamSpec('recording_dir', 'string', '',
              'Folder ~/record writes its rosbag2 folders into (created if missing). Empty: '
              '$ROS_HOME/lie_dynamics/recordings ($ROS_HOME defaults to ~/.ros).', True),
    ParamSpec('recording_max_s', 'double', 300.0,
              'Longest ~/record recording, s of joint_states (stamp time): then it stops by itself, is written, '
              'and says so in the log.', True, (0.1, 3600.0)),
    ParamSpec('diagnostics_period', 'double', 1.0, 'Period of /diagnostics, s.', False, (0.05, 60.0)),
    # external joint torques and collision detection (contact.py)
    ParamSpec('observer.enabled', 'bool', True,
              'Estimate external joint torques (~/external_torques, ~/collision) from the measured efforts with a '
              'generalized-momentum observer, whenever joint_states carries them.', True),
    ParamSpec('observer.gain', 'double', 50.0,
              'Observer gain K, 1/s: the estimate follows tau_ext as a first-order filter of time constant 1/K '
              '(higher: faster, noisier).', True, (0.1, 1000.0)),
    ParamSpec('measured_effort', 'string', 'total',
              'What joint_states effort holds. total: the motor torque, gravity included (ros2_control effort '
              'interfaces, most drives); gravity_removed: motor torque minus the gravity torques (g(q) is added '
              'back); none: no usable effort, the observer is off.', True, choices=EFFORT_CONVENTIONS),
    ParamSpec('collision.threshold', 'double_array', [10.0],
              'Collision when |external torque| exceeds this, N m (or N): one value for every joint, or one per '
              'controlled joint.', True, constraints='1 or n finite doubles > 0', per_joint='required', minimum=0.0,
              above=True, unit='N m'),
    ParamSpec('collision.hold_time', 'double', 0.01,
              'Seconds a threshold crossing (and its end) must last before ~/collision changes.', True, (0.0, 10.0)),
    # the contact link and the external wrench (contact_link.py)
    ParamSpec('contact.wrench_frame', 'string', '',
              'Link at which ~/contact/tool_wrench gives the wrench the external torques imply if all contact '
              'happens there (force and torque at its origin in its axes), at every observer sample. Empty: off. '
              'A link no controlled joint moves is refused.', True),
    ParamSpec('contact.rcond', 'double', RCOND,
              'Singular values of the transposed link Jacobian below this fraction of the largest are not solved '
              'for: the wrench components the joints barely see stay 0 (~/contact/wrench, ~/contact/tool_wrench; '
              'rank and smallest singular value used in the diagnostics).', True, (1e-12, 0.999)),
    ParamSpec('contact.tolerance', 'double', TOLERANCE,
              'Isolation: a joint torque is explained (or quiet) within this fraction of its collision.threshold '
              'at most; less where the residual\'s measured noise allows (6 x its noise, down to 0.2 x this). '
              'Above the residual\'s noise and model error in free motion, relative to the thresholds.', True,
              (1e-6, 1.0)),
    ParamSpec('contact.strict_isolation', 'bool', False,
              'Name a link only if no point contact within contact.link_radius of a link further out could give '
              'the same external torques with that link\'s own joints quiet (else: ambiguous). false: the most '
              'proximal link that explains the torques (ambiguous where its wrench, fully seen, is a force whose '
              'line may pass through the next link\'s joint axis), strict only for a weak residual '
              '(contact.strict_below).', True),
    ParamSpec('contact.link_radius', 'double', RADIUS,
              'A point contact lies within this distance (m) of the segments from a link\'s origin to its frames '
              'and next joints (contact.strict_isolation, and the next-link check of a fully seen wrench).', True,
              (1e-3, 10.0), unit='m'),
    ParamSpec('contact.strict_below', 'double', STRICT_BELOW,
              'A decision on a residual whose largest |external torque| / collision.threshold is below this uses '
              'the strict rule (as contact.strict_isolation), above it the default one: a weak push on a link '
              'hides from its own joint within a wider band of its axis, where the default rule names the link '
              f'before. {STRICT_BELOW:g} (default): never wrong in the benchmark, ambiguous more often below it; '
              '0: off (right more often below it, sometimes wrong).', True, (0.0, 1e6)),
    # dynamics terms for other nodes (dynamics_topics.py)
    ParamSpec('dynamics.publish', 'string_array', None,
              'Dynamics terms published on ~/dynamics/<term> after each command: gravity (g(q)), coriolis '
              '(C(q, qd) qd), mass_matrix (M(q)), jacobian (of dynamics.link). Empty: off.', True,
              constraints='a subset of ' + ', '.join(DYNAMICS_TERMS), choices=DYNAMICS_TERMS),
    ParamSpec('dynamics.rate', 'double', 100.0,
              'Most dynamics messages per second, by the joint_states stamps (steady clock for unstamped '
              'states); 0: one per accepted state.', True, (0.0, 100_000.0)),
    ParamSpec('dynamics.link', 'string', '',
              'Link of ~/dynamics/jacobian. Empty: the tip of the controlled chain (the last URDF link on the '
              'last body of the model).', True),
    ParamSpec('dynamics.jacobian_frame', 'string', 'world_aligned',
              'Frame of ~/dynamics/jacobian, as Model.jacobian: world_aligned (link origin velocity and angular '
              'velocity in root axes), local (the same in link axes), world (spatial twist).', True,
              choices=JACOBIAN_FRAMES),
)

SPECS = {p.name: p for p in PARAMS}
# The payload parameters, set together (~/set_payload, identification) and blended as one change.
PAYLOAD_KEYS = tuple(p.name for p in PARAMS if p.name.startswith('payload.'))


def _shown(value):
    """A value as a rejection reason quotes it: bounded (the reason goes back to the caller and the log)."""
    return clip(repr(value), 120)


def _finite_list(value, name):
    try:
        vals = [float(v) for v in value]
    except (TypeError, ValueError):
        raise ValueError(f'{name} must be a list of doubles') from None
    if not all(math.isfinite(v) for v in vals):
        raise ValueError(f'{name} must contain finite values, got {_shown(vals)}')
    return vals


def check_value(name, value):
    """Validate one parameter value independently of the model; return it normalised.

    Arrays come back as lists ([] for unset). Raises ValueError with the reason.
    """
    spec = SPECS.get(name)
    if spec is None:
        raise ValueError(f'unknown parameter {_shown(name)}')
    if spec.kind == 'bool':
        if not isinstance(value, bool):
            raise ValueError(f'{name} must be a bool')
        return value
    if spec.kind == 'string':
        if not isinstance(value, str):
            raise ValueError(f'{name} must be a string')
        if spec.choices and value not in spec.choices:
            raise ValueError(f'{name} must be one of {list(spec.choices)}, got {_shown(value)}')
        if spec.nonempty and not value.strip():
            raise ValueError(f'{name} must not be empty')
        return value
    if spec.kind == 'integer':
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError(f'{name} must be an integer')
        if spec.range and not spec.range[0] <= value <= spec.range[1]:
            raise ValueError(f'{name} must be in [{spec.range[0]}, {spec.range[1]}], got {value}')
        return value
    if spec.kind == 'double':
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f'{name} must be a double')
        v = float(value)
        if not math.isfinite(v):
            raise ValueError(f'{name} must be finite')
        if spec.range and not spec.range[0] <= v <= spec.range[1]:
            raise ValueError(f'{name} must be in [{spec.range[0]}, {spec.range[1]}], got {v}')
        return v
    if value is None:
        return []
    if spec.kind == 'string_array':
        vals = list(value)
        if not all(isinstance(v, str) and v for v in vals):
            raise ValueError(f'{name} must be a list of non-empty strings')
        if len(set(vals)) != len(vals):
            raise ValueError(f'{name} lists a name twice: {_shown(vals)}')
        bad = [v for v in vals if spec.choices and v not in spec.choices]
        if bad:
            raise ValueError(f'{name}: unknown {_shown(bad[0])}, use a subset of {list(spec.choices)}')
        return vals
    vals = _finite_list(value, name)
    if spec.lengths and len(vals) not in spec.lengths:
        sizes = ' or '.join(str(k) for k in spec.lengths if k)
        need = f'be empty or have {sizes}' if 0 in spec.lengths else f'have {sizes}'
        raise ValueError(f'{name} must {need} values, got {len(vals)}')
    if spec.norm_max is not None and math.sqrt(sum(v * v for v in vals)) > spec.norm_max:
        raise ValueError(f'{name} norm must be <= {spec.norm_max:g} {spec.unit} (units?), got {_shown(vals)}')
    need = 'one or more values' if spec.per_joint == 'required' else ''
    lo = spec.minimum
    if (need and not vals) or (lo is not None and any(v < lo or (spec.above and v == lo) for v in vals)):
        bound = '' if lo is None else f"{' ' if need else ''}{'>' if spec.above else '>='} {lo:g}"
        raise ValueError(f'{name} must be {need}{bound}, got {_shown(vals)}')
    return vals


def per_joint_values(name, values, n, urdf=None):
    """Per-joint parameter `name` (its spec's per_joint shape) for n controlled joints, as n floats:
    broadcast_joints of its values; empty is `urdf` (shape 'urdf'), zeros ('zero') or refused
    ('required'). Every entry finite and within the spec's minimum. Raises ValueError."""
    spec = SPECS[name]
    if len(values) == 0 and spec.per_joint == 'urdf':
        out = np.asarray(urdf, dtype=float).copy()
    elif len(values) == 0 and spec.per_joint == 'zero':
        out = np.zeros(n)
    else:
        out = broadcast_joints(values, n)
    if out is None:
        counts = '0, 1 or' if spec.per_joint == 'urdf' else '1 or'
        raise ValueError(f'{name} must have {counts} {n} values (one per controlled joint), got {len(values)}')
    lo = spec.minimum
    if not np.all(np.isfinite(out)) or (lo is not None and (np.any(out < lo) or (spec.above and np.any(out == lo)))):
        bound = '' if lo is None else f" and {'>' if spec.above else '>='} {lo:g}"
        unit = f' ({spec.unit})' if spec.unit else ''
        raise ValueError(f'{name} must be finite{bound}{unit}, got {_shown(out.tolist())}')
    return out


# `dynamics_node --help`: what it does, the parameters most set-ups touch, an example.
HELP_DESCRIPTION = """\
Gravity compensation / torque feedforward: turns each sensor_msgs/JointState on joint_states into
a std_msgs/Float64MultiArray effort command (ros2_control JointGroupEffortController), computed
from the robot model (robot_description topic or parameter, or urdf_path). Also fills the effort
of trajectories on ~/trajectory_in (-> ~/trajectory_out) and publishes /diagnostics.

Every parameter, topic, service and QoS: docs/node.md in the source repository, or
`ros2 param describe /dynamics_node <name>` on a running node."""
HELP_EXAMPLE = """
python -m lie_dynamics.dynamics_node --ros-args -p urdf_path:=config/arm7.urdf
dynamics_node --ros-args --params-file config/arm7_gravity.yaml -p mode:=feedforward -p "kp:=[50.0]"
"""
HELP_PARAMS = ('robot_description', 'urdf_path', 'joints', 'command_topic', 'mode', 'kp', 'kd', 'gravity',
               'include_velocity_terms', 'effort_limit_scale', 'stale_timeout', 'stale_action', 'enabled',
               'inertia_policy', 'payload.link', 'payload.mass')


def help_rows(names=HELP_PARAMS):
    """(name, default, meaning) rows for --help: the first sentence of each description, and
    the accepted values of a choice."""
    rows = []
    for name in names:
        spec = SPECS[name]
        meaning = spec.description.split('. ')[0].rstrip('.')
        if spec.kind == 'string' and spec.constraints and spec.constraints.split(' or ')[-1] not in meaning:
            meaning += f': {spec.constraints}'
        rows.append((name, [] if spec.default is None else spec.default, meaning))
    return rows


def defaults():
    """{name: normalised default value}."""
    return {p.name: check_value(p.name, p.default) for p in PARAMS}
