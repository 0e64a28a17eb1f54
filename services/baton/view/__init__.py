"""The live fleet view: a web page of the stations, their ranges and the drones moving,
fed by what the stations and drones report (``baton fleet view``)."""
