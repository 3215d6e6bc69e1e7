"""Which magnetometer PX4's EKF fused decides whether the logged yaw is independent of the compass being fitted.

Every PX4 log was fitted heading-free ("its yaw is the EKF's, which fused this compass"), whatever compass the EKF
used: a real Cube Orange log (PX4 1.15-dev, held out, docs/autopilot.md) shows every ``estimator_status`` instance
with ``mag_device_id`` 8944643 (compass 2), so compass 1's fit could take the full vector, as ArduPilot's
``COMPASS_USE2 = 0`` case does. ``EKF2_MAG_TYPE = 5`` (none) fuses no magnetometer at all. Where the log does not
say (no ``estimator_status.mag_device_id``, PX4 before 1.12), the fit stays heading-free.
"""

from __future__ import annotations

import numpy as np

from trimag.app._firmware import _circularity
from trimag.io.logs.px4 import _ekf_mag_device_ids


def test_the_fused_magnetometers_are_read_from_every_estimator_instance() -> None:
    data = {("estimator_status", 0): {"mag_device_id": np.array([0, 8944643, 8944643])},
            ("estimator_status", 1): {"mag_device_id": np.array([8944643, 589858])},
            ("vehicle_attitude", 0): {"q[0]": np.ones(3)}}
    assert _ekf_mag_device_ids(data) == (589858, 8944643)
    assert _ekf_mag_device_ids({("estimator_status", 0): {"timestamp": np.arange(3)}}) is None


def _info(device: int, fused: list[int] | None, **params: float) -> dict:
    return {"format": "PX4 ULog", "device_id": device, "ekf_mag_device_ids": fused, "parameters": params,
            "attitude_source": "vehicle_attitude.q"}


def test_a_compass_the_ekf_did_not_fuse_has_an_independent_yaw() -> None:
    circular, said = _circularity("px4", _info(589858, [8944643]))
    assert not circular and "did not use this compass" in said and "8944643" in said, said
    circular, said = _circularity("px4", _info(8944643, [8944643]))
    assert circular and "fused this compass" in said
    circular, _ = _circularity("px4", _info(589858, None))  # the log does not say: heading-free
    assert circular
    circular, said = _circularity("px4", _info(589858, [589858], EKF2_MAG_TYPE=5.0))
    assert not circular and "EKF2_MAG_TYPE = 5" in said
