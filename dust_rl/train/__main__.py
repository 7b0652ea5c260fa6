"""``torchrun --nproc-per-node N -m dust_rl.train ARGS``: as ``dust-rl train ARGS``."""

import sys

from dust_rl.cli import main

main(["train", *sys.argv[1:]])
