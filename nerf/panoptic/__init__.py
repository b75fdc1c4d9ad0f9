"""The panoptic part of a window's model, bottom-up: heads (delta grid, semantic and instance heads) ->
losses and assignment -> samples (what the heads see of a ray batch) -> result (trained part, checkpoint)
-> train (the panoptic phase) -> post (2D post-processing) -> render -> complete (3D instance completion).
Import from the modules; this package re-exports nothing."""
