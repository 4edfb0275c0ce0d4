"""Benchmarks behind ``bmi bench TARGET``.

Each module here that defines ``register(subparsers)`` adds one target
(``bmi bench psf``, ``bmi bench render``…). Benchmarks print a table and can
append it to ``docs/benchmarks.md`` with the exact command that made it; speed
never lives in tests.
"""
