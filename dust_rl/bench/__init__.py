"""Benchmarks and studies that print a table: ``dust-rl bench suite|average|gpu`` and the ``python -m
dust_rl.bench.<name>`` speed scripts."""
