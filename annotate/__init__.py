"""annotate: see README.md."""
