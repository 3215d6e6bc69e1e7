"""How good a fit is: the Cramér–Rao bound (``crlb``), sphere coverage and identifiability (``diagnostics``), the
honest uncertainty every fit's covariance gets (``honesty``), error metrics (``metrics``) and the report's figures.

May import the foundation (``errors``, ``units``, ``validation``, ``calibration``), ``_core``, ``models``, ``io`` and
``fields``; nothing that fits (``estimators``, ``vehicle``, ``aircraft``), nor ``app``, ``live`` or the CLI.
"""
