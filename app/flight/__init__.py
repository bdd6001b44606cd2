"""Flight: when midair may take control of the vehicle and how it hands it back
(``engagement``, ``testflight``), and the offboard loop that ticks them (``loop``).

No MAVSDK here (that is ``hardware.px4``). May import: the base modules, ``app.perception``,
``app.decision`` and itself.
"""
