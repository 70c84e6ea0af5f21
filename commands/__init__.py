"""The console scripts, one module each, and the options they share (`commands.options`).

This is the composition root: a command may import every layer (it is where `--sim` puts the
virtual drive behind the master); no library layer imports a command.
"""
