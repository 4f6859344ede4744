"""The synthetic world: rendering a BIM with a stereo camera, flights with ground truth, a simulated vehicle; the
vehicle's side of the wire (agent: the reference onboard agent, over Zenoh), ground-truth-only flights
(truth_flight) and the closed-loop demo (demo) that runs the service against it."""
