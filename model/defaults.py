"""Defaults of the model work that the commands show in their help (`identify --cutoff`,
`model-gap --horizon`): kept apart from the numerical code so that a `--help` answers at once,
without importing scipy and numba (about 2 s)."""

# Hz: the zero-phase low-pass applied to the recordings before differentiation; the
# exciting trajectories' content lies below ~5 Hz and the sensors' noise well above
CUTOFF_HZ = 25.0
HORIZON = 0.5  # s of open-loop simulation before model-gap restarts from the measured state
