"""``baton station``: one process per edge node, hosting the controller of every
mission whose ring holds it."""
