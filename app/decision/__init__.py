"""Decision: stage 4 — each confirmed track's distance from depth, its 3-D state and time to
collision, and the command (emergency stop or evasion) with its safety rules.

Pure logic on numpy arrays and dataclasses. May import: the base modules (``app.config``,
``app.errors``, ``app.ratelimit``, ``app.camera``), ``app.perception`` and itself.
"""
