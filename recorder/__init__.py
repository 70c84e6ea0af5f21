"""Experiments on the drive (exciting trajectories), recordings in MCAP and CSV, and
Zenoh-to-MCAP recording."""
