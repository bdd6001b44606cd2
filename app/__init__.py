"""midair: see a flying object coming with the forward camera and get out of its way.

Packages by layer; a module imports only from its own layer or the layers below it
(``tests/test_architecture.py`` checks this on every run):

0. base: ``config``, ``errors``, ``ratelimit``, ``camera`` (the calibration model)
1. ``perception`` — stages 1-3 and the track confidence
2. ``decision`` — stage 4: depth, threat, escape
3. ``flight`` — engagement logic and the offboard loop
4. ``hardware`` (top-level package) — the D435i and PX4/MAVSDK adapters
5. ``runtime`` — the flight process: three coroutines, sources, flight record
6. ``sim`` — synthetic frames, the closed-loop world, campaigns, the stand-in vehicle
7. ``tools`` — replay, evaluate, bench, fit-confidence, annotate
8. ``cli`` — the ``midair`` command; nothing imports it
"""

__version__ = "0.1.0"
