"""midair: see a flying object coming with the forward camera and get out of its way."""

__version__ = "0.1.0"
