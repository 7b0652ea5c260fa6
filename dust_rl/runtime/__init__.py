"""Where work runs: the device, and the env processes (multiprocessing or Ray) behind torchrl's collectors."""
