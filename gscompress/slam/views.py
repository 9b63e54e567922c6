"""The views a refinement runs on: a torch-free module, so that the offline commands that name
them (prune, share, merge options) can do so without loading torch."""

REFINE_VIEWS = ("frames", "keyframes")
"""What a refinement runs on: every frame of a run, or its keyframes (every `keyframes.every`-th;
the SLAM's own final refinement adds the last frame)."""
