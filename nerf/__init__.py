"""The model library: encoding, field, render, poses, assignment, losses, trainer, metrics."""
