"""Benchmark targets for `python -m gear bench`; one module each (see gear.commands.bench)."""
