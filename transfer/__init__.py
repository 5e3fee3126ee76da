"""transfer: see README.md."""
