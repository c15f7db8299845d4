"""What a highway-env road object is made of: the field vocabulary and the class registry.

Every attribute found in a vehicle's or object's ``__dict__`` must either be in
:data:`FIELDS` (it is stored in the snapshot) or in :data:`DERIVED_ATTRIBUTES` (it
is rebuilt on restore). Anything else makes the snapshot fail with an
:class:`~torchrl_grpo.envs.UnknownFieldError` that names the class and attribute,
because silently dropping it could change the future.

Users extend both tables for their own classes with :func:`register_vehicle_class`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.controller import ControlledVehicle, MDPVehicle
from highway_env.vehicle.dynamics import BicycleVehicle
from highway_env.vehicle.kinematics import Vehicle
from highway_env.vehicle.objects import Landmark, Obstacle

FieldKind = Literal[
    "float",
    "int",
    "bool",
    "vec2",
    "lane",
    "route",
    "speeds",
    "color",
    "ref",
    "enum",
    "action",
    "array",
]

MAX_COLOR = 4  # RGB or RGBA


@dataclass(frozen=True)
class Field:
    """How one attribute of a road object is stored.

    Args:
        kind: the encoding. ``float``/``int``/``bool``: a scalar; ``vec2``: a float64[2]
            array; ``lane``: a lane index ``(from, to, id)``; ``route``: a list of lane
            indices; ``speeds``: a 1-D array of target speeds; ``color``: a tuple of
            ints; ``ref``: another road object; ``enum``: one of ``choices``;
            ``action``: the ``{"steering", "acceleration"}`` dict; ``array``: a float64
            array of ``shape``.
        shape: the shape of an ``array`` field.
        choices: the values of an ``enum`` field.

    Example:
        >>> Field("float")
        Field(kind='float', shape=(), choices=())
    """

    kind: FieldKind
    shape: tuple[int, ...] = ()
    choices: tuple[str, ...] = ()


FIELDS: dict[str, Field] = {
    # RoadObject
    "position": Field("vec2"),
    "heading": Field("float"),
    "speed": Field("float"),
    "lane_index": Field("lane"),
    "collidable": Field("bool"),
    "solid": Field("bool"),
    "check_collisions": Field("bool"),
    "diagonal": Field("float"),
    "crashed": Field("bool"),
    "hit": Field("bool"),
    # A displacement applied on the NEXT frame: it can cross an env.step boundary.
    "impact": Field("vec2"),
    # Per-instance overrides of class constants (parking walls, u-turn ego, speed_range).
    "LENGTH": Field("float"),
    "WIDTH": Field("float"),
    "MIN_SPEED": Field("float"),
    "MAX_SPEED": Field("float"),
    "PURSUIT_TAU": Field("float"),
    # Vehicle
    "prediction_type": Field("enum", choices=("constant_steering", "zero_steering")),
    "action": Field("action"),
    "color": Field("color"),
    "goal": Field("ref"),
    # ControlledVehicle / MDPVehicle
    "target_lane_index": Field("lane"),
    "target_speed": Field("float"),
    "route": Field("route"),
    "target_speeds": Field("speeds"),
    "speed_index": Field("int"),
    # IDMVehicle (and intersection regulation)
    "enable_lane_change": Field("bool"),
    "timer": Field("float"),
    "DELTA": Field("float"),
    "is_yielding": Field("bool"),
    "yield_timer": Field("int"),
    # BicycleVehicle
    "lateral_speed": Field("float"),
    "yaw_rate": Field("float"),
}

# Rebuilt on restore rather than stored: references to the env's road and lane
# objects, render-only buffers, and BicycleVehicle's linearised dynamics (a pure
# function of class constants, recomputed before every use).
DERIVED_ATTRIBUTES: frozenset[str] = frozenset(
    {"road", "lane", "log", "history", "theta", "A_lat", "B_lat"}
)

VEHICLE_CLASSES: list[type] = [
    Obstacle,
    Landmark,
    Vehicle,
    ControlledVehicle,
    MDPVehicle,
    IDMVehicle,
    BicycleVehicle,
]

# Class attributes that scenarios overwrite for the whole process (intersection-v0
# writes these on IDMVehicle). They are part of the state: without them a state is
# not exact in a process that created intersection-v0 before.
CLASS_PARAMETERS: list[tuple[type, str]] = [
    (IDMVehicle, "COMFORT_ACC_MAX"),
    (IDMVehicle, "COMFORT_ACC_MIN"),
    (IDMVehicle, "DISTANCE_WANTED"),
]

# The values the classes are defined with, so that a fresh episode does not inherit
# another scenario's overwrite (highway-env itself would).
PRISTINE_CLASS_PARAMETERS: dict[tuple[type, str], float] = {
    (cls, name): float(getattr(cls, name)) for cls, name in CLASS_PARAMETERS
}


def register_vehicle_class(cls: type, fields: dict[str, Field] | None = None) -> None:
    """Make a road-object class, and the extra attributes it carries, snapshottable.

    Call it before creating the env whose scenario uses the class: an env fixes its
    state layout when it is built.

    Args:
        cls: a subclass of highway-env's ``RoadObject``.
        fields: its attributes that the vocabulary does not hold yet, by name.

    Raises:
        ValueError: a field name is already registered with another kind.

    Example:
        >>> from highway_env.vehicle.behavior import IDMVehicle
        >>> class PatientIDM(IDMVehicle):
        ...     pass
        >>> register_vehicle_class(PatientIDM, {"patience": Field("float")})
        >>> PatientIDM in VEHICLE_CLASSES
        True
    """
    for name, field in (fields or {}).items():
        known = FIELDS.get(name)
        if known is not None and known != field:
            raise ValueError(
                f"field {name!r} is already registered as {known}; cannot register it as {field}"
            )
    FIELDS.update(fields or {})
    if cls not in VEHICLE_CLASSES:
        VEHICLE_CLASSES.append(cls)


def register_class_parameter(cls: type, name: str) -> None:
    """Store a process-global class attribute in every state captured from now on.

    Use it for class constants that your scenario overwrites at run time.

    Args:
        cls: the class holding the attribute.
        name: the attribute name.

    Example:
        >>> class Weather:
        ...     FRICTION = 1.0
        >>> register_class_parameter(Weather, "FRICTION")
        >>> (Weather, "FRICTION") in CLASS_PARAMETERS
        True
    """
    if (cls, name) not in CLASS_PARAMETERS:
        CLASS_PARAMETERS.append((cls, name))
        PRISTINE_CLASS_PARAMETERS[(cls, name)] = float(getattr(cls, name))
