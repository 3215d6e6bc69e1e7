"""The vehicle's own field and its acceptance: offsets that follow logged channels (motor current, throttle,
temperature: ``regressors``), eddy currents, the joint vector + scalar fit, quick recalibration with a prior, the
magnetometer-to-accelerometer alignment, heading, attitudes from a second clock, and the acceptance policy.

May import the foundation (``errors``, ``units``, ``validation``, ``calibration``), ``_core``, ``models``, ``io``,
``fields`` and ``quality``; never ``estimators``' modules, ``aircraft``, ``app``, ``live`` or the CLI.
"""
