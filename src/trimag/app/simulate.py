"""``trimag simulate``: a simulated log of a sensor with known errors (and its true parameters)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import TrimagInputError
from ..io.atomic import atomic_write_text, check_distinct_outputs
from ..units import normalise_unit
from ..validation import load_json
from .requests import SimulateRequest

__all__ = ["simulate_to_file"]


def simulate_to_file(request: SimulateRequest | None = None, **arguments: Any) -> dict[str, Any]:
    """Simulate a sensor with the parameters in ``params_path`` (JSON ``{name: value}``) and write a CSV log with
    columns ``x, y, z`` (raw), ``qw, qx, qy, qz`` (attitude, scalar first, body -> navigation NED) and, with
    ``truth``, a JSON file with the true parameters and settings.

    ``request``: a :class:`~trimag.app.requests.SimulateRequest`, or its fields as keyword arguments.
    """
    req = request if request is not None else SimulateRequest(**arguments)
    if request is not None and arguments:
        raise TrimagInputError("give either a SimulateRequest or its arguments, not both")
    model, n, noise, seed, attitudes, field, units = (req.model, req.n, req.noise, req.seed, req.attitudes, req.field,
                                                      req.units)
    from ..models import get_model
    from ..simulate import simulate

    p = Path(req.params_path)
    check_distinct_outputs({"the parameter file": p}, {"out": req.out, "truth": req.truth})
    if not p.is_file():
        raise TrimagInputError(f"{p}: no such parameter file (JSON object of model parameters)")
    params = load_json(p.read_text(encoding="utf-8"), str(p))
    if isinstance(params, dict) and "params" in params and isinstance(params["params"], dict):
        params = params["params"]
    if n < 1:
        raise TrimagInputError(f"`n` must be a positive number of samples; got {n}")
    if noise < 0 or not np.isfinite(noise):
        raise TrimagInputError(f"`noise` must be a non-negative standard deviation; got {noise}")
    if not (np.isfinite(field) and field > 0):
        raise TrimagInputError(f"`field` must be a positive field magnitude; got {field}")
    if seed < 0:
        raise TrimagInputError(f"`seed` must be a whole number of 0 or more; got {seed}")
    unit = normalise_unit(units)  # before anything is written
    if not isinstance(params, dict):
        raise TrimagInputError(f"{p}: expected a JSON object {{name: value}} of model parameters")
    bad = {k: v for k, v in params.items()
           if isinstance(v, bool) or not isinstance(v, int | float) or not np.isfinite(float(v))}
    if bad:
        raise TrimagInputError(f"{p}: every parameter must be a finite number; got "
                               f"{', '.join(f'{k} = {v!r}' for k, v in list(bad.items())[:3])}")
    params, defaulted = _with_identity_defaults(get_model(model), params)
    truth_model = get_model(model).from_dict(params)
    try:
        with np.errstate(over="ignore", invalid="ignore"):  # values too large are refused below, not warned about
                sim = simulate(truth_model, n=n, field_nav=(field, 0.0, 0.0), noise=noise, attitudes=attitudes,
                           seed=seed)
    except np.linalg.LinAlgError:
        sim = None
    if sim is None or not np.isfinite(sim.raw).all() or np.abs(sim.raw).max() > 1e12 * field:
        raise TrimagInputError(f"{p}: these parameters give no finite readings (a soft-iron matrix that cannot be "
                               "inverted, such as all zeros, or readings beyond 1e12 times the field): give a matrix "
                               "with a non-zero determinant (identity, w11 = w22 = w33 = 1, is no error) and offsets "
                               "of the field's size")
    q = sim.attitude.as_quat(scalar_first=True)
    table = np.column_stack([sim.raw, q])
    header = "x,y,z,qw,qx,qy,qz"
    import io as _stdio

    buf = _stdio.StringIO()
    np.savetxt(buf, table, delimiter=",", header=header, comments="", fmt="%.17g")
    written = {"data": str(atomic_write_text(req.out, buf.getvalue()))}
    if req.truth is not None:
        doc = {
            "model": model,
            "params": truth_model.as_dict(),
            "n": len(sim.raw),
            "noise": noise,
            "seed": seed,
            "attitudes": attitudes,
            "field_nav": [field, 0.0, 0.0],
            "units": unit,
        }
        written["truth"] = str(atomic_write_text(req.truth, json.dumps(doc, indent=2) + "\n"))
    return {"n": len(sim.raw), "outputs": written, "defaulted": defaulted}


def _with_identity_defaults(cls: Any, params: dict[str, Any]) -> tuple[dict[str, Any], list[str]]:
    """``params`` completed with the model's values for no error (identity matrix, zero offset) and the names so
    completed; a name the model does not have is refused."""
    known = cls.param_names()
    unknown = sorted(set(params) - set(known))
    if unknown:
        raise TrimagInputError(f"model {cls.name!r} has no parameter {', '.join(map(repr, unknown))}; its parameters "
                               f"are {', '.join(known)} (those not given default to no error: identity, zero)")
    identity = cls.from_matrix_offset(np.eye(3), np.zeros(3)).as_dict()
    defaulted = [name for name in known if name not in params]
    return {**identity, **params}, defaulted

