"""The parts of `make prove` (tools/prove.py): Frama-C runs, Eva, WP, assumptions, self-test."""
