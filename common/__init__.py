"""Types both libraries use (`graph/` and `perception/`): errors, a keyframe's view for place recognition, rotation
angles. Imports nothing of the project."""
