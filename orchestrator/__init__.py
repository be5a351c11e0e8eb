"""The collection daemon: config, run plan, session loop, bus, recorder and CLI.

This is the only package with threads, processes, signals, files on disk and the zenoh
session; it wires ``drivers``, ``trajectories`` and ``tracking`` together.
"""

__version__ = "0.1.0"
