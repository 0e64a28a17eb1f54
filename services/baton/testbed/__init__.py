"""The local testbed: every part as a process on loopback, supervised, with a report."""
