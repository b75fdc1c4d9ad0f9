"""One module per pipeline stage, all of the same shape (see pipeline/stage.py)."""
