"""Zenoh subscribers for people watching the robot: a Foxglove bridge, a terminal dashboard and
a one-line command path to change the reference and the weights."""
