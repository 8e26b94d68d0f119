"""The simulated autopilot's parameter protocol (PARAM_REQUEST_LIST / _READ, PARAM_SET ->
PARAM_VALUE), in ArduPilot's (C cast) or PX4's (byte-wise) integer encoding.

Mixed into :class:`skyfix.datasets.sim.server.VehicleServer`.
"""

from __future__ import annotations

import math

from skyfix.datasets.sim.vehicle import INT_PARAMS
from skyfix.drivers.mav import mavlink
from skyfix.drivers.units import param_from_wire, param_to_wire

M = mavlink


class ParamProtocol:
    """PARAM_* handlers over ``self.vehicle.params``."""

    def _param_type(self, name: str) -> int:
        return M.MAV_PARAM_TYPE_INT32 if name in INT_PARAMS else M.MAV_PARAM_TYPE_REAL32

    def _param_value(self, name: str):
        names = list(self.vehicle.params)
        ptype = self._param_type(name)
        wire = param_to_wire(self.vehicle.params[name], ptype, self.vehicle.flavour == "px4")
        return M.MAVLink_param_value_message(name.encode(), wire, ptype, len(names), names.index(name))

    def _on_param_list(self, msg, addr) -> None:
        for name in list(self.vehicle.params):
            self.send(self._param_value(name), addr)

    def _on_param_read(self, msg, addr) -> None:
        names = list(self.vehicle.params)
        name = msg.param_id if isinstance(msg.param_id, str) else msg.param_id.decode(errors="replace")
        name = name.rstrip("\x00")
        if msg.param_index >= 0:
            if msg.param_index >= len(names):
                return
            name = names[msg.param_index]
        if name in self.vehicle.params:
            self.send(self._param_value(name), addr)

    def _on_param_set(self, msg, addr) -> None:
        name = msg.param_id if isinstance(msg.param_id, str) else msg.param_id.decode(errors="replace")
        name = name.rstrip("\x00")
        if name not in self.vehicle.params:
            self.statustext(f"Param set failed: {name} not found", M.MAV_SEVERITY_WARNING)
            return
        # decoded with the parameter's own type (a client sending the wrong type gets what
        # the firmware would make of the bytes)
        value = param_from_wire(msg.param_value, self._param_type(name), self.vehicle.flavour == "px4")
        if not math.isfinite(value):
            self.statustext(f"Param set failed: {name} not finite", M.MAV_SEVERITY_WARNING)
            return
        self.vehicle.params[name] = value
        self.send(self._param_value(name))
