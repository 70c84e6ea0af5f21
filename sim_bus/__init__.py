"""A virtual CiA 402 elbow drive on a python-can bus, its physics from `model/`."""
