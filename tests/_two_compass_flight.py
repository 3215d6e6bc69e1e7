"""A simulated ArduPilot flight with two compasses, written as a binary DataFlash log, for the tests that chain
compass 2 through every command (issue 39): the vehicle turns through every heading and tilts up to 35 deg, so
``fit --target ardupilot`` can identify compass 2's calibration (the bundled ``ardusub_small.BIN`` is static and is
refused: issue 38, item 1).

Compass 1 is ``test_firmware_fit``'s TRUTH (mounted yawed 270 deg, logged corrected by ONBOARD), compass 2 its
SECOND (logged raw: its parameters in the log are neutral). The device ids are the bundled ArduSub log's.
"""

from __future__ import annotations

import sys
from pathlib import Path

from _helpers import TESTS_DIR

#: the bundled ArduSub log's COMPASS_DEV_ID and COMPASS_DEV_ID2 (compass 1 and compass 2)
DEVICE_ID_1, DEVICE_ID_2 = 1379337, 1245450
#: the simulated flight's place and date (test_firmware_fit's LAT, LON, ALT in km, the GPS week's date)
SITE = "52.8,-4.12,0.03,2023-07-06"


def write_two_compass_flight(path: Path, n: int = 1500, seed: int = 1, tilt_deg: float = 35.0) -> Path:
    """Write the flight to ``path`` (a ``.BIN``): MAG instances 0 and 1, ATT, BAT, GPS and PARM with
    ``COMPASS_DEV_ID``/``COMPASS_DEV_ID2`` and compass 2's neutral calibration (``COMPASS_OFS2_*`` 0,
    ``COMPASS_DIA2_*`` 1...); roll and pitch within ``tilt_deg``. Returns ``path``."""
    sys.path.insert(0, str(TESTS_DIR / "app"))
    from test_firmware_fit import _write_log

    from trimag.models.firmware import ArduPilotCompass

    neutral2 = ArduPilotCompass(orientation=0).parameters(1)
    return _write_log(path, n=n, seed=seed, tilt=tilt_deg, second=True,
                      parameters={**neutral2, "COMPASS_EXTERN2": 1.0, "COMPASS_DEV_ID": float(DEVICE_ID_1),
                                  "COMPASS_DEV_ID2": float(DEVICE_ID_2)})
