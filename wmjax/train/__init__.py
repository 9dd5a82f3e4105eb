"""Training: state and optimiser, the sharded train step."""
