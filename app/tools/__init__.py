"""Tools for the desk: replay a recording, evaluate against ground truth, benchmark, fit the
track confidence, draw annotated video, time the flight link.

May import everything but the CLI.
"""
