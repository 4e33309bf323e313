"""The CMC method: plane sweep, model, losses, training and its ETA."""
