"""Scene simulator: a snowy city block around the synthetic walk, rendered by ray casting."""
