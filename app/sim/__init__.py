"""Simulation: synthetic frames with exact truth (``synthetic``), the rendered world
(``world``), closed-loop encounters and campaigns (``simulate``, ``campaign``) and the
PX4-faithful MAVLink stand-in vehicle (``px4``; a simulator, not hardware).

May import everything below it: the base modules, ``app.perception``, ``app.decision``,
``app.flight``, ``hardware``, ``app.runtime`` and itself.
"""
