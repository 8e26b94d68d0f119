"""Autopilot parameters, typed: PARAM_REQUEST_READ / PARAM_SET -> PARAM_VALUE.

Integer parameters come back as ``int`` and floats as ``float``. The wire encoding of
integers differs (see :func:`skyfix.drivers.units.param_from_wire`): ArduPilot casts them
to float, PX4 copies their bytes. A write uses the type the autopilot reported for the
name (read first when unknown), so an INT32 goes out as an INT32 on either autopilot.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

from skyfix import validate
from skyfix.drivers import units
from skyfix.drivers.mav import mavlink
from skyfix.drivers.request import AGAIN, DONE, transact
from skyfix.errors import CommandRejected, InputError, SkyfixTimeout

if TYPE_CHECKING:
    from skyfix.drivers.vehicle import Vehicle

M = mavlink


def param_name(msg) -> str:
    """The parameter name of a PARAM_VALUE (NUL padding removed)."""
    pid = msg.param_id if isinstance(msg.param_id, str) else msg.param_id.decode(errors="replace")
    return pid.rstrip("\x00")


def check_name(name: str) -> str:
    if not isinstance(name, str) or not 0 < len(name) <= 16:
        raise InputError(f"parameter name must be a string of 1-16 characters, got {name!r}")
    return name


def bytewise(vehicle: Vehicle) -> bool:
    """PX4 encodes integer parameters byte-wise; ArduPilot casts them."""
    return vehicle.autopilot == "px4"


def decode(vehicle: Vehicle, msg) -> int | float:
    return units.param_from_wire(msg.param_value, msg.param_type, bytewise(vehicle))


def get_param(vehicle: Vehicle, name: str, *, timeout_s: float = 1.0, retries: int = 3) -> int | float:
    """Read one parameter; int for the autopilot's integer types, float otherwise."""
    name = check_name(name)
    try:
        msg = transact(vehicle, M.MAVLink_param_request_read_message(
            vehicle.system_id, vehicle.component_id, name.encode(), -1),
            lambda m: DONE if param_name(m) == name else None, types=("PARAM_VALUE",),
            timeout_s=timeout_s, retries=retries, what=f"PARAM_REQUEST_READ {name}")
    except SkyfixTimeout as exc:
        raise SkyfixTimeout(f"vehicle {vehicle.system_id} did not report parameter {name} (it may "
                            f"not exist on this {vehicle.autopilot} firmware): {exc}") from None
    return decode(vehicle, msg)


def set_param(vehicle: Vehicle, name: str, value: float, *, timeout_s: float = 1.0,
              retries: int = 3) -> int | float:
    """Write one parameter and wait for the PARAM_VALUE echo; returns the value it holds."""
    name = check_name(name)
    value = validate.finite_scalar(f"value of {name}", value)
    ptype = vehicle.param_types.get(name)
    if ptype is None:
        get_param(vehicle, name, timeout_s=timeout_s, retries=retries)
        ptype = vehicle.param_types.get(name, units.REAL32)
    if units.param_is_int(ptype) and value != round(value):
        raise InputError(f"{name} is an integer parameter on vehicle {vehicle.system_id}, got {value}")
    wire = units.param_to_wire(value, ptype, bytewise(vehicle))

    def holds(got: float) -> bool:
        return abs(got - value) <= 1e-6 * max(1.0, abs(value))

    def verdict(m) -> str | None:
        # an echo of another value may be a late one of an earlier set of the same name (a retry's, or a loop that
        # sets it every period: SITL under load, tests/datasets/test_sitl_gnss.py): set again; the last attempt's
        # answer stands (the autopilot refused or clamped the value)
        if param_name(m) != name:
            return None
        return DONE if holds(decode(vehicle, m)) else AGAIN

    msg = transact(vehicle, M.MAVLink_param_set_message(vehicle.system_id, vehicle.component_id,
                                                        name.encode(), wire, ptype),
                   verdict, types=("PARAM_VALUE",), timeout_s=timeout_s, retries=retries,
                   what=f"PARAM_SET {name}={value:g}")
    got = decode(vehicle, msg)
    if not holds(got):
        raise CommandRejected(f"vehicle {vehicle.system_id} kept {name}={got} instead of {value:g}"
                              f"{vehicle._reasons(time.monotonic() - 2.0)}", command="PARAM_SET")
    return got
