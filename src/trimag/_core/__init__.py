"""trimag's numerical core (private): what every estimator shares, and every performance trick, documented once;
it imports nothing of trimag but itself and :mod:`trimag.errors`.

- :mod:`~trimag._core.chunks`: the one chunk setting of every pass over samples (working memory per chunk).
- :mod:`~trimag._core.rowwise`: component-major passes over (N, 3) samples and the reused scratch buffers.
- :mod:`~trimag._core.qr`: the blocked (streaming) QR of a tall design, in cache-sized panels.
- :mod:`~trimag._core.solve`: the Gauss-Newton driver with a Levenberg-Marquardt fallback.
- :mod:`~trimag._core.quadric`: quadric moments and scatter, and the one quadric -> centre + shape reduction.
- :mod:`~trimag._core.normalise`: translation/scale normalisation of samples.
- :mod:`~trimag._core.threads`: one BLAS thread while trimag computes.

Modules here import only numpy, scipy, :mod:`trimag.errors` and each other (``tests/test_architecture.py``).
"""
