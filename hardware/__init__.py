"""The edge to physical devices: the D435i (``realsense``, pyrealsense2) and PX4 (``px4``,
MAVSDK), and the files a Pi/PX4 set-up needs (udev rule, PX4 parameters). Only here are
``pyrealsense2`` and ``mavsdk`` imported, and both lazily where the rest must work without.

May import: the base modules, ``app.perception``, ``app.decision``, ``app.flight`` and itself.
"""
