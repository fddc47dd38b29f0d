"""The dynamics node's parameters and its own two services: the rclpy side of
loading/parameter_change.py, which decides.

rclpy calls the on-set callback (`validate`) with the whole change; only when it accepts are
the values set, and then the post-set callback (`apply`) runs: the plan becomes current (the one
zero command on disable, the timer period, ~/commanded_efforts, the features) and a new
description or policy starts loading in the background.

Services (QoS: interfaces.py)
    ~/set_enabled    std_srvs/SetBool: sets the `enabled` parameter (the same checks and ramp)
    ~/reload_model   std_srvs/Trigger: starts the reload and answers at once; the running model
                     answers until the new one is ready (result: log, diagnostics)
"""
from rcl_interfaces.msg import SetParametersResult
from rclpy.parameter import Parameter

from . import interfaces
from .core.log import guarded
from .core.params import SPECS
from .loading.parameter_change import ParameterChanges, reload_answer


class Control:
    """Attached to a DynamicsNode `node` (its public core, lock, background, sources, outputs,
    features and log); check(settings): the checks that need the layout or the model."""

    def __init__(self, node, check):
        self.node, self.core, self.log_event = node, node.core, node.log_event   # log_event: for guarded
        self.changes = ParameterChanges(node.core, check, node.background.precheck, self.current_source)
        interfaces.service(node, '~/set_enabled', self._srv_set_enabled)
        interfaces.service(node, '~/reload_model', self._srv_reload)
        node.add_on_set_parameters_callback(self.validate)
        node.add_post_set_parameters_callback(self.apply)

    def current_source(self):
        """(kind, text) to reload (Sources.reload_source), or (None, None)."""
        node = self.node
        return node.sources.reload_source(node.get_parameter('robot_description').value,
                                          node.get_parameter('urdf_path').value)

    def validate(self, params):
        node = self.node
        with node.lock:
            reason = self.changes.validate({p.name: p.value for p in params if p.name in SPECS})
            if reason is not None:
                node.drain_events()
        return SetParametersResult(successful=reason is None, reason=reason or '')

    def apply(self, params):
        changes = {p.name: p.value for p in params if p.name in SPECS}
        if not changes:
            return
        node, core = self.node, self.core
        with node.lock:
            try:
                cmd, load = self.changes.apply(changes)
            except ValueError as exc:  # only if the state moved between validation and now
                node.log_event('error', 'parameters', f'parameter change {sorted(changes)} not applied: {exc}')
                node.drain_events()
                return
            if cmd is not None:
                node.outputs.command(cmd, core.layout)
            if load is not None:
                node.background.request(*load)
            if 'stale_timeout' in changes:
                node.set_tick_period()
            if 'publish_joint_state' in changes:
                node.outputs.joint_state(core.settings.publish_joint_state)
            node.configure_features()  # publishers made here, not on the control path
            node.drain_events()

    @guarded
    def _srv_set_enabled(self, request, response):
        result = self.node.set_parameters([Parameter('enabled', Parameter.Type.BOOL, bool(request.data))])[0]
        response.success = result.successful
        response.message = ('enabled' if request.data else 'disabled') if result.successful else result.reason
        return response

    @guarded
    def _srv_reload(self, request, response):
        node = self.node
        with node.lock:
            kind, text = self.current_source()
            err = None if kind is None else node.background.request(kind, text)
            node.drain_events()
        response.success, response.message = reload_answer(kind, text, err)
        return response
