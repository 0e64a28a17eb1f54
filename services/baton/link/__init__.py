"""The link emulator (``baton link``): a TCP proxy with per-direction latency and bandwidth.

The local testbed puts one in front of every link so that measured handover
delays mean something (the paper's controller links: 20 ms, 25 Mbit/s).
``LinkProxy`` runs one inside an existing event loop; ``shaper`` holds the
timing model alone.
"""
