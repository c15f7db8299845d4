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
from highway_env.vehicle.objects import Landmark, Obstacle, RoadObject

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

BUILTIN_FIELDS: frozenset[str] = frozenset(FIELDS)

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

# Open intervals the class parameters must lie in: IDM's desired gap divides by
# sqrt(COMFORT_ACC_MAX * -COMFORT_ACC_MIN), which is 0 or NaN outside them.
CLASS_PARAMETER_DOMAINS: dict[tuple[type, str], tuple[float, float]] = {
    (IDMVehicle, "COMFORT_ACC_MAX"): (0.0, float("inf")),
    (IDMVehicle, "COMFORT_ACC_MIN"): (float("-inf"), 0.0),
}

#: The largest magnitude a float of a highway-env state may hold (metres, m/s,
#: radians, seconds): a billion seconds of driving would not reach it, and larger
#: values (a flipped exponent bit) overflow to inf within a few steps.
MAX_MAGNITUDE = 1e9

# Closed ranges of float fields narrower than MAX_MAGNITUDE: a road object of zero
# length or width is a degenerate polygon, which the collision test cannot handle.
FIELD_DOMAINS: dict[str, tuple[float, float]] = {
    "LENGTH": (5e-324, MAX_MAGNITUDE),
    "WIDTH": (5e-324, MAX_MAGNITUDE),
}

# Fields every instance of a class (and of its subclasses) holds: what the class's
# __init__ sets. A restored object without them would fail mid-step.
CLASS_FIELDS: dict[type, frozenset[str]] = {
    RoadObject: frozenset(
        {
            "position",
            "heading",
            "speed",
            "lane_index",
            "collidable",
            "solid",
            "check_collisions",
            "diagonal",
            "crashed",
            "hit",
            "impact",
        }
    ),
    Vehicle: frozenset({"action", "prediction_type"}),
    ControlledVehicle: frozenset({"target_lane_index", "target_speed", "route"}),
    MDPVehicle: frozenset({"target_speeds", "speed_index"}),
    IDMVehicle: frozenset({"enable_lane_change", "timer"}),
    BicycleVehicle: frozenset({"lateral_speed", "yaw_rate"}),
}

# The built-in fields highway-env sets to None: every other built-in field holds a
# value (fields users register may be None).
NULLABLE_FIELDS: frozenset[str] = frozenset({"impact", "route", "color", "goal"})


def required_fields(cls: type) -> frozenset[str]:
    """The fields every instance of ``cls`` holds (see :data:`CLASS_FIELDS`).

    Example:
        >>> sorted(required_fields(IDMVehicle) - required_fields(Vehicle))
        ['enable_lane_change', 'route', 'target_lane_index', 'target_speed', 'timer']
    """
    out: frozenset[str] = frozenset()
    for base in cls.__mro__:
        out |= CLASS_FIELDS.get(base, frozenset())
    return out


def not_nullable_fields() -> frozenset[str]:
    """The built-in fields that are never ``None``: the module's own but the nullable ones.

    Example:
        >>> {"speed", "impact"} & not_nullable_fields()
        {'speed'}
    """
    return BUILTIN_FIELDS - NULLABLE_FIELDS


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
