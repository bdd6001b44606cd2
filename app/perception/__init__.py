"""Perception: stages 1-3 of the paper and the track confidence — frames in, confirmed
tracks out (detection, recognition, tracking, confidence, the chain in ``pipeline``).

Pure numpy/OpenCV: no device, no network, no drawing. May import: ``app.config``,
``app.errors``, ``app.ratelimit``, ``app.camera`` and itself.
"""
