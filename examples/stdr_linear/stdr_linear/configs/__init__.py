"""Config groups stdr searches after its own (the `stdr.configs` entry point)."""
