"""Runtime: the flight process — the three coroutines (``process``: capture, perception in
its worker thread, offboard), frame sources (``sources``), the flight record (``record``)
and systemd notification (``notify``).

May import: the base modules, ``app.perception``, ``app.decision``, ``app.flight``,
``hardware`` and itself.
"""
