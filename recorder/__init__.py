"""Experiments on the drive (exciting trajectories), recordings in MCAP and CSV, identification
and Zenoh-to-MCAP recording; `recorder` and `identify`."""
