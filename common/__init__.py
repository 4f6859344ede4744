"""Types both libraries use (`graph/` and `perception/`): errors, a keyframe's view for place recognition, rotation
angles, and how a component's parameter is declared (`parameters.param`). Imports nothing of the project."""
