"""Node parameters declared from tables (issue 21).

A node keeps the static part of its parameters - name, default, description, range, choices,
a value check - in a module-level tuple of :class:`ParamSpec`, and declares them in one call,
:func:`declare_params`, that goes through :meth:`TrackingNode.param` (so the descriptors, the
validation of initial values and of changes, and the live updates stay what ``param`` does).
What needs the node instance - the ``live`` callbacks that reconfigure it after an accepted
change, and checks that read its state - is attached by parameter name in ``__init__``.

The table reads like the parameter list of the node's documentation and is short per line;
defaults that belong to a core config dataclass are taken from an instance of it (e.g.
``WorldAlignmentConfig().hard_iron_sigma``), so the node and the core cannot disagree.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any, Callable, Iterable, Mapping

import numpy as np

if TYPE_CHECKING:
    from ..core.imu_orientation import ImuCalibration
    from .node_base import TrackingNode

Validator = Callable[[Any], 'str | None']


def one_of(choices: Iterable[str], reason: str = 'must be one of') -> Validator:
    """Parameter validator: the value is one of ``choices``; the reason lists them."""
    options = tuple(choices)
    return lambda v: None if v in options else f'{reason} {", ".join(options)}'


def frame_name(v: Any) -> str | None:
    """Parameter validator: a TF frame name (not empty, no leading slash, no surrounding spaces)."""
    if v and v.strip() == v and not v.startswith('/'):
        return None
    return 'a frame name: not empty, no leading slash or spaces'


def length_is(n: int) -> Validator:
    """Parameter validator: a list of exactly n values."""
    return lambda v: None if len(v) == n else f'needs {n} values, got {len(v)}'


def unit_quaternion(v: Any) -> str | None:
    """Parameter validator: a unit quaternion (x, y, z, w), norm within 1e-3 of one."""
    if len(v) != 4:
        return f'needs 4 values (x, y, z, w), got {len(v)}'
    norm = float(np.linalg.norm(np.asarray(v, dtype=float)))
    return None if abs(norm - 1.0) < 1e-3 else f'not a unit quaternion (norm {norm:.4g})'


def invertible_3x3(v: Any) -> str | None:
    """Parameter validator: a row-major 3x3 matrix that can be inverted."""
    if len(v) != 9:
        return f'needs 9 values (row-major 3x3), got {len(v)}'
    if abs(float(np.linalg.det(np.reshape(np.asarray(v, float), (3, 3))))) < 1e-6:
        return 'matrix is singular'
    return None


@dataclass(frozen=True)
class ParamSpec:
    """The static declaration of one node parameter.

    ``min_value``/``max_value`` become the descriptor's range (numbers only); ``choices`` and
    ``validate`` check the initial value and every change (both must pass; ``choices`` is
    checked first). ``read_only`` is what ``TrackingNode.param`` takes: a parameter is writable
    at run time only when the node attaches a ``live`` callback to it.
    """

    name: str
    default: Any
    description: str
    min_value: float | None = None
    max_value: float | None = None
    read_only: bool = True
    choices: tuple[str, ...] | None = None
    validate: Validator | None = None

    def validator(self, extra: Validator | None = None) -> Validator | None:
        """The combined check of ``choices``, ``validate`` and ``extra`` (None if there is none)."""
        by_choice = one_of(self.choices) if self.choices is not None else None
        checks = [c for c in (by_choice, self.validate, extra) if c is not None]
        if not checks:
            return None
        if len(checks) == 1:
            return checks[0]

        def check(v: Any) -> str | None:
            for c in checks:
                reason = c(v)
                if reason is not None:
                    return reason
            return None

        return check


def declare_params(
    node: TrackingNode,
    table: Iterable[ParamSpec],
    *,
    live: Mapping[str, Callable[[Any], None]] | None = None,
    validate: Mapping[str, Validator] | None = None,
) -> dict[str, Any]:
    """Declare every parameter of ``table`` on ``node`` (in table order); name -> value.

    ``live`` attaches the callback that applies an accepted change (the parameter is then
    writable), ``validate`` adds a check that needs the node; both are keyed by parameter name,
    and a name that is not in the table is a programming error (KeyError), so a renamed
    parameter cannot silently lose its callback.
    """
    specs = list(table)
    names = [s.name for s in specs]
    if len(set(names)) != len(names):
        raise KeyError(f'parameter table declares a name twice: {sorted({n for n in names if names.count(n) > 1})}')
    live = dict(live or {})
    validate = dict(validate or {})
    unknown = (set(live) | set(validate)) - set(names)
    if unknown:
        raise KeyError(f'callbacks for parameters not in the table: {", ".join(sorted(unknown))}')
    values: dict[str, Any] = {}
    for s in specs:
        # a list default is copied, so that nothing the node does with the value changes the table
        default = list(s.default) if isinstance(s.default, list) else s.default
        values[s.name] = node.param(
            s.name, default, s.description,
            min_value=s.min_value, max_value=s.max_value, read_only=s.read_only,
            validate=s.validator(validate.get(s.name)), live=live.get(s.name),
        )
    return values


def with_defaults(table: Iterable[ParamSpec], **defaults: Any) -> tuple[ParamSpec, ...]:
    """The table with the defaults of the named parameters replaced (a subclass's own default,
    e.g. camera_replay's topics); a name that is not in the table is a KeyError."""
    specs = tuple(table)
    unknown = set(defaults) - {s.name for s in specs}
    if unknown:
        raise KeyError(f'defaults for parameters not in the table: {", ".join(sorted(unknown))}')
    return tuple(replace(s, default=defaults[s.name]) if s.name in defaults else s for s in specs)


#: The device calibration every node that reads raw IMU samples shares (imu_magnetometer,
#: hybrid_orientation_filter), in the order it was always declared: a node splices it into its
#: table where the calibration belongs (``PARAMS = (..., *IMU_CALIBRATION_PARAMS, ...)``) and
#: builds the core calibration from the declared values with :func:`imu_calibration`.
IMU_CALIBRATION_PARAMS = (
    ParamSpec('hard_iron_offset', [0.0, 0.0, 0.0], 'Hard-iron offset subtracted from the raw field, tesla',
              validate=length_is(3)),
    ParamSpec('gyro_bias', [0.0, 0.0, 0.0], 'Gyro bias subtracted from angular_velocity, rad/s (x, y, z)',
              validate=length_is(3)),
    ParamSpec('accel_bias', [0.0, 0.0, 0.0], 'Accelerometer bias subtracted from linear_acceleration, m/s^2',
              validate=length_is(3)),
    ParamSpec('soft_iron_matrix', [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
              'Soft-iron correction, row-major 3x3: field = M (raw - hard_iron_offset)', validate=invertible_3x3),
)


def imu_calibration(values: Mapping[str, Any], extra_hard_iron: Any = (0.0, 0.0, 0.0)) -> ImuCalibration:
    """The core ImuCalibration of the declared :data:`IMU_CALIBRATION_PARAMS` values (name ->
    value, as :func:`declare_params` returns them); ``extra_hard_iron`` is added to the offset
    (imu_magnetometer's imu_filter_madgwick-named mag_bias_x/y/z)."""
    from ..core.imu_orientation import ImuCalibration

    return ImuCalibration(
        gyro_bias=values['gyro_bias'],
        accel_bias=values['accel_bias'],
        hard_iron_offset=np.asarray(values['hard_iron_offset'], dtype=float) + np.asarray(extra_hard_iron, dtype=float),
        soft_iron_matrix=values['soft_iron_matrix'],
    )
