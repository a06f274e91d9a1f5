"""tal's lab: experiments, datasets, training, evaluation, reports, the in-process closed loop and offline
replay. No nodes; it may depend on every runtime package, and nothing that runs on the robot depends on it.
"""
