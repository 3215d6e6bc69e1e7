"""The fields and frames a fit is judged against: scalar and vector references (IGRF-14 via ppigrf, a number, a
column: ``reference``) and attitudes (Euler angles and quaternions to Rotations, the body-frame field: ``attitude``).

May import the foundation (``errors``, ``units``, ``validation``) and ``_core``; nothing else of trimag.
"""
