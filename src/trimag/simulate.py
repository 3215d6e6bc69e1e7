"""Synthetic sensors with known truth: attitude generators, noise, and distorted samples.

Convention (``docs/conventions.md``): an attitude is a :class:`scipy.spatial.transform.Rotation` ``R`` giving the
body's orientation in the navigation frame (body -> navigation). A navigation-frame field ``H_n`` is seen in the
body frame as ``H_b = R.inv().apply(H_n)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from .errors import TrimagInputError
from .fields.attitude import body_field
from .models.base import ErrorModel

__all__ = [
    "Simulation",
    "add_noise",
    "axis_turns",
    "body_field",
    "great_circle_directions",
    "hemisphere_directions",
    "random_attitudes",
    "simulate",
    "uniform_directions",
]


def random_attitudes(n: int, seed: int | np.random.Generator | None = None) -> Rotation:
    """``n`` attitudes uniformly distributed over SO(3)."""
    rng = np.random.default_rng(seed)
    return Rotation.random(n, random_state=rng)


def axis_turns(n_per_axis: int, *, axes: str = "xyz", offset: Rotation | None = None) -> Rotation:
    """Attitudes sampled uniformly during one full turn about each body axis in ``axes``, in turn.

    Parameters
    ----------
    n_per_axis : int
        Samples per turn (angles ``2 pi k / n_per_axis``).
    axes : str
        Which turns, e.g. ``"xyz"`` (paper A's three turns) or ``"z"`` (a single-axis turn).
    offset : Rotation, optional
        A fixed starting attitude, applied before each turn (so a turn about body z is not a turn about
        the field direction).

    Returns
    -------
    Rotation of length ``len(axes) * n_per_axis``
    """
    angles = 2.0 * np.pi * np.arange(n_per_axis) / n_per_axis
    basis = {"x": np.array([1.0, 0, 0]), "y": np.array([0, 1.0, 0]), "z": np.array([0, 0, 1.0])}
    parts = []
    for ax in axes:
        if ax not in basis:
            raise TrimagInputError(f"axes must be made of x, y, z; got {axes!r}")
        turn = Rotation.from_rotvec(angles[:, None] * basis[ax])
        parts.append(turn if offset is None else offset * turn)
    return Rotation.concatenate(parts)


def uniform_directions(n: int, seed: int | np.random.Generator | None = None) -> NDArray[np.float64]:
    """``n`` unit vectors uniform on the sphere, shape (n, 3)."""
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def hemisphere_directions(n: int, seed: int | np.random.Generator | None = None) -> NDArray[np.float64]:
    """``n`` unit vectors uniform on the upper (z >= 0) hemisphere, shape (n, 3)."""
    v = uniform_directions(n, seed)
    v[:, 2] = np.abs(v[:, 2])
    return v


def great_circle_directions(n: int) -> NDArray[np.float64]:
    """``n`` unit vectors on the three orthogonal great circles (xy, yz, zx planes), shape (n, 3).

    Each circle is complete and evenly sampled (``n // 3`` points, one more on the first ``n % 3`` circles), as
    full turns on a turntable at constant rate give, so the directions sum to zero.
    """
    parts = []
    for i in range(3):  # circle i: (cos, sin, 0) with its columns rolled by i -> xy, yz, zx planes
        k = n // 3 + (1 if i < n % 3 else 0)
        t = 2.0 * np.pi * np.arange(k) / max(k, 1)
        parts.append(np.roll(np.column_stack([np.cos(t), np.sin(t), np.zeros(k)]), i, axis=1))
    return np.vstack(parts)


def add_noise(
    B: ArrayLike, sigma: float, seed: int | np.random.Generator | None = None
) -> NDArray[np.float64]:
    """Add independent Gaussian noise of standard deviation ``sigma`` (field units) to each axis."""
    rng = np.random.default_rng(seed)
    arr = np.asarray(B, dtype=np.float64)
    return arr + rng.normal(scale=sigma, size=arr.shape) if sigma > 0 else arr.copy()


@dataclass(frozen=True)
class Simulation:
    """A simulated log: ``raw`` (N, 3) sensor output, ``true`` (N, 3) true body field, the ``attitude``
    (N rotations, body -> navigation), the ``truth`` model and the simulation settings."""

    raw: NDArray[np.float64]
    true: NDArray[np.float64]
    attitude: Rotation
    truth: ErrorModel
    settings: dict[str, Any]


def simulate(
    truth: ErrorModel,
    *,
    n: int,
    field_nav: ArrayLike = (1.0, 0.0, 0.0),
    noise: float = 0.0,
    attitudes: str | Rotation = "random",
    seed: int | None = 0,
) -> Simulation:
    """Simulate a sensor with error model ``truth`` turned through ``attitudes`` in a constant field.

    Parameters
    ----------
    truth : ErrorModel
        The sensor's true errors (``truth.distort`` maps true body fields to raw output).
    n : int
        Number of samples (for ``"axes"``, rounded down to a multiple of 3).
    field_nav : array_like, shape (3,)
        Constant field in the navigation frame, in the output unit.
    noise : float
        Standard deviation of white Gaussian noise per axis, same unit.
    attitudes : "random", "axes", or Rotation
        Uniform random attitudes, full turns about the three body axes, or given attitudes.
    seed : int, optional
    """
    rng = np.random.default_rng(seed)
    if isinstance(attitudes, Rotation):
        att = attitudes
    elif attitudes == "random":
        att = random_attitudes(n, rng)
    elif attitudes == "axes":
        att = axis_turns(max(n // 3, 1), offset=Rotation.from_euler("zyx", [0.3, 0.2, 0.1]))
    else:
        raise TrimagInputError(f"attitudes must be 'random', 'axes' or a Rotation; got {attitudes!r}")
    true = body_field(att, field_nav)
    raw = add_noise(truth.distort(true), noise, rng)
    settings = {"n": len(raw), "noise": noise, "field_nav": np.asarray(field_nav, dtype=float).tolist()}
    return Simulation(raw, true, att, truth, settings)


@dataclass(frozen=True)
class AircraftSimulation:
    """A simulated aeromagnetic calibration box (:func:`simulate_aircraft`).

    Attributes
    ----------
    time_s : ndarray, shape (N,)
    vector_nT : ndarray, shape (N, 3)
        Vector magnetometer (the Earth's field in the body frame, forward-right-down, plus noise).
    scalar_nT : ndarray, shape (N,)
        Scalar magnetometer: |Earth field| + slow geology + the aircraft's TL field + noise.
    attitude_deg : ndarray, shape (N, 3)
        Yaw, pitch, roll (degrees; Z-Y-X, body -> NED).
    coefficients : ndarray, shape (p,)
        True TL coefficients (MagNav.jl order and scale, terms ``terms``).
    terms : tuple of str
    segments : list of (start, stop)
        Row ranges of the four straight legs (the turns between them are not in any segment).
    rate_hz : float
    """

    time_s: NDArray[np.float64]
    vector_nT: NDArray[np.float64]
    scalar_nT: NDArray[np.float64]
    attitude_deg: NDArray[np.float64]
    coefficients: NDArray[np.float64]
    terms: tuple[str, ...]
    segments: list[tuple[int, int]]
    rate_hz: float
    #: noise-free body-frame Earth field (N, 3), nT
    body_nT: NDArray[np.float64] | None = None
    #: the vector magnetometer's interference (``K``, ``c``, ``E``) when simulated, else None
    interference: dict[str, NDArray[np.float64]] | None = None
    #: the slow geology the scalar magnetometer sees (N,), nT (the simulated vector magnetometer does not see it)
    geology_nT: NDArray[np.float64] | None = None


def simulate_aircraft(
    seconds_per_heading: float = 120.0,
    *,
    rate_hz: float = 10.0,
    terms: str | tuple[str, ...] | None = None,
    coefficients: ArrayLike | None = None,
    earth_ned_nT: ArrayLike = (18_000.0, 1_000.0, 46_000.0),
    scalar_noise_nT: float = 0.01,
    vector_noise_nT: float = 0.0,
    amplitude_deg: tuple[float, float, float] = (5.0, 5.0, 10.0),
    turn_seconds: float = 20.0,
    seed: int = 0,
    vector_K: ArrayLike | None = None,
    vector_c: ArrayLike | None = None,
    vector_E: ArrayLike | None = None,
) -> AircraftSimulation:
    """A calibration box: four headings (N, E, S, W) joined by smooth turns, flown with yaw, pitch, roll manoeuvres.

    The manoeuvres are sums of sines (periods 4-12 s, the band that a Tolles–Lawson fit keeps), the geology a slow
    drift below 0.05 Hz that the band-pass removes. The scalar magnetometer reads
    ``|H_earth| + geology + A(vector) @ coefficients + noise`` (equation (1) of
    :mod:`trimag.models.tolles_lawson`), with the design computed from the noise-free vector field.

    Parameters
    ----------
    seconds_per_heading : float
        Length of each heading's manoeuvres, s.
    coefficients : array_like, optional
        True TL coefficients; default: random, of realistic size (permanent and induced ~10 nT, eddy ~100 nT).
    amplitude_deg : (yaw, pitch, roll)
        Manoeuvre amplitudes, degrees.
    vector_K, vector_c, vector_E : array_like, (3, 3), (3,), (3, 3), optional
        The vector magnetometer's interference (``interference12`` with eddy-current terms,
        :mod:`trimag.vehicle.eddy`): it then reads ``H_m = K H_b + c + E dH_m/dt`` (nT, ``E`` in s), solved exactly
        for ``H_m`` with the same finite differences (central, one-sided at the ends) as the fit, before the noise.
        Default: none (``H_m = H_b``).
    """
    from .models.tolles_lawson import design, parse_terms, term_names

    groups = parse_terms(terms)
    names = term_names(groups)
    rng = np.random.default_rng(seed)
    if coefficients is None:
        scale = np.array([100.0 if n.startswith("eddy") else 10.0 for n in names])
        coef = rng.normal(size=len(names)) * scale
    else:
        coef = np.asarray(coefficients, dtype=np.float64)
        if coef.shape != (len(names),):
            raise TrimagInputError(f"{len(names)} coefficients expected for terms {groups}; got {coef.shape}")
    n_leg = round(seconds_per_heading * rate_hz)
    n_turn = round(turn_seconds * rate_hz)
    n = 4 * n_leg + 3 * n_turn
    t = np.arange(n) / rate_hz
    yaw_base = np.zeros(n)
    segments = []
    for k in range(4):
        start = k * (n_leg + n_turn)
        segments.append((start, start + n_leg))
        yaw_base[start : start + n_leg] = 90.0 * k
        if k < 3:  # a smooth 90-degree turn to the next heading
            ramp = 0.5 - 0.5 * np.cos(np.pi * np.arange(1, n_turn + 1) / (n_turn + 1))
            yaw_base[start + n_leg : start + n_leg + n_turn] = 90.0 * (k + ramp)
    angles = []
    for amp in amplitude_deg:
        periods = rng.uniform(4.0, 12.0, size=3)
        phases = rng.uniform(0, 2 * np.pi, size=3)
        angles.append(amp * np.sin(2 * np.pi * t[:, None] / periods + phases).sum(axis=1) / np.sqrt(1.5))
    attitude = np.column_stack([yaw_base + angles[0], angles[1], angles[2]])
    rot = Rotation.from_euler("ZYX", attitude, degrees=True)
    earth = np.asarray(earth_ned_nT, dtype=np.float64)
    body = rot.inv().apply(earth)
    time_s = t
    A = design(body, groups)
    geology = 3.0 * np.sin(2 * np.pi * time_s / 200.0) + 1.0 * np.sin(2 * np.pi * time_s / 47.0)
    scalar = np.linalg.norm(earth) + geology + A @ coef + rng.normal(scale=scalar_noise_nT, size=n)
    interference = None
    measured = body
    if vector_K is not None or vector_c is not None or vector_E is not None:
        K = np.eye(3) if vector_K is None else np.asarray(vector_K, dtype=np.float64)
        c = np.zeros(3) if vector_c is None else np.asarray(vector_c, dtype=np.float64)
        E = np.zeros((3, 3)) if vector_E is None else np.asarray(vector_E, dtype=np.float64)
        measured = _solve_eddy(body @ K.T + c, E, rate_hz)
        interference = {"K": K, "c": c, "E": E}
    vector = measured + (rng.normal(scale=vector_noise_nT, size=body.shape) if vector_noise_nT else 0.0)
    return AircraftSimulation(time_s, vector, scalar, attitude, coef, groups, segments, rate_hz, body, interference,
                              geology)


def _solve_eddy(rhs: NDArray[np.float64], E: NDArray[np.float64], rate_hz: float) -> NDArray[np.float64]:
    """``H`` (N, 3) with ``H - E D(H) = rhs``, ``D`` the finite-difference time derivative of :mod:`trimag.vehicle.eddy`
    (central inside, one-sided at the ends, per second): one sparse (3N x 3N) solve."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import spsolve

    n = len(rhs)
    main = np.zeros(n)
    upper, lower = np.full(n - 1, 0.5), np.full(n - 1, -0.5)
    upper[0], main[0] = 1.0, -1.0  # forward difference at the start
    lower[-1], main[-1] = -1.0, 1.0  # backward difference at the end
    D = sp.diags([lower, main, upper], [-1, 0, 1], format="csr") * rate_hz
    system = sp.identity(3 * n, format="csr") - sp.kron(sp.csr_matrix(E), D, format="csr")
    h = spsolve(system.tocsc(), rhs.T.ravel())  # component-major: [H_x; H_y; H_z]
    return np.asarray(h, dtype=np.float64).reshape(3, n).T


__all__ += ["AircraftSimulation", "simulate_aircraft"]


def current_profile(
    n: int, seed: int | np.random.Generator | None = None, *, max_current: float = 20.0, cycles: float = 3.0,
) -> NDArray[np.float64]:
    """A motor-current series (n,), amperes, between 0 and ``max_current``: a throttle that swings ``cycles``
    times over the log (random phase), with random steps of up to half the range on every sample (gusts, motor
    commands), clipped at 0 and ``max_current`` (docs/vehicle.md).

    Examples
    --------
    >>> current_profile(1000, 0).shape
    (1000,)
    """
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 1.0, n)
    mid = 0.5 * max_current
    swing = mid * np.sin(2.0 * np.pi * cycles * t + rng.uniform(0.0, 2.0 * np.pi)) * rng.uniform(0.5, 1.0, n)
    return np.asarray(np.clip(mid + swing, 0.0, max_current), dtype=np.float64)


def temperature_ramp(
    n: int, seed: int | np.random.Generator | None = None, *, start: float = 20.0, stop: float = 35.0,
    noise: float = 0.2,
) -> NDArray[np.float64]:
    """A temperature series (n,), degrees Celsius: a linear warm-up from ``start`` to ``stop`` plus white noise of
    ``noise`` (the sensor's reading)."""
    rng = np.random.default_rng(seed)
    return np.asarray(np.linspace(start, stop, n) + rng.normal(0.0, noise, n), dtype=np.float64)


__all__ += ["current_profile", "temperature_ramp"]


#: Standard gravity, m/s^2 (the simulated accelerometer's scale).
GRAVITY = 9.80665


@dataclass(frozen=True)
class VehicleSimulation:
    """A simulated vehicle log with a magnetometer mounted at an angle to the accelerometer (:func:`simulate_vehicle`).

    Attributes
    ----------
    raw : ndarray, shape (N, 3)
        Magnetometer output, nT: ``W^-1 (R_align^T h_body) + b + noise``.
    accel : ndarray, shape (N, 3)
        Accelerometer specific force in the body frame, m/s^2 (level and at rest ``(0, 0, -g)``), with noise.
    attitude_deg : ndarray, shape (N, 3)
        Yaw (= true heading, 0-360), pitch, roll, degrees; Z-Y-X, body -> NED.
    field_body : ndarray, shape (N, 3)
        The true field in the body (accelerometer) frame, nT.
    alignment : ndarray, shape (3, 3)
        The true rotation, corrected magnetometer frame -> accelerometer (body) frame.
    matrix, offset : ndarray
        The true correction ``W`` (symmetric by default) and hard iron ``b``: ``W (raw - b)`` is the field in the
        magnetometer's frame.
    field_ned : ndarray, shape (3,)
        The Earth's field, nT.
    """

    raw: NDArray[np.float64]
    accel: NDArray[np.float64]
    attitude_deg: NDArray[np.float64]
    field_body: NDArray[np.float64]
    alignment: NDArray[np.float64]
    matrix: NDArray[np.float64]
    offset: NDArray[np.float64]
    field_ned: NDArray[np.float64]

    @property
    def dip_deg(self) -> float:
        """The true inclination of the field, degrees (positive down)."""
        n, e, d = self.field_ned
        return float(np.degrees(np.arctan2(d, np.hypot(n, e))))

    @property
    def declination_deg(self) -> float:
        """The true declination, degrees east of true north."""
        return float(np.degrees(np.arctan2(self.field_ned[1], self.field_ned[0])))


def simulate_vehicle(
    n: int,
    seed: int | np.random.Generator | None = 0,
    *,
    alignment: ArrayLike | Rotation | None = None,
    matrix: ArrayLike | None = None,
    offset: ArrayLike = (300.0, -200.0, 150.0),
    field_ned_nT: ArrayLike = (19_000.0, 1_000.0, 45_150.0),
    max_pitch_deg: float = 75.0,
    max_roll_deg: float = 180.0,
    mag_noise_nT: float = 20.0,
    accel_noise: float = 0.005,
) -> VehicleSimulation:
    """A vehicle at rest in ``n`` attitudes (yaw uniform over 0-360 degrees, pitch and roll uniform within the
    limits) with an accelerometer and a magnetometer mounted at an angle (issue 20, item 2; docs/vehicle.md).

    Parameters
    ----------
    n : int
        Samples.
    alignment : rotation, optional
        Corrected magnetometer frame -> body frame (a ``Rotation`` or a 3x3 matrix); default a 90-degree yaw
        mounting plus 2 degrees about (1, -1, 2)/|.|.
    matrix : array_like, shape (3, 3), optional
        The correction ``W``; default a mild symmetric soft iron (a symmetric ``W`` leaves the sensor's axes where
        they are, so ``alignment`` is also the rotation of the sensor's own axes).
    offset : array_like, shape (3,)
        Hard iron, nT.
    field_ned_nT : array_like, shape (3,)
        The Earth's field (N, E, D), nT; the default is 49 000 nT, inclination 67.2 deg, declination 3.0 deg.
    max_pitch_deg, max_roll_deg : float
        Limits of the uniform pitch (at most 90) and roll, degrees; small values give a (nearly) level vehicle.
    mag_noise_nT, accel_noise : float
        White noise per axis: magnetometer nT, accelerometer m/s^2.
    """
    rng = np.random.default_rng(seed)
    if alignment is None:
        tilt = np.radians(2.0) * np.array([1.0, -1.0, 2.0]) / np.sqrt(6.0)
        R_al = (Rotation.from_rotvec(tilt) * Rotation.from_euler("Z", 90.0, degrees=True)).as_matrix()
    elif isinstance(alignment, Rotation):
        R_al = alignment.as_matrix()
    else:
        R_al = np.asarray(alignment, dtype=np.float64)
    W = (np.array([[1.04, 0.02, -0.01], [0.02, 0.97, 0.03], [-0.01, 0.03, 1.01]]) if matrix is None
         else np.asarray(matrix, dtype=np.float64))
    b = np.asarray(offset, dtype=np.float64)
    H = np.asarray(field_ned_nT, dtype=np.float64)
    yaw = rng.uniform(0.0, 360.0, n)
    pitch = rng.uniform(-max_pitch_deg, max_pitch_deg, n)
    roll = rng.uniform(-max_roll_deg, max_roll_deg, n)
    att = Rotation.from_euler("ZYX", np.column_stack([yaw, pitch, roll]), degrees=True)
    h_body = body_field(att, H)
    accel = body_field(att, [0.0, 0.0, -GRAVITY]) + rng.normal(0.0, accel_noise, (n, 3))
    h_mag = h_body @ R_al  # R_al^T h per row
    raw = np.linalg.solve(W, h_mag.T).T + b + rng.normal(0.0, mag_noise_nT, (n, 3))
    return VehicleSimulation(raw, accel, np.column_stack([yaw, pitch, roll]), h_body, R_al, W, b, H)


__all__ += ["GRAVITY", "VehicleSimulation", "simulate_vehicle"]
