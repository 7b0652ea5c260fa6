"""dust-rl."""
