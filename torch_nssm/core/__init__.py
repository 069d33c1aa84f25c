"""The model contract: the state-space model, the batch of sequences, parametric modules, noise."""
