"""The console scripts, one module each, and the options they share, split by job
(`parsing`, `bus_options`, `sim_options`, `model_options`, `zenoh_options`, `file_options`,
`log_options`).

A command parses its command line, checks it whole and turns errors into exit codes; the robot
layer (`robot/`) opens the drives (it is where `--sim` puts the virtual drive behind the
master). No library layer imports a command.
"""
