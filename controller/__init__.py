"""iLQR with exponential barriers, the MPC loop at 1 kHz, Zenoh telemetry."""
