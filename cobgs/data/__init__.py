"""Scene readers and the synthetic scene generator."""
