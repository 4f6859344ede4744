"""The synthetic world: rendering a BIM with a stereo camera, flights with ground truth, a simulated vehicle."""
