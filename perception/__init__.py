"""Images to observations: detector (ONNX inference), line refinement, stereo depth, 3D corners, odometry.

A pure library: it never imports `service`, zenoh or the CLI. torch is used by the training script only.
"""
