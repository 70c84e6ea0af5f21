"""The robot and its wiring, below the commands: the robot description (`description`: robot
files, checked whole before any bus is opened), the opening of drives for one joint or a whole
robot on their CAN buses and EtherCAT lines, real or virtual with `--sim` (`wiring`), and CAN
logging as a python-can bus wrapper (`can_log`). Tests and programs build a robot here without
the command line; nothing here parses command-line text."""
