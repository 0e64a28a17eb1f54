"""Offline replay of saved mission logs against a mission program (``baton replay``)."""
