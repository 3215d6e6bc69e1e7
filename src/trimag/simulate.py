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


@dataclass(frozen=True)
class GyroSimulation:
    """A simulated magnetometer beside a gyroscope (:func:`simulate_gyro`), with the truth.

    Attributes
    ----------
    time_s : ndarray, shape (N,)
        Sample times, s (both sensors sample together).
    raw : ndarray, shape (N, 3)
        Magnetometer output: ``inv(W) R^T h + b + noise``.
    rate : ndarray, shape (M, 3)
        Gyroscope output, rad/s: the body's angular rate + ``gyro_bias`` + white noise, at ``gyro_time_s``.
    gyro_time_s : ndarray, shape (M,)
        The gyroscope's time stamps on its own clock (``time_s`` itself when the two sample together).
    lag_s : float
        Gyroscope clock - magnetometer clock: the gyroscope sample stamped ``t + lag_s`` is the one taken with the
        magnetometer's sample stamped ``t``.
    attitude : Rotation
        True attitude, body (= gyroscope frame) -> navigation frame.
    field_body : ndarray, shape (N, 3)
        True field in the gyroscope's frame.
    matrix, offset : ndarray
        True correction ``W`` (upper triangular) and hard iron ``b``: ``W (raw - b)`` is the field in the corrected
        magnetometer frame.
    alignment : ndarray, shape (3, 3)
        True rotation, corrected magnetometer frame -> gyroscope frame.
    gyro_bias : ndarray, shape (3,)
        rad/s.
    field_nav : ndarray, shape (3,)
    positions : ndarray, shape (N, 3)
        The sensor's position, m (the path of :func:`simulate_gyro`'s ``path_m``; zeros when still).
    """

    time_s: NDArray[np.float64]
    raw: NDArray[np.float64]
    rate: NDArray[np.float64]
    gyro_time_s: NDArray[np.float64]
    lag_s: float
    attitude: Rotation
    field_body: NDArray[np.float64]
    matrix: NDArray[np.float64]
    offset: NDArray[np.float64]
    alignment: NDArray[np.float64]
    gyro_bias: NDArray[np.float64]
    field_nav: NDArray[np.float64]
    positions: NDArray[np.float64]

    def angular_rate(self) -> Any:
        """The gyroscope as the gyro-aided fit takes it (:class:`trimag.fields.gyro.AngularRate`)."""
        from .fields.gyro import AngularRate

        if self.gyro_time_s is self.time_s:
            return AngularRate.same_rows(self.time_s, self.rate, source="simulated gyroscope")
        return AngularRate(self.time_s, self.gyro_time_s, self.rate, 0.0, True, "simulated gyroscope, own clock")

    @property
    def soft_iron(self) -> NDArray[np.float64]:
        """``M = inv(R W)``: raw = ``M h + b`` with ``h`` in the gyroscope's frame."""
        return np.asarray(np.linalg.inv(self.alignment @ self.matrix), dtype=np.float64)


def smooth_attitudes(t: ArrayLike, *, motion: str = "tumble", cone_deg: float = 90.0, speed: float = 1.0,
                     axis: ArrayLike = (0.0, 0.0, 1.0), seed: int | np.random.Generator | None = 0) -> Rotation:
    """Smooth attitudes (body -> navigation) at times ``t`` (s): sums of sinusoids with random phases.

    ``motion="tumble"``: the rotation vector wanders over all attitudes (rates about ``speed`` rad/s RMS).
    ``motion="cone"``: turns freely about the navigation-frame ``axis`` (e.g. the field's direction) and tilts away
    from it by at most ``cone_deg / 2``: a body-frame vector along ``axis`` stays within a cone of full aperture
    ``cone_deg`` (a partial rotation: what a vehicle that cannot tumble records).
    """
    rng = np.random.default_rng(seed)
    tt = np.asarray(t, dtype=np.float64)
    freqs = speed * rng.uniform(0.15, 0.6, (3, 3))
    phases = rng.uniform(0, 2 * np.pi, (3, 3))
    waves = np.stack([np.sum(np.sin(freqs[a][:, None] * tt + phases[a][:, None]), axis=0) for a in range(3)], axis=1)
    if motion == "tumble":
        return Rotation.from_rotvec(1.2 * waves)
    if motion != "cone":
        raise TrimagInputError(f"motion must be 'tumble' or 'cone'; got {motion!r}")
    z = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    a = np.eye(3)[int(np.argmin(np.abs(z)))]
    e1 = np.cross(z, a) / np.linalg.norm(np.cross(z, a))
    e2 = np.cross(z, e1)
    half = np.radians(cone_deg / 2.0)
    # a tilt perpendicular to the axis: its size sweeps 0..half, its azimuth turns (both smoothly)
    size = half * (0.5 - 0.5 * np.cos(0.35 * speed * tt + phases[0, 0]))
    azimuth = 0.8 * speed * tt + waves[:, 0]
    tilt = size[:, None] * (np.cos(azimuth)[:, None] * e1 + np.sin(azimuth)[:, None] * e2)
    spin = 2.0 * speed * tt + 1.5 * waves[:, 2]
    return Rotation.from_rotvec(spin[:, None] * z) * Rotation.from_rotvec(tilt)


def body_rate(attitude_at: Any, t: ArrayLike, h: float = 1e-5) -> NDArray[np.float64]:
    """The body's angular rate (rad/s, body frame) of ``attitude_at(t)`` (a function of time returning a Rotation),
    by a central difference of the rotation: ``log(R(t - h)^T R(t + h)) / 2h`` (error ``O(h^2)``)."""
    tt = np.asarray(t, dtype=np.float64)
    return np.asarray((attitude_at(tt - h).inv() * attitude_at(tt + h)).as_rotvec() / (2 * h), dtype=np.float64)


def simulate_gyro(
    n: int,
    seed: int | np.random.Generator | None = 0,
    *,
    rate_hz: float = 100.0,
    motion: str = "tumble",
    cone_deg: float = 90.0,
    speed: float = 1.0,
    matrix: ArrayLike | None = None,
    offset: ArrayLike = (12.0, -30.0, 7.0),
    alignment: ArrayLike | Rotation | None = None,
    gyro_bias: ArrayLike = (0.01, -0.02, 0.015),
    gyro_noise: float = 0.002,
    mag_noise: float = 0.3,
    field_nav: ArrayLike = (20.0, 1.0, 45.0),
    gyro_rate_hz: float | None = None,
    lag_s: float = 0.0,
) -> GyroSimulation:
    """A magnetometer and a gyroscope sampled together at ``rate_hz`` while the sensor turns smoothly
    (:func:`smooth_attitudes`; issue 31). Defaults: a phone-like sensor in uT (field 49.3 uT, hard iron (12, -30, 7)
    uT, a mild soft iron, 0.3 uT noise per axis), a gyroscope with a bias of (0.01, -0.02, 0.015) rad/s and 0.002
    rad/s of white noise, the magnetometer turned by 2 degrees about (1, -1, 2) from the gyroscope's axes.

    ``motion="cone"`` keeps the field's body-frame direction within a cone of full aperture ``cone_deg`` (the sensor
    turns about the field and tilts away from it by at most half of it). With ``gyro_rate_hz`` or ``lag_s`` the
    gyroscope has its own clock: it samples at ``gyro_rate_hz`` (default ``rate_hz``) from 1 s before the
    magnetometer's first sample to 1 s after its last, its stamps ``lag_s`` ahead of the magnetometer's.
    """
    rng = np.random.default_rng(seed)
    t = np.arange(n) / float(rate_hz)
    H = np.asarray(field_nav, dtype=np.float64)
    motion_seed = int(rng.integers(0, 2**31))

    def att(tt: NDArray[np.float64]) -> Rotation:
        return smooth_attitudes(tt, motion=motion, cone_deg=cone_deg, speed=speed, axis=H, seed=motion_seed)

    R_true = att(t)
    rate_true = body_rate(att, t)
    if alignment is None:
        R_al = Rotation.from_rotvec(np.radians(2.0) * np.array([1.0, -1.0, 2.0]) / np.sqrt(6.0)).as_matrix()
    elif isinstance(alignment, Rotation):
        R_al = alignment.as_matrix()
    else:
        R_al = np.asarray(alignment, dtype=np.float64)
    W = (np.array([[1.05, 0.03, -0.02], [0.0, 0.96, 0.04], [0.0, 0.0, 1.01]]) if matrix is None
         else np.asarray(matrix, dtype=np.float64))
    b = np.asarray(offset, dtype=np.float64)
    bias = np.asarray(gyro_bias, dtype=np.float64)
    h_body = body_field(R_true, H)
    raw = np.linalg.solve(W, (h_body @ R_al).T).T + b + rng.normal(0.0, mag_noise, (n, 3))
    t_gyro = t
    if gyro_rate_hz is not None or lag_s != 0.0:  # its own clock: stamps lag_s ahead of the magnetometer's
        t_gyro = np.arange(-1.0, t[-1] + 1.0, 1.0 / float(gyro_rate_hz or rate_hz)) + lag_s
        rate_true = body_rate(att, t_gyro - lag_s)
    rate = rate_true + bias + rng.normal(0.0, gyro_noise, rate_true.shape)
    return GyroSimulation(t, raw, rate, t_gyro, float(lag_s), R_true, h_body, W, b, R_al, bias, H, np.zeros((n, 3)))


__all__ += ["GyroSimulation", "body_rate", "simulate_gyro", "smooth_attitudes"]


@dataclass(frozen=True)
class RoomSimulation:
    """A sensor carried through a room whose background changes with position (:func:`simulate_room`).

    ``raw = K C^T (H_0 + G p) + c + noise``: ``time_s`` (N,), ``raw`` (N, 3), ``attitude`` (body -> the room's
    frame), ``positions`` (N, 3) m, ``K`` (3, 3), ``c`` (3,), ``background`` ``H_0`` (3,) at the room's origin (every
    recording of :func:`simulate_room` is in the same room), and the gradient ``G`` (3, 3), unit per metre
    (symmetric and traceless)."""

    time_s: NDArray[np.float64]
    raw: NDArray[np.float64]
    attitude: Rotation
    positions: NDArray[np.float64]
    K: NDArray[np.float64]
    c: NDArray[np.float64]
    background: NDArray[np.float64]
    gradient: NDArray[np.float64]


def simulate_room(
    n: int,
    seed: int | np.random.Generator | None = 0,
    *,
    rate_hz: float = 50.0,
    background: ArrayLike = (12_000.0, -30_000.0, 38_000.0),
    gradient_terms: ArrayLike = (4000.0, -1500.0, 2500.0, -2000.0, 1000.0),
    K: ArrayLike | None = None,
    c: ArrayLike = (250.0, -120.0, 80.0),
    noise: float = 20.0,
    reach_m: float = 0.4,
    centre_m: ArrayLike = (0.0, 0.0, 0.0),
    dipole_at_m: ArrayLike | None = None,
    dipole_moment_Am2: ArrayLike = (0.0, 0.0, 0.0),
) -> RoomSimulation:
    """A lab recording (issue 31, item 4): the sensor tumbles (:func:`smooth_attitudes`) while a hand carries it
    within ``reach_m`` of ``centre_m``, in a background with a gradient (nT per metre: the five terms ``g_xx, g_xy,
    g_xz, g_yy, g_yz`` of a symmetric, traceless tensor; the default changes the field by a few thousand nT over the
    reach, as indoors near steel), paper C's ``K`` and ``c``, white noise per axis (unit nT). With ``dipole_at_m``
    a point source (moment in A m^2) adds a field that is not linear in position: ``100 (3 (m . r^) r^ - m) / r^3``
    nT (``mu_0 / 4 pi = 100 nT m^3 / (A m^2)``), which a gradient only approximates near where it was fitted;
    ``gradient`` is then the linear part alone."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / float(rate_hz)
    att = smooth_attitudes(t, seed=int(rng.integers(0, 2**31)))
    freqs = rng.uniform(0.05, 0.25, (3, 2))
    phases = rng.uniform(0, 2 * np.pi, (3, 2))
    walk = np.column_stack([np.sin(freqs[a, 0] * 2 * np.pi * t + phases[a, 0])
                            + 0.5 * np.sin(freqs[a, 1] * 2 * np.pi * t + phases[a, 1]) for a in range(3)])
    positions = np.asarray(centre_m, dtype=np.float64) + reach_m * walk / 1.5
    g = np.asarray(gradient_terms, dtype=np.float64)
    G = np.array([[g[0], g[1], g[2]], [g[1], g[3], g[4]], [g[2], g[4], -g[0] - g[3]]])
    H0 = np.asarray(background, dtype=np.float64)
    Hn = H0 + positions @ G.T
    if dipole_at_m is not None:
        r = positions - np.asarray(dipole_at_m, dtype=np.float64)
        dist = np.linalg.norm(r, axis=1, keepdims=True)
        u = r / dist
        m = np.asarray(dipole_moment_Am2, dtype=np.float64)
        Hn = Hn + 100.0 * (3.0 * (u @ m)[:, None] * u - m) / dist**3
    K_m = (np.array([[1.02, 0.01, -0.02], [0.015, 0.98, 0.01], [-0.01, 0.02, 1.01]]) if K is None
           else np.asarray(K, dtype=np.float64))
    c_v = np.asarray(c, dtype=np.float64)
    Hb = np.einsum("nji,nj->ni", att.as_matrix(), Hn)
    raw = Hb @ K_m.T + c_v + rng.normal(0.0, noise, (n, 3))
    return RoomSimulation(t, raw, att, positions, K_m, c_v, H0, G)


__all__ += ["RoomSimulation", "simulate_room"]
