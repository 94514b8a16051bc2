"""What a finished run gives its user: renders along a path, held-out scores, and exports other programs read."""
