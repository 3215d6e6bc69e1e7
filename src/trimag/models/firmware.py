"""The parameters ArduPilot and PX4 load for a magnetometer, and each firmware's own correction, in its order.

**ArduPilot** (``libraries/AP_Compass/AP_Compass_Backend.cpp``: ``rotate_field`` then ``correct_field``; 4.x order)::

    r = R v                                  R = COMPASS_ORIENTn (external) or AHRS_ORIENTATION (internal)
    B = M (s (r + OFS)) + MOT x              mGauss, body frame
    M = [[DIA_X, ODI_X, ODI_Y], [ODI_X, DIA_Y, ODI_Z], [ODI_Y, ODI_Z, DIA_Z]]

``s`` = ``COMPASS_SCALEn``, applied only within [1/1.5, 1.5] (``Compass::have_scale_factor``, ``AP_Compass_config.h``;
0, the default, means "no scale"); ``M`` is skipped when every DIA is zero; ``x`` = throttle 0..1
(``COMPASS_MOTCT`` = 1, set only by Copter and Sub: ``Copter::update_batt_compass``) or the battery current in A
(``COMPASS_MOTCT`` = 2), and ``MOT x`` is added after the matrix ("matches the way compassmot computes it").

**PX4** (``src/lib/sensor_calibration/Magnetometer.hpp``, ``Magnetometer::Correct``)::

    B = R (S ((v + p COMP) - OFF))            gauss; OFF and COMP in the sensor's frame
    S = [[XSCALE, XODIAG, YODIAG], [XODIAG, YSCALE, ZODIAG], [YODIAG, ZODIAG, ZSCALE]]

``R`` from ``CAL_MAGn_ROT`` (``get_rot_matrix``, ``src/lib/conversion/rotation.cpp``); ``p`` = thrust 0..1
(``CAL_MAG_COMP_TYP`` = 1) or the battery current in **kA** (2: battery 0, 3: battery 1; ``current_a * 0.001`` in
``VehicleMagnetometer::UpdatePowerCompensation``, ``src/modules/sensors/vehicle_magnetometer``).

Rotations ``v' = R v`` with ``R = Rz(yaw) Ry(pitch) Rx(roll)`` (ArduPilot ``Matrix3::from_euler``, PX4
``matrix::Dcm(Euler)``); the angles of each enum value are those of ArduPilot's ``libraries/AP_Math/rotations.h``
and its ``tests/test_rotations.cpp`` (value 38: 68.8 / 293.3 deg), PX4's ``src/lib/conversion/rotation.h``
(``rot_lookup``: 0..40, value 38 with the integer angles 68 / 293).

Both firmwares reduce to one algebra that the fit works in (:mod:`trimag.vehicle.firmware`): with ``u`` the raw
reading in the firmware's frame (ArduPilot: after ``R``; PX4: before it) and ``A`` symmetric,

    B~ = A (u + o) + m x         ArduPilot: A = s M, o = OFS, m = MOT, B~ = B
                                 PX4:       A = S,  o = -OFF, m = S COMP f, B~ = R^T B

(``f`` = 0.001 kA per A for a current, 1 for thrust).
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Collection, Mapping
from typing import Any, ClassVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import TrimagInputError

__all__ = [
    "ARDUPILOT_ROTATIONS",
    "COMPLETE_PARAMETER_LIST",
    "FEATURE_NAMES",
    "FIRMWARE_FEATURES",
    "FIRMWARE_TARGETS",
    "ORIENTATION_TOLERANCE_DEG",
    "PX4_ROTATIONS",
    "ArduPilotCompass",
    "FirmwareCompass",
    "PX4Magnetometer",
    "Violation",
    "absent_features",
    "absent_parameters",
    "compass_from_affine",
    "euler_matrix",
    "firmware_class",
    "instance_names",
    "nearest_rotation",
    "rotation_matrix",
    "without_features",
]

FIRMWARE_TARGETS = ("ardupilot", "px4")
#: The largest rotation (degrees) beyond the nearest standard sensor rotation that a calibration may leave to the
#: firmware's symmetric matrix (which cannot hold it: it stays as a heading error of about this size).
ORIENTATION_TOLERANCE_DEG = 5.0

#: ArduPilot ``enum Rotation`` (``libraries/AP_Math/rotations.h``): value -> (name, roll, pitch, yaw) in degrees
#: (``tests/test_rotations.cpp``, ``TEST(RotationsTest, TestEulers)``). ``COMPASS_ORIENTn`` takes 0..43.
ARDUPILOT_ROTATIONS: dict[int, tuple[str, float, float, float]] = {
    0: ("NONE", 0, 0, 0), 1: ("YAW_45", 0, 0, 45), 2: ("YAW_90", 0, 0, 90), 3: ("YAW_135", 0, 0, 135),
    4: ("YAW_180", 0, 0, 180), 5: ("YAW_225", 0, 0, 225), 6: ("YAW_270", 0, 0, 270), 7: ("YAW_315", 0, 0, 315),
    8: ("ROLL_180", 180, 0, 0), 9: ("ROLL_180_YAW_45", 180, 0, 45), 10: ("ROLL_180_YAW_90", 180, 0, 90),
    11: ("ROLL_180_YAW_135", 180, 0, 135), 12: ("PITCH_180", 0, 180, 0), 13: ("ROLL_180_YAW_225", 180, 0, 225),
    14: ("ROLL_180_YAW_270", 180, 0, 270), 15: ("ROLL_180_YAW_315", 180, 0, 315), 16: ("ROLL_90", 90, 0, 0),
    17: ("ROLL_90_YAW_45", 90, 0, 45), 18: ("ROLL_90_YAW_90", 90, 0, 90), 19: ("ROLL_90_YAW_135", 90, 0, 135),
    20: ("ROLL_270", 270, 0, 0), 21: ("ROLL_270_YAW_45", 270, 0, 45), 22: ("ROLL_270_YAW_90", 270, 0, 90),
    23: ("ROLL_270_YAW_135", 270, 0, 135), 24: ("PITCH_90", 0, 90, 0), 25: ("PITCH_270", 0, 270, 0),
    26: ("PITCH_180_YAW_90", 0, 180, 90), 27: ("PITCH_180_YAW_270", 0, 180, 270),
    28: ("ROLL_90_PITCH_90", 90, 90, 0), 29: ("ROLL_180_PITCH_90", 180, 90, 0),
    30: ("ROLL_270_PITCH_90", 270, 90, 0), 31: ("ROLL_90_PITCH_180", 90, 180, 0),
    32: ("ROLL_270_PITCH_180", 270, 180, 0), 33: ("ROLL_90_PITCH_270", 90, 270, 0),
    34: ("ROLL_180_PITCH_270", 180, 270, 0), 35: ("ROLL_270_PITCH_270", 270, 270, 0),
    36: ("ROLL_90_PITCH_180_YAW_90", 90, 180, 90), 37: ("ROLL_90_YAW_270", 90, 0, 270),
    38: ("ROLL_90_PITCH_68_YAW_293", 90, 68.8, 293.3), 39: ("PITCH_315", 0, 315, 0),
    40: ("ROLL_90_PITCH_315", 90, 315, 0), 41: ("PITCH_7", 0, 7, 0), 42: ("ROLL_45", 45, 0, 0),
    43: ("ROLL_315", 315, 0, 0),
}
#: PX4 ``rot_lookup`` (``src/lib/conversion/rotation.h``): 0..40 as ArduPilot's, 38 with integer angles.
PX4_ROTATIONS: dict[int, tuple[str, float, float, float]] = {
    k: v for k, v in ARDUPILOT_ROTATIONS.items() if k <= 40
}
PX4_ROTATIONS[38] = ("ROLL_90_PITCH_68_YAW_293", 90, 68, 293)


#: The optional parts of each firmware's compass calibration and the parameters (regular expressions over the names,
#: any instance) that carry them: a firmware that lacks a part (older versions: ArduPilot before 3.4 has no DIA/ODI,
#: before 4.0 no COMPASS_SCALE; PX4 before 1.11 no ODIAG / COMP) ignores or refuses them.
FIRMWARE_FEATURES: dict[str, dict[str, str]] = {
    "ardupilot": {"scale": r"COMPASS_SCALE\d?$", "matrix": r"COMPASS_(DIA|ODI)\d?_[XYZ]$",
                  "motor": r"COMPASS_(MOT\d?_[XYZ]|MOTCT)$"},
    "px4": {"offdiagonal": r"CAL_MAG\d_[XYZ]ODIAG$", "motor": r"CAL_MAG(\d_[XYZ]COMP|_COMP_TYP)$"},
}


#: How the user reads each part of :data:`FIRMWARE_FEATURES`.
FEATURE_NAMES: dict[str, str] = {"scale": "COMPASS_SCALE", "matrix": "COMPASS_DIA/ODI",
                                 "offdiagonal": "CAL_MAGn_xODIAG",
                                 "motor": "the motor term (COMPASS_MOT / CAL_MAGn_xCOMP)"}


def without_features(target: str, params: Mapping[str, float], absent: Collection[str]) -> dict[str, float]:
    """``params`` without the parameters of the parts ``absent`` (:data:`FIRMWARE_FEATURES`): what a firmware that
    lacks them loads."""
    patterns = [re.compile(FIRMWARE_FEATURES[target][a]) for a in absent if a in FIRMWARE_FEATURES[target]]
    return {k: v for k, v in params.items() if not any(r.match(k) for r in patterns)}


def absent_features(target: str, params: Mapping[str, float]) -> tuple[str, ...]:
    """The parts of :data:`FIRMWARE_FEATURES` that a log's firmware lacks: its parameter list (``params``, the
    log's, which holds every parameter the firmware has) has none of their first compass's parameters. A list
    without the compass's offsets (no PARM, or a truncated one) says nothing."""
    probe = {"ardupilot": ("COMPASS_OFS_X", {"scale": "COMPASS_SCALE", "matrix": "COMPASS_DIA_X",
                                             "motor": "COMPASS_MOTCT"}),
             "px4": ("CAL_MAG0_XOFF", {"offdiagonal": "CAL_MAG0_XODIAG", "motor": "CAL_MAG0_XCOMP"})}
    offsets, features = probe[target]
    if offsets not in params:
        return ()
    return tuple(feature for feature, name in features.items() if name not in params)


_FIRST_INSTANCE = {
    "ardupilot": (re.compile(r"\bCOMPASS_(OFS|DIA|ODI|MOT)_"), re.compile(r"\bCOMPASS_(SCALE|ORIENT)\b")),
    "px4": (re.compile(r"\bCAL_MAG0_"), None),
}


def instance_names(target: str, obj: Any, instance: int) -> Any:
    """``obj`` (a parameter name, a text, or dicts and lists of them, keys included) with the first compass's
    parameter names of ``target`` (``COMPASS_OFS_X``, ``COMPASS_SCALE``, ``COMPASS_ORIENT``; ``CAL_MAG0_XOFF``)
    written as compass ``instance``'s (0-based: ``COMPASS_OFS2_X``, ``COMPASS_SCALE2``; ``CAL_MAG1_XOFF``), the
    names the firmware loads for it; the parameters every compass shares (``COMPASS_MOTCT``, ``CAL_MAG_COMP_TYP``)
    are unchanged.

    Examples
    --------
    >>> instance_names("ardupilot", {"COMPASS_OFS_X": 1.0, "COMPASS_MOTCT": 2.0}, 1)
    {'COMPASS_OFS2_X': 1.0, 'COMPASS_MOTCT': 2.0}
    >>> instance_names("px4", "CAL_MAG0_XOFF held", 2)
    'CAL_MAG2_XOFF held'
    """
    if instance == 0 or target not in _FIRST_INSTANCE:
        return obj
    if isinstance(obj, str):
        matrix, single = _FIRST_INSTANCE[target]
        if target == "ardupilot":
            n = str(instance + 1)
            text = matrix.sub(lambda m: f"COMPASS_{m.group(1)}{n}_", obj)
            return single.sub(lambda m: f"COMPASS_{m.group(1)}{n}", text) if single is not None else text
        return matrix.sub(f"CAL_MAG{instance}_", obj)
    if isinstance(obj, Mapping):
        return {instance_names(target, k, instance): instance_names(target, v, instance) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(instance_names(target, v, instance) for v in obj)
    return obj


#: A log's parameter list is taken as the firmware's whole list from this many parameters on (ArduPilot and PX4
#: have several hundred; a telemetry log may hold only the few a ground station asked for).
COMPLETE_PARAMETER_LIST = 200


def absent_parameters(target: str, params: Mapping[str, float], instance: int) -> tuple[str, ...]:
    """The parameters of compass ``instance`` (0-based; and those every compass shares) that a log's firmware lacks:
    its parameter list (``params``, which holds every parameter the firmware has) has the instance's offsets but not
    them (an ArduCopter 3.2 log has ``COMPASS_OFS2_X`` but no ``COMPASS_ORIENT2``, ``COMPASS_DIA2_X`` or
    ``COMPASS_SCALE2``). A list without the instance's offsets, or shorter than :data:`COMPLETE_PARAMETER_LIST` (a
    telemetry log that received part of the list), says nothing (empty)."""
    klass = firmware_class(target)
    names = klass(motor_type="current").parameters(instance)
    offsets = list(names)[:3]  # every firmware has them
    if len(params) < COMPLETE_PARAMETER_LIST or not all(n in params for n in offsets):
        return ()
    return tuple(name for name in names if name not in params and name not in offsets)


def euler_matrix(roll_deg: float, pitch_deg: float, yaw_deg: float) -> NDArray[np.float64]:
    """``Rz(yaw) Ry(pitch) Rx(roll)`` (ArduPilot ``Matrix3::from_euler``, PX4 ``Dcm(Euler)``), shape (3, 3).

    Examples
    --------
    >>> euler_matrix(0, 0, 90).round(12) @ [1.0, 0.0, 0.0]     # the sensor's x is the body's y (right)
    array([0., 1., 0.])
    """
    r, p, y = np.radians([roll_deg, pitch_deg, yaw_deg])
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return np.array([[cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy],
                     [cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy],
                     [-sp, sr * cp, cr * cp]])


def rotation_matrix(target: str, value: int) -> NDArray[np.float64]:
    """The matrix of rotation ``value`` of ``target``'s enum (``v' = R v``), shape (3, 3)."""
    table = firmware_class(target).rotations
    if int(value) not in table:
        raise TrimagInputError(f"{target} has no sensor rotation {value}; it takes {min(table)}..{max(table)}")
    _, roll, pitch, yaw = table[int(value)]
    return euler_matrix(roll, pitch, yaw)


@dataclasses.dataclass(frozen=True)
class Violation:
    """A parameter the firmware cannot load: ``parameter`` (its name), ``value`` and the ``limit`` (text)."""

    parameter: str
    value: float
    limit: str

    def __str__(self) -> str:
        return f"{self.parameter} = {self.value:.6g} is outside {self.limit}"


def _vector(value: ArrayLike, name: str) -> NDArray[np.float64]:
    arr = np.asarray(value, dtype=np.float64).reshape(-1)
    if arr.shape != (3,) or not np.isfinite(arr).all():
        raise TrimagInputError(f"`{name}` must be 3 finite numbers; got {np.asarray(value).tolist()}")
    arr.setflags(write=False)
    return arr


def symmetric(diagonal: ArrayLike, offdiagonal: ArrayLike) -> NDArray[np.float64]:
    """The symmetric matrix of a diagonal (3,) and off-diagonal (01, 02, 12) triple (both firmwares' layout)."""
    d, o = np.asarray(diagonal, dtype=np.float64), np.asarray(offdiagonal, dtype=np.float64)
    return np.array([[d[0], o[0], o[1]], [o[0], d[1], o[2]], [o[1], o[2], d[2]]])


@dataclasses.dataclass(frozen=True)
class FirmwareCompass:
    """One magnetometer's calibration as a firmware loads it (see the module docstring; subclasses per target).

    Attributes
    ----------
    orientation : int
        The rotation enum value (``COMPASS_ORIENTn`` / ``CAL_MAGn_ROT``).
    offsets : ndarray, shape (3,)
        ArduPilot ``COMPASS_OFSn`` (mGauss, added, body frame); PX4 ``CAL_MAGn_xOFF`` (gauss, subtracted, sensor
        frame).
    scale : float
        ArduPilot ``COMPASS_SCALEn`` (0: off); PX4: 1 (it has none).
    diagonal, offdiagonal : ndarray, shape (3,)
        ArduPilot ``DIA``, ``ODI`` (xy, xz, yz); PX4 ``xSCALE``, ``xODIAG`` (the same slots).
    motor : ndarray, shape (3,)
        ArduPilot ``COMPASS_MOTn`` (mGauss per A or per unit throttle); PX4 ``CAL_MAGn_xCOMP`` (gauss per kA or per
        unit thrust).
    motor_type : str or None
        ``"current"``, ``"throttle"`` or None (no motor term).
    """

    orientation: int = 0
    offsets: NDArray[np.float64] = dataclasses.field(default_factory=lambda: np.zeros(3))
    scale: float = 1.0
    diagonal: NDArray[np.float64] = dataclasses.field(default_factory=lambda: np.ones(3))
    offdiagonal: NDArray[np.float64] = dataclasses.field(default_factory=lambda: np.zeros(3))
    motor: NDArray[np.float64] = dataclasses.field(default_factory=lambda: np.zeros(3))
    motor_type: str | None = None

    target: ClassVar[str] = ""
    unit: ClassVar[str] = ""
    rotations: ClassVar[dict[int, tuple[str, float, float, float]]] = {}
    #: firmware power unit per logged unit: current A -> the firmware's current unit; throttle 0..1 as is
    current_factor: ClassVar[float] = 1.0

    def __post_init__(self) -> None:
        for name in ("offsets", "diagonal", "offdiagonal", "motor"):
            object.__setattr__(self, name, _vector(getattr(self, name), name))
        if self.motor_type not in (None, "current", "throttle"):
            raise TrimagInputError(f"`motor_type` must be 'current', 'throttle' or None; got {self.motor_type!r}")
        if int(self.orientation) not in self.rotations:
            raise TrimagInputError(f"{self.target} has no sensor rotation {self.orientation}; it takes "
                                   f"{min(self.rotations)}..{max(self.rotations)}")

    # ------------------------------------------------------------------ algebra
    @property
    def matrix(self) -> NDArray[np.float64]:
        """The symmetric matrix (``M`` / ``S``), shape (3, 3)."""
        return symmetric(self.diagonal, self.offdiagonal)

    @property
    def rotation(self) -> NDArray[np.float64]:
        """The sensor rotation's matrix, shape (3, 3)."""
        return rotation_matrix(self.target, self.orientation)

    @property
    def rotation_name(self) -> str:
        """The rotation's name (``ROTATION_YAW_90``)."""
        return "ROTATION_" + self.rotations[int(self.orientation)][0]

    def power(self, values: ArrayLike | None, n: int) -> NDArray[np.float64]:
        """The firmware's power signal ``x`` (n,) from logged values (current in A, throttle 0..1)."""
        if self.motor_type is None:
            return np.zeros(n)
        if values is None:
            raise TrimagInputError(f"this {self.target} calibration has a {self.motor_type} term: give the "
                                   f"{self.motor_type} at every sample")
        x = np.broadcast_to(np.asarray(values, dtype=np.float64), (n,))
        return x * (self.current_factor if self.motor_type == "current" else 1.0)

    def correct(self, raw: ArrayLike, motor_values: ArrayLike | None = None) -> NDArray[np.float64]:
        """The firmware's corrected field of raw readings (N, 3), in its formula's own order (module docstring).

        ``raw`` is what the firmware's correction receives before its rotation (in :attr:`unit`);
        ``motor_values`` the current (A) or throttle (0..1) at each sample when :attr:`motor_type` is set.
        """
        raise NotImplementedError

    def uncorrect(self, field: ArrayLike, motor_values: ArrayLike | None = None) -> NDArray[np.float64]:
        """The raw readings (N, 3) the firmware turns into ``field`` (the inverse of :meth:`correct`)."""
        raise NotImplementedError

    # ------------------------------------------------------------------ names and limits
    def parameters(self, instance: int = 0) -> dict[str, float]:
        """The firmware's parameter names and values for magnetometer ``instance`` (0-based)."""
        raise NotImplementedError

    def violations(self, **limits: Any) -> list[Violation]:
        """The parameters the firmware cannot load (empty when every one is within its limits)."""
        raise NotImplementedError

    @classmethod
    def from_parameters(cls, params: Mapping[str, float], instance: int = 0) -> FirmwareCompass:
        """The calibration a firmware holds, from its parameters (a log's ``PARM`` / ULog parameters)."""
        raise NotImplementedError

    def as_dict(self) -> dict[str, Any]:
        """Plain JSON types: the target, orientation, the vectors and the motor type."""
        return {"target": self.target, "unit": self.unit, "orientation": int(self.orientation),
                "orientation_name": self.rotation_name, "offsets": self.offsets.tolist(), "scale": float(self.scale),
                "diagonal": self.diagonal.tolist(), "offdiagonal": self.offdiagonal.tolist(),
                "motor": self.motor.tolist(), "motor_type": self.motor_type}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> FirmwareCompass:
        """Rebuild from :meth:`as_dict` (the ``target`` entry picks the class)."""
        klass = firmware_class(str(data.get("target")))
        try:
            return klass(orientation=int(data["orientation"]), offsets=data["offsets"], scale=float(data["scale"]),
                         diagonal=data["diagonal"], offdiagonal=data["offdiagonal"], motor=data["motor"],
                         motor_type=data.get("motor_type"))
        except (KeyError, TypeError, ValueError) as exc:
            raise TrimagInputError(f"the calibration's firmware parameters are incomplete or not numbers ({exc})") \
                from None

    # ------------------------------------------------------------------ the shared algebra (module docstring)
    def algebra(self) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """``(A, o, m)`` of ``B~ = A (u + o) + m x`` (module docstring)."""
        raise NotImplementedError

    @classmethod
    def from_algebra(cls, A: ArrayLike, o: ArrayLike, m: ArrayLike, *, orientation: int,
                     motor_type: str | None, scale: float | None = None) -> FirmwareCompass:
        """The parameters of ``(A, o, m)`` (the inverse of :meth:`algebra`); ``scale``: ArduPilot's
        ``COMPASS_SCALE`` to use (default: the mean of ``A``'s diagonal)."""
        raise NotImplementedError


def _triple(params: Mapping[str, float], prefix: str, suffixes: Any, default: float,
            zero: float | None = None) -> NDArray[np.float64]:
    """Three parameters ``prefix + suffix`` as a vector (``default`` where absent; ``zero`` replaces 0)."""
    out = np.array([float(params.get(prefix + sfx, default)) for sfx in suffixes])
    if zero is not None:
        out[out == 0] = zero
    return out


_AP_SCALE_MIN, _AP_SCALE_MAX = 1.0 / 1.5, 1.5  # COMPASS_MIN/MAX_SCALE_FACTOR (AP_Compass_config.h)


def _ap_suffix(instance: int) -> str:
    return "" if instance == 0 else str(instance + 1)


@dataclasses.dataclass(frozen=True)
class ArduPilotCompass(FirmwareCompass):
    """ArduPilot's ``COMPASS_*`` parameters of one compass (module docstring)."""

    scale: float = 0.0

    target: ClassVar[str] = "ardupilot"
    unit: ClassVar[str] = "mG"
    rotations: ClassVar[dict[int, tuple[str, float, float, float]]] = ARDUPILOT_ROTATIONS
    #: ``COMPASS_OFFS_MAX``'s default (``AP_COMPASS_OFFSETS_MAX_DEFAULT``)
    OFFSETS_MAX: ClassVar[float] = 1800.0

    @property
    def effective_scale(self) -> float:
        """``s`` as ``correct_field`` uses it: ``COMPASS_SCALE`` within [1/1.5, 1.5], else 1."""
        s = float(self.scale)
        return s if _AP_SCALE_MIN <= s <= _AP_SCALE_MAX else 1.0

    @property
    def effective_matrix(self) -> NDArray[np.float64]:
        """``M`` as ``correct_field`` uses it: the identity when every DIA is zero."""
        return np.eye(3) if not np.any(self.diagonal) else self.matrix

    def correct(self, raw: ArrayLike, motor_values: ArrayLike | None = None) -> NDArray[np.float64]:
        v = np.atleast_2d(np.asarray(raw, dtype=np.float64))
        mag = v @ self.rotation.T  # rotate_field: mag.rotate(orientation)
        mag = mag + self.offsets  # correct_field: mag += offsets
        mag = mag * self.effective_scale  # if (have_scale_factor) mag *= scale
        mag = mag @ self.effective_matrix.T  # if (!diagonals.is_zero()) mag = mat * mag
        x = self.power(motor_values, len(v))
        return np.asarray(mag + x[:, None] * self.motor, dtype=np.float64)  # mag += motor_offset

    def uncorrect(self, field: ArrayLike, motor_values: ArrayLike | None = None) -> NDArray[np.float64]:
        B = np.atleast_2d(np.asarray(field, dtype=np.float64))
        x = self.power(motor_values, len(B))
        r = np.linalg.solve(self.effective_matrix, (B - x[:, None] * self.motor).T).T / self.effective_scale
        return np.asarray((r - self.offsets) @ self.rotation, dtype=np.float64)

    def parameters(self, instance: int = 0) -> dict[str, float]:
        n = _ap_suffix(instance)
        out = {f"COMPASS_OFS{n}_{a}": float(v) for a, v in zip("XYZ", self.offsets, strict=True)}
        out.update({f"COMPASS_DIA{n}_{a}": float(v) for a, v in zip("XYZ", self.diagonal, strict=True)})
        out.update({f"COMPASS_ODI{n}_{a}": float(v) for a, v in zip("XYZ", self.offdiagonal, strict=True)})
        out[f"COMPASS_SCALE{n}"] = float(self.scale)
        out[f"COMPASS_ORIENT{n}"] = float(self.orientation)
        if self.motor_type is not None:
            out.update({f"COMPASS_MOT{n}_{a}": float(v) for a, v in zip("XYZ", self.motor, strict=True)})
            out["COMPASS_MOTCT"] = 1.0 if self.motor_type == "throttle" else 2.0
        return out

    def violations(self, **limits: Any) -> list[Violation]:
        """Limits of ``CompassCalibrator::fit_acceptable`` (DIA 0.2..5, |ODI| < 1), ``AP_Arming::compass_checks``
        (``|OFS| <= COMPASS_OFFS_MAX``, ``offsets_max`` here, default 1800), ``have_scale_factor`` (SCALE 0 or
        within [1/1.5, 1.5]), ``COMPASS_MOT`` ±1000 (``var_info``) and the rotation enum (0..43).
        ``instance`` (0-based) names the parameters."""
        n = _ap_suffix(int(limits.get("instance", 0)))
        offsets_max = float(limits.get("offsets_max") or self.OFFSETS_MAX)
        out: list[Violation] = []
        size = float(np.linalg.norm(self.offsets))
        if size > offsets_max:
            out.append(Violation(f"|COMPASS_OFS{n}_X..Z|", size,
                                 f"COMPASS_OFFS_MAX = {offsets_max:g} mGauss (the offset vector's length, "
                                 "AP_Arming::compass_checks; COMPASS_OFFS_MAX goes up to 3000)"))
        for a, v in zip("XYZ", self.diagonal if np.any(self.diagonal) else (), strict=False):  # all 0: no matrix
            if not 0.2 < v < 5.0:
                out.append(Violation(f"COMPASS_DIA{n}_{a}", float(v), "(0.2, 5) (CompassCalibrator::fit_acceptable)"))
        for a, v in zip("XYZ", self.offdiagonal, strict=True):
            if not abs(v) < 1.0:
                out.append(Violation(f"COMPASS_ODI{n}_{a}", float(v), "(-1, 1) (CompassCalibrator::fit_acceptable)"))
        if self.scale != 0.0 and not _AP_SCALE_MIN <= self.scale <= _AP_SCALE_MAX:
            out.append(Violation(f"COMPASS_SCALE{n}", float(self.scale),
                                 "[0.667, 1.5] (COMPASS_MIN/MAX_SCALE_FACTOR: the firmware ignores the scale "
                                 "outside it)"))
        for a, v in zip("XYZ", self.motor, strict=True):
            if abs(v) > 1000.0:
                out.append(Violation(f"COMPASS_MOT{n}_{a}", float(v), "[-1000, 1000] (COMPASS_MOT's range)"))
        if np.any(np.linalg.eigvalsh(self.effective_matrix * self.effective_scale) <= 0):
            out.append(Violation(f"COMPASS_DIA{n}_X", float(self.diagonal[0]),
                                 "a positive definite DIA/ODI matrix (this one reflects or collapses an axis)"))
        return out

    @classmethod
    def from_parameters(cls, params: Mapping[str, float], instance: int = 0) -> ArduPilotCompass:
        n = _ap_suffix(instance)
        get = params.get
        external = get(f"COMPASS_EXTERN{n}" if n else "COMPASS_EXTERNAL", 1.0)
        orient = get(f"COMPASS_ORIENT{n}", 0.0) if external else get("AHRS_ORIENTATION", 0.0)
        motct = int(get("COMPASS_MOTCT", 0.0))
        return cls(orientation=int(orient) if int(orient) in ARDUPILOT_ROTATIONS else 0,
                   offsets=_triple(params, f"COMPASS_OFS{n}_", "XYZ", 0.0),
                   scale=float(get(f"COMPASS_SCALE{n}", 0.0)),
                   diagonal=_triple(params, f"COMPASS_DIA{n}_", "XYZ", 0.0),
                   offdiagonal=_triple(params, f"COMPASS_ODI{n}_", "XYZ", 0.0),
                   motor=_triple(params, f"COMPASS_MOT{n}_", "XYZ", 0.0),
                   motor_type={1: "throttle", 2: "current"}.get(motct))

    def algebra(self) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        return self.effective_scale * self.effective_matrix, self.offsets.copy(), self.motor.copy()

    @classmethod
    def from_algebra(cls, A: ArrayLike, o: ArrayLike, m: ArrayLike, *, orientation: int,
                     motor_type: str | None, scale: float | None = None) -> ArduPilotCompass:
        """``COMPASS_SCALE`` = ``scale`` or the mean of ``A``'s diagonal (as MAGFit renormalises) within the range
        the firmware uses, [1/1.5, 1.5] (beyond it ``DIA``, 0.2..5, carries the rest), ``DIA``/``ODI`` = ``A /
        SCALE``."""
        A = np.asarray(A, dtype=np.float64)
        s = float(np.clip(np.mean(np.diag(A)), _AP_SCALE_MIN, _AP_SCALE_MAX)) if scale is None else float(scale)
        M = A / s
        return cls(orientation=orientation, offsets=np.asarray(o, dtype=np.float64), scale=s, diagonal=np.diag(M),
                   offdiagonal=np.array([M[0, 1], M[0, 2], M[1, 2]]),
                   motor=np.zeros(3) if motor_type is None else np.asarray(m, dtype=np.float64), motor_type=motor_type)


@dataclasses.dataclass(frozen=True)
class PX4Magnetometer(FirmwareCompass):
    """PX4's ``CAL_MAGn_*`` parameters of one magnetometer (module docstring)."""

    target: ClassVar[str] = "px4"
    unit: ClassVar[str] = "G"
    rotations: ClassVar[dict[int, tuple[str, float, float, float]]] = PX4_ROTATIONS
    current_factor: ClassVar[float] = 0.001  # current_a * 0.001 (kA): VehicleMagnetometer::UpdatePowerCompensation

    def correct(self, raw: ArrayLike, motor_values: ArrayLike | None = None) -> NDArray[np.float64]:
        v = np.atleast_2d(np.asarray(raw, dtype=np.float64))
        p = self.power(motor_values, len(v))
        inner = (v + p[:, None] * self.motor) - self.offsets  # (data + _power * _power_compensation) - _offset
        return np.asarray(inner @ self.matrix.T @ self.rotation.T, dtype=np.float64)  # _rotation * (_scale * ...)

    def uncorrect(self, field: ArrayLike, motor_values: ArrayLike | None = None) -> NDArray[np.float64]:
        B = np.atleast_2d(np.asarray(field, dtype=np.float64))
        p = self.power(motor_values, len(B))
        inner = np.linalg.solve(self.matrix, (B @ self.rotation).T).T
        return np.asarray(inner + self.offsets - p[:, None] * self.motor, dtype=np.float64)

    def parameters(self, instance: int = 0) -> dict[str, float]:
        n = instance
        out = {f"CAL_MAG{n}_{a}OFF": float(v) for a, v in zip("XYZ", self.offsets, strict=True)}
        out.update({f"CAL_MAG{n}_{a}SCALE": float(v) for a, v in zip("XYZ", self.diagonal, strict=True)})
        out.update({f"CAL_MAG{n}_{a}ODIAG": float(v) for a, v in zip("XYZ", self.offdiagonal, strict=True)})
        out[f"CAL_MAG{n}_ROT"] = float(self.orientation)
        if self.motor_type is not None:
            out.update({f"CAL_MAG{n}_{a}COMP": float(v) for a, v in zip("XYZ", self.motor, strict=True)})
            out["CAL_MAG_COMP_TYP"] = 1.0 if self.motor_type == "throttle" else 2.0
        return out

    def violations(self, **limits: Any) -> list[Violation]:
        """``CAL_MAGn_xSCALE`` within its metadata range [0.1, 3] (``src/modules/sensors/module.yaml``; the code
        requires > 0), a positive definite ``S``, and ``CAL_MAGn_ROT`` 0..40 (``ROTATION_MAX`` = 41)."""
        n = int(limits.get("instance", 0))
        out: list[Violation] = []
        for a, v in zip("XYZ", self.diagonal, strict=True):
            if not 0.1 <= v <= 3.0:
                out.append(Violation(f"CAL_MAG{n}_{a}SCALE", float(v), "[0.1, 3] (CAL_MAGn_xSCALE's range)"))
        if not out and np.any(np.linalg.eigvalsh(self.matrix) <= 0):
            out.append(Violation(f"CAL_MAG{n}_XSCALE", float(self.diagonal[0]),
                                 "a positive definite scale matrix (this one reflects or collapses an axis)"))
        return out

    @classmethod
    def from_parameters(cls, params: Mapping[str, float], instance: int = 0) -> PX4Magnetometer:
        n = instance
        get = params.get
        rot = int(get(f"CAL_MAG{n}_ROT", -1.0))
        if rot < 0:  # internal: the board's rotation (Magnetometer::set_rotation, GetBoardRotation)
            rot = int(get("SENS_BOARD_ROT", 0.0))
        comp = int(get("CAL_MAG_COMP_TYP", 0.0))
        return cls(orientation=rot if rot in PX4_ROTATIONS else 0,
                   offsets=_triple(params, f"CAL_MAG{n}_", ("XOFF", "YOFF", "ZOFF"), 0.0),
                   scale=1.0,
                   diagonal=_triple(params, f"CAL_MAG{n}_", ("XSCALE", "YSCALE", "ZSCALE"), 1.0, zero=1.0),
                   offdiagonal=_triple(params, f"CAL_MAG{n}_", ("XODIAG", "YODIAG", "ZODIAG"), 0.0),
                   motor=_triple(params, f"CAL_MAG{n}_", ("XCOMP", "YCOMP", "ZCOMP"), 0.0),
                   motor_type={1: "throttle", 2: "current", 3: "current"}.get(comp))

    def algebra(self) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        f = self.current_factor if self.motor_type == "current" else 1.0
        return self.matrix, -self.offsets, self.matrix @ self.motor * f

    @classmethod
    def from_algebra(cls, A: ArrayLike, o: ArrayLike, m: ArrayLike, *, orientation: int,
                     motor_type: str | None, scale: float | None = None) -> PX4Magnetometer:
        A = np.asarray(A, dtype=np.float64)
        f = cls.current_factor if motor_type == "current" else 1.0
        comp = np.zeros(3) if motor_type is None else np.linalg.solve(A, np.asarray(m, dtype=np.float64)) / f
        return cls(orientation=orientation, offsets=-np.asarray(o, dtype=np.float64), scale=1.0,
                   diagonal=np.diag(A), offdiagonal=np.array([A[0, 1], A[0, 2], A[1, 2]]),
                   motor=np.asarray(comp, dtype=np.float64), motor_type=motor_type)


def firmware_class(target: str) -> type[FirmwareCompass]:
    """The parameter set of ``target`` (``"ardupilot"`` or ``"px4"``)."""
    classes: dict[str, type[FirmwareCompass]] = {"ardupilot": ArduPilotCompass, "px4": PX4Magnetometer}
    if target not in classes:
        raise TrimagInputError(f"unknown firmware target {target!r}; choose one of {', '.join(FIRMWARE_TARGETS)}")
    return classes[target]


def _polar_rotation(G: NDArray[np.float64]) -> NDArray[np.float64]:
    """The rotation ``Q`` of ``G = P Q`` (which is also that of ``G = Q P``: ``U S V^T = (U S U^T)(U V^T) =
    (U V^T)(V S V^T)``), shape (3, 3)."""
    U, _, Vt = np.linalg.svd(G)
    Q = U @ Vt
    if np.linalg.det(Q) < 0:
        raise TrimagInputError("the calibration matrix reflects the axes (det < 0): no firmware can load it")
    return np.asarray(Q, dtype=np.float64)


def _angle_deg(R: NDArray[np.float64]) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def nearest_rotation(target: str, matrix: ArrayLike) -> tuple[int, float]:
    """The standard rotation of ``target``'s enum nearest to a rotation matrix, and the angle (degrees) between."""
    Q = np.asarray(matrix, dtype=np.float64)
    best = min((_angle_deg(Q @ rotation_matrix(target, k).T), k) for k in firmware_class(target).rotations)
    return best[1], best[0]


def compass_from_affine(
    target: str, matrix: ArrayLike, offset: ArrayLike, *, motor: tuple[ArrayLike, str] | None = None,
    input_orientation: int | None = None, rotation_determined: bool = False,
    tolerance_deg: float = ORIENTATION_TOLERANCE_DEG,
) -> tuple[FirmwareCompass, list[str]]:
    """The firmware parameters of a general calibration ``B = W (v - b) + m x`` (raw ``v`` in the frame of the
    rotation ``input_orientation`` already applied; None: the sensor's own frame), in the firmware's unit.

    ``rotation_determined`` (a fit against attitudes): ``W``'s rotation is the sensor's orientation: the nearest
    standard rotation is written and what remains is left to the symmetric matrix up to ``tolerance_deg`` (refused
    beyond, naming the angle). Otherwise (a magnitude-only fit) the rotation is arbitrary: the orientation in force
    is kept and the output frame is rotated so that the matrix is symmetric (the polar factor: the same corrected
    magnitude).

    Returns
    -------
    compass, notes
    """
    klass = firmware_class(target)
    W = np.asarray(matrix, dtype=np.float64)
    b = np.asarray(offset, dtype=np.float64)
    R0 = np.eye(3) if input_orientation is None else rotation_matrix(target, input_orientation)
    Q = _polar_rotation(W @ R0)
    notes: list[str] = []
    if rotation_determined:
        G = np.eye(3)
        value, angle = nearest_rotation(target, Q)
        if angle > tolerance_deg:
            raise TrimagInputError(
                f"this calibration (fitted with attitudes) rotates the sensor's axes {angle:.1f} deg from the nearest "
                f"standard orientation {klass(orientation=value).rotation_name} ({value}); {target}'s symmetric "
                f"matrix can hold at most {tolerance_deg:g} deg of it (dropping the rest would change the heading): "
                "export it to c-header, json, ros-yaml or matlab, which keep the full matrix"
            )
        if angle > 1e-6:
            notes.append(f"orientation {klass(orientation=value).rotation_name} ({value}); the remaining "
                         f"{angle:.2f} deg rotation is approximated by the symmetric matrix")
    else:
        G = R0 @ Q.T  # rotates the output so that the matrix is symmetric: R0 P R0^T (ArduPilot), P (PX4)
        value = 0 if input_orientation is None else int(input_orientation)
        angle = _angle_deg(Q)
        if angle > 1e-9:
            notes.append(f"the matrix is not symmetric: exported its symmetric polar factor (same corrected magnitude; "
                         f"drops a {angle:.3f} deg rotation that a magnitude calibration does not determine)")
    R = rotation_matrix(target, value)
    GW = G @ W
    if target == "ardupilot":
        P_u, P_h = R @ R0.T, np.eye(3)
        A_raw = GW @ P_u.T  # G W = A P_u
    else:
        P_u, P_h = R0.T, R.T
        A_raw = R.T @ GW @ R0  # G W = R A R0^T
    A = (A_raw + A_raw.T) / 2.0
    o = -P_u @ b
    kind = None
    m = np.zeros(3)
    if motor is not None:
        m_body, kind = np.asarray(motor[0], dtype=np.float64), motor[1]
        m = P_h @ (G @ m_body)
    scale = 1.0 if target == "ardupilot" else None  # COMPASS_SCALE 1: the matrix is all in DIA/ODI (as before)
    return klass.from_algebra(A, o, m, orientation=value, motor_type=kind, scale=scale), notes
