"""The embedded sim vehicle: a MAVLink multicopter MAVSDK connects to like PX4 SITL.

``kinematics`` is the pure physics, ``server`` the MAVLink UDP side
(``SimVehicle``), ``cli`` the ``baton sim-vehicle`` program.
"""
